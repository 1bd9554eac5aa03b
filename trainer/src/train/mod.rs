//! Training through the pipeline: the trainer child acts (epsilon-greedy with the learner's
//! latest weights) on the main thread while the learner trains on a second thread, so acting
//! and learning overlap on our two cores. Greedy test episodes, checkpoints and resume live
//! here; the run's configuration is `config.rs`, its metrics `metrics.rs`, the learning itself
//! `learn/`.

pub mod budget;
pub mod config;
pub mod evaluate;
pub mod marl_eval;
pub mod metrics;
pub mod reference;

pub use config::{paper_designs_dir, preset_overrides, preset_then, protocol_files, resolve_paper_spec, RunSection, TrainConfig, PRESETS};
pub use metrics::{read_metrics, CheckpointWritten, Metrics, MetricsResume, MetricsRow};

use crate::dataset::{Dataset, DatasetHeader, Trajectory};
use crate::episode::{Episode, EpisodeDims};
use crate::learn::methods::AgentNet;
use crate::learn::{Controller, LearnConfig, LearnRng, Learner};
use crate::pipeline::Actor;
use anyhow::{bail, Context, Result};
use lmac_shm_schema::{Slot, FLAG_FIRST};
use parking_lot::Mutex;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::sync::Arc;
use std::time::Instant;

/// When the learner owes updates, as a function of the episodes collected so far: none until
/// `first_episode` (the buffer must hold a batch first), then `ratio` per episode, counting
/// the episode that completes the batch (pymarl trains right after inserting it).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct UpdateSchedule {
    pub ratio: f64,
    pub first_episode: u64,
    pub updates_before: u64,
}

impl UpdateSchedule {
    /// For a learner that has added `episodes`, done `updates` and holds `buffered` episodes:
    /// a fresh run owes its first update at episode `batch_size`; a run resumed without its
    /// buffer refills `batch_size` episodes first; one resumed with it goes on at once.
    pub fn new(ratio: f64, batch_size: usize, episodes: u64, updates: u64, buffered: usize) -> Self {
        let refill = (batch_size.saturating_sub(buffered) as u64).max(1);
        UpdateSchedule { ratio, first_episode: episodes + refill, updates_before: updates }
    }

    /// Updates owed once `episodes` episodes have been collected.
    pub fn due(&self, episodes: u64) -> u64 {
        if episodes < self.first_episode {
            return self.updates_before;
        }
        self.updates_before + (((episodes - self.first_episode + 1) as f64) * self.ratio).floor() as u64
    }
}

/// What the learner thread shares with the actor.
#[derive(Default)]
struct Shared {
    /// Newest acting weights, taken by the actor.
    agent: Option<AgentNet>,
    updates: u64,
    /// The method's terms of the last update.
    method: Vec<(&'static str, f32)>,
    loss: Option<f32>,
    grad_norm: Option<f32>,
    q_taken_mean: Option<f32>,
    error: Option<String>,
    last_checkpoint: Option<PathBuf>,
    /// Checkpoints written and not yet logged to `metrics.jsonl`.
    checkpoints: Vec<CheckpointWritten>,
}

enum ToLearner {
    Episode(Episode),
    Checkpoint,
    /// A test phase scored better than any before: keep the learner's state as the best
    /// checkpoint (what a final evaluation reads).
    SaveBest(BestTest),
}

/// The best test phase so far, saved next to the best checkpoint (`best_test.json`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct BestTest {
    pub test_return: f64,
    pub t_env: u64,
}

/// The best test phase of a run so far, if one was saved. A file that cannot be read is
/// reported and treated as none (the next best test phase rewrites it).
pub fn read_best_test(run_dir: &Path) -> Option<BestTest> {
    let path = run_dir.join("best_test.json");
    let bytes = std::fs::read(&path).ok()?;
    match serde_json::from_slice(&bytes) {
        Ok(b) => Some(b),
        Err(e) => {
            eprintln!("lmac: trainer: ignoring {}: {e}", path.display());
            None
        }
    }
}

/// The actor side of training: epsilon-greedy acting, test episodes, metrics.
pub struct TrainActor {
    cfg: TrainConfig,
    learn: LearnConfig,
    controllers: Vec<Controller>,
    rng: LearnRng,
    dims: EpisodeDims,
    /// Per member, per env: is the current episode a greedy test episode?
    testing: Vec<Vec<bool>>,
    /// Per member, per env: whether each episode started and not yet reported done is a test
    /// episode, oldest first. `act` may see an env's next episode start before or after
    /// `episode_done` gets the one that ended, so the finished episode's own flag is looked up
    /// here, never in `testing` (which already belongs to the next episode).
    started_tests: Vec<Vec<std::collections::VecDeque<bool>>>,
    test_pending: usize,
    test_returns: Vec<(f32, bool)>,
    /// The run reached its step budget and asked for its final test phase (a run always ends
    /// with a test at its last step, so its final return is measured there).
    final_test: bool,
    next_test: u64,
    next_log: u64,
    /// A metrics row fell due during a test phase: the test phase's row carries it, so no t_env
    /// gets two rows (a training row and a test row at the same step).
    log_due: bool,
    next_checkpoint: u64,
    t_env: u64,
    episodes: u64,
    train_returns: Vec<f32>,
    tx: mpsc::Sender<ToLearner>,
    shared: Arc<Mutex<Shared>>,
    episodes_sent: u64,
    schedule: UpdateSchedule,
    metrics: Metrics,
    /// A metrics write that failed: it ends the run.
    failed: Option<String>,
    started: Instant,
    /// `wall_s` already spent by earlier segments of a resumed run.
    wall_offset: f64,
    t_env_at_start: u64,
    scratch_first: Vec<bool>,
    bar: Option<indicatif::ProgressBar>,
    last_test_return: Option<f64>,
    /// The best test phase so far (its checkpoint is in `best_checkpoint_dir`).
    best_test: Option<BestTest>,
    /// Checkpoints asked of the learner and not yet logged.
    checkpoints_pending: u64,
    /// The trajectory dataset being collected once training is done (`run.dataset_episodes`).
    dataset: Vec<Trajectory>,
    /// Observation columns without messages (what the dataset keeps).
    obs_dim: usize,
}

impl TrainActor {
    /// A test phase is asked for or under way (a running test episode is in `started_tests`
    /// until it is reported done).
    fn test_in_progress(&self) -> bool {
        self.test_pending > 0 || !self.test_returns.is_empty() || self.started_tests.iter().flatten().any(|q| q.contains(&true))
    }

    /// Training is done and the dataset is being collected (no learning, no test phases).
    fn collecting(&self) -> bool {
        self.t_env >= self.cfg.run.steps && self.cfg.run.dataset_episodes > 0
    }

    fn epsilon(&self) -> f32 {
        match self.cfg.run.dataset_epsilon {
            Some(e) if self.collecting() => e,
            _ => self.learn.epsilon_at(self.t_env),
        }
    }

    fn wait_for_learner(&self) {
        // Keep updates per episode at the configured ratio: acting waits while the learner lags
        // by more than two updates.
        let due = self.schedule.due(self.episodes_sent);
        loop {
            let s = self.shared.lock();
            if s.error.is_some() || s.updates + 2 >= due {
                return;
            }
            drop(s);
            std::thread::sleep(std::time::Duration::from_micros(500));
        }
    }

    fn fail(&mut self, e: anyhow::Error) {
        if self.failed.is_none() {
            self.failed = Some(format!("{e:#}"));
        }
    }

    /// Log the checkpoints the learner wrote since the last call.
    fn log_checkpoints(&mut self) {
        let written = std::mem::take(&mut self.shared.lock().checkpoints);
        self.checkpoints_pending = self.checkpoints_pending.saturating_sub(written.len() as u64);
        for c in &written {
            if let Err(e) = self.metrics.checkpoint(c) {
                self.fail(e);
            }
        }
    }

    fn log(&mut self, test: Option<(f64, f64)>) {
        // A checkpoint asked for at an earlier step is logged before this row, so metrics.jsonl
        // stays in t_env order even when the learner writes it late (behind a best-checkpoint
        // save or a backlog of updates). Checkpoints are rare: this waits at most once per one.
        let deadline = Instant::now() + std::time::Duration::from_secs(60);
        while self.checkpoints_pending > 0 && Instant::now() < deadline && self.shared.lock().error.is_none() {
            self.log_checkpoints();
            if self.checkpoints_pending > 0 {
                std::thread::sleep(std::time::Duration::from_millis(2));
            }
        }
        let s = self.shared.lock();
        let secs = self.started.elapsed().as_secs_f64();
        let row = MetricsRow {
            t_env: self.t_env,
            episodes: self.episodes,
            updates: s.updates,
            wall_s: self.wall_offset + secs,
            env_steps_per_s: (self.t_env - self.t_env_at_start) as f64 / secs.max(1e-9),
            epsilon: self.epsilon(),
            train_return_mean: ((test.is_none() || self.log_due) && !self.train_returns.is_empty())
                .then(|| self.train_returns.iter().map(|&r| r as f64).sum::<f64>() / self.train_returns.len() as f64),
            test_return_mean: test.map(|t| t.0),
            test_win_rate: test.map(|t| t.1),
            loss: s.loss,
            grad_norm: s.grad_norm,
            q_taken_mean: s.q_taken_mean,
            method: s.method.iter().map(|&(k, v)| (k.to_string(), v)).collect(),
        };
        drop(s);
        if test.is_none() || self.log_due {
            self.train_returns.clear();
        }
        self.log_due = false;
        if let Err(e) = self.metrics.write(&row) {
            self.fail(e);
        }
    }
}

impl Actor for TrainActor {
    fn act(&mut self, member: usize, slot: &Slot<'_>, obs_width: usize, actions: &mut [i32]) {
        if let Some(agent) = self.shared.lock().agent.take() {
            // Each env switches to these weights when its next episode starts.
            for c in &mut self.controllers {
                c.offer_agent(agent.clone());
            }
        }
        let l = slot.layout();
        assert_eq!(l.row_width, obs_width, "the slab reserves exactly the protocol's message columns");
        self.scratch_first.clear();
        for e in 0..l.num_envs {
            let first = slot.env_meta(e).2 & FLAG_FIRST != 0;
            self.scratch_first.push(first);
            if first {
                // Start a greedy test episode here if a test phase wants more.
                self.testing[member][e] = self.test_pending > 0;
                self.started_tests[member][e].push_back(self.testing[member][e]);
                if self.test_pending > 0 {
                    self.test_pending -= 1;
                }
            }
        }
        let state = if self.learn.agent_sees_state { Some(slot.state()) } else { None };
        let eps = self.epsilon();
        let acts = self.controllers[member].select_actions(
            slot.obs(),
            state,
            slot.last_actions(),
            slot.avail(),
            &self.scratch_first,
            eps,
            &mut self.rng,
        );
        actions.copy_from_slice(&acts);
        // Test envs act greedily on the same Q-values.
        let (n, a) = (self.dims.n_agents, self.dims.n_actions);
        let q = self.controllers[member].last_q();
        let avail = slot.avail();
        for e in (0..l.num_envs).filter(|&e| self.testing[member][e]) {
            for ag in 0..n {
                let r = e * n + ag;
                let (qs, av) = (&q[r * a..(r + 1) * a], &avail[r * a..(r + 1) * a]);
                actions[r] = crate::learn::controller::greedy_available(qs, av).unwrap_or(0) as i32;
            }
        }
    }

    fn episode_done(&mut self, member: usize, env: usize, ep: Episode, won: bool) {
        if self.started_tests[member][env].pop_front().unwrap_or(false) {
            self.test_returns.push((ep.team_return(), won));
            if self.test_returns.len() >= self.cfg.run.test_episodes {
                let n = self.test_returns.len() as f64;
                let ret = self.test_returns.iter().map(|x| x.0 as f64).sum::<f64>() / n;
                let win = self.test_returns.iter().filter(|x| x.1).count() as f64 / n;
                self.test_returns.clear();
                self.last_test_return = Some(ret);
                self.log(Some((ret, win)));
                if self.best_test.is_none_or(|b| ret > b.test_return) {
                    let best = BestTest { test_return: ret, t_env: self.t_env };
                    self.best_test = Some(best);
                    let _ = self.tx.send(ToLearner::SaveBest(best));
                }
            }
            return;
        }
        if self.collecting() {
            if self.dataset.len() < self.cfg.run.dataset_episodes {
                self.dataset.push(Trajectory::from_episode(&ep, self.dims.n_agents, self.obs_dim));
                if let Some(b) = &self.bar {
                    b.set_message(format!("collecting the dataset: {}/{} episodes", self.dataset.len(), self.cfg.run.dataset_episodes));
                }
            }
            return;
        }
        if self.t_env >= self.cfg.run.steps {
            // Past the budget, waiting for the final test phase: not trained on, not counted.
            return;
        }
        self.t_env += ep.len as u64;
        self.episodes += 1;
        self.train_returns.push(ep.team_return());
        if self.tx.send(ToLearner::Episode(ep)).is_ok() {
            self.episodes_sent += 1;
        }
        if self.t_env >= self.next_test {
            self.next_test = budget::next_multiple(self.t_env, self.cfg.run.test_interval);
            self.test_pending = self.cfg.run.test_episodes;
        }
        if self.t_env >= self.cfg.run.steps && !self.final_test {
            self.final_test = true;
            if !self.test_in_progress() {
                self.test_pending = self.cfg.run.test_episodes;
            }
        }
        if self.t_env >= self.next_log {
            self.next_log = budget::next_multiple(self.t_env, self.cfg.run.log_interval);
            if self.test_in_progress() && self.cfg.run.test_episodes > 0 {
                self.log_due = true; // written with the test phase's row, at its t_env
            } else {
                self.log(None);
            }
        }
        if self.t_env >= self.next_checkpoint {
            self.next_checkpoint = budget::next_multiple(self.t_env, self.cfg.run.checkpoint_interval);
            if self.tx.send(ToLearner::Checkpoint).is_ok() {
                self.checkpoints_pending += 1;
            }
        }
        self.log_checkpoints();
        if let Some(b) = &self.bar {
            b.set_position(self.t_env.min(self.cfg.run.steps));
            let upd = self.shared.lock().updates;
            b.set_message(format!(
                "eps {:.2} updates {upd} test return {}",
                self.epsilon(),
                self.last_test_return.map_or("-".into(), |r| format!("{r:.3}"))
            ));
        }
        self.wait_for_learner();
    }

    fn finished(&self) -> bool {
        (self.t_env >= self.cfg.run.steps && self.dataset.len() >= self.cfg.run.dataset_episodes && !self.test_in_progress())
            || self.failed.is_some()
            || self.shared.lock().error.is_some()
    }
}

/// Where a run stores its trajectory dataset (`run.dataset_episodes`).
pub fn dataset_dir(run_dir: &Path) -> PathBuf {
    run_dir.join("dataset")
}

fn save_dataset(run_dir: &Path, actor: &TrainActor, args: &crate::pipeline::TrainerArgs) -> Result<()> {
    let s = &args.schema;
    let eps = actor.epsilon();
    let header = DatasetHeader {
        env: actor.cfg.run.env.clone(),
        n_agents: s.n_agents,
        obs_dim: s.obs_dim,
        state_dim: s.state_dim,
        n_actions: s.n_actions,
        episode_limit: s.episode_limit,
        protocol: args.protocol.to_string(),
        policy: format!(
            "{} ({} mixer) after {} env steps, epsilon-greedy with epsilon {eps:.3}",
            actor.cfg.run.algo,
            format!("{:?}", actor.learn.mixer).to_lowercase(),
            actor.t_env
        ),
        seed: actor.learn.seed,
    };
    let ds = Dataset { header, episodes: actor.dataset.clone() };
    let dir = dataset_dir(run_dir);
    ds.save(&dir).with_context(|| format!("saving the dataset to {}", dir.display()))?;
    eprintln!("lmac: trainer: dataset of {} episodes saved in {}", ds.episodes.len(), dir.display());
    Ok(())
}

/// Where the learner keeps its latest checkpoint inside a run directory.
pub fn checkpoint_dir(run_dir: &Path) -> PathBuf {
    run_dir.join("checkpoint")
}

/// Where the learner keeps the checkpoint of the best test phase so far (without the replay
/// buffer), with `best_test.json` beside it in the run directory.
pub fn best_checkpoint_dir(run_dir: &Path) -> PathBuf {
    run_dir.join("checkpoint_best")
}

/// Refuse to start `run_dir` from t_env 0 when it has no usable checkpoint but its metrics
/// show it trained before (its checkpoint was lost or moved): starting again would drop every
/// row. Says what to do instead.
pub fn refuse_restart_over_metrics(run_dir: &Path) -> Result<()> {
    let logged = metrics::logged_t_env(run_dir);
    if logged > 0 {
        let ck = checkpoint_dir(run_dir);
        bail!(
            "{}: no usable checkpoint ({}, {}.old or a complete {}.tmp), but its metrics go up to t_env {logged}: \
             refusing to train it again from t_env 0 over them. Restore the checkpoint, or move metrics.csv and \
             metrics.jsonl away to start this run afresh",
            run_dir.display(),
            ck.display(),
            ck.display(),
            ck.display()
        );
    }
    Ok(())
}

/// The trainer child's training entry point: build (or resume) the learner, start its thread,
/// run the pipeline with the training actor, and finish with a checkpoint.
pub fn train_in_child(run_dir: &Path, args: &crate::pipeline::TrainerArgs, progress: bool) -> Result<crate::pipeline::TrainerReport> {
    let cfg = TrainConfig::load(run_dir)?;
    let learn = cfg.effective_learn()?;
    let schema = &args.schema;
    let dims = EpisodeDims {
        n_agents: schema.n_agents,
        obs_width: schema.obs_dim + args.msg_used,
        state_dim: schema.state_dim,
        n_actions: schema.n_actions,
    };
    let device = crate::learn::Device::default();
    let ck = checkpoint_dir(run_dir);
    let agent_cfg = cfg.agent_config(schema, args.msg_used)?;
    let learner = if crate::learn::checkpoint::checkpoint_exists(&ck) {
        let info = crate::learn::checkpoint::peek_checkpoint(&ck).map_err(|e| anyhow::anyhow!("resuming: {e}"))?;
        if info.dims != dims {
            bail!("checkpoint {} was made for {:?}, this run has {:?}", info.dir.display(), info.dims, dims);
        }
        let l = Learner::load_checkpoint(&ck, device).map_err(|e| anyhow::anyhow!("resuming from {}: {e}", info.dir.display()))?;
        let c = l.counters();
        let buffer_note = if info.has_buffer {
            format!("with its replay buffer ({} episodes)", l.buffer().len())
        } else {
            format!(
                "without a replay buffer (run.save_buffer = false): the learner refills it with {} episodes before it updates again",
                learn.batch_size
            )
        };
        eprintln!("lmac: trainer: resuming from {} at t_env {} ({} updates), {buffer_note}", info.dir.display(), c.t_env, c.updates);
        l
    } else {
        refuse_restart_over_metrics(run_dir)?;
        Learner::with_agent(dims, learn.clone(), agent_cfg, device)?
    };
    let counters = learner.counters();
    let (metrics, earlier) = Metrics::open(run_dir, counters.t_env, learner.agent_config().stat_names())?;
    if earlier.dropped_rows > 0 {
        eprintln!(
            "lmac: trainer: dropped {} metrics rows logged after t_env {} (after the checkpoint, before the run stopped)",
            earlier.dropped_rows, counters.t_env
        );
    }
    if counters.t_env == 0 {
        for w in budget::warnings(&cfg, schema.episode_limit) {
            eprintln!("lmac: trainer: warning: {w}");
        }
    }
    let schedule =
        UpdateSchedule::new(cfg.run.updates_per_episode, learn.batch_size, counters.episodes, counters.updates, learner.buffer().len());
    // One controller per ring member (a sub-batch of an env server), each driving its environments.
    // The ring has env servers x sub-batches members (`args.n_members`).
    let envs_per_slab = cfg.run.envs * cfg.run.servers / args.n_members;
    let controllers = (0..args.n_members).map(|_| Controller::new(&learner, envs_per_slab)).collect();
    let shared = Arc::new(Mutex::new(Shared { updates: counters.updates, ..Default::default() }));
    let (tx, rx) = mpsc::channel::<ToLearner>();
    let learner_thread = {
        let shared = shared.clone();
        let ck = ck.clone();
        let run_dir = run_dir.to_path_buf();
        let save_buffer = cfg.run.save_buffer;
        std::thread::Builder::new()
            .name("learner".into())
            .spawn(move || learner_loop(learner, rx, shared, ck, &run_dir, save_buffer, schedule))?
    };
    let bar = progress.then(|| {
        let b = indicatif::ProgressBar::new(cfg.run.steps);
        b.set_style(
            indicatif::ProgressStyle::with_template("[{elapsed_precise}] {bar:30} {pos}/{len} env steps {per_sec} eta {eta} {msg}")
                .expect("template"),
        );
        b.set_position(counters.t_env);
        b
    });
    let mut actor = TrainActor {
        testing: vec![vec![false; envs_per_slab]; args.n_members],
        started_tests: vec![vec![std::collections::VecDeque::new(); envs_per_slab]; args.n_members],
        test_pending: if counters.t_env == 0 { cfg.run.test_episodes } else { 0 },
        test_returns: Vec::new(),
        final_test: false,
        next_test: budget::next_multiple(counters.t_env, cfg.run.test_interval),
        next_log: budget::next_multiple(counters.t_env, cfg.run.log_interval),
        log_due: false,
        next_checkpoint: budget::next_multiple(counters.t_env, cfg.run.checkpoint_interval),
        t_env: counters.t_env,
        episodes: counters.episodes,
        train_returns: Vec::new(),
        tx,
        shared: shared.clone(),
        episodes_sent: counters.episodes,
        schedule,
        metrics,
        failed: None,
        started: Instant::now(),
        wall_offset: earlier.wall_s,
        t_env_at_start: counters.t_env,
        scratch_first: Vec::new(),
        bar,
        last_test_return: None,
        best_test: read_best_test(run_dir),
        checkpoints_pending: 0,
        dataset: Vec::new(),
        obs_dim: schema.obs_dim,
        rng: LearnRng::seed_from(learn.seed ^ 0xAC70_0000 ^ counters.t_env),
        controllers,
        dims,
        learn,
        cfg,
    };
    let result = crate::pipeline::run(args, &mut actor);
    if let Some(b) = &actor.bar {
        b.finish_and_clear();
    }
    if actor.cfg.run.dataset_episodes > 0 && actor.dataset.len() >= actor.cfg.run.dataset_episodes {
        save_dataset(run_dir, &actor, args)?;
    }
    // Final checkpoint, whatever happened to the pipeline: the learner thread saves on exit.
    drop(std::mem::replace(&mut actor.tx, mpsc::channel().0));
    let joined = learner_thread.join();
    actor.log_checkpoints();
    if let Some(e) = &actor.failed {
        bail!("{e}");
    }
    let s = actor.shared.lock();
    if let Some(e) = &s.error {
        bail!("{e}");
    }
    if joined.is_err() {
        bail!("the learner thread panicked");
    }
    let ck_note = s.last_checkpoint.as_ref().map(|p| format!(" (last checkpoint: {})", p.display())).unwrap_or_default();
    match result {
        Ok(r) => Ok(r),
        Err(e) => bail!("{e}{ck_note}"),
    }
}

fn learner_loop(
    mut learner: Learner,
    rx: mpsc::Receiver<ToLearner>,
    shared: Arc<Mutex<Shared>>,
    ck: PathBuf,
    run_dir: &Path,
    save_buffer: bool,
    schedule: UpdateSchedule,
) {
    // A checkpoint that cannot be written ends the run (its error names the file).
    let save = |learner: &Learner, shared: &Mutex<Shared>| -> bool {
        match learner.save_checkpoint(&ck, save_buffer) {
            Ok(()) => {
                let c = learner.counters();
                let mut s = shared.lock();
                s.last_checkpoint = Some(ck.clone());
                s.checkpoints.push(CheckpointWritten { t_env: c.t_env, episodes: c.episodes, updates: c.updates, path: ck.clone() });
                true
            }
            Err(e) => {
                shared.lock().error.get_or_insert(format!("writing the checkpoint failed: {e}"));
                false
            }
        }
    };
    let mut saved_at = None;
    let mut disconnected = false;
    while !disconnected {
        // Take everything that arrived; block briefly when idle.
        let first = rx.recv_timeout(std::time::Duration::from_millis(50));
        let mut msgs = Vec::new();
        match first {
            Ok(m) => msgs.push(m),
            Err(mpsc::RecvTimeoutError::Disconnected) => disconnected = true,
            Err(mpsc::RecvTimeoutError::Timeout) => {}
        }
        while let Ok(m) = rx.try_recv() {
            msgs.push(m);
        }
        for m in msgs {
            match m {
                ToLearner::Episode(ep) => {
                    if let Err(e) = learner.add_episode(ep) {
                        shared.lock().error = Some(format!("learner: {e}"));
                        return;
                    }
                }
                ToLearner::Checkpoint => {
                    if !save(&learner, &shared) {
                        return;
                    }
                    saved_at = Some(learner.counters());
                }
                ToLearner::SaveBest(best) => {
                    // The checkpoint first, then the record that names it: a crash between the
                    // two leaves an older record, never one without its checkpoint.
                    let saved = learner.save_checkpoint(best_checkpoint_dir(run_dir), false).map_err(|e| e.to_string()).and_then(|()| {
                        let path = run_dir.join("best_test.json");
                        let tmp = path.with_extension("json.tmp");
                        std::fs::write(&tmp, serde_json::to_vec_pretty(&best).expect("a plain struct"))
                            .and_then(|()| std::fs::rename(&tmp, &path))
                            .map_err(|e| format!("{}: {e}", path.display()))
                    });
                    if let Err(e) = saved {
                        shared.lock().error.get_or_insert(format!("writing the best checkpoint failed: {e}"));
                        return;
                    }
                }
            }
        }
        let due = schedule.due(learner.counters().episodes);
        let mut did = false;
        while learner.can_train() && learner.counters().updates < due {
            match learner.train_step() {
                Ok(st) => {
                    if !st.loss.is_finite() || !st.grad_norm.is_finite() {
                        let c = learner.counters();
                        let mut s = shared.lock();
                        s.error = Some(format!(
                            "the loss became {} at update {} (t_env {}); the last good checkpoint is {}",
                            st.loss,
                            c.updates,
                            c.t_env,
                            s.last_checkpoint.as_ref().map_or("none yet".into(), |p| p.display().to_string())
                        ));
                        return;
                    }
                    let mut s = shared.lock();
                    s.updates = learner.counters().updates;
                    s.loss = Some(st.loss);
                    s.grad_norm = Some(st.grad_norm);
                    s.q_taken_mean = Some(st.q_taken_mean);
                    s.method = st.method;
                    did = true;
                }
                Err(e) => {
                    shared.lock().error = Some(format!("learner: {e}"));
                    return;
                }
            }
        }
        if did {
            shared.lock().agent = Some(learner.acting_net().agent);
        }
    }
    // The last checkpoint, unless the one just written already holds this state.
    if saved_at != Some(learner.counters()) {
        save(&learner, &shared);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_update_schedule_starts_with_a_full_batch_and_refills_after_a_resume_without_buffer() {
        // EPyMARL's episode runner: an update right after the 32nd episode, then one per episode.
        let fresh = UpdateSchedule::new(1.0, 32, 0, 0, 0);
        assert_eq!([fresh.due(31), fresh.due(32), fresh.due(33), fresh.due(232)], [0, 1, 2, 201]);
        // The default: one update per 8 episodes.
        let slow = UpdateSchedule::new(0.125, 32, 0, 0, 0);
        assert_eq!([slow.due(32), slow.due(38), slow.due(39), slow.due(32 + 799)], [0, 0, 1, 100]);
        // Resumed at 1000 episodes and 969 updates without the buffer: 32 episodes to refill first.
        let refill = UpdateSchedule::new(1.0, 32, 1000, 969, 0);
        assert_eq!([refill.due(1000), refill.due(1031), refill.due(1032), refill.due(1033)], [969, 969, 970, 971]);
        // With the buffer: on from the next episode.
        let kept = UpdateSchedule::new(1.0, 32, 1000, 969, 5000);
        assert_eq!([kept.due(1000), kept.due(1001)], [969, 970]);
    }
}
