//! The runner process: receives each slot from the env servers, applies the message plan to its
//! observation rows in place (no copy of the batch), and hands the slot to the trainer.

use crate::plan::{MessagePlan, StepView};
use lmac_shm_schema::ring::{Port, RingError, RingSpec, KIND_BYE, KIND_SLOT};
use lmac_shm_schema::{EnvSchema, Slab, Stage};
use std::time::{Duration, Instant};

pub struct RunnerArgs {
    pub run: String,
    pub schema: EnvSchema,
    pub n_members: usize,
    pub n_slots: usize,
    pub startup_timeout: Duration,
}

#[derive(Debug, Default, Clone)]
pub struct RunnerStats {
    pub slots: u64,
    pub busy: Duration,
}

#[derive(Debug, thiserror::Error)]
pub enum RunnerError {
    #[error("protocol runner: {0}")]
    Ring(#[from] RingError),
    #[error("protocol runner: {0}")]
    Slab(#[from] lmac_shm_schema::SlabError),
    #[error("protocol runner: plan {plan} writes {need} message columns but the slab reserves {have}")]
    Width { plan: String, need: usize, have: usize },
    #[error("protocol runner: slab {slab} has {found} slots but the ring has {ring}: the env server and the runner disagree")]
    Slots { slab: String, found: usize, ring: usize },
}

pub use lmac_shm_schema::slab::slab_name;

/// Apply `plan` to one slot this process owns.
pub fn apply_to_slot(plan: &mut dyn MessagePlan, slab: &Slab, slot: usize) -> Result<(), RunnerError> {
    let mut s = slab.slot(slot, Stage::Runner)?;
    let l = s.layout().clone();
    let (rows, first, last_actions) = s.runner_parts();
    let mut view =
        StepView { num_envs: l.num_envs, n_agents: l.n_agents, obs_dim: l.obs_dim, msg_dim: l.msg_dim, rows, first: &first, last_actions };
    plan.apply(&mut view);
    Ok(())
}

/// Run until every ring member has said goodbye (or a peer dies / a stop is requested).
/// `plans[s]` serves ring member `s` (each plan keeps its own observation history).
pub fn run(args: &RunnerArgs, plans: &mut [Box<dyn MessagePlan>]) -> Result<RunnerStats, RunnerError> {
    assert_eq!(plans.len(), args.n_members, "one plan per ring member");
    let mut slabs = Vec::new();
    for (s, plan) in plans.iter().enumerate() {
        let slab = Slab::open(&slab_name(&args.run, s), &args.schema, args.startup_timeout)?;
        // Ring messages are checked against the ring's slot count; the slab must have as many.
        if slab.layout().n_slots != args.n_slots {
            return Err(RunnerError::Slots { slab: slab.name().to_string(), found: slab.layout().n_slots, ring: args.n_slots });
        }
        if plan.msg_dim() > slab.layout().msg_dim {
            return Err(RunnerError::Width { plan: plan.name(), need: plan.msg_dim(), have: slab.layout().msg_dim });
        }
        slabs.push(slab);
    }
    let mut port =
        Port::new(RingSpec { run: args.run.clone(), n_members: args.n_members, n_slots: args.n_slots, role: Stage::Runner, member: 0 })?;
    port.set_startup_timeout(args.startup_timeout);
    let mut stats = RunnerStats::default();
    let mut byes = 0;
    while byes < args.n_members {
        let Some(m) = port.recv(Duration::from_millis(500))? else { continue };
        match m.kind {
            KIND_SLOT => {
                // `Port::recv` has checked member and slot against the ring's sizes.
                let t0 = Instant::now();
                let (member, slot) = (m.member as usize, m.slot as usize);
                apply_to_slot(plans[member].as_mut(), &slabs[member], slot)?;
                slabs[member].set_stage(slot, Stage::Trainer);
                port.send_slot(member, slot, m.seq)?;
                stats.slots += 1;
                stats.busy += t0.elapsed();
            }
            KIND_BYE => byes += 1,
            _ => {}
        }
    }
    Ok(stats)
}
