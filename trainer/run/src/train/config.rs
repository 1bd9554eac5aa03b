//! The configuration of a training run: `[run]` (everything that is not a learner
//! hyperparameter), `[learn]` (the learner's, `learn/config.rs`) and `[method]` (the method's own
//! settings, checked by the method), presets, `key=value` overrides, and the protocol a run's
//! method gets.

use crate::learn::methods::{self, AgentConfig, Messages, MethodContext};
use crate::learn::LearnConfig;
use crate::safe_fs::{read_capped, read_text_capped, TEXT_CAP};
use anyhow::{bail, Context, Result};
use lmac_protocol_runner::{CompiledProtocol, ProtocolSpec};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Everything about a run that is not a learner hyperparameter.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct RunSection {
    /// The environment, `family:variant` (`lmac envs` lists them; e.g. `smaclite:1o_10b_vs_1r`,
    /// `pz:mpe2.simple_spread_v3`): its schema file is `env-server/schemas/<family>/<variant>.toml`.
    pub env: String,
    /// The method: one of the registry's `--algo` names (`lmac train --help` lists them with a
    /// line each; their settings are the `[method]` section).
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
    /// Gradient updates per collected (training) episode. The default 1 is the LMAC paper's
    /// schedule (the authors' EPyMARL episode runner: one update per episode once the buffer
    /// holds a batch); 0.125 is pymarl's parallel runner with 8 environments (one update per 8
    /// episodes, `--preset pymarl-parallel`, the schedule of lmac's figures trained before the
    /// paper's was affordable). The target network is copied every
    /// `learn.target_update_interval_episodes` episodes, so at 1 its 200 episodes are 200
    /// updates, at 0.125 they are 25.
    pub updates_per_episode: f64,
    /// Env steps between greedy test phases.
    pub test_interval: u64,
    /// Greedy episodes per test phase.
    pub test_episodes: usize,
    /// Greedy episodes of the final evaluation of the best test phase's checkpoint when the
    /// run ends (marl-eval's absolute metrics, in `marl_eval.json`); absent = 10 x
    /// `test_episodes`, 0 = none.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub final_eval_episodes: Option<usize>,
    /// Env steps between training-metric rows.
    pub log_interval: u64,
    /// Env steps between checkpoints.
    pub checkpoint_interval: u64,
    /// Also store the replay buffer in checkpoints (exact resumption; large).
    pub save_buffer: bool,
    /// Message protocol for the runner: empty = the algorithm's own (`none` for qmix, vdn,
    /// qplex, qmix-state, cola (which sends none), ndq, maic, masia and t2mac, which make their
    /// messages inside the network;
    /// `fullcomm` for fullcomm); else a design directory (its
    /// `phase<k>/protocol.json` files), protocol files joined by '+'
    /// (`phase0.json+phase1.json`), or a shipped design of the LMAC authors (`protocols/paper/`):
    /// `paper` (the one for run.env) or `paper:<task>`. Required by lmac; not allowed with fullcomm.
    pub protocol: String,
    /// Use the design's phases 0..=k only (the paper's k: 0, 1 or 2); absent = all of them.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub design_k: Option<usize>,
    /// Set by lmac when the run is made: the SHA-256 (first 16 hex digits) of the protocol
    /// files' contents, in order. A resume whose files now read differently is refused (or, with
    /// `--allow-changed`, says so); the run directory keeps a copy of the files in `protocol/`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub protocol_sha256: Option<String>,
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
            updates_per_episode: 1.0,
            test_interval: 10_000,
            test_episodes: 32,
            final_eval_episodes: None,
            log_interval: 5_000,
            checkpoint_interval: 100_000,
            save_buffer: false,
            protocol: String::new(),
            design_k: None,
            protocol_sha256: None,
            dataset_episodes: 0,
            dataset_epsilon: None,
        }
    }
}

pub use crate::learn::MAX_ENV_STEPS;
/// Most environments per env server process.
const MAX_ENVS: usize = 1 << 16;
/// Most env server processes of one run.
const MAX_SERVERS: usize = 1 << 10;
/// Most episodes of a test phase, a final evaluation or a dataset.
const MAX_EPISODES: usize = 1 << 24;
/// Highest design phase index (designs have three phases, 0..=2).
const MAX_DESIGN_K: usize = 1 << 10;
/// Most gradient updates per collected episode.
const MAX_UPDATES_PER_EPISODE: f64 = 1024.0;

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
    /// The source tree that resolved this configuration (written with every new run; absent in
    /// runs made before lmac recorded it).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub build: Option<super::build::BuildInfo>,
}

/// Named bundles of settings (`lmac train --preset NAME`), applied before `--set` overrides.
/// `paper` is the default schedule spelled out so that a config pins it, with the LMAC authors'
/// treatment of the time limit.
pub const PRESETS: &[(&str, &str)] = &[
    (
        "paper",
        "the LMAC authors' settings: the paper's schedule, which is the default (the authors' EPyMARL \
         episode runner, Table C.3): one update of 32 episodes per collected episode once the buffer \
         holds 32, target copy every 200 episodes (= 200 updates), and each update on both cores \
         (acting waits for the learner at this ratio, so the second core is free): the batch's two \
         halves on two threads where the method's losses split exactly (learn.data_parallel), else the \
         target network unrolled on the second; the time limit a termination, as their runner \
         treats it (learn.time_limit); and for LMAC their module: the GRU-gate encoder \
         (method.encoder), the consistency loss averaged over padded steps too \
         (method.mask_consistency = false) and the embedding's dropout in every forward, acting and \
         the target network included (method.dropout_when_acting)",
    ),
    (
        "epymarl",
        "EPyMARL's episode-runner learning schedule on one core: one update of 32 episodes per \
         collected episode (updates start once the buffer holds 32), target copy every 200 episodes = \
         200 updates, no second learner thread",
    ),
    (
        "pymarl-parallel",
        "pymarl's parallel runner with 8 environments: 0.125 updates per collected episode (one per 8), \
         target copy every 200 episodes = 25 updates, one learner thread: lmac's default before the \
         paper's schedule was affordable, exactly, and the schedule of every figure trained before it",
    ),
    (
        "released",
        "everything as the LMAC authors' released code runs it, where lmac's defaults and `paper` differ \
         by measured choice: `paper`'s schedule, time limit and LMAC module settings, their episode \
         runner (one env, one server; 100 greedy test episodes every 50k steps), and for LMAC their \
         rewards (standardised over the padded batch: \
         learn.reward_standardisation = \"released\"); other methods keep raw rewards, as the \
         authors' QMIX config does. The state without last actions is an env variant (smaclite's \
         -no-last-action)",
    ),
];

/// The overrides of an optional preset followed by `sets` (`--set` after `--preset`), as
/// `lmac train`, `lmac experiment` and `lmac config show` apply them. `algo` is the run's method
/// where the caller knows it; else the last `run.algo` in `sets`, else the default method.
pub fn preset_then(preset: Option<&str>, algo: Option<&str>, sets: &[String]) -> Result<Vec<String>> {
    // The last `run.algo` override, its value read as `resolve` reads values.
    let from_sets = || {
        sets.iter().rev().find_map(|s| {
            let (key, val) = s.split_once('=')?;
            (key.trim() == "run.algo").then(|| override_value(val.trim()).as_str().map(str::to_string)).flatten()
        })
    };
    let algo = algo.map(str::to_string).or_else(from_sets).unwrap_or_else(|| RunSection::default().algo);
    let mut o = match preset {
        Some(p) => preset_overrides(p, &algo)?,
        None => Vec::new(),
    };
    o.extend(sets.iter().cloned());
    Ok(o)
}

/// The `key=value` overrides of a preset for a run of method `algo` (only `released` sets
/// anything per method).
pub fn preset_overrides(name: &str, algo: &str) -> Result<Vec<String>> {
    let schedule = |updates_per_episode: &str, second_thread: bool| {
        vec![
            format!("run.updates_per_episode={updates_per_episode}"),
            "learn.batch_size=32".into(),
            "learn.target_update_interval_episodes=200".into(),
            format!("learn.parallel_target={second_thread}"),
            format!("learn.data_parallel={second_thread}"),
        ]
    };
    // The authors' settings where lmac's differ, but where a measured choice is better (see
    // `docs/reference/fidelity.md`): for LMAC their module as released (GRU-gate encoder,
    // consistency loss averaged over padded steps too, dropout in every forward).
    let paper = || {
        let mut o = schedule("1.0", true);
        o.push("learn.time_limit=\"terminal\"".into());
        if algo == "lmac" {
            o.extend(["method.encoder=\"gru-gate\"", "method.mask_consistency=false", "method.dropout_when_acting=true"].map(String::from));
        }
        o
    };
    Ok(match name {
        "paper" => paper(),
        "epymarl" => schedule("1.0", false),
        "pymarl-parallel" => schedule("0.125", false),
        "released" => {
            let mut o = paper();
            o.extend(["run.envs=1", "run.servers=1", "run.test_interval=50000", "run.test_episodes=100"].map(String::from));
            if algo == "lmac" {
                o.push("learn.reward_standardisation=\"released\"".into());
            }
            o
        }
        other => bail!("--preset: unknown preset {other:?}; known: {}", PRESETS.iter().map(|(n, _)| *n).collect::<Vec<_>>().join(", ")),
    })
}

/// The environment a design directory was made for (its `summary.json` or `options.json`).
fn design_env(dir: &Path) -> Option<String> {
    ["summary.json", "options.json"].iter().find_map(|f| {
        let v: serde_json::Value = serde_json::from_slice(&read_capped(&dir.join(f), TEXT_CAP).ok()?).ok()?;
        v.get("env")?.as_str().map(str::to_string)
    })
}

/// Whether a design made for one environment reads the same on another: the agents observe the
/// same values with the same meanings, and one state is the start of the other (a variant may
/// leave out the state's last actions), so every critical dim the compiler accepts as in range
/// means the same.
fn same_meanings(a: &str, b: &str) -> bool {
    let load = |e: &str| lmac_shm_schema::schema::load_env(e).ok();
    match (load(a), load(b)) {
        (Some(x), Some(y)) => {
            let (s, t) = (x.state_meanings(), y.state_meanings());
            let n = s.len().min(t.len());
            x.n_agents == y.n_agents && x.obs_dim == y.obs_dim && x.obs_meanings() == y.obs_meanings() && s[..n] == t[..n]
        }
        _ => false,
    }
}

/// Where the authors' own designs ship: `protocols/paper/<env with ':' as '_'>/`, each a design
/// directory whose `options.json` names its env and the archive task it came from.
pub fn paper_designs_dir() -> Result<std::path::PathBuf> {
    Ok(crate::supervisor::repo_root()?.join("protocols").join("paper"))
}

/// The shipped paper designs: (design directory, env, archive task), sorted by directory.
fn paper_designs() -> Result<Vec<(std::path::PathBuf, String, String)>> {
    let root = paper_designs_dir()?;
    let entries = std::fs::read_dir(&root).with_context(|| format!("reading the paper designs in {}", root.display()))?;
    let mut out = Vec::new();
    for e in entries.flatten() {
        let dir = e.path();
        let file = dir.join("options.json");
        if !file.is_file() {
            continue;
        }
        let v: serde_json::Value = serde_json::from_slice(&read_capped(&file, TEXT_CAP).context("reading a paper design")?)
            .with_context(|| format!("{}: not JSON", file.display()))?;
        let text = |k: &str| v.get(k).and_then(|x| x.as_str()).map(str::to_string);
        let (Some(env), Some(task)) = (text("env"), text("task")) else {
            bail!("{}: needs \"env\" and \"task\" strings", file.display());
        };
        out.push((dir, env, task));
    }
    out.sort();
    Ok(out)
}

/// A protocol spec naming a shipped paper design, resolved to its design directory: `paper` is
/// the design for `env`; `paper:<task>` the design of that archive task (`1o_10b_vs_1r`,
/// `Foraging-8x8-2p-2f-s1True`, ...) or env (`smaclite:1o_10b_vs_1r`). Any other spec is
/// returned unchanged (a design directory or protocol files). The caller's env check
/// (`design_env`) refuses a task made for another env.
pub fn resolve_paper_spec(spec: &str, env: &str) -> Result<String> {
    let wanted = match spec.split_once(':') {
        _ if spec == "paper" => env,
        Some(("paper", t)) if !t.is_empty() => t,
        Some(("paper", _)) => {
            bail!("run.protocol: {spec:?}: name a task after 'paper:', e.g. paper:1o_10b_vs_1r, or use 'paper' for the run's env")
        }
        _ => return Ok(spec.to_string()),
    };
    let designs = paper_designs()?;
    let known = || designs.iter().map(|(_, e, t)| format!("{t} ({e})")).collect::<Vec<_>>().join(", ");
    match designs.iter().find(|(_, e, t)| t == wanted || e == wanted) {
        Some((dir, _, _)) => Ok(dir.display().to_string()),
        None if spec == "paper" => bail!("run.protocol: no paper design is shipped for {env}; shipped: {}", known()),
        None => bail!("run.protocol: no paper design is shipped for {wanted:?}; shipped: {}", known()),
    }
}

/// The protocol files of `spec`: a design directory gives its `phase<i>/protocol.json` for
/// i = 0..=k (all phases present when `k` is absent) except the phases its `summary.json` says
/// were dropped (`lmac design` keeps their files for the record); files
/// joined by '+' give the first k + 1.
pub fn protocol_files(spec: &str, k: Option<usize>) -> Result<Vec<String>> {
    let path = Path::new(spec);
    let files: Vec<String> = if path.is_dir() {
        let dropped = dropped_phases(path)?;
        let found: Vec<String> = (0..)
            .map(|i| path.join(format!("phase{i}")).join("protocol.json"))
            .take_while(|p| p.exists())
            .enumerate()
            .filter(|(i, _)| !dropped.contains(i))
            .map(|(_, p)| p.display().to_string())
            .collect();
        if found.is_empty() {
            bail!("run.protocol: {spec} is a directory without phase0/protocol.json (not a design directory)");
        }
        found
    } else {
        spec.parse::<ProtocolSpec>().map_err(|e| anyhow::anyhow!("run.protocol: {e}"))?.files().to_vec()
    };
    match k {
        Some(k) if k + 1 > files.len() => bail!("run.design_k: {k} asks for {} phases but {spec} has {}", k + 1, files.len()),
        Some(k) => Ok(files[..=k].to_vec()),
        None => Ok(files),
    }
}

/// The phases a design directory's `summary.json` marks as dropped (its i-th evaluation is
/// design phase i); none when it has no summary (a directory of hand-written phases).
fn dropped_phases(dir: &Path) -> Result<Vec<usize>> {
    let file = dir.join("summary.json");
    let Ok(text) = read_text_capped(&file, TEXT_CAP) else { return Ok(Vec::new()) };
    let doc: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("run.protocol: {} is not valid JSON", file.display()))?;
    let Some(evals) = doc.get("evaluations") else { return Ok(Vec::new()) };
    let evals = evals.as_array().with_context(|| format!("run.protocol: {}: \"evaluations\" is not a list", file.display()))?;
    Ok(evals.iter().enumerate().filter(|(_, e)| e.get("dropped").and_then(|d| d.as_bool()) == Some(true)).map(|(i, _)| i).collect())
}

/// The value of a `key=value` override: a TOML value, else the text as a string. Exactly one
/// key: a value with a newline cannot smuggle in other keys (`1\nother = 2`) or leave `x` out.
pub fn override_value(val: &str) -> toml::Value {
    toml::from_str::<toml::Table>(&format!("x = {val}"))
        .ok()
        .filter(|t| t.len() == 1)
        .and_then(|mut t| t.remove("x"))
        .unwrap_or_else(|| toml::Value::String(val.to_string()))
}

/// A run as a process uses it, derived from its config once ([`TrainConfig::resolve_run`]):
/// the environment's schema, the protocol compiled for it and the method's agent network.
pub struct ResolvedRun {
    pub schema: lmac_shm_schema::EnvSchema,
    pub protocol: ProtocolSpec,
    /// The compiled protocol; its plan is never applied (each ring member takes `fresh()`).
    pub compiled: CompiledProtocol,
    pub agent: AgentConfig,
}

impl ResolvedRun {
    /// Message columns after each observation.
    pub fn msg_dim(&self) -> usize {
        self.compiled.msg_dim()
    }
}

impl TrainConfig {
    /// A run directory's resolved `config.toml`; errors name the file.
    pub fn load(run_dir: &Path) -> Result<TrainConfig> {
        let path = run_dir.join("config.toml");
        let text = read_text_capped(&path, TEXT_CAP).context("reading the run's configuration")?;
        toml::from_str(&text).map_err(|e| anyhow::anyhow!("{}: {}", path.display(), e.message()))
    }

    /// The settings in which `self` differs from `now`, one `key: self -> now` line each
    /// (dotted keys, TOML values; the build that wrote each is not a setting). A method setting
    /// added since `self` was written reads as its default: a new setting's default is the
    /// behaviour from before it existed.
    pub fn settings_changed(&self, now: &TrainConfig) -> Result<Vec<String>> {
        let table = |c: &TrainConfig| -> Result<toml::Table> {
            let mut c = c.clone();
            c.write_method_defaults()?;
            let mut t = toml::Table::try_from(&c).context("writing a configuration as TOML")?;
            t.remove("build");
            Ok(t)
        };
        fn walk(prefix: &str, a: Option<&toml::Value>, b: Option<&toml::Value>, out: &mut Vec<String>) {
            match (a, b) {
                (Some(toml::Value::Table(x)), Some(toml::Value::Table(y))) => {
                    let keys: std::collections::BTreeSet<&String> = x.keys().chain(y.keys()).collect();
                    for k in keys {
                        let key = if prefix.is_empty() { k.clone() } else { format!("{prefix}.{k}") };
                        walk(&key, x.get(k), y.get(k), out);
                    }
                }
                (a, b) if a != b => {
                    let shown = |v: Option<&toml::Value>| v.map_or("(unset)".to_string(), |v| v.to_string());
                    out.push(format!("{prefix}: {} -> {}", shown(a), shown(b)));
                }
                _ => {}
            }
        }
        let (a, b) = (toml::Value::Table(table(self)?), toml::Value::Table(table(now)?));
        let mut out = Vec::new();
        walk("", Some(&a), Some(&b), &mut out);
        Ok(out)
    }

    /// Read a config file (TOML), apply `key=value` overrides (dotted paths such as
    /// `learn.lr=0.001`, `run.envs=8`), then check it. Errors name the field.
    pub fn resolve(file: Option<&Path>, overrides: &[String]) -> Result<TrainConfig> {
        Self::resolve_with_run(file, overrides).map(|(cfg, _)| cfg)
    }

    /// [`resolve`](Self::resolve), with the run's resolution the check made
    /// ([`resolve_run`](Self::resolve_run)), for a caller that trains it in the same process.
    pub fn resolve_with_run(file: Option<&Path>, overrides: &[String]) -> Result<(TrainConfig, ResolvedRun)> {
        let mut v: toml::Value = match file {
            Some(p) => toml::from_str(&read_text_capped(p, TEXT_CAP).context("reading the configuration")?)
                .with_context(|| format!("{}: not valid TOML", p.display()))?,
            None => toml::Value::Table(Default::default()),
        };
        for o in overrides {
            let (key, val) = o.split_once('=').with_context(|| format!("override {o:?} must look like section.key=value"))?;
            let parsed = override_value(val);
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
        // Errors name the file (and say when --set took part) and the field by its path, whatever
        // the value's type: `run = 5` names `run`, a table where a number belongs names its key.
        let origin = match (file, overrides.is_empty()) {
            (Some(p), true) => format!("config {}", p.display()),
            (Some(p), false) => format!("config {} with --set overrides", p.display()),
            (None, _) => "config".to_string(),
        };
        let mut cfg: TrainConfig = serde_path_to_error::deserialize(v).map_err(|e| {
            let path = e.path().to_string();
            // toml's own message, without the key it appends itself (the path here names it).
            let e = e.into_inner().message().trim().to_string();
            if path.is_empty() || path == "." {
                anyhow::anyhow!("{origin}: {e}")
            } else {
                anyhow::anyhow!("{origin}: {path}: {e}")
            }
        })?;
        let run = cfg.resolve_run().map_err(|e| anyhow::anyhow!("{origin}: {e:#}"))?;
        cfg.write_method_defaults()?;
        cfg.build = Some(super::build::BuildInfo::current());
        cfg.run.protocol_sha256 = cfg.protocol_digest()?;
        Ok((cfg, run))
    }

    /// The SHA-256 (first 16 hex digits) of the run's protocol files' contents in order, or None
    /// when the run reads no protocol files (no messages, FullComm).
    pub fn protocol_digest(&self) -> Result<Option<String>> {
        use sha2::{Digest, Sha256};
        let ProtocolSpec::Files(files) = self.protocol()? else { return Ok(None) };
        let mut h = Sha256::new();
        for f in &files {
            let bytes = read_capped(Path::new(f), lmac_protocol_runner::protocol::MAX_FILE_BYTES).context("run.protocol")?;
            h.update((bytes.len() as u64).to_le_bytes());
            h.update(&bytes);
        }
        Ok(Some(h.finalize().iter().take(8).map(|b| format!("{b:02x}")).collect()))
    }

    /// Write the run's `config.toml` into `dir` (a new run directory), with a copy of its
    /// protocol files in `dir/protocol/` (`phase0.json`, ...), so the run keeps what it trained
    /// with wherever the originals go.
    pub fn save_new_run(&self, dir: &Path) -> Result<()> {
        if let ProtocolSpec::Files(files) = self.protocol()? {
            let copies = dir.join("protocol");
            std::fs::create_dir(&copies).with_context(|| format!("creating {}", copies.display()))?;
            for (k, f) in files.iter().enumerate() {
                let bytes = read_capped(Path::new(f), lmac_protocol_runner::protocol::MAX_FILE_BYTES).context("run.protocol")?;
                let copy = copies.join(format!("phase{k}.json"));
                std::fs::write(&copy, &bytes).with_context(|| format!("writing {}", copy.display()))?;
            }
        }
        let path = dir.join("config.toml");
        std::fs::write(&path, toml::to_string_pretty(self)?).with_context(|| format!("writing {}", path.display()))
    }

    /// Fill `[method]` with every setting of `run.algo`'s method that the run left at its
    /// default, so the saved `config.toml` states every setting the run trained with (a later
    /// build with other defaults still reads back what this run used). Defaults come from the
    /// method's settings schema, the one the configuration reference is generated from;
    /// settings whose default is "absent" stay absent.
    pub fn write_method_defaults(&mut self) -> Result<()> {
        let m = methods::method(&self.run.algo).map_err(|e| anyhow::anyhow!("run.algo: {e}"))?;
        let Some(schema) = m.settings else { return Ok(()) };
        let schema = schema();
        let Some(props) = schema.as_value().get("properties").and_then(serde_json::Value::as_object) else {
            return Ok(());
        };
        for (key, prop) in props {
            let Some(default) = prop.get("default").filter(|d| !d.is_null()) else { continue };
            if self.method.contains_key(key) {
                continue;
            }
            let mut value =
                toml::Value::try_from(default).with_context(|| format!("method.{key}: its default {default} has no TOML form"))?;
            // An f32 setting's default arrives widened (0.1 as 0.10000000149011612): write the
            // shortest text that reads back to the same f32.
            if let toml::Value::Float(x) = value {
                if (x as f32) as f64 == x {
                    value = toml::Value::Float(format!("{:?}", x as f32).parse().unwrap_or(x));
                }
            }
            self.method.insert(key.clone(), value);
        }
        Ok(())
    }

    /// Validate everything: the run, the learner, the protocol against the environment and the
    /// method's settings ([`resolve_run`](Self::resolve_run), its result dropped).
    pub fn check(&self) -> Result<()> {
        self.resolve_run().map(drop)
    }

    /// Resolve the run once: every field checked, the environment's schema loaded, the
    /// protocol compiled for it (the one width check) and the method's agent network configured
    /// against the plan. What a process derives from the config, it takes from here.
    pub fn resolve_run(&self) -> Result<ResolvedRun> {
        self.check_fields()?;
        let schema = lmac_shm_schema::schema::load_env(&self.run.env).map_err(|e| anyhow::anyhow!("run.env: {e}"))?;
        let protocol = self.protocol()?;
        let compiled = lmac_protocol_runner::compile_for(&protocol, &schema).map_err(|e| anyhow::anyhow!("run.protocol: {e}"))?;
        let agent = self.agent_config(&schema, &compiled)?;
        Ok(ResolvedRun { schema, protocol, compiled, agent })
    }

    /// The checks of the fields themselves (ranges, the learner, the method's name).
    fn check_fields(&self) -> Result<()> {
        methods::method(&self.run.algo).map_err(|e| anyhow::anyhow!("run.algo: {e}"))?;
        self.learn.validate()?;
        let r = &self.run;
        // Every number is range-checked: bounds far above any real run, low enough that a typo or
        // a hostile file cannot ask for an allocation the machine cannot hold, a schedule that
        // never arrives (1e300 updates per episode) or an overflow.
        for (field, v) in [
            ("run.steps", r.steps),
            ("run.test_interval", r.test_interval),
            ("run.log_interval", r.log_interval),
            ("run.checkpoint_interval", r.checkpoint_interval),
        ] {
            if !(1..=MAX_ENV_STEPS).contains(&v) {
                bail!("{field}: must be between 1 and {MAX_ENV_STEPS}, got {v}");
            }
        }
        for (field, v, lo, hi) in [
            ("run.envs", r.envs, 1, MAX_ENVS),
            ("run.servers", r.servers, 1, MAX_SERVERS),
            ("run.test_episodes", r.test_episodes, 0, MAX_EPISODES),
            ("run.final_eval_episodes", r.final_eval_episodes.unwrap_or(0), 0, MAX_EPISODES),
            ("run.dataset_episodes", r.dataset_episodes, 0, MAX_EPISODES),
            ("run.design_k", r.design_k.unwrap_or(0), 0, MAX_DESIGN_K),
        ] {
            if !(lo..=hi).contains(&v) {
                bail!("{field}: must be between {lo} and {hi}, got {v}");
            }
        }
        // 0 takes the default, which always divides (supervisor::default_sub_batches).
        if r.sub_batches != 0 && r.envs % r.sub_batches != 0 {
            bail!("run.sub_batches: {} does not divide run.envs {}", r.sub_batches, r.envs);
        }
        if !(r.updates_per_episode.is_finite() && r.updates_per_episode > 0.0 && r.updates_per_episode <= MAX_UPDATES_PER_EPISODE) {
            bail!("run.updates_per_episode: must be positive and at most {MAX_UPDATES_PER_EPISODE}, got {}", r.updates_per_episode);
        }
        if let Some(e) = r.dataset_epsilon {
            if !(0.0..=1.0).contains(&e) {
                bail!("run.dataset_epsilon: must be in [0, 1], got {e}");
            }
        }
        Ok(())
    }

    /// The protocol the runner applies: the method's own, or `run.protocol` resolved to files.
    pub fn protocol(&self) -> Result<ProtocolSpec> {
        let m = methods::method(&self.run.algo).map_err(|e| anyhow::anyhow!("run.algo: {e}"))?;
        let given = !self.run.protocol.is_empty();
        match m.messages {
            Messages::FullComm if given => {
                let takes: Vec<&str> = methods::REGISTRY.iter().filter(|x| x.messages != Messages::FullComm).map(|x| x.name).collect();
                bail!("run.protocol: {} fixes its protocol (fullcomm); give a protocol to {}", m.name, takes.join(", "))
            }
            Messages::FullComm => Ok(ProtocolSpec::FullComm),
            Messages::Designed if !given => bail!(
                "run.protocol: {} needs a designed protocol: --protocol <design directory> (from `lmac design`) or phase files a.json+b.json",
                m.name
            ),
            Messages::Optional if !given => {
                if self.run.design_k.is_some() {
                    bail!("run.design_k: set, but run.protocol is empty");
                }
                Ok(ProtocolSpec::None)
            }
            _ => {
                let spec = resolve_paper_spec(&self.run.protocol, &self.run.env)?;
                let dir = Path::new(&spec);
                if let Some(env) = design_env(dir).filter(|e| *e != self.run.env) {
                    // A variant of the same environment (smaclite's `-liberty` unit data or
                    // `-no-last-action` state, say) reads the same values: its protocol files
                    // then only warn.
                    if !same_meanings(&env, &self.run.env) {
                        bail!("run.protocol: the design in {} was made for {env}, this run is on {}, whose observations differ", dir.display(), self.run.env);
                    }
                }
                Ok(ProtocolSpec::Files(protocol_files(&spec, self.run.design_k)?))
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
    /// the environment and the compiled protocol (its message columns and critical dims) give it.
    pub fn agent_config(&self, schema: &lmac_shm_schema::EnvSchema, protocol: &CompiledProtocol) -> Result<AgentConfig> {
        let m = methods::method(&self.run.algo).map_err(|e| anyhow::anyhow!("run.algo: {e}"))?;
        let ctx = MethodContext {
            msg_cols: protocol.msg_dim(),
            alpha: schema.alpha,
            critical_dims: protocol.critical_dims.clone(),
            state_dim: schema.state_dim,
        };
        (m.configure)(&self.method, &ctx).map_err(|e| anyhow::anyhow!("{}: {e}", m.name))
    }
}

#[cfg(test)]
mod tests {

    /// A design directory's phases minus those its summary.json marks dropped; a corrupt
    /// summary is an error naming the file, no summary keeps every phase.
    #[test]
    fn dropped_design_phases_are_not_trained_with() {
        let dir = std::env::temp_dir().join(format!("lmac-config-dropped-{}", std::process::id()));
        for k in 0..3 {
            std::fs::create_dir_all(dir.join(format!("phase{k}"))).unwrap();
            std::fs::write(dir.join(format!("phase{k}/protocol.json")), "{}").unwrap();
        }
        let spec = dir.to_str().unwrap();
        assert_eq!(protocol_files(spec, None).unwrap().len(), 3);
        let summary = r#"{"evaluations": [{"phase": 0, "dropped": false}, {"phase": 1, "dropped": true}, {"phase": 2, "dropped": false}]}"#;
        std::fs::write(dir.join("summary.json"), summary).unwrap();
        let files = protocol_files(spec, None).unwrap();
        assert_eq!(files.len(), 2, "{files:?}");
        assert!(files[0].ends_with("phase0/protocol.json") && files[1].ends_with("phase2/protocol.json"), "{files:?}");
        std::fs::write(dir.join("summary.json"), "{not json").unwrap();
        let err = format!("{:#}", protocol_files(spec, None).unwrap_err());
        assert!(err.contains("summary.json") && err.contains("not valid JSON"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    use super::*;

    #[test]
    fn the_epymarl_preset_sets_one_update_per_episode_and_can_be_overridden() {
        let mut o = preset_overrides("epymarl", "qmix").unwrap();
        let c = TrainConfig::resolve(None, &o).unwrap();
        assert_eq!(c.run.updates_per_episode, 1.0);
        assert_eq!(c.learn.target_update_interval_episodes, 200);
        o.push("run.updates_per_episode=0.5".into());
        assert_eq!(TrainConfig::resolve(None, &o).unwrap().run.updates_per_episode, 0.5, "--set comes after the preset");
        assert!(preset_overrides("pymarl2", "qmix").unwrap_err().to_string().contains("known: paper, epymarl, pymarl-parallel, released"));
        let paper = TrainConfig::resolve(None, &preset_overrides("paper", "qmix").unwrap()).unwrap();
        assert_eq!((paper.run.updates_per_episode, paper.learn.target_update_interval_episodes), (1.0, 200));
        assert!(paper.learn.parallel_target, "the paper schedule unrolls the target on the second core");
        assert!(paper.learn.data_parallel, "and splits the batch over both cores where the method allows");
        assert_eq!(paper.learn.time_limit, crate::learn::TimeLimit::Terminal, "the authors' runner does not bootstrap at the limit");
        let default = TrainConfig::resolve(None, &[]).unwrap();
        assert_eq!(
            (default.run.updates_per_episode, default.learn.target_update_interval_episodes, default.learn.data_parallel),
            (1.0, 200, true),
            "the paper's schedule is the default"
        );
        assert_eq!(default.learn.time_limit, crate::learn::TimeLimit::Bootstrap, "lmac bootstraps at a time limit by default");
        let old = TrainConfig::resolve(None, &preset_overrides("pymarl-parallel", "qmix").unwrap()).unwrap();
        assert_eq!(old.run.updates_per_episode, 0.125);
        assert!(!old.learn.parallel_target && !old.learn.data_parallel, "the old default's one learner thread");
        assert!(!c.learn.parallel_target && !c.learn.data_parallel, "epymarl is the schedule on one core");
    }

    #[test]
    fn lmac_without_a_protocol_or_with_another_environments_design_is_a_clear_error() {
        let e = TrainConfig::resolve(None, &["run.algo=\"lmac\"".into()]).unwrap_err().to_string();
        assert!(e.contains("needs a designed protocol"), "{e}");
        let design = concat!(env!("CARGO_MANIFEST_DIR"), "/../../docs/figures/design_lbf8x8");
        let ok = TrainConfig::resolve(None, &["run.algo=\"lmac\"".into(), format!("run.protocol={design:?}")]).unwrap();
        assert!(ok.protocol().unwrap().to_string().contains("phase2"), "all three phases by default");
        let k0 =
            TrainConfig::resolve(None, &["run.algo=\"lmac\"".into(), format!("run.protocol={design:?}"), "run.design_k=0".into()]).unwrap();
        assert_eq!(k0.protocol().unwrap().files().len(), 1, "k = 0: phase 0 alone");
        let other = ["run.algo=\"lmac\"".into(), format!("run.protocol={design:?}"), "run.env=\"smaclite:1o_10b_vs_1r\"".into()];
        let e = format!("{:#}", TrainConfig::resolve(None, &other).unwrap_err());
        assert!(e.contains("lbf:8x8-2p-2f-s1-coop") && e.contains("smaclite:1o_10b_vs_1r"), "{e}");
        let bad = ["run.algo=\"lmac\"".into(), format!("run.protocol={design:?}"), "method.latent_dims=3".into()];
        let e = format!("{:#}", TrainConfig::resolve(None, &bad).unwrap_err());
        assert!(e.contains("latent_dims"), "an unknown [method] key is named: {e}");
    }

    /// `paper` gives LMAC the authors' encoder, consistency loss and dropout; `released` is the authors'
    /// code for the method at hand: LMAC's module, dropout and rewards as released, other methods' raw
    /// rewards; the method comes from `--algo` or from the sets.
    #[test]
    fn the_released_preset_follows_the_method() {
        let lmac = |o: Vec<String>| {
            let mut o = o;
            o.extend(["run.algo=\"lmac\"", "run.env=\"smaclite:1o_10b_vs_1r\"", "run.protocol=\"paper\""].map(String::from));
            TrainConfig::resolve(None, &o).unwrap()
        };
        let paper = toml::to_string(&lmac(preset_then(Some("paper"), Some("lmac"), &[]).unwrap()).method).unwrap();
        assert!(paper.contains("encoder = \"gru-gate\"") && paper.contains("mask_consistency = false"), "{paper}");
        let plain = toml::to_string(&lmac(Vec::new()).method).unwrap();
        assert!(plain.contains("encoder = \"window\""), "lmac's own default stays the window encoder: {plain}");
        assert!(!preset_overrides("paper", "qmix").unwrap().iter().any(|s| s.starts_with("method.")), "no LMAC setting for QMIX");
        let c = lmac(preset_then(Some("released"), Some("lmac"), &[]).unwrap());
        assert_eq!((c.run.envs, c.run.servers, c.run.test_interval, c.run.test_episodes), (1, 1, 50_000, 100));
        assert_eq!(c.learn.time_limit, crate::learn::TimeLimit::Terminal);
        assert_eq!(c.learn.reward_standardisation, crate::learn::RewardStandardisation::Released);
        let method = toml::to_string(&c.method).unwrap();
        assert!(method.contains("encoder = \"gru-gate\"") && method.contains("mask_consistency = false"), "{method}");
        assert!(method.contains("dropout_when_acting = true") && paper.contains("dropout_when_acting = true"), "{method}");
        let from_sets = preset_then(Some("released"), None, &["run.algo = \"lmac\"".into()]).unwrap();
        assert!(from_sets.iter().any(|s| s.starts_with("method.encoder")), "{from_sets:?}");
        let q = TrainConfig::resolve(None, &preset_then(Some("released"), Some("qmix"), &["run.algo=\"qmix\"".into()]).unwrap()).unwrap();
        assert_eq!(q.learn.reward_standardisation, crate::learn::RewardStandardisation::Method, "their QMIX config keeps raw rewards");
        assert_eq!(q.run.envs, 1);
    }

    /// A run written before a method setting existed does not differ from today's config by
    /// that setting (it reads as its default); a setting set otherwise does.
    #[test]
    fn a_setting_added_since_a_run_was_written_is_not_a_change() {
        let o: Vec<String> =
            ["run.algo=\"lmac\"", "run.env=\"smaclite:1o_10b_vs_1r\"", "run.protocol=\"paper\""].iter().map(|s| s.to_string()).collect();
        let now = TrainConfig::resolve(None, &o).unwrap();
        let mut old = now.clone();
        old.method.remove("dropout_when_acting").expect("the default is written out");
        assert_eq!(old.settings_changed(&now).unwrap(), Vec::<String>::new());
        old.method.insert("dropout_when_acting".into(), toml::Value::Boolean(true));
        assert_eq!(old.settings_changed(&now).unwrap(), vec!["method.dropout_when_acting: true -> false".to_string()]);
    }

    /// A saved config states every setting the run trained with: the method's defaults written
    /// out (LMAC's `[method]` holds them when nothing was set), a `--set` kept, f32 defaults in
    /// their short form, and the source tree that resolved it; it reads back to the same config.
    #[test]
    fn a_resolved_config_writes_every_method_setting_and_its_build() {
        let o: Vec<String> = ["run.algo=\"lmac\"", "run.env=\"smaclite:1o_10b_vs_1r\"", "run.protocol=\"paper\"", "method.window=5"]
            .iter()
            .map(|s| s.to_string())
            .collect();
        let c = TrainConfig::resolve(None, &o).unwrap();
        assert_eq!(c.method.get("window").and_then(toml::Value::as_integer), Some(5), "a --set stays");
        assert_eq!(c.method.get("encoder").and_then(toml::Value::as_str), Some("window"), "a default is written");
        assert_eq!(c.method.get("dropout").and_then(toml::Value::as_float), Some(0.1), "an f32 default in its short form");
        assert!(!c.method.contains_key("alpha"), "a setting whose default is absent stays absent");
        let build = c.build.clone().expect("the build is recorded");
        assert!(build.commit == "unknown" || build.commit.len() == 40, "{build:?}");
        let text = toml::to_string_pretty(&c).unwrap();
        assert!(text.contains("[method]") && text.contains("[build]"), "{text}");
        let back: TrainConfig = toml::from_str(&text).unwrap();
        assert_eq!(back, c);
        let qmix = TrainConfig::resolve(None, &[]).unwrap();
        assert!(qmix.method.is_empty(), "a method without settings has no [method]");
    }

    /// A run records its protocol files' content hash and keeps a copy of them: the authors'
    /// 1o_10b design pins three phases; other bytes give another hash.
    #[test]
    fn a_new_run_pins_its_protocol_by_content_and_keeps_a_copy() {
        let o: Vec<String> =
            ["run.env=\"smaclite:1o_10b_vs_1r\"", "run.algo=\"lmac\"", "run.protocol=\"paper\""].iter().map(|s| s.to_string()).collect();
        let c = TrainConfig::resolve(None, &o).unwrap();
        let pinned = c.run.protocol_sha256.clone().expect("a protocol run is pinned");
        assert_eq!(pinned.len(), 16);
        let dir = std::env::temp_dir().join(format!("lmac-config-pin-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        c.save_new_run(&dir).unwrap();
        let ProtocolSpec::Files(files) = c.protocol().unwrap() else { panic!("files") };
        for (k, f) in files.iter().enumerate() {
            assert_eq!(std::fs::read(dir.join(format!("protocol/phase{k}.json"))).unwrap(), std::fs::read(f).unwrap());
        }
        let back = TrainConfig::load(&dir).unwrap();
        assert_eq!(back.run.protocol_sha256.as_deref(), Some(pinned.as_str()));
        // The copies as the run's protocol read the same bytes: the same hash.
        let mut copy = back.clone();
        copy.run.protocol =
            (0..files.len()).map(|k| dir.join(format!("protocol/phase{k}.json")).display().to_string()).collect::<Vec<_>>().join("+");
        assert_eq!(copy.protocol_digest().unwrap().as_deref(), Some(pinned.as_str()));
        copy.run.design_k = Some(0);
        assert_ne!(copy.protocol_digest().unwrap().as_deref(), Some(pinned.as_str()));
        assert_eq!(TrainConfig::resolve(None, &[]).unwrap().run.protocol_sha256, None, "no protocol, no pin");
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A resume by another build, or of a run started from a modified tree, says so.
    #[test]
    fn a_build_difference_is_named() {
        use super::super::build::BuildInfo;
        let a = BuildInfo { commit: "a".repeat(40), modified: false };
        let b = BuildInfo { commit: "b".repeat(40), modified: false };
        assert_eq!(a.difference(&a), None);
        let note = a.difference(&b).unwrap();
        assert!(note.contains(&"a".repeat(40)) && note.contains(&"b".repeat(40)), "{note}");
        let dirty = BuildInfo { modified: true, ..a.clone() };
        assert!(dirty.difference(&dirty).unwrap().contains("(modified)"));
    }

    /// Every number is range-checked (a value like 1e300 updates per episode would hang a run, a
    /// 60000-wide GRU abort the process), and errors name the file and the field by its path
    /// whatever the value's type.
    #[test]
    fn out_of_range_settings_are_refused_naming_the_file_and_the_field() {
        let refused = |file: Option<&Path>, o: &[&str]| {
            let o: Vec<String> = o.iter().map(|s| s.to_string()).collect();
            format!("{:#}", TrainConfig::resolve(file, &o).expect_err("refused"))
        };
        let e = refused(None, &["run.updates_per_episode=1e300"]);
        assert!(e.contains("run.updates_per_episode") && e.contains("at most"), "{e}");
        let e = refused(None, &["learn.rnn_hidden_dim=60000"]);
        assert!(e.contains("rnn_hidden_dim") && e.contains("at most 4096"), "{e}");
        for (o, field) in [
            ("run.steps=1152921504606846976", "run.steps"),
            ("run.envs=100000000", "run.envs"),
            ("run.design_k=1152921504606846976", "run.design_k"),
        ] {
            let e = refused(None, &[o]);
            assert!(e.contains(field) && e.contains("between"), "{o}: {e}");
        }
        let dir = std::env::temp_dir().join(format!("lmac-config-range-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let write = |name: &str, text: &str| {
            let p = dir.join(name);
            std::fs::write(&p, text).unwrap();
            p
        };
        let f = write("run5.toml", "run = 5\n");
        let e = refused(Some(&f), &[]);
        assert!(e.contains(&f.display().to_string()) && e.contains(": run: ") && !e.contains("steps"), "{e}");
        let f = write("table.toml", "[learn]\nlr = { a = 1 }\n");
        let e = refused(Some(&f), &[]);
        assert!(e.contains(&f.display().to_string()) && e.contains("learn.lr"), "{e}");
        let f = write("zero.toml", "[run]\nsteps = 0\n");
        let e = refused(Some(&f), &["learn.lr=0.001"]);
        assert!(e.contains(&f.display().to_string()) && e.contains("--set") && e.contains("run.steps"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
