//! `lmac evaluate`, the trainer's side: greedy test episodes with a run's last checkpoint,
//! optionally with the method's test-time settings changed (NDQ's message cut, MAIC's pruning),
//! through the same pipeline as training (env servers, protocol runner, shared memory).

use std::collections::VecDeque;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use lmac_shm_schema::{Slot, FLAG_FIRST};
use serde::{Deserialize, Serialize};

use super::{best_checkpoint_dir, checkpoint_dir, TrainConfig};
use crate::episode::Episode;
use crate::learn::{Controller, Learner};
use crate::pipeline::{Actor, TrainerArgs};

/// What to evaluate, written by `lmac evaluate` for its trainer child.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct EvalSpec {
    /// Greedy test episodes to run.
    pub episodes: usize,
    /// `[method]` settings that replace the run's for this evaluation (test-time ones only).
    pub method: toml::Table,
    /// Evaluate the best test phase's checkpoint (`checkpoint_best/`) instead of the last one;
    /// a run without one falls back to its last checkpoint (the result says which).
    #[serde(default)]
    pub best: bool,
}

/// One evaluation of one run's checkpoint.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct EvalResult {
    pub run_dir: PathBuf,
    pub algo: String,
    pub seed: u64,
    /// Which checkpoint was evaluated: "best" or "last".
    pub checkpoint: String,
    /// The checkpoint's env steps and updates.
    pub t_env: u64,
    pub updates: u64,
    /// The `[method]` settings changed for this evaluation.
    pub method: toml::Table,
    pub episodes: usize,
    pub mean_return: f64,
    pub std_return: f64,
    pub win_rate: f64,
    pub returns: Vec<f32>,
}

impl EvalSpec {
    /// Where the child writes its result for a spec file.
    pub fn result_path(spec: &Path) -> PathBuf {
        spec.with_extension("result.json")
    }
}

/// Greedy actions in every environment; the first `want` episodes that start are counted.
struct EvalActor {
    controllers: Vec<Controller>,
    agent_sees_state: bool,
    want: usize,
    started: usize,
    /// Per member, per env: whether each started, not yet finished episode is counted, oldest
    /// first (an env's next episode may start before the finished one is reported).
    counted: Vec<Vec<VecDeque<bool>>>,
    results: Vec<(f32, bool)>,
    first: Vec<bool>,
}

impl Actor for EvalActor {
    fn act(&mut self, member: usize, slot: &Slot<'_>, _obs_width: usize, actions: &mut [i32]) {
        let l = slot.layout();
        self.first.clear();
        for e in 0..l.num_envs {
            let first = slot.env_meta(e).2 & FLAG_FIRST != 0;
            self.first.push(first);
            if first {
                self.counted[member][e].push_back(self.started < self.want);
                self.started += 1;
            }
        }
        let state = if self.agent_sees_state { Some(slot.state()) } else { None };
        let acts = self.controllers[member].greedy_actions(slot.obs(), state, slot.last_actions(), slot.avail(), &self.first);
        actions.copy_from_slice(&acts);
    }

    fn episode_done(&mut self, member: usize, env: usize, ep: Episode, won: bool) {
        if self.counted[member][env].pop_front().unwrap_or(false) {
            self.results.push((ep.team_return(), won));
        }
    }

    fn finished(&self) -> bool {
        self.results.len() >= self.want
    }
}

/// Run the evaluation `spec_path` describes on `run_dir`'s last checkpoint; the result is
/// written next to the spec (see [`EvalSpec::result_path`]) and returned.
pub fn evaluate_in_child(run_dir: &Path, spec_path: &Path, args: &TrainerArgs) -> Result<EvalResult> {
    let spec: EvalSpec =
        serde_json::from_slice(&crate::safe_fs::read_capped(spec_path, crate::safe_fs::TEXT_CAP).context("reading the evaluation")?)
            .with_context(|| format!("{}", spec_path.display()))?;
    if spec.episodes == 0 {
        bail!("evaluate: 0 episodes asked for");
    }
    let mut cfg = TrainConfig::load(run_dir)?;
    let best = best_checkpoint_dir(run_dir);
    let use_best = spec.best && crate::learn::checkpoint::checkpoint_exists(&best);
    let ck = if use_best { best } else { checkpoint_dir(run_dir) };
    if !crate::learn::checkpoint::checkpoint_exists(&ck) {
        bail!("{} has no checkpoint to evaluate", run_dir.display());
    }
    let learner = Learner::load_checkpoint(&ck, crate::learn::Device::default()).map_err(|e| anyhow::anyhow!("{}: {e}", ck.display()))?;
    cfg.method.extend(spec.method.clone());
    let wanted = cfg.agent_config(&args.schema, &args.compiled)?;
    let mut agent = learner.acting_net().agent;
    agent.retune(learner.agent_config(), &wanted).map_err(|e| anyhow::anyhow!("{}: {e}", run_dir.display()))?;

    let envs_per_slab = cfg.run.envs * cfg.run.servers / args.n_members;
    let controllers = (0..args.n_members)
        .map(|_| {
            let mut c = Controller::new(&learner, envs_per_slab);
            c.set_agent(agent.clone());
            c
        })
        .collect();
    let mut actor = EvalActor {
        controllers,
        agent_sees_state: learner.config().agent_sees_state,
        want: spec.episodes,
        started: 0,
        counted: vec![vec![VecDeque::new(); envs_per_slab]; args.n_members],
        results: Vec::new(),
        first: Vec::new(),
    };
    crate::pipeline::run(args, &mut actor)?;
    if actor.results.len() < spec.episodes {
        bail!("the pipeline stopped after {} of {} evaluation episodes", actor.results.len(), spec.episodes);
    }
    let returns: Vec<f32> = actor.results.iter().map(|r| r.0).collect();
    let n = returns.len() as f64;
    let mean = returns.iter().map(|&r| r as f64).sum::<f64>() / n;
    let var = returns.iter().map(|&r| (r as f64 - mean).powi(2)).sum::<f64>() / n;
    let c = learner.counters();
    let result = EvalResult {
        run_dir: run_dir.to_path_buf(),
        algo: cfg.run.algo.clone(),
        checkpoint: if use_best { "best" } else { "last" }.into(),
        seed: cfg.learn.seed,
        t_env: c.t_env,
        updates: c.updates,
        method: spec.method,
        episodes: returns.len(),
        mean_return: mean,
        std_return: var.sqrt(),
        win_rate: actor.results.iter().filter(|r| r.1).count() as f64 / n,
        returns,
    };
    let out = EvalSpec::result_path(spec_path);
    crate::safe_fs::write_replace(&out, &serde_json::to_vec_pretty(&result)?).context("writing the evaluation's result")?;
    Ok(result)
}
