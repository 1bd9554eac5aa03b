//! Training through the pipeline: the trainer child acts (epsilon-greedy with the learner's
//! latest weights) on the main thread while the learner trains on a second thread, so acting
//! and learning overlap on our two cores. Greedy test episodes, metrics (CSV + JSON lines),
//! atomic checkpoints and resume live here; the learning itself is `learn/`.

use crate::design::dataset::{Dataset, DatasetHeader, Trajectory};
use crate::episode::{Episode, EpisodeDims};
use crate::learn::{Controller, LearnConfig, LearnRng, Learner, MixerKind};
use crate::pipeline::Actor;
use anyhow::{bail, Context, Result};
use lmac_shm_schema::{Slot, FLAG_FIRST};
use parking_lot::Mutex;
use serde::{Deserialize, Serialize};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::sync::Arc;
use std::time::Instant;

/// Everything about a run that is not a learner hyperparameter.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RunSection {
    pub env: String,
    /// qmix | vdn | qplex | fullcomm | qmix-state (see `Algo`).
    pub algo: String,
    /// Environment steps to train for.
    pub steps: u64,
    /// Environments per env server.
    pub envs: usize,
    /// Env server processes.
    pub servers: usize,
    /// Sub-batches per env server (double buffering, see `supervisor::RunPlan`); 0: two when
    /// `envs` is even and the schema allows it (`double_buffer`), else one.
    pub sub_batches: usize,
    /// Gradient updates per collected (training) episode. pymarl does one update per run of
    /// `batch_size_run` parallel episodes (EPyMARL's parallel runner: 1/8 to 1/10); 0.125
    /// matches 8 parallel environments.
    pub updates_per_episode: f64,
    /// Env steps between greedy test phases.
    pub test_interval: u64,
    /// Greedy episodes per test phase.
    pub test_episodes: usize,
    /// Env steps between training-metric rows.
    pub log_interval: u64,
    /// Env steps between checkpoints.
    pub checkpoint_interval: u64,
    /// Also store the replay buffer in checkpoints (exact resumption; large).
    pub save_buffer: bool,
    /// Message protocol for the runner: empty = the algorithm's own (`none` for qmix, vdn,
    /// qplex and qmix-state, `fullcomm` for fullcomm); else protocol files joined by '+'
    /// (`phase0.json+phase1.json`), for the message-less algorithms only.
    pub protocol: String,
    /// After `steps`, keep acting epsilon-greedy without learning for this many episodes and
    /// store them as the trajectory dataset B in `<run dir>/dataset` (protocol design).
    pub dataset_episodes: usize,
    /// Epsilon while collecting the dataset; absent = the schedule's value at the end of training.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub dataset_epsilon: Option<f32>,
}

impl Default for RunSection {
    fn default() -> Self {
        RunSection {
            env: "lbf:8x8-2p-2f-s1-coop".into(),
            algo: "qmix".into(),
            steps: 2_000_000,
            envs: 16,
            servers: 2,
            sub_batches: 0,
            updates_per_episode: 0.125,
            test_interval: 10_000,
            test_episodes: 32,
            log_interval: 5_000,
            checkpoint_interval: 100_000,
            save_buffer: false,
            protocol: String::new(),
            dataset_episodes: 0,
            dataset_epsilon: None,
        }
    }
}

/// The resolved configuration of one run, saved as `config.toml` in its directory.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrainConfig {
    pub run: RunSection,
    pub learn: LearnConfig,
}

/// An algorithm = a protocol for the runner + what the agents see; the backbone (mixer) is
/// orthogonal (`learn.mixer`).
pub struct Algo {
    pub protocol: &'static str,
    pub sees_state: bool,
    pub mixer: Option<MixerKind>,
}

pub fn algo(name: &str) -> Result<Algo> {
    Ok(match name {
        "qmix" => Algo { protocol: "none", sees_state: false, mixer: Some(MixerKind::Qmix) },
        "vdn" => Algo { protocol: "none", sees_state: false, mixer: Some(MixerKind::Vdn) },
        "qplex" => Algo { protocol: "none", sees_state: false, mixer: Some(MixerKind::Qplex) },
        "fullcomm" => Algo { protocol: "fullcomm", sees_state: false, mixer: None },
        "qmix-state" => Algo { protocol: "none", sees_state: true, mixer: None },
        other => bail!("run.algo: unknown algorithm {other:?}; use qmix, vdn, qplex, fullcomm or qmix-state"),
    })
}

impl TrainConfig {
    /// Read a config file (TOML), apply `key=value` overrides (dotted paths such as
    /// `learn.lr=0.001`, `run.envs=8`), then check it. Errors name the field.
    pub fn resolve(file: Option<&Path>, overrides: &[String]) -> Result<TrainConfig> {
        let mut v: toml::Value = match file {
            Some(p) => toml::from_str(&std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?)
                .with_context(|| format!("{}: not valid TOML", p.display()))?,
            None => toml::Value::Table(Default::default()),
        };
        for o in overrides {
            let (key, val) = o.split_once('=').with_context(|| format!("override {o:?} must look like section.key=value"))?;
            // A TOML value, else the text as a string. Exactly one key: a value with a newline
            // cannot smuggle in other keys (`1\nother = 2`) or leave `x` out.
            let parsed: toml::Value = toml::from_str::<toml::Table>(&format!("x = {val}"))
                .ok()
                .filter(|t| t.len() == 1)
                .and_then(|mut t| t.remove("x"))
                .unwrap_or_else(|| toml::Value::String(val.to_string()));
            let mut cur = &mut v;
            let parts: Vec<&str> = key.split('.').collect();
            for (i, part) in parts.iter().enumerate() {
                let table = cur.as_table_mut().with_context(|| format!("override {key}: {part} is not a section"))?;
                if i + 1 == parts.len() {
                    table.insert(part.to_string(), parsed.clone());
                    break;
                }
                cur = table.entry(part.to_string()).or_insert(toml::Value::Table(Default::default()));
            }
        }
        let text = toml::to_string(&v).map_err(|e| anyhow::anyhow!("config: cannot re-serialize after the overrides: {e}"))?;
        let cfg: TrainConfig = toml::from_str(&text).map_err(|e| {
            // toml's message does not name the key of a mistyped value; its span does: the key
            // is on the span's line, under the last [section] above it.
            let before = e.span().and_then(|s| text.get(..s.start)).unwrap_or("");
            let key = before.lines().last().and_then(|l| l.split_once('=')).map(|(k, _)| k.trim().trim_matches('"'));
            let section = before.lines().rev().find_map(|l| l.trim().strip_prefix('[').and_then(|l| l.strip_suffix(']')));
            match (section, key) {
                (Some(s), Some(k)) => anyhow::anyhow!("config: {s}.{k}: {}", e.message()),
                _ => anyhow::anyhow!("config: {}", e.message()),
            }
        })?;
        cfg.check()?;
        Ok(cfg)
    }

    /// Apply the algorithm's implications (mixer for qmix/vdn/qplex, state for qmix-state)
    /// and validate everything.
    pub fn check(&self) -> Result<()> {
        algo(&self.run.algo)?;
        self.learn.validate()?;
        let r = &self.run;
        for (field, v) in [
            ("run.steps", r.steps),
            ("run.test_interval", r.test_interval),
            ("run.log_interval", r.log_interval),
            ("run.checkpoint_interval", r.checkpoint_interval),
        ] {
            if v == 0 {
                bail!("{field}: must be at least 1");
            }
        }
        if r.envs == 0 || r.servers == 0 {
            bail!("run.envs and run.servers: must be at least 1");
        }
        // 0 takes the default, which always divides (supervisor::default_sub_batches).
        if r.sub_batches != 0 && r.envs % r.sub_batches != 0 {
            bail!("run.sub_batches: {} does not divide run.envs {}", r.sub_batches, r.envs);
        }
        if !(r.updates_per_episode.is_finite() && r.updates_per_episode > 0.0) {
            bail!("run.updates_per_episode: must be positive, got {}", r.updates_per_episode);
        }
        if let Some(e) = r.dataset_epsilon {
            if !(0.0..=1.0).contains(&e) {
                bail!("run.dataset_epsilon: must be in [0, 1], got {e}");
            }
        }
        let schema = lmac_shm_schema::schema::load_env(&r.env).map_err(|e| anyhow::anyhow!("run.env: {e}"))?;
        let protocol = self.protocol()?;
        let plan = lmac_protocol_runner::plan_for(&protocol, &schema).map_err(|e| anyhow::anyhow!("run.protocol: {e}"))?;
        if plan.msg_dim() > schema.message_columns {
            bail!("run.protocol: {protocol} writes {} message columns but {} allows {}", plan.msg_dim(), r.env, schema.message_columns);
        }
        Ok(())
    }

    /// The protocol the runner applies: `run.protocol` if set, else the algorithm's.
    pub fn protocol(&self) -> Result<String> {
        let a = algo(&self.run.algo)?;
        if self.run.protocol.is_empty() {
            return Ok(a.protocol.to_string());
        }
        if a.protocol != "none" {
            bail!(
                "run.protocol: algorithm {} fixes its protocol ({}); use qmix, vdn, qplex or qmix-state with a protocol",
                self.run.algo,
                a.protocol
            );
        }
        Ok(self.run.protocol.clone())
    }

    /// The learner config with the algorithm's settings applied.
    pub fn effective_learn(&self) -> Result<LearnConfig> {
        let a = algo(&self.run.algo)?;
        let mut l = self.learn.clone();
        if let Some(m) = a.mixer {
            l.mixer = m;
        }
        l.agent_sees_state |= a.sees_state;
        Ok(l)
    }
}

/// One metrics row; empty fields are written as blanks in the CSV.
#[derive(Clone, Debug, Default, Serialize)]
pub struct MetricsRow {
    pub t_env: u64,
    pub episodes: u64,
    pub updates: u64,
    pub wall_s: f64,
    pub env_steps_per_s: f64,
    pub epsilon: f32,
    pub train_return_mean: Option<f64>,
    pub test_return_mean: Option<f64>,
    pub test_win_rate: Option<f64>,
    pub loss: Option<f32>,
    pub grad_norm: Option<f32>,
    pub q_taken_mean: Option<f32>,
}

const CSV_HEADER: &str =
    "t_env,episodes,updates,wall_s,env_steps_per_s,epsilon,train_return_mean,test_return_mean,test_win_rate,loss,grad_norm,q_taken_mean";

/// The metrics of a run: CSV, JSON lines and TensorBoard scalars, side by side in its directory.
pub struct Metrics {
    csv: std::fs::File,
    jsonl: std::fs::File,
    tb: crate::tensorboard::EventWriter,
}

fn opt<T: std::fmt::Display>(v: &Option<T>) -> String {
    v.as_ref().map(|x| x.to_string()).unwrap_or_default()
}

impl Metrics {
    pub fn open(dir: &Path) -> Result<Metrics> {
        let csv_path = dir.join("metrics.csv");
        let new = !csv_path.exists();
        let mut csv = std::fs::OpenOptions::new().create(true).append(true).open(&csv_path)?;
        if new {
            writeln!(csv, "{CSV_HEADER}")?;
        }
        let jsonl = std::fs::OpenOptions::new().create(true).append(true).open(dir.join("metrics.jsonl"))?;
        let tb = crate::tensorboard::EventWriter::create(dir)?;
        Ok(Metrics { csv, jsonl, tb })
    }

    pub fn write(&mut self, r: &MetricsRow) -> Result<()> {
        writeln!(
            self.csv,
            "{},{},{},{:.2},{:.1},{:.4},{},{},{},{},{},{}",
            r.t_env,
            r.episodes,
            r.updates,
            r.wall_s,
            r.env_steps_per_s,
            r.epsilon,
            opt(&r.train_return_mean),
            opt(&r.test_return_mean),
            opt(&r.test_win_rate),
            opt(&r.loss),
            opt(&r.grad_norm),
            opt(&r.q_taken_mean)
        )?;
        writeln!(self.jsonl, "{}", serde_json::to_string(r)?)?;
        let f = |v: Option<f64>| v.unwrap_or(f64::NAN);
        self.tb.scalars(
            r.t_env,
            &[
                ("env_steps_per_s", r.env_steps_per_s),
                ("epsilon", r.epsilon as f64),
                ("train_return_mean", f(r.train_return_mean)),
                ("test_return_mean", f(r.test_return_mean)),
                ("test_win_rate", f(r.test_win_rate)),
                ("loss", f(r.loss.map(f64::from))),
                ("grad_norm", f(r.grad_norm.map(f64::from))),
                ("q_taken_mean", f(r.q_taken_mean.map(f64::from))),
            ],
        )?;
        self.csv.flush()?;
        self.jsonl.flush()?;
        Ok(())
    }
}

/// What the learner thread shares with the actor.
#[derive(Default)]
struct Shared {
    /// Newest acting weights, taken by the actor.
    agent: Option<crate::learn::agent::RnnAgent>,
    updates: u64,
    loss: Option<f32>,
    grad_norm: Option<f32>,
    q_taken_mean: Option<f32>,
    error: Option<String>,
    last_checkpoint: Option<PathBuf>,
}

enum ToLearner {
    Episode(Episode),
    Checkpoint,
}

/// The actor side of training: epsilon-greedy acting, test episodes, metrics.
pub struct TrainActor {
    cfg: TrainConfig,
    learn: LearnConfig,
    controllers: Vec<Controller>,
    rng: LearnRng,
    dims: EpisodeDims,
    /// Per server, per env: is the current episode a greedy test episode?
    testing: Vec<Vec<bool>>,
    test_pending: usize,
    test_returns: Vec<(f32, bool)>,
    next_test: u64,
    next_log: u64,
    next_checkpoint: u64,
    t_env: u64,
    episodes: u64,
    train_returns: Vec<f32>,
    tx: mpsc::Sender<ToLearner>,
    shared: Arc<Mutex<Shared>>,
    episodes_sent: u64,
    metrics: Metrics,
    started: Instant,
    t_env_at_start: u64,
    scratch_first: Vec<bool>,
    bar: Option<indicatif::ProgressBar>,
    last_test_return: Option<f64>,
    /// The trajectory dataset being collected once training is done (`run.dataset_episodes`).
    dataset: Vec<Trajectory>,
    /// Observation columns without messages (what the dataset keeps).
    obs_dim: usize,
}

impl TrainActor {
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
        // by more than two updates (only once the buffer can be sampled).
        let ratio = self.cfg.run.updates_per_episode;
        loop {
            let s = self.shared.lock();
            if s.error.is_some() {
                return;
            }
            let can = self.episodes_sent as usize >= self.learn.batch_size;
            let due = ((self.episodes_sent.saturating_sub(self.learn.batch_size as u64)) as f64 * ratio) as u64;
            if !can || s.updates + 2 >= due {
                return;
            }
            drop(s);
            std::thread::sleep(std::time::Duration::from_micros(500));
        }
    }

    fn log(&mut self, test: Option<(f64, f64)>) {
        let s = self.shared.lock();
        let secs = self.started.elapsed().as_secs_f64();
        let row = MetricsRow {
            t_env: self.t_env,
            episodes: self.episodes,
            updates: s.updates,
            wall_s: secs,
            env_steps_per_s: (self.t_env - self.t_env_at_start) as f64 / secs.max(1e-9),
            epsilon: self.epsilon(),
            train_return_mean: (test.is_none() && !self.train_returns.is_empty())
                .then(|| self.train_returns.iter().map(|&r| r as f64).sum::<f64>() / self.train_returns.len() as f64),
            test_return_mean: test.map(|t| t.0),
            test_win_rate: test.map(|t| t.1),
            loss: s.loss,
            grad_norm: s.grad_norm,
            q_taken_mean: s.q_taken_mean,
        };
        drop(s);
        if test.is_none() {
            self.train_returns.clear();
        }
        if let Err(e) = self.metrics.write(&row) {
            eprintln!("lmac: trainer: writing metrics failed: {e}");
        }
    }
}

impl Actor for TrainActor {
    fn act(&mut self, server: usize, slot: &Slot<'_>, obs_width: usize, actions: &mut [i32]) {
        if let Some(agent) = self.shared.lock().agent.take() {
            for c in &mut self.controllers {
                c.set_agent(agent.clone());
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
                self.testing[server][e] = self.test_pending > 0;
                if self.test_pending > 0 {
                    self.test_pending -= 1;
                }
            }
        }
        let state = if self.learn.agent_sees_state { Some(slot.state()) } else { None };
        let eps = self.epsilon();
        let acts = self.controllers[server].select_actions(
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
        let q = self.controllers[server].last_q();
        let avail = slot.avail();
        for e in (0..l.num_envs).filter(|&e| self.testing[server][e]) {
            for ag in 0..n {
                let r = e * n + ag;
                let (qs, av) = (&q[r * a..(r + 1) * a], &avail[r * a..(r + 1) * a]);
                let best = (0..a).filter(|&i| av[i] != 0).max_by(|&i, &j| qs[i].total_cmp(&qs[j]).then(j.cmp(&i)));
                actions[r] = best.unwrap_or(0) as i32;
            }
        }
    }

    fn episode_done(&mut self, server: usize, env: usize, ep: Episode, won: bool) {
        if self.testing[server][env] {
            self.testing[server][env] = false;
            self.test_returns.push((ep.team_return(), won));
            if self.test_returns.len() >= self.cfg.run.test_episodes {
                let n = self.test_returns.len() as f64;
                let ret = self.test_returns.iter().map(|x| x.0 as f64).sum::<f64>() / n;
                let win = self.test_returns.iter().filter(|x| x.1).count() as f64 / n;
                self.test_returns.clear();
                self.last_test_return = Some(ret);
                self.log(Some((ret, win)));
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
        self.t_env += ep.len as u64;
        self.episodes += 1;
        self.train_returns.push(ep.team_return());
        if self.tx.send(ToLearner::Episode(ep)).is_ok() {
            self.episodes_sent += 1;
        }
        if self.t_env >= self.next_test {
            self.next_test += self.cfg.run.test_interval;
            self.test_pending = self.cfg.run.test_episodes;
        }
        if self.t_env >= self.next_log {
            self.next_log += self.cfg.run.log_interval;
            self.log(None);
        }
        if self.t_env >= self.next_checkpoint {
            self.next_checkpoint += self.cfg.run.checkpoint_interval;
            let _ = self.tx.send(ToLearner::Checkpoint);
        }
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
        (self.t_env >= self.cfg.run.steps && self.dataset.len() >= self.cfg.run.dataset_episodes) || self.shared.lock().error.is_some()
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
        protocol: args.protocol.clone(),
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

/// The trainer child's training entry point: build (or resume) the learner, start its thread,
/// run the pipeline with the training actor, and finish with a checkpoint.
pub fn train_in_child(run_dir: &Path, args: &crate::pipeline::TrainerArgs, progress: bool) -> Result<crate::pipeline::TrainerReport> {
    let cfg: TrainConfig = toml::from_str(&std::fs::read_to_string(run_dir.join("config.toml"))?)
        .map_err(|e| anyhow::anyhow!("{}: {}", run_dir.join("config.toml").display(), e.message()))?;
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
    let learner = if ck.join("state.json").exists() {
        let l = Learner::load_checkpoint(&ck, device).map_err(|e| anyhow::anyhow!("resuming from {}: {e}", ck.display()))?;
        if *l.dims() != dims {
            bail!("checkpoint {} was made for {:?}, this run has {:?}", ck.display(), l.dims(), dims);
        }
        eprintln!("lmac: trainer: resuming from {} at t_env {}", ck.display(), l.counters().t_env);
        l
    } else {
        Learner::new(dims, learn.clone(), device)?
    };
    let counters = learner.counters();
    // One controller per ring server (sub-batch), each driving that sub-batch's environments.
    // The ring has servers x sub-batches members (`args.n_servers`).
    let envs_per_slab = cfg.run.envs * cfg.run.servers / args.n_servers;
    let controllers = (0..args.n_servers).map(|_| Controller::new(&learner, envs_per_slab)).collect();
    let shared = Arc::new(Mutex::new(Shared { updates: counters.updates, ..Default::default() }));
    let (tx, rx) = mpsc::channel::<ToLearner>();
    let learner_thread = {
        let shared = shared.clone();
        let ck = ck.clone();
        let (save_buffer, ratio) = (cfg.run.save_buffer, cfg.run.updates_per_episode);
        std::thread::Builder::new().name("learner".into()).spawn(move || learner_loop(learner, rx, shared, ck, save_buffer, ratio))?
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
        testing: vec![vec![false; envs_per_slab]; args.n_servers],
        test_pending: if counters.t_env == 0 { cfg.run.test_episodes } else { 0 },
        test_returns: Vec::new(),
        next_test: (counters.t_env / cfg.run.test_interval + 1) * cfg.run.test_interval,
        next_log: (counters.t_env / cfg.run.log_interval + 1) * cfg.run.log_interval,
        next_checkpoint: (counters.t_env / cfg.run.checkpoint_interval + 1) * cfg.run.checkpoint_interval,
        t_env: counters.t_env,
        episodes: counters.episodes,
        train_returns: Vec::new(),
        tx,
        shared: shared.clone(),
        episodes_sent: counters.episodes,
        metrics: Metrics::open(run_dir)?,
        started: Instant::now(),
        t_env_at_start: counters.t_env,
        scratch_first: Vec::new(),
        bar,
        last_test_return: None,
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
    let TrainActor { tx, shared: sh, .. } = actor;
    drop(tx);
    let joined = learner_thread.join();
    let s = sh.lock();
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
    save_buffer: bool,
    ratio: f64,
) {
    let save = |learner: &Learner, shared: &Mutex<Shared>| match learner.save_checkpoint(&ck, save_buffer) {
        Ok(()) => shared.lock().last_checkpoint = Some(ck.clone()),
        Err(e) => eprintln!("lmac: trainer: checkpoint failed: {e}"),
    };
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
                ToLearner::Checkpoint => save(&learner, &shared),
            }
        }
        let c = learner.counters();
        let bs = learner.config().batch_size as u64;
        let due = ((c.episodes.saturating_sub(bs)) as f64 * ratio) as u64;
        let mut did = false;
        while learner.can_train() && learner.counters().updates < due.max(1) {
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
    save(&learner, &shared);
}
