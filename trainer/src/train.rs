//! Training through the pipeline: the trainer child acts (epsilon-greedy with the learner's
//! latest weights) on the main thread while the learner trains on a second thread, so acting
//! and learning overlap on our two cores. Greedy test episodes, metrics (CSV + JSON lines),
//! atomic checkpoints and resume live here; the learning itself is `learn/`.

use crate::dataset::{Dataset, DatasetHeader, Trajectory};
use crate::episode::{Episode, EpisodeDims};
use crate::learn::methods::{self, AgentConfig, AgentNet, Messages, MethodContext};
use crate::learn::{Controller, LearnConfig, LearnRng, Learner};
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
    /// A method of `learn::methods::REGISTRY`: qmix, vdn, qplex, fullcomm, qmix-state, lmac.
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
    /// Gradient updates per collected (training) episode. The default 0.125 is pymarl's parallel
    /// runner with 8 environments (one update per 8 episodes); EPyMARL's episode runner does 1
    /// (`--preset epymarl`). The target network is copied every
    /// `learn.target_update_interval_episodes` episodes, so at 0.125 its 200 episodes are 25
    /// updates, at 1 they are 200.
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
    /// qplex and qmix-state, `fullcomm` for fullcomm); else a design directory (its
    /// `phase<k>/protocol.json` files) or protocol files joined by '+'
    /// (`phase0.json+phase1.json`). Required by lmac; not allowed with fullcomm.
    pub protocol: String,
    /// Use the design's phases 0..=k only (the paper's k: 0, 1 or 2); absent = all of them.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub design_k: Option<usize>,
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
            design_k: None,
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
    /// The settings of `run.algo`'s method (see its file in `learn/methods/`); checked by the
    /// method, unknown keys are errors.
    #[serde(skip_serializing_if = "toml::Table::is_empty")]
    pub method: toml::Table,
}

/// Named bundles of settings (`lmac train --preset NAME`), applied before `--set` overrides.
pub const PRESETS: &[(&str, &str)] = &[(
    "epymarl",
    "EPyMARL's episode-runner learning schedule: one update of 32 episodes per collected episode \
     (updates start once the buffer holds 32), target copy every 200 episodes = 200 updates",
)];

/// The `key=value` overrides of a preset.
pub fn preset_overrides(name: &str) -> Result<Vec<String>> {
    Ok(match name {
        "epymarl" => {
            vec!["run.updates_per_episode=1.0".into(), "learn.batch_size=32".into(), "learn.target_update_interval_episodes=200".into()]
        }
        other => bail!("--preset: unknown preset {other:?}; known: {}", PRESETS.iter().map(|(n, _)| *n).collect::<Vec<_>>().join(", ")),
    })
}

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

/// The environment a design directory was made for (its `summary.json` or `options.json`).
fn design_env(dir: &Path) -> Option<String> {
    ["summary.json", "options.json"].iter().find_map(|f| {
        let v: serde_json::Value = serde_json::from_slice(&std::fs::read(dir.join(f)).ok()?).ok()?;
        v.get("env")?.as_str().map(str::to_string)
    })
}

/// The protocol files of `spec`: a design directory gives its `phase<i>/protocol.json` for
/// i = 0..=k (all phases present when `k` is absent); files joined by '+' give the first k + 1.
pub fn protocol_files(spec: &str, k: Option<usize>) -> Result<Vec<String>> {
    let path = Path::new(spec);
    let files: Vec<String> = if path.is_dir() {
        let found: Vec<String> = (0..)
            .map(|i| path.join(format!("phase{i}")).join("protocol.json"))
            .take_while(|p| p.exists())
            .map(|p| p.display().to_string())
            .collect();
        if found.is_empty() {
            bail!("run.protocol: {spec} is a directory without phase0/protocol.json (not a design directory)");
        }
        found
    } else {
        spec.split('+').map(str::to_string).collect()
    };
    match k {
        Some(k) if k + 1 > files.len() => bail!("run.design_k: {k} asks for {} phases but {spec} has {}", k + 1, files.len()),
        Some(k) => Ok(files[..=k].to_vec()),
        None => Ok(files),
    }
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

    /// Validate everything: the run, the learner, the protocol against the environment and the
    /// method's settings.
    pub fn check(&self) -> Result<()> {
        methods::method(&self.run.algo).map_err(|e| anyhow::anyhow!("run.algo: {e}"))?;
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
        self.agent_config(&schema, plan.msg_dim())?;
        Ok(())
    }

    /// The protocol the runner applies: the method's own, or `run.protocol` resolved to files.
    pub fn protocol(&self) -> Result<String> {
        let m = methods::method(&self.run.algo).map_err(|e| anyhow::anyhow!("run.algo: {e}"))?;
        let given = !self.run.protocol.is_empty();
        match m.messages {
            Messages::FullComm if given => {
                bail!("run.protocol: {} fixes its protocol (fullcomm); give a protocol to qmix, vdn, qplex, qmix-state or lmac", m.name)
            }
            Messages::FullComm => Ok("fullcomm".into()),
            Messages::Designed if !given => bail!(
                "run.protocol: {} needs a designed protocol: --protocol <design directory> (from `lmac design`) or phase files a.json+b.json",
                m.name
            ),
            Messages::Optional if !given => {
                if self.run.design_k.is_some() {
                    bail!("run.design_k: set, but run.protocol is empty");
                }
                Ok("none".into())
            }
            _ => {
                let dir = Path::new(&self.run.protocol);
                if let Some(env) = design_env(dir).filter(|e| *e != self.run.env) {
                    bail!("run.protocol: the design in {} was made for {env}, this run is on {}", dir.display(), self.run.env);
                }
                Ok(protocol_files(&self.run.protocol, self.run.design_k)?.join("+"))
            }
        }
    }

    /// The learner config with the method's backbone and inputs applied.
    pub fn effective_learn(&self) -> Result<LearnConfig> {
        let m = methods::method(&self.run.algo).map_err(|e| anyhow::anyhow!("run.algo: {e}"))?;
        let mut l = self.learn.clone();
        if let Some(mixer) = m.mixer {
            l.mixer = mixer;
        }
        l.agent_sees_state |= m.agent_sees_state;
        Ok(l)
    }

    /// The method's agent network for this run: its `[method]` settings checked against what
    /// the environment and the protocol (`msg_cols` message columns) give it.
    pub fn agent_config(&self, schema: &lmac_shm_schema::EnvSchema, msg_cols: usize) -> Result<AgentConfig> {
        let m = methods::method(&self.run.algo).map_err(|e| anyhow::anyhow!("run.algo: {e}"))?;
        let protocol = self.protocol()?;
        let mut critical = std::collections::BTreeSet::new();
        if protocol != "none" && protocol != "fullcomm" {
            let files: Vec<&str> = protocol.split('+').collect();
            let env = lmac_protocol_runner::protocol_env(schema);
            for phase in lmac_protocol_runner::load_phases(&files, &env).map_err(|e| anyhow::anyhow!("run.protocol: {e}"))? {
                critical.extend(phase.critical_dims);
            }
        }
        let ctx = MethodContext { msg_cols, alpha: schema.alpha, critical_dims: critical.into_iter().collect(), state_dim: schema.state_dim };
        (m.configure)(&self.method, &ctx).map_err(|e| anyhow::anyhow!("{}: {e}", m.name))
    }
}

/// One metrics row; empty fields are written as blanks in the CSV.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
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
    /// The method's extra losses and diagnostics of the last update (LMAC's, for example).
    #[serde(flatten, default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub method: std::collections::BTreeMap<String, f32>,
}

const CSV_HEADER: &str =
    "t_env,episodes,updates,wall_s,env_steps_per_s,epsilon,train_return_mean,test_return_mean,test_win_rate,loss,grad_norm,q_taken_mean";

/// The metrics of a run: CSV, JSON lines and TensorBoard scalars, side by side in its directory.
pub struct Metrics {
    /// The method's columns after the common ones (`AgentConfig::stat_names`).
    method_columns: Vec<String>,
    csv: std::fs::File,
    jsonl: std::fs::File,
    tb: crate::tensorboard::EventWriter,
    dir: PathBuf,
}

fn opt<T: std::fmt::Display>(v: &Option<T>) -> String {
    v.as_ref().map(|x| x.to_string()).unwrap_or_default()
}

/// The metrics rows of a run directory, from `metrics.jsonl` (checkpoint lines skipped).
pub fn read_metrics(dir: &Path) -> Result<Vec<MetricsRow>> {
    let path = dir.join("metrics.jsonl");
    let text = std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    let mut rows = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let v: serde_json::Value = serde_json::from_str(line).with_context(|| format!("{} line {}", path.display(), i + 1))?;
        if v.get("checkpoint").is_none() {
            rows.push(serde_json::from_value(v).with_context(|| format!("{} line {}", path.display(), i + 1))?);
        }
    }
    Ok(rows)
}

/// What [`Metrics::open`] found of an earlier segment of the run.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct MetricsResume {
    /// Rows dropped because they were logged after the checkpoint the run continues from (or
    /// were cut off by the crash).
    pub dropped_rows: usize,
    /// `wall_s` of the last row kept: the resumed segment's clock continues from it.
    pub wall_s: f64,
}

/// Keep the lines of `path` that `keep` accepts (the first `header` lines always), rewriting
/// the file atomically when any is dropped; returns (dropped, kept lines).
fn keep_lines(path: &Path, header: usize, keep: impl Fn(&str) -> bool) -> Result<(usize, Vec<String>)> {
    // Only regular files are read (a device such as /dev/full would never end).
    if std::fs::metadata(path).is_ok_and(|m| !m.is_file()) {
        return Ok((0, Vec::new()));
    }
    let text = match std::fs::read(path) {
        Ok(b) => String::from_utf8_lossy(&b).into_owned(),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok((0, Vec::new())),
        Err(e) => return Err(anyhow::anyhow!("reading {}: {e}", path.display())),
    };
    // A last line without its newline was cut off by the crash: never kept.
    let complete = if text.ends_with('\n') { &text[..] } else { &text[..text.rfind('\n').map_or(0, |i| i + 1)] };
    let mut kept = Vec::new();
    let mut dropped = usize::from(complete.len() < text.len());
    for (i, line) in complete.lines().enumerate() {
        if i < header || keep(line) {
            kept.push(line.to_string());
        } else {
            dropped += 1;
        }
    }
    if dropped > 0 {
        let tmp = path.with_extension("tmp");
        let mut body = kept.join("\n");
        if !body.is_empty() {
            body.push('\n');
        }
        std::fs::write(&tmp, body).with_context(|| format!("writing {}", tmp.display()))?;
        std::fs::rename(&tmp, path).with_context(|| format!("replacing {}", path.display()))?;
    }
    Ok((dropped, kept))
}

impl Metrics {
    /// Open the run's metrics for appending. `resume_t_env` is the step of the checkpoint the run
    /// continues from (0 for a fresh start): rows logged after it are dropped from the CSV and
    /// the JSON lines, and TensorBoard is told to discard its later events, so no curve steps
    /// backwards.
    pub fn open(dir: &Path, resume_t_env: u64, method_columns: &[&str]) -> Result<(Metrics, MetricsResume)> {
        let csv_path = dir.join("metrics.csv");
        let jsonl_path = dir.join("metrics.jsonl");
        // A run resumed by a build whose method logs other terms keeps the columns its file has.
        let existing = std::fs::read_to_string(&csv_path).ok().and_then(|t| t.lines().next().map(str::to_string));
        let header: String = match existing.filter(|h| h.starts_with(CSV_HEADER)) {
            Some(h) => h,
            None => std::iter::once(CSV_HEADER).chain(method_columns.iter().copied()).collect::<Vec<_>>().join(","),
        };
        let method_columns: Vec<String> = header.split(',').skip(CSV_HEADER.split(',').count()).map(str::to_string).collect();
        let columns = header.split(',').count();
        let t_env_of_csv = |line: &str| line.split(',').next().and_then(|v| v.parse::<u64>().ok());
        let ok_csv = |line: &str| line.split(',').count() == columns && t_env_of_csv(line).is_some_and(|t| t <= resume_t_env);
        let (dropped_csv, kept) = keep_lines(&csv_path, 1, ok_csv)?;
        let wall_s = kept.iter().skip(1).last().and_then(|l| l.split(',').nth(3)).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
        let ok_json = |line: &str| {
            serde_json::from_str::<serde_json::Value>(line).ok().and_then(|v| v["t_env"].as_u64()).is_some_and(|t| t <= resume_t_env)
        };
        let (dropped_json, _) = keep_lines(&jsonl_path, 0, ok_json)?;
        let open =
            |p: &Path| std::fs::OpenOptions::new().create(true).append(true).open(p).with_context(|| format!("opening {}", p.display()));
        let new = kept.is_empty();
        let mut csv = open(&csv_path)?;
        if new {
            writeln!(csv, "{header}").with_context(|| format!("writing {}", csv_path.display()))?;
        }
        let jsonl = open(&jsonl_path)?;
        let mut tb =
            crate::tensorboard::EventWriter::create(dir).with_context(|| format!("creating TensorBoard events in {}", dir.display()))?;
        if resume_t_env > 0 {
            tb.session_start(resume_t_env + 1).with_context(|| format!("writing {}", tb.path().display()))?;
        }
        Ok((Metrics { method_columns, csv, jsonl, tb, dir: dir.to_path_buf() }, MetricsResume { dropped_rows: dropped_csv.max(dropped_json), wall_s }))
    }

    pub fn write(&mut self, r: &MetricsRow) -> Result<()> {
        let csv_err = |e: std::io::Error| anyhow::anyhow!("writing {}: {e}", self.dir.join("metrics.csv").display());
        let method: String = self.method_columns.iter().map(|c| format!(",{}", opt(&r.method.get(c)))).collect();
        writeln!(
            self.csv,
            "{},{},{},{:.2},{:.1},{:.4},{},{},{},{},{},{}{method}",
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
        )
        .and_then(|_| self.csv.flush())
        .map_err(csv_err)?;
        self.json_line(&serde_json::to_value(r)?)?;
        let f = |v: Option<f64>| v.unwrap_or(f64::NAN);
        let mut scalars = vec![
            ("env_steps_per_s", r.env_steps_per_s),
            ("epsilon", r.epsilon as f64),
            ("train_return_mean", f(r.train_return_mean)),
            ("test_return_mean", f(r.test_return_mean)),
            ("test_win_rate", f(r.test_win_rate)),
            ("loss", f(r.loss.map(f64::from))),
            ("grad_norm", f(r.grad_norm.map(f64::from))),
            ("q_taken_mean", f(r.q_taken_mean.map(f64::from))),
        ];
        scalars.extend(self.method_columns.iter().map(|c| (c.as_str(), f(r.method.get(c).map(|&v| f64::from(v))))));
        self.tb
            .scalars(r.t_env, &scalars)
            .map_err(|e| anyhow::anyhow!("writing {}: {e}", self.tb.path().display()))?;
        Ok(())
    }

    /// A checkpoint was written: its path and step go into `metrics.jsonl` (so a scheduler
    /// following the run knows where to resume from).
    pub fn checkpoint(&mut self, c: &CheckpointWritten) -> Result<()> {
        self.json_line(&serde_json::json!({"t_env": c.t_env, "episodes": c.episodes, "updates": c.updates, "checkpoint": c.path}))
    }

    fn json_line(&mut self, v: &serde_json::Value) -> Result<()> {
        writeln!(self.jsonl, "{v}")
            .and_then(|_| self.jsonl.flush())
            .map_err(|e| anyhow::anyhow!("writing {}: {e}", self.dir.join("metrics.jsonl").display()))
    }
}

/// A checkpoint the learner wrote.
#[derive(Clone, Debug)]
pub struct CheckpointWritten {
    pub t_env: u64,
    pub episodes: u64,
    pub updates: u64,
    pub path: PathBuf,
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
        for c in &written {
            if let Err(e) = self.metrics.checkpoint(c) {
                self.fail(e);
            }
        }
    }

    fn log(&mut self, test: Option<(f64, f64)>) {
        let s = self.shared.lock();
        let secs = self.started.elapsed().as_secs_f64();
        let row = MetricsRow {
            t_env: self.t_env,
            episodes: self.episodes,
            updates: s.updates,
            wall_s: self.wall_offset + secs,
            env_steps_per_s: (self.t_env - self.t_env_at_start) as f64 / secs.max(1e-9),
            epsilon: self.epsilon(),
            train_return_mean: (test.is_none() && !self.train_returns.is_empty())
                .then(|| self.train_returns.iter().map(|&r| r as f64).sum::<f64>() / self.train_returns.len() as f64),
            test_return_mean: test.map(|t| t.0),
            test_win_rate: test.map(|t| t.1),
            loss: s.loss,
            grad_norm: s.grad_norm,
            q_taken_mean: s.q_taken_mean,
            method: s.method.iter().map(|&(k, v)| (k.to_string(), v)).collect(),
        };
        drop(s);
        if test.is_none() {
            self.train_returns.clear();
        }
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
        if self.testing[member][env] {
            self.testing[member][env] = false;
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
        (self.t_env >= self.cfg.run.steps && self.dataset.len() >= self.cfg.run.dataset_episodes)
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
        let save_buffer = cfg.run.save_buffer;
        std::thread::Builder::new().name("learner".into()).spawn(move || learner_loop(learner, rx, shared, ck, save_buffer, schedule))?
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
        schedule,
        metrics,
        failed: None,
        started: Instant::now(),
        wall_offset: earlier.wall_s,
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

    #[test]
    fn the_epymarl_preset_sets_one_update_per_episode_and_can_be_overridden() {
        let mut o = preset_overrides("epymarl").unwrap();
        let c = TrainConfig::resolve(None, &o).unwrap();
        assert_eq!(c.run.updates_per_episode, 1.0);
        assert_eq!(c.learn.target_update_interval_episodes, 200);
        o.push("run.updates_per_episode=0.5".into());
        assert_eq!(TrainConfig::resolve(None, &o).unwrap().run.updates_per_episode, 0.5, "--set comes after the preset");
        assert!(preset_overrides("pymarl2").unwrap_err().to_string().contains("known: epymarl"));
    }

    #[test]
    fn resuming_drops_the_metrics_rows_after_the_checkpoint_and_a_cut_off_line() {
        let dir = std::env::temp_dir().join(format!("lmac-metrics-trim-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let row = |t: u64, wall: f64| format!("{t},1,0,{wall:.2},1.0,1.0,,,,,,\n");
        let csv = format!("{CSV_HEADER}\n{}{}{}12", row(100, 1.0), row(200, 2.0), row(300, 3.0));
        std::fs::write(dir.join("metrics.csv"), csv).unwrap();
        std::fs::write(dir.join("metrics.jsonl"), "{\"t_env\":100}\n{\"t_env\":200,\"checkpoint\":\"x\"}\n{\"t_env\":300}\n{\"t_e")
            .unwrap();
        let (mut m, r) = Metrics::open(&dir, 200, &[]).unwrap();
        assert_eq!(r, MetricsResume { dropped_rows: 2, wall_s: 2.0 }, "row 300 and the cut-off line go");
        m.write(&MetricsRow { t_env: 250, ..Default::default() }).unwrap();
        let csv = std::fs::read_to_string(dir.join("metrics.csv")).unwrap();
        let t: Vec<&str> = csv.lines().skip(1).map(|l| l.split(',').next().unwrap()).collect();
        assert_eq!(t, ["100", "200", "250"]);
        let json = std::fs::read_to_string(dir.join("metrics.jsonl")).unwrap();
        assert_eq!(json.lines().count(), 3, "{json}");
        assert!(json.lines().all(|l| serde_json::from_str::<serde_json::Value>(l).is_ok()));
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_resumed_run_keeps_the_method_columns_its_metrics_file_has() {
        let dir = std::env::temp_dir().join(format!("lmac-metrics-cols-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let (mut m, _) = Metrics::open(&dir, 0, &["a", "b"]).unwrap();
        let row = |t| MetricsRow { t_env: t, method: [("a".to_string(), 1.5), ("b".to_string(), 2.5)].into(), ..Default::default() };
        m.write(&row(100)).unwrap();
        drop(m);
        // A newer build logs a third term: the file keeps its two, and no row is dropped.
        let (mut m, r) = Metrics::open(&dir, 100, &["a", "b", "c"]).unwrap();
        assert_eq!(r.dropped_rows, 0);
        m.write(&row(200)).unwrap();
        let csv = std::fs::read_to_string(dir.join("metrics.csv")).unwrap();
        assert!(csv.lines().next().unwrap().ends_with(",a,b"), "{csv}");
        assert!(csv.lines().skip(1).all(|l| l.ends_with(",1.5,2.5")), "{csv}");
        assert_eq!(read_metrics(&dir).unwrap()[1].method["b"], 2.5);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_metrics_write_that_fails_names_the_file() {
        let dir = std::env::temp_dir().join(format!("lmac-metrics-full-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        // Every write to /dev/full fails with "no space left on device".
        std::os::unix::fs::symlink("/dev/full", dir.join("metrics.jsonl")).unwrap();
        let (mut m, _) = Metrics::open(&dir, 0, &[]).unwrap();
        let err = m.write(&MetricsRow::default()).unwrap_err().to_string();
        assert!(err.contains("metrics.jsonl") && err.contains("No space left"), "{err}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
