//! The trainer's side of the data plane: receive slots from the protocol runner, copy each env's
//! step into its episode (the trainer's only copy), choose actions, write them into the slot and
//! hand it back to the env server. Counts throughput and checks the data-plane invariants.

use crate::episode::{Episode, EpisodeDims, NextStep};
use lmac_shm_schema::ring::{Port, RingError, RingSpec, KIND_SLOT};
use lmac_shm_schema::{EnvSchema, Slab, Slot, Stage, FLAG_FINAL, FLAG_FIRST, FLAG_PREV_WON};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};
use std::time::{Duration, Instant};

/// Chooses the actions of one batched step. The learner's epsilon-greedy controller implements
/// this too; `RandomActor` is the policy until a learner is attached.
pub trait Actor {
    /// `slot` is owned by the trainer; write `num_envs * n_agents` actions into `actions`.
    fn act(&mut self, member: usize, slot: &Slot<'_>, obs_width: usize, actions: &mut [i32]);
    /// An episode of env `env` of member `member` finished (`won`: the env's success flag).
    fn episode_done(&mut self, _member: usize, _env: usize, _ep: Episode, _won: bool) {}
    /// True when the actor wants the run to end (e.g. a training budget is spent, an error).
    fn finished(&self) -> bool {
        false
    }
}

/// Uniform over the available actions.
pub struct RandomActor {
    rng: StdRng,
}

impl RandomActor {
    pub fn new(seed: u64) -> Self {
        RandomActor { rng: StdRng::seed_from_u64(seed) }
    }
}

impl Actor for RandomActor {
    fn act(&mut self, _member: usize, slot: &Slot<'_>, _obs_width: usize, actions: &mut [i32]) {
        let na = slot.layout().n_actions;
        for (k, av) in slot.avail().chunks_exact(na).enumerate() {
            let n_avail = av.iter().filter(|&&a| a != 0).count();
            actions[k] = if n_avail == 0 {
                0
            } else {
                let pick = self.rng.random_range(0..n_avail);
                crate::learn::controller::nth_available(av, pick).map_or(0, |i| i as i32)
            };
        }
    }
}

/// What the runner's messages must look like, checked on every slot when verifying.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MessageCheck {
    None,
    /// Built-in fullcomm: [obs_j, onehot(j)] for every other agent j.
    FullComm,
    /// A compiled protocol: recompute the messages with an independent plan per member (it sees
    /// the same steps, so it must agree column for column).
    Recompute,
}

pub struct TrainerArgs {
    pub run: String,
    pub schema: EnvSchema,
    pub n_members: usize,
    pub n_slots: usize,
    /// The run's protocol compiled once in this process: its width sizes the episodes (obs_dim
    /// + its message columns), its critical dims configure the method, and
    /// `MessageCheck::Recompute` replays a fresh copy of its plan per member.
    pub compiled: lmac_protocol_runner::CompiledProtocol,
    /// Stop after this many env steps (counted after warm-up).
    pub env_steps: u64,
    /// Batched steps before the clock starts.
    pub warmup_slots: u64,
    pub startup_timeout: Duration,
    pub verify: Option<MessageCheck>,
    /// The protocol the runner applies, as given (recorded with a dataset).
    pub protocol: lmac_protocol_runner::ProtocolSpec,
    /// Draw a progress bar on stderr.
    pub progress: bool,
}

impl TrainerArgs {
    /// Message columns the plan writes (the episode's obs width is obs_dim + this).
    pub fn msg_used(&self) -> usize {
        self.compiled.msg_dim()
    }
}

#[derive(Debug, Default, Serialize, Deserialize)]
pub struct EpisodeSummary {
    pub member: usize,
    pub env: usize,
    pub episode_id: u64,
    pub len: usize,
    pub team_return: f32,
    pub terminated: bool,
    pub truncated: bool,
    pub won: bool,
}

/// What the trainer child reports to the parent when its run ends (a JSON file, `--report`).
#[derive(Debug, Default, Serialize, Deserialize)]
pub struct TrainerReport {
    pub env: String,
    pub members: usize,
    pub envs_per_member: usize,
    pub env_steps: u64,
    pub batched_steps: u64,
    pub seconds: f64,
    pub env_steps_per_s: f64,
    pub episodes: u64,
    pub mean_return: f64,
    /// Time spent in the trainer per batched step (assembly + acting), microseconds.
    pub trainer_us_per_slot: f64,
    pub violation_count: u64,
    pub violations: Vec<String>,
    #[serde(skip)]
    pub episode_log: Vec<EpisodeSummary>,
}

#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    #[error("trainer: {0}")]
    Ring(#[from] RingError),
    #[error("trainer: {0}")]
    Slab(#[from] lmac_shm_schema::SlabError),
    #[error("trainer: protocol: {0}")]
    Protocol(String),
    #[error("trainer: slab {slab}: {problem}")]
    Layout { slab: String, problem: String },
}

/// Where an env's rows stand.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Phase {
    /// No row seen yet.
    Fresh,
    /// An episode is being assembled.
    Open,
    /// A truncated episode's final row was seen; the next row must start a new episode.
    AwaitFirst,
}

/// Per env: the episode being assembled.
struct EnvTrack {
    ep: Episode,
    episode_id: u64,
    expect_step: u32,
    phase: Phase,
}

pub struct Assembler {
    dims: EpisodeDims,
    limit: usize,
    tracks: Vec<Vec<EnvTrack>>,
    /// (member, env, episode id, episode, won)
    pub finished: Vec<(usize, usize, u64, Episode, bool)>,
    violations: Vec<String>,
    violation_count: u64,
}

impl Assembler {
    pub fn new(dims: EpisodeDims, limit: usize, n_members: usize, num_envs: usize) -> Self {
        let tracks = (0..n_members)
            .map(|_| {
                (0..num_envs)
                    .map(|_| EnvTrack { ep: Episode::with_capacity(&dims, limit), episode_id: 0, expect_step: 0, phase: Phase::Fresh })
                    .collect()
            })
            .collect();
        Assembler { dims, limit, tracks, finished: Vec::new(), violations: Vec::new(), violation_count: 0 }
    }

    fn violate(&mut self, msg: String) {
        self.violation_count += 1;
        if self.violations.len() < 20 {
            self.violations.push(msg);
        }
    }

    /// Take in the step of every env in `slot`: close the previous transition with this row's
    /// reward (finishing the episode if it ended) and open the next one with this row's obs. A
    /// truncated episode's final row (`FLAG_FINAL`) becomes the episode's `next` step.
    pub fn ingest(&mut self, member: usize, slot: &Slot<'_>) {
        let l = slot.layout().clone();
        let d = self.dims;
        let (obs, state, avail) = (slot.obs(), slot.state(), slot.avail());
        let (reward, term, trunc) = (slot.reward(), slot.terminated(), slot.truncated());
        let na = l.n_agents * l.n_actions;
        let rows_of = |e: usize| -> Vec<f32> {
            let mut v = Vec::with_capacity(l.n_agents * d.obs_width);
            for a in 0..l.n_agents {
                let base = (e * l.n_agents + a) * l.row_width;
                v.extend_from_slice(&obs[base..base + d.obs_width]);
            }
            v
        };
        for e in 0..l.num_envs {
            let (eid, step, flags) = slot.env_meta(e);
            let (first, last) = (flags & FLAG_FIRST != 0, flags & FLAG_FINAL != 0);
            let (te, tr) = (term[e] != 0, trunc[e] != 0);
            let mut t = std::mem::replace(
                &mut self.tracks[member][e],
                EnvTrack { ep: Episode::default(), episode_id: 0, expect_step: 0, phase: Phase::Fresh },
            );
            if first && last {
                self.violate(format!("member {member} env {e}: a row flagged both first and final (episode {eid})"));
            }
            match t.phase {
                Phase::Open => {
                    // This row's reward/termination belong to the previous step of this env.
                    t.ep.reward.push(reward[e]);
                    t.ep.len += 1;
                    if te && tr {
                        self.violate(format!("member {member} env {e}: episode {} both terminated and truncated", t.episode_id));
                    }
                    if tr && t.ep.len != self.limit {
                        self.violate(format!(
                            "member {member} env {e}: episode {} truncated after {} steps, limit is {}",
                            t.episode_id, t.ep.len, self.limit
                        ));
                    }
                    if t.ep.len > self.limit {
                        self.violate(format!(
                            "member {member} env {e}: episode {} ran {} steps, limit is {}",
                            t.episode_id, t.ep.len, self.limit
                        ));
                    }
                    // A termination is reported on the next episode's first row, a truncation
                    // on the episode's own final row.
                    if te != first || tr != last {
                        self.violate(format!(
                            "member {member} env {e}: episode {} end flags (terminated {te}, truncated {tr}) disagree with the row's flags (first {first}, final {last})",
                            t.episode_id
                        ));
                    }
                    if te || tr {
                        t.ep.terminated = te;
                        t.ep.truncated = tr;
                        if last {
                            t.ep.next = Some(NextStep {
                                obs: rows_of(e),
                                state: state[e * l.state_dim..(e + 1) * l.state_dim].to_vec(),
                                avail: avail[e * na..(e + 1) * na].to_vec(),
                            });
                        }
                        let done = std::mem::replace(&mut t.ep, Episode::with_capacity(&d, self.limit));
                        self.finished.push((member, e, t.episode_id, done, flags & FLAG_PREV_WON != 0));
                    }
                }
                Phase::AwaitFirst => {
                    if !first || te || tr || reward[e] != 0.0 {
                        self.violate(format!(
                            "member {member} env {e}: the row after episode {}'s final row is not a clean first step (first {first}, terminated {te}, truncated {tr}, reward {})",
                            t.episode_id, reward[e]
                        ));
                    }
                }
                Phase::Fresh => {
                    if !first {
                        self.violate(format!("member {member} env {e}: the first step seen is not flagged as an episode start"));
                    }
                }
            }
            if last {
                // The final row is not a step of any episode: the next row starts one.
                if eid != t.episode_id {
                    self.violate(format!("member {member} env {e}: final row of episode {eid}, expected {}", t.episode_id));
                }
                t.phase = Phase::AwaitFirst;
                self.tracks[member][e] = t;
                continue;
            }
            if first {
                if t.phase != Phase::Fresh && eid == t.episode_id {
                    self.violate(format!("member {member} env {e}: a new episode reuses id {eid}"));
                }
                t.episode_id = eid;
                t.expect_step = 0;
            } else if eid != t.episode_id {
                self.violate(format!("member {member} env {e}: episode id changed {} -> {eid} without a first-step flag", t.episode_id));
            }
            if step != t.expect_step {
                self.violate(format!("member {member} env {e}: episode {eid} step {step}, expected {}", t.expect_step));
            }
            t.expect_step = step.wrapping_add(1);
            t.phase = Phase::Open;
            t.ep.obs.extend_from_slice(&rows_of(e));
            t.ep.state.extend_from_slice(&state[e * l.state_dim..(e + 1) * l.state_dim]);
            t.ep.avail.extend_from_slice(&avail[e * na..(e + 1) * na]);
            self.tracks[member][e] = t;
        }
    }

    /// Record the actions chosen for the step just ingested (not on final rows: those actions
    /// are ignored by the env server).
    pub fn record_actions(&mut self, member: usize, actions: &[i32]) {
        let n = self.dims.n_agents;
        for (e, t) in self.tracks[member].iter_mut().enumerate() {
            if t.phase == Phase::Open {
                t.ep.actions.extend_from_slice(&actions[e * n..(e + 1) * n]);
            }
        }
    }

    /// Recompute the messages of `slot` with `plan` on a copy of its rows and compare.
    pub fn recheck_messages(&mut self, member: usize, slot: &Slot<'_>, plan: &mut dyn lmac_protocol_runner::plan::MessagePlan) {
        let l = slot.layout();
        let mut rows = slot.obs().to_vec();
        let first: Vec<bool> = (0..l.num_envs).map(|e| slot.env_meta(e).2 & FLAG_FIRST != 0).collect();
        for row in rows.chunks_exact_mut(l.row_width) {
            row[l.obs_dim..].fill(f32::NAN); // must all be overwritten
        }
        let mut view = lmac_protocol_runner::plan::StepView {
            num_envs: l.num_envs,
            n_agents: l.n_agents,
            obs_dim: l.obs_dim,
            msg_dim: l.msg_dim,
            rows: &mut rows,
            first: &first,
            last_actions: slot.last_actions(),
        };
        plan.apply(&mut view);
        let got = slot.obs();
        for (k, (a, b)) in rows.chunks_exact(l.row_width).zip(got.chunks_exact(l.row_width)).enumerate() {
            if a[l.obs_dim..].iter().zip(&b[l.obs_dim..]).any(|(x, y)| x.to_bits() != y.to_bits()) {
                self.violate(format!(
                    "member {member} env {} agent {}: message columns differ from the recomputed protocol",
                    k / l.n_agents,
                    k % l.n_agents
                ));
            }
        }
    }

    /// Check the message columns against the rule the runner applies.
    pub fn check_messages(&mut self, member: usize, slot: &Slot<'_>, check: MessageCheck) {
        let l = slot.layout();
        let (n, od, rw) = (l.n_agents, l.obs_dim, l.row_width);
        let obs = slot.obs();
        for e in 0..l.num_envs {
            for i in 0..n {
                let row = &obs[(e * n + i) * rw..(e * n + i + 1) * rw];
                let mut expect = Vec::with_capacity(l.msg_dim);
                if check == MessageCheck::FullComm {
                    for j in (0..n).filter(|&j| j != i) {
                        expect.extend_from_slice(&obs[(e * n + j) * rw..(e * n + j) * rw + od]);
                        expect.extend((0..n).map(|k| if k == j { 1.0 } else { 0.0 }));
                    }
                }
                expect.resize(l.msg_dim, 0.0);
                if row[od..] != expect[..] {
                    self.violate(format!("member {member} env {e} agent {i}: message columns differ from the {check:?} rule"));
                }
            }
        }
    }
}

/// Run the trainer loop with `actor` until `env_steps` env steps have been collected.
pub fn run(args: &TrainerArgs, actor: &mut dyn Actor) -> Result<TrainerReport, PipelineError> {
    let mut slabs = Vec::new();
    for s in 0..args.n_members {
        slabs.push(Slab::open(&lmac_protocol_runner::runner::slab_name(&args.run, s), &args.schema, args.startup_timeout)?);
    }
    let l0 = slabs[0].layout().clone();
    // Every slab of the run must share one layout (actions and episodes are sized from it), with
    // the ring's slot count and the protocol's message columns.
    for (s, slab) in slabs.iter().enumerate() {
        let p = slab.layout().params();
        let problem = if p != l0.params() {
            Some(format!("layout {p:?} differs from member 0's {:?}", l0.params()))
        } else if p.n_slots != args.n_slots {
            Some(format!("{} slots, the ring has {}", p.n_slots, args.n_slots))
        } else if p.msg_dim != args.msg_used() {
            Some(format!("{} message columns, the protocol writes {}", p.msg_dim, args.msg_used()))
        } else {
            None
        };
        if let Some(problem) = problem {
            return Err(PipelineError::Layout { slab: lmac_protocol_runner::runner::slab_name(&args.run, s), problem });
        }
    }
    let dims = EpisodeDims {
        n_agents: args.schema.n_agents,
        obs_width: args.schema.obs_dim + args.msg_used(),
        state_dim: args.schema.state_dim,
        n_actions: args.schema.n_actions,
    };
    let mut port =
        Port::new(RingSpec { run: args.run.clone(), n_members: args.n_members, n_slots: args.n_slots, role: Stage::Trainer, member: 0 })?;
    port.set_startup_timeout(args.startup_timeout);
    let mut recheck = Vec::new();
    if args.verify == Some(MessageCheck::Recompute) {
        for _ in 0..args.n_members {
            recheck.push(args.compiled.plan.fresh());
        }
    }
    let mut asm = Assembler::new(dims, args.schema.episode_limit, args.n_members, l0.num_envs);
    let mut actions = vec![0i32; l0.num_envs * l0.n_agents];
    let mut report =
        TrainerReport { env: args.schema.name.clone(), members: args.n_members, envs_per_member: l0.num_envs, ..Default::default() };
    let bar = if args.progress {
        let b = indicatif::ProgressBar::new(args.env_steps);
        b.set_style(
            indicatif::ProgressStyle::with_template(
                "{spinner} [{elapsed_precise}] {bar:32} {pos}/{len} env steps {per_sec} eta {eta} {msg}",
            )
            .expect("valid template"),
        );
        Some(b)
    } else {
        None
    };
    let (mut slots_seen, mut timed_steps) = (0u64, 0u64);
    // The clock starts after the warm-up slots (at least the first, which carries start-up).
    let warmup = args.warmup_slots.max(1);
    let mut t_start: Option<Instant> = None;
    let mut busy = Duration::ZERO;
    let mut return_sum = 0.0f64;
    while timed_steps < args.env_steps && !actor.finished() {
        let Some(m) = port.recv(Duration::from_millis(500))? else { continue };
        if m.kind != KIND_SLOT {
            continue;
        }
        let t0 = Instant::now();
        let (member, idx) = (m.member as usize, m.slot as usize);
        {
            let mut slot = slabs[member].slot(idx, Stage::Trainer)?;
            match args.verify {
                Some(MessageCheck::Recompute) => asm.recheck_messages(member, &slot, recheck[member].as_mut()),
                Some(check) => asm.check_messages(member, &slot, check),
                None => {}
            }
            asm.ingest(member, &slot);
            actor.act(member, &slot, dims.obs_width, &mut actions);
            slot.actions_mut().copy_from_slice(&actions);
            asm.record_actions(member, &actions);
        }
        slabs[member].set_stage(idx, Stage::Env);
        port.send_slot(member, idx, m.seq)?;
        for (s, e, eid, ep, won) in asm.finished.drain(..) {
            report.episodes += 1;
            return_sum += ep.team_return() as f64;
            report.episode_log.push(EpisodeSummary {
                member: s,
                env: e,
                episode_id: eid,
                len: ep.len,
                team_return: ep.team_return(),
                terminated: ep.terminated,
                truncated: ep.truncated,
                won,
            });
            actor.episode_done(s, e, ep, won);
        }
        slots_seen += 1;
        if slots_seen == warmup {
            t_start = Some(Instant::now());
        }
        if slots_seen > warmup {
            timed_steps += l0.num_envs as u64;
            report.batched_steps += 1;
            busy += t0.elapsed();
            if let Some(b) = &bar {
                b.set_position(timed_steps.min(args.env_steps));
            }
        }
    }
    let secs = t_start.map_or(0.0, |t| t.elapsed().as_secs_f64());
    if let Some(b) = bar {
        b.finish_and_clear();
    }
    for s in 0..args.n_members {
        port.send_bye(s)?;
    }
    // Keep the publishers alive until the env servers have taken their goodbye.
    let _ = port.wait_peers_gone(Duration::from_secs(5));
    report.env_steps = timed_steps;
    report.seconds = secs;
    report.env_steps_per_s = if secs > 0.0 { timed_steps as f64 / secs } else { 0.0 };
    report.mean_return = if report.episodes > 0 { return_sum / report.episodes as f64 } else { 0.0 };
    report.trainer_us_per_slot = if report.batched_steps > 0 { busy.as_secs_f64() * 1e6 / report.batched_steps as f64 } else { 0.0 };
    report.violation_count = asm.violation_count;
    report.violations = asm.violations.clone();
    Ok(report)
}
