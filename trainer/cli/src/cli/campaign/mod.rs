//! `lmac campaign`: a grid of training runs (stages x tasks x methods x seeds) described by one
//! TOML file and trained into one results tree, in the file's order, resumably, on this machine
//! or as Ray tasks on a cluster.
//!
//! The tree is `<out>/<stage>/<env>/` per stage and task, each an `lmac experiment` directory
//! (`experiment.json`, `runs/<method>/seed<k>/`), so every tool that reads experiments and run
//! directories reads a campaign too. A cell is one run directory; its id is
//! `<stage>/<env>/<method>/seed<k>`. Cells are created (their `config.toml` written) before any
//! trains, and trained stage by stage, seed by seed: every cell's first seed before any
//! cell's second. A cell that would run longer than `max_cell_hours` is stopped there and kept
//! as a reduced cell (`reduced.json`: the steps it reached, the steps planned and why), which
//! every status and report line shows. A cell's kept config is compared with what the campaign
//! resolves to today (a preset whose meaning changed, say): a cell not yet trained is written
//! again, a trained one is said to differ everywhere it is shown, and `run --retrain-changed`
//! moves it under `<out>/superseded/` and trains it again.

mod report;

use super::experiment::{claim_dir, design_protocol, prepare_runs, run_overrides, ExperimentSpec, Resolutions};
use super::parse_steps;
use anyhow::{bail, Context, Result};
use clap::Subcommand;
use lmac_run::learn::checkpoint::{checkpoint_exists, peek_checkpoint};
use lmac_run::run_dir::env_dir_name;
use lmac_run::safe_fs;
use lmac_run::train::{checkpoint_dir, read_metrics, ResolvedRun, TrainConfig};
use lmac_run::workflow::{interrupt_flag, train_dirs_holding};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

#[derive(Subcommand)]
pub(crate) enum CampaignCmd {
    /// Create every cell's run directory, then train the unfinished cells in order (rerun to
    /// resume: finished cells are skipped, unfinished ones continue from their checkpoints).
    Run {
        /// The campaign file (TOML: [campaign], [[stage]], optional [[reference]]).
        file: PathBuf,
        /// The results tree (default: the file's campaign.out).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Run the cells as Ray tasks on this cluster (`auto`, HEAD:6379, or `local` for a Ray
        /// started on this machine) through `python -m lmac_sweep.campaign`; the results tree
        /// must then be on storage every node sees.
        #[arg(long)]
        ray: Option<String>,
        /// With --ray: CPUs a cell takes on its node.
        #[arg(long, default_value_t = 2.0, requires = "ray")]
        cpus_per_cell: f64,
        /// Stop after training this many cells (the rest waits for the next run).
        #[arg(long)]
        max_cells: Option<usize>,
        /// Train again the cells trained with settings the campaign no longer resolves to (a
        /// preset's meaning changed, say); each old run is moved, whole, to
        /// `<out>/superseded/<time>/<cell id>`. Without it they are kept and said to differ.
        #[arg(long)]
        retrain_changed: bool,
    },
    /// What is finished, running or left, and roughly how long the rest takes (from the speed of
    /// the cells trained so far).
    Status {
        /// The campaign file.
        file: PathBuf,
        /// The results tree (default: the file's campaign.out).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Print the cells as JSON: each one's id, directory, state and estimated time left.
        #[arg(long)]
        json: bool,
    },
    /// The results page: per task and method, our last-5-tests score over the seeds trained so
    /// far, beside the [[reference]] values at the same steps, with what is missing said.
    Report {
        /// The campaign file.
        file: PathBuf,
        /// The results tree to read (default: the file's campaign.out).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Copy each cell's config.toml, metrics.csv, marl_eval.json and reduced.json into this
        /// directory (the same tree, small files only: what docs/figures commits), and read the
        /// page from the copy.
        #[arg(long)]
        export: Option<PathBuf>,
        /// Write the page here (Markdown; a .json with the same stem beside it) instead of
        /// printing it.
        #[arg(long)]
        page: Option<PathBuf>,
    },
    /// Train one cell (what each Ray task runs).
    #[command(hide = true)]
    Cell {
        /// The campaign file.
        file: PathBuf,
        /// The cell's id, `<stage>/<env>/<method>/seed<k>`.
        id: String,
        /// The results tree (default: the file's campaign.out).
        #[arg(long)]
        out: Option<PathBuf>,
    },
}

/// A campaign file.
#[derive(Deserialize, Debug)]
#[serde(deny_unknown_fields)]
struct CampaignFile {
    campaign: Head,
    #[serde(rename = "stage")]
    stages: Vec<Stage>,
    #[serde(rename = "reference", default)]
    references: Vec<Reference>,
}

#[derive(Deserialize, Debug)]
#[serde(deny_unknown_fields)]
struct Head {
    /// The results page's title.
    title: String,
    /// The results tree (relative to the current directory).
    out: PathBuf,
    /// A preset for every run (`lmac train --preset`).
    #[serde(default)]
    preset: Option<String>,
    /// Settings for every run, as `--set`.
    #[serde(default)]
    set: Vec<String>,
    /// A cell still training after this many hours is stopped and kept as a reduced cell.
    #[serde(default)]
    max_cell_hours: Option<f64>,
    /// Markdown the results page carries under its title (how the reference maps to ours, say).
    #[serde(default)]
    notes: Option<String>,
}

#[derive(Deserialize, Debug)]
#[serde(deny_unknown_fields)]
struct Stage {
    name: String,
    tasks: Vec<String>,
    algos: Vec<String>,
    seeds: Vec<u64>,
    steps: StepCount,
    /// The design LMAC trains with: `paper` (the authors' design for each task) or a design
    /// directory.
    #[serde(default)]
    design: Option<String>,
    /// Settings for this stage's runs, after the campaign's.
    #[serde(default)]
    set: Vec<String>,
    /// This stage's preset, in place of the campaign's.
    #[serde(default)]
    preset: Option<String>,
}

impl Stage {
    fn preset<'a>(&'a self, head: &'a Head) -> Option<&'a str> {
        self.preset.as_deref().or(head.preset.as_deref())
    }
}

#[derive(Deserialize, Debug)]
#[serde(untagged)]
enum StepCount {
    Number(u64),
    Text(String),
}

/// Published values to stand beside ours: one task, a value per method at each step count.
#[derive(Deserialize, Serialize, Debug, Clone)]
#[serde(deny_unknown_fields)]
struct Reference {
    task: String,
    /// Where the values come from, and how they were read.
    source: String,
    /// What the values measure: `win_rate` (test win rate) or `return` (test return).
    metric: Metric,
    /// The values' unit: 100 for percent.
    #[serde(default = "one")]
    scale: f64,
    /// Env steps of each value.
    steps: Vec<u64>,
    /// Method -> its values at `steps`.
    values: BTreeMap<String, Vec<f64>>,
}

fn one() -> f64 {
    1.0
}

#[derive(Deserialize, Serialize, Debug, Clone, Copy, PartialEq)]
#[serde(rename_all = "snake_case")]
enum Metric {
    WinRate,
    Return,
}

/// A campaign read and checked, with where its tree is.
struct Campaign {
    file: PathBuf,
    spec: CampaignFile,
    out: PathBuf,
}

/// One run of the grid.
#[derive(Serialize, Clone, Debug)]
struct Cell {
    id: String,
    stage: String,
    task: String,
    algo: String,
    seed: u64,
    dir: PathBuf,
}

/// Where a cell stands.
#[derive(Serialize, Clone, Debug, PartialEq)]
#[serde(tag = "state", rename_all = "snake_case")]
enum CellState {
    Pending,
    Partial {
        t_env: u64,
        steps: u64,
    },
    Finished {
        t_env: u64,
    },
    Reduced {
        t_env: u64,
        planned_steps: u64,
        reason: String,
    },
    /// Its last attempt stopped on an error (`failed.json`); the next `campaign run` retries it.
    Failed {
        t_env: u64,
        error: String,
    },
}

/// Why a cell's last attempt stopped (`failed.json` in its directory, removed when it trains).
#[derive(Serialize, Deserialize, Debug)]
struct Failed {
    error: String,
}

/// Why a cell trained fewer steps than planned (`reduced.json` in its directory).
#[derive(Serialize, Deserialize, Debug)]
struct Reduced {
    planned_steps: u64,
    steps: u64,
    reason: String,
}

impl Campaign {
    fn load(file: &Path, out: Option<PathBuf>) -> Result<Campaign> {
        let text = safe_fs::read_text_capped(file, safe_fs::TEXT_CAP).with_context(|| format!("reading {}", file.display()))?;
        let spec: CampaignFile = toml::from_str(&text).map_err(|e| anyhow::anyhow!("{}: {}", file.display(), e))?;
        check(&spec).map_err(|e| anyhow::anyhow!("{}: {e:#}", file.display()))?;
        let out = out.unwrap_or_else(|| spec.campaign.out.clone());
        Ok(Campaign { file: file.to_path_buf(), spec, out })
    }

    /// Every cell in training order: stage by stage, seed by seed, task by task, method by
    /// method.
    fn cells(&self) -> Vec<Cell> {
        let mut cells = Vec::new();
        for st in &self.spec.stages {
            for &seed in &st.seeds {
                for task in &st.tasks {
                    for algo in &st.algos {
                        let env = env_dir_name(task);
                        cells.push(Cell {
                            id: format!("{}/{env}/{algo}/seed{seed}", st.name),
                            stage: st.name.clone(),
                            task: task.clone(),
                            algo: algo.clone(),
                            seed,
                            dir: self.out.join(&st.name).join(&env).join("runs").join(algo).join(format!("seed{seed}")),
                        });
                    }
                }
            }
        }
        cells
    }

    fn stage(&self, name: &str) -> &Stage {
        self.spec.stages.iter().find(|st| st.name == name).expect("a cell's stage is the campaign's")
    }

    /// What the experiment directory of a stage and task is made for.
    fn experiment_spec(&self, st: &Stage, task: &str) -> Result<ExperimentSpec> {
        Ok(ExperimentSpec {
            env: task.to_string(),
            steps: st.steps.get()?,
            set: self.spec.campaign.set.iter().chain(&st.set).cloned().collect(),
            preset: st.preset(&self.spec.campaign).map(str::to_string),
        })
    }

    /// `run.protocol` of a stage's LMAC runs on a task.
    fn protocol(&self, st: &Stage, task: &str) -> Result<Option<String>> {
        st.design
            .as_ref()
            .map(|d| design_protocol(Path::new(d), task))
            .transpose()
            .with_context(|| format!("stage {}, task {task}", st.name))
    }

    /// The configuration the campaign resolves for `cell` today.
    fn resolve(&self, cell: &Cell) -> Result<TrainConfig> {
        let st = self.stage(&cell.stage);
        let spec = self.experiment_spec(st, &cell.task)?;
        let o = run_overrides(&spec, self.protocol(st, &cell.task)?.as_deref(), &cell.algo, &cell.algo, &[], cell.seed)?;
        TrainConfig::resolve(None, &o).with_context(|| format!("cell {}", cell.id))
    }

    /// The cell's kept configuration, or before `run` has created the cell (a new campaign or
    /// stage) the one it will be created with.
    fn config(&self, cell: &Cell) -> Result<TrainConfig> {
        if cell.dir.join("config.toml").exists() {
            TrainConfig::load(&cell.dir).with_context(|| format!("cell {}", cell.id))
        } else {
            self.resolve(cell)
        }
    }

    /// The settings in which a cell's kept config differs from the config the campaign resolves
    /// for it today (none for a cell without one). A reduced cell's lowered steps are its own.
    fn settings_changed(&self, cell: &Cell) -> Result<Vec<String>> {
        if !cell.dir.join("config.toml").exists() {
            return Ok(Vec::new());
        }
        let now = self.resolve(cell)?;
        let kept = TrainConfig::load(&cell.dir).with_context(|| format!("cell {}", cell.id))?;
        let reduced = cell.dir.join("reduced.json").exists();
        Ok(kept.settings_changed(&now)?.into_iter().filter(|d| !(reduced && d.starts_with("run.steps:"))).collect())
    }

    /// Create every cell's run directory with its config.toml, resolved once and kept. A kept
    /// config that differs from today's resolution is written again when its cell never
    /// trained; a trained cell is moved under `<out>/superseded/` and made again with
    /// `retrain_changed`, else kept and said to differ.
    fn prepare(&self, retrain_changed: bool) -> Result<Resolutions> {
        // A stage whose settings are now written otherwise (a setting named that a preset used to
        // imply, say) keeps its tree when its cells resolve to the configs they have.
        for st in &self.spec.stages {
            for task in &st.tasks {
                let spec = self.experiment_spec(st, task)?;
                let dir = self.out.join(&st.name).join(env_dir_name(task));
                let Err(refused) = claim_dir(&dir, &spec) else { continue };
                let mut changed = Vec::new();
                for cell in self.cells().iter().filter(|c| c.stage == st.name && &c.task == task) {
                    changed.extend(self.settings_changed(cell)?.into_iter().map(|d| format!("{}: {d}", cell.id)));
                }
                if !changed.is_empty() {
                    return Err(refused).with_context(|| {
                        format!("stage {}, task {task}: its cells would train otherwise ({})", st.name, changed.join("; "))
                    });
                }
                eprintln!(
                    "lmac: campaign: stage {}, task {task}: its settings are written otherwise and resolve to the configs its cells have",
                    st.name
                );
                std::fs::write(dir.join("experiment.json"), serde_json::to_string_pretty(&spec)?)?;
            }
        }
        let superseded = self.out.join("superseded").join(lmac_run::run_dir::stamp());
        for cell in self.cells() {
            // A partly trained cell whose checkpoint is not here (a tree restored from an export
            // on another machine, say) cannot resume: its steps so far are set aside and it
            // trains from the start.
            if let Ok(CellState::Partial { t_env, .. }) = cell_state(&cell) {
                if !checkpoint_exists(&checkpoint_dir(&cell.dir)) {
                    let to = set_aside(&cell, &superseded)?;
                    eprintln!(
                        "lmac: campaign: cell {} trained {t_env} steps but has no checkpoint to resume from: moved to {}; it trains from the start",
                        cell.id,
                        to.display()
                    );
                    continue;
                }
            }
            let changed = self.settings_changed(&cell)?;
            if changed.is_empty() {
                continue;
            }
            // Not while another lmac trains it (`campaign cell` on a second worker, say).
            let lock = lmac_run::run_dir::lock(&cell.dir).with_context(|| format!("cell {}", cell.id))?;
            let trained = has_trained(&cell);
            let what = changed.join("; ");
            if !trained {
                eprintln!("lmac: campaign: cell {} has not trained; its config is written again with today's settings ({what})", cell.id);
                std::fs::remove_file(cell.dir.join("config.toml"))?;
                // A start that failed before its first step leaves a checkpoint of step 0 under
                // the old settings: it holds nothing, and the trainer would refuse to resume
                // from it under the new ones.
                let ck = checkpoint_dir(&cell.dir);
                if ck.exists() {
                    std::fs::remove_dir_all(&ck).with_context(|| format!("removing {}", ck.display()))?;
                }
                drop(lock);
            } else if retrain_changed {
                drop(lock);
                let to = set_aside(&cell, &superseded)?;
                eprintln!(
                    "lmac: campaign: cell {} trained with other settings ({what}): moved to {}; it trains again",
                    cell.id,
                    to.display()
                );
            } else {
                eprintln!(
                    "lmac: campaign: cell {} trained with settings the campaign no longer resolves to ({what}); kept as it is \
                     (`campaign run --retrain-changed` trains it again)",
                    cell.id
                );
            }
        }
        let mut resolved = Resolutions::new();
        for st in &self.spec.stages {
            for task in &st.tasks {
                let spec = self.experiment_spec(st, task)?;
                let dir = self.out.join(&st.name).join(env_dir_name(task));
                claim_dir(&dir, &spec).with_context(|| format!("stage {}, task {task}", st.name))?;
                let protocol = self.protocol(st, task)?;
                let rows: Vec<(String, String, Vec<String>)> = st.algos.iter().map(|a| (a.clone(), a.clone(), Vec::new())).collect();
                prepare_runs(&dir, &spec, protocol.as_deref(), &rows, &st.seeds, &mut resolved)
                    .with_context(|| format!("stage {}, task {task}", st.name))?;
            }
        }
        Ok(resolved)
    }

    fn max_cell_s(&self) -> Option<f64> {
        self.spec.campaign.max_cell_hours.map(|h| h * 3600.0)
    }
}

impl StepCount {
    fn get(&self) -> Result<u64> {
        let n = match self {
            StepCount::Number(n) => *n,
            StepCount::Text(t) => parse_steps(t).map_err(anyhow::Error::msg)?,
        };
        if n == 0 {
            bail!("steps must be at least 1");
        }
        Ok(n)
    }
}

/// The file's own rules (each method's and env's settings are checked when its runs are made).
fn check(f: &CampaignFile) -> Result<()> {
    if f.stages.is_empty() {
        bail!("no [[stage]]: a campaign needs at least one");
    }
    if let Some(h) = f.campaign.max_cell_hours {
        if !(h > 0.0 && h.is_finite()) {
            bail!("campaign.max_cell_hours = {h}: must be a positive number of hours");
        }
    }
    let presets = std::iter::once(("campaign.preset".to_string(), &f.campaign.preset))
        .chain(f.stages.iter().map(|st| (format!("stage {}: preset", st.name), &st.preset)));
    for (field, p) in presets {
        if let Some(p) = p {
            if !lmac_run::train::PRESETS.iter().any(|(name, _)| name == p) {
                let names: Vec<&str> = lmac_run::train::PRESETS.iter().map(|(n, _)| *n).collect();
                bail!("{field} {p:?} is not a preset (one of {})", names.join(", "));
            }
        }
    }
    let mut names = Vec::new();
    for st in &f.stages {
        let plain = !st.name.is_empty() && st.name.chars().all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_'));
        if !plain {
            bail!("stage {:?}: a stage's name is a plain word (letters, digits, - and _): it names a folder", st.name);
        }
        if names.contains(&&st.name) {
            bail!("two stages are called {:?}", st.name);
        }
        names.push(&st.name);
        for (what, empty) in [("tasks", st.tasks.is_empty()), ("algos", st.algos.is_empty()), ("seeds", st.seeds.is_empty())] {
            if empty {
                bail!("stage {}: {what} is empty", st.name);
            }
        }
        st.steps.get().with_context(|| format!("stage {}", st.name))?;
        let known: Vec<&str> = lmac_run::learn::methods::REGISTRY.iter().map(|m| m.name).collect();
        for a in &st.algos {
            if !known.contains(&a.as_str()) {
                bail!("stage {}: unknown method {a:?} (one of {})", st.name, known.join(", "));
            }
        }
        if st.algos.iter().any(|a| a == "lmac") && st.design.is_none() {
            bail!("stage {}: lmac needs a design: design = \"paper\" (the authors' design for each task) or a design directory", st.name);
        }
    }
    for r in &f.references {
        for (m, v) in &r.values {
            if v.len() != r.steps.len() {
                bail!("reference for {}: {m} has {} values for {} step counts", r.task, v.len(), r.steps.len());
            }
        }
    }
    Ok(())
}

/// Move a cell's whole run directory to `<superseded>/<cell id>`; returns where it went.
fn set_aside(cell: &Cell, superseded: &Path) -> Result<PathBuf> {
    let to = superseded.join(&cell.id);
    std::fs::create_dir_all(to.parent().expect("a cell id has folders"))?;
    std::fs::rename(&cell.dir, &to).with_context(|| format!("moving {} to {}", cell.dir.display(), to.display()))?;
    Ok(to)
}

/// Where a cell stands, read from its directory.
fn cell_state(c: &Cell) -> Result<CellState> {
    // Not created yet: a stage or campaign `run` has not prepared.
    if !c.dir.exists() {
        return Ok(CellState::Pending);
    }
    let cfg = TrainConfig::load(&c.dir).with_context(|| format!("cell {}", c.id))?;
    let ck = checkpoint_dir(&c.dir);
    // The checkpoint's step; in an exported copy (no checkpoints) the metrics' last.
    let t_env = if checkpoint_exists(&ck) {
        peek_checkpoint(&ck).map_err(|e| anyhow::anyhow!("cell {}: {e}", c.id))?.counters.t_env
    } else {
        read_metrics(&c.dir).ok().and_then(|m| m.last().map(|r| r.t_env)).unwrap_or(0)
    };
    if let Some(r) = read_json::<Reduced>(&c.dir.join("reduced.json"))? {
        return Ok(CellState::Reduced { t_env, planned_steps: r.planned_steps, reason: r.reason });
    }
    Ok(if t_env >= cfg.run.steps {
        CellState::Finished { t_env }
    } else if let Some(f) = read_json::<Failed>(&c.dir.join("failed.json"))? {
        CellState::Failed { t_env, error: f.error }
    } else if t_env == 0 {
        CellState::Pending
    } else {
        CellState::Partial { t_env, steps: cfg.run.steps }
    })
}

/// Whether a cell has trained any env steps; one that failed before it did holds nothing its
/// config must keep (a cell that cannot be read counts as trained: nothing is moved or
/// rewritten on a guess).
fn has_trained(c: &Cell) -> bool {
    cell_state(c).map_or(true, |s| s.trained())
}

impl CellState {
    /// See [`has_trained`].
    fn trained(&self) -> bool {
        match self {
            CellState::Pending => false,
            CellState::Failed { t_env, .. } => *t_env > 0,
            _ => true,
        }
    }
}

/// A cell's small JSON record (`reduced.json`, `failed.json`), if it has one.
fn read_json<T: serde::de::DeserializeOwned>(p: &Path) -> Result<Option<T>> {
    if !p.exists() {
        return Ok(None);
    }
    let bytes = safe_fs::read_capped(p, safe_fs::TEXT_CAP)?;
    Ok(Some(serde_json::from_slice(&bytes).with_context(|| format!("reading {}", p.display()))?))
}

fn done(s: &CellState) -> bool {
    matches!(s, CellState::Finished { .. } | CellState::Reduced { .. })
}

/// Wall seconds per env step of a run, from its metrics (None before its first logged row).
fn seconds_per_step(dir: &Path) -> Option<f64> {
    let last = read_metrics(dir).ok()?.pop()?;
    (last.t_env > 0).then(|| last.wall_s / last.t_env as f64)
}

/// The status of every cell, and the estimate of what is left.
struct Status {
    cells: Vec<(Cell, CellState, Option<f64>)>,
    /// Cell id -> the settings its kept config has that the campaign no longer resolves to.
    changed: BTreeMap<String, Vec<String>>,
}

impl Status {
    fn read(c: &Campaign) -> Result<Status> {
        let cells = c.cells();
        let mut states = Vec::new();
        let mut changed = BTreeMap::new();
        for cell in &cells {
            states.push(cell_state(cell)?);
            let d = c.settings_changed(cell)?;
            if !d.is_empty() {
                changed.insert(cell.id.clone(), d);
            }
        }
        // Seconds per step of each (task, method): its cells trained so far, pooled.
        let mut rates: BTreeMap<(String, String), Vec<f64>> = BTreeMap::new();
        for (cell, st) in cells.iter().zip(&states) {
            if !matches!(st, CellState::Pending) {
                if let Some(r) = seconds_per_step(&cell.dir) {
                    rates.entry((cell.task.clone(), cell.algo.clone())).or_default().push(r);
                }
            }
        }
        let mut out = Vec::new();
        for (cell, st) in cells.into_iter().zip(states) {
            let left_steps = match &st {
                CellState::Pending => Some(c.config(&cell)?.run.steps),
                CellState::Partial { t_env, steps } => Some(steps - t_env),
                CellState::Failed { t_env, .. } => Some(c.config(&cell)?.run.steps.saturating_sub(*t_env)),
                _ => None,
            };
            let rate = rates.get(&(cell.task.clone(), cell.algo.clone())).map(|v| lmac_run::stats::mean(v));
            let mut eta = left_steps.and_then(|s| rate.map(|r| r * s as f64));
            if let (Some(e), Some(limit)) = (eta, c.max_cell_s()) {
                eta = Some(e.min(limit));
            }
            out.push((cell, st, eta));
        }
        Ok(Status { cells: out, changed })
    }

    fn summary(&self) -> String {
        let n = self.cells.len();
        let finished = self.cells.iter().filter(|c| matches!(c.1, CellState::Finished { .. })).count();
        let reduced = self.cells.iter().filter(|c| matches!(c.1, CellState::Reduced { .. })).count();
        let partial = self.cells.iter().filter(|c| matches!(c.1, CellState::Partial { .. })).count();
        let failed = self.cells.iter().filter(|c| matches!(c.1, CellState::Failed { .. })).count();
        let left: Vec<_> = self.cells.iter().filter(|c| !done(&c.1)).collect();
        let known: f64 = left.iter().filter_map(|c| c.2).sum();
        let unknown = left.iter().filter(|c| c.2.is_none()).count();
        let mut s = format!(
            "{n} cells: {finished} finished, {reduced} reduced, {partial} partly trained, {failed} failed, {} not started",
            left.len() - partial - failed
        );
        if left.len() > unknown {
            s.push_str(&format!("; left: about {} for the {} cells with an estimate", duration(known), left.len() - unknown));
        }
        if unknown > 0 {
            s.push_str(&format!(
                "; {unknown} cells without an estimate yet (no cell of their task and method has trained; the first one gives the speed)"
            ));
        }
        let trained_otherwise = self.cells.iter().filter(|c| self.changed.contains_key(&c.0.id) && c.1.trained()).count();
        if trained_otherwise > 0 {
            s.push_str(&format!(
                "; {trained_otherwise} cells trained with settings the campaign no longer resolves to (`campaign run --retrain-changed` trains them again)"
            ));
        }
        s
    }
}

pub(crate) fn campaign(cmd: CampaignCmd) -> Result<i32> {
    match cmd {
        CampaignCmd::Run { file, out, ray, cpus_per_cell, max_cells, retrain_changed } => {
            let c = Campaign::load(&file, out)?;
            std::fs::create_dir_all(&c.out).with_context(|| format!("creating {}", c.out.display()))?;
            let _lock = lmac_run::run_dir::lock(&c.out)?;
            let resolved = c.prepare(retrain_changed)?;
            let st = Status::read(&c)?;
            eprintln!("lmac: campaign {} in {}: {}", c.spec.campaign.title, c.out.display(), st.summary());
            let pending: Vec<Cell> =
                st.cells.iter().filter(|x| !done(&x.1)).map(|x| x.0.clone()).take(max_cells.unwrap_or(usize::MAX)).collect();
            if let Some(address) = ray {
                return run_on_ray(&c, &pending, &address, cpus_per_cell);
            }
            let interrupted = interrupt_flag();
            // A cell that fails (an env that cannot start here, say) is reported and the next
            // one trains: one broken task does not stop the grid.
            let mut failed = Vec::new();
            for (k, cell) in pending.iter().enumerate() {
                eprintln!("lmac: campaign: cell {} of {} left: {}", k + 1, pending.len(), cell.id);
                if let Err(e) = train_cell(&c, cell, resolved.get(&cell.dir), interrupted.clone()) {
                    if interrupted.load(Ordering::SeqCst) {
                        return Err(e);
                    }
                    eprintln!("lmac: campaign: cell {} failed: {e:#}", cell.id);
                    failed.push(format!("{}: {e:#}", cell.id));
                }
            }
            eprintln!("lmac: campaign: {}", Status::read(&c)?.summary());
            if !failed.is_empty() {
                bail!("{} cells failed (rerun to retry them):\n  {}", failed.len(), failed.join("\n  "));
            }
            Ok(0)
        }
        CampaignCmd::Status { file, out, json } => {
            let c = Campaign::load(&file, out)?;
            if !c.out.join(&c.spec.stages[0].name).exists() {
                bail!("{}: no cell has been created yet: `lmac campaign run {}` creates them", c.out.display(), file.display());
            }
            let st = Status::read(&c)?;
            if json {
                let cells: Vec<_> = st
                    .cells
                    .iter()
                    .map(|(cell, s, eta)| {
                        let changed = st.changed.get(&cell.id).cloned().unwrap_or_default();
                        serde_json::json!({"cell": cell, "status": s, "eta_s": eta, "settings_changed": changed})
                    })
                    .collect();
                println!("{}", serde_json::to_string_pretty(&serde_json::json!({"out": c.out, "cells": cells}))?);
                return Ok(0);
            }
            for (cell, s, eta) in &st.cells {
                let what = match s {
                    CellState::Pending => "not started".to_string(),
                    CellState::Partial { t_env, steps } => format!("{t_env} of {steps} steps"),
                    CellState::Finished { t_env } => format!("finished ({t_env} steps)"),
                    CellState::Reduced { t_env, planned_steps, reason } => format!("REDUCED: {t_env} of {planned_steps} steps ({reason})"),
                    CellState::Failed { t_env, error } => format!("FAILED at {t_env} steps (the next run retries it): {error}"),
                };
                let eta = eta.map(|e| format!(", about {} left", duration(e))).unwrap_or_default();
                let changed = match st.changed.get(&cell.id) {
                    None => String::new(),
                    Some(d) if !s.trained() => format!("; the next run writes its config again: {}", d.join("; ")),
                    Some(d) => format!("; TRAINED WITH OTHER SETTINGS than the campaign's now: {}", d.join("; ")),
                };
                println!("{:<60} {what}{eta}{changed}", cell.id);
            }
            println!("{}", st.summary());
            Ok(0)
        }
        CampaignCmd::Report { file, out, export, page } => {
            let mut c = Campaign::load(&file, out)?;
            // The progress is the results tree's, which holds every cell (an export holds only
            // the trained ones).
            let progress = Status::read(&c).map(|s| s.summary()).unwrap_or_else(|e| format!("status unavailable: {e:#}"));
            if let Some(to) = export {
                report::export_tree(&c, &to)?;
                c.out = to;
            }
            let (md, json) = report::report(&c, &progress)?;
            match page {
                Some(p) => {
                    std::fs::write(&p, md).with_context(|| format!("writing {}", p.display()))?;
                    let j = p.with_extension("json");
                    std::fs::write(&j, serde_json::to_string_pretty(&json)?)?;
                    eprintln!("written: {} and {}", p.display(), j.display());
                }
                None => print!("{md}"),
            }
            Ok(0)
        }
        CampaignCmd::Cell { file, id, out } => {
            let c = Campaign::load(&file, out)?;
            let cell = c.cells().into_iter().find(|x| x.id == id).with_context(|| format!("{}: no cell {id:?}", file.display()))?;
            if !cell.dir.join("config.toml").exists() {
                bail!("cell {id}: {} has no config.toml: `lmac campaign run` creates the cells", cell.dir.display());
            }
            train_cell(&c, &cell, None, interrupt_flag())?;
            Ok(0)
        }
    }
}

/// Train one cell (see `train_cell_to_limit`) and record how its attempt ended: `failed.json`
/// with the error when it stops on one (not when interrupted), removed when it trains through,
/// so `status` and `report` say which cells failed and why, from the tree alone.
fn train_cell(c: &Campaign, cell: &Cell, resolved: Option<&ResolvedRun>, interrupted: Arc<AtomicBool>) -> Result<()> {
    let record = cell.dir.join("failed.json");
    let result = train_cell_to_limit(c, cell, resolved, interrupted.clone());
    match &result {
        Ok(()) if record.exists() => std::fs::remove_file(&record).with_context(|| format!("removing {}", record.display()))?,
        Err(e) if !interrupted.load(Ordering::SeqCst) => {
            std::fs::write(&record, serde_json::to_string_pretty(&Failed { error: format!("{e:#}") })?)
                .with_context(|| format!("writing {}", record.display()))?
        }
        _ => {}
    }
    result
}

/// Train one cell to its steps, or to the campaign's time limit: a cell still training then is
/// stopped, its steps lowered to those of its last checkpoint and `reduced.json` written, and
/// its final evaluation runs on what it reached.
fn train_cell_to_limit(c: &Campaign, cell: &Cell, resolved: Option<&ResolvedRun>, interrupted: Arc<AtomicBool>) -> Result<()> {
    // The cell's resolution from when its config was written, if this process wrote it; the
    // steps it may lower below do not enter a resolution.
    let train = |stop: Arc<AtomicBool>| train_dirs_holding(std::slice::from_ref(&cell.dir), Vec::new(), &[resolved], false, stop);
    let Some(limit) = c.max_cell_s() else { return train(interrupted) };
    let spent = read_metrics(&cell.dir).ok().and_then(|m| m.last().map(|r| r.wall_s)).unwrap_or(0.0);
    let stop = Arc::new(AtomicBool::new(false));
    let (timed_out, finished) = (Arc::new(AtomicBool::new(false)), Arc::new(AtomicBool::new(false)));
    let watcher = {
        let (stop, timed_out, finished, interrupted) = (stop.clone(), timed_out.clone(), finished.clone(), interrupted.clone());
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs_f64((limit - spent).max(0.0));
        std::thread::spawn(move || {
            while !finished.load(Ordering::SeqCst) {
                if interrupted.load(Ordering::SeqCst) {
                    stop.store(true, Ordering::SeqCst);
                    return;
                }
                if std::time::Instant::now() >= deadline {
                    timed_out.store(true, Ordering::SeqCst);
                    stop.store(true, Ordering::SeqCst);
                    return;
                }
                std::thread::sleep(std::time::Duration::from_millis(200));
            }
        })
    };
    let result = train(stop);
    finished.store(true, Ordering::SeqCst);
    let _ = watcher.join();
    if !timed_out.load(Ordering::SeqCst) || interrupted.load(Ordering::SeqCst) {
        return result;
    }
    let mut cfg = TrainConfig::load(&cell.dir)?;
    let ck = checkpoint_dir(&cell.dir);
    let reached =
        if checkpoint_exists(&ck) { peek_checkpoint(&ck).map_err(|e| anyhow::anyhow!("cell {}: {e}", cell.id))?.counters.t_env } else { 0 };
    if reached == 0 {
        bail!(
            "cell {}: no checkpoint within the campaign's limit of {}: lower run.checkpoint_interval or raise max_cell_hours",
            cell.id,
            duration(limit)
        );
    }
    let r = Reduced {
        planned_steps: cfg.run.steps,
        steps: reached,
        reason: format!("still training at the campaign's limit of {}; its last checkpoint was at {reached} steps", duration(limit)),
    };
    eprintln!("lmac: campaign: cell {} reduced: {}", cell.id, r.reason);
    std::fs::write(cell.dir.join("reduced.json"), serde_json::to_string_pretty(&r)?)?;
    cfg.run.steps = reached;
    std::fs::write(cell.dir.join("config.toml"), toml::to_string_pretty(&cfg)?)?;
    // Now finished at its new step count: the final evaluation of its best checkpoint.
    train(interrupted)
}

/// Hand the cells to Ray: `python -m lmac_sweep.campaign` runs `lmac campaign cell` for each as
/// a Ray task (in this order) and waits for them.
fn run_on_ray(c: &Campaign, cells: &[Cell], address: &str, cpus_per_cell: f64) -> Result<i32> {
    if cells.is_empty() {
        eprintln!("lmac: campaign: nothing left to train");
        return Ok(0);
    }
    let lmac = std::env::current_exe()?;
    let mut cmd = lmac_run::supervisor::python_command()?;
    cmd.args(["-m", "lmac_sweep.campaign", "--address", address, "--cpus-per-cell", &cpus_per_cell.to_string()])
        .arg("--lmac")
        .arg(&lmac)
        .arg("--file")
        .arg(std::fs::canonicalize(&c.file)?)
        .arg("--out")
        .arg(std::fs::canonicalize(&c.out)?);
    for cell in cells {
        cmd.arg(&cell.id);
    }
    eprintln!("lmac: campaign: {} cells to Ray at {address} ({cpus_per_cell} CPUs each)", cells.len());
    let status = cmd.status().context("starting python -m lmac_sweep.campaign")?;
    eprintln!("lmac: campaign: {}", Status::read(c)?.summary());
    Ok(status.code().unwrap_or(1))
}

/// Seconds as a person reads them: "2.5 h", "14 min", "40 s".
fn duration(s: f64) -> String {
    if s >= 5400.0 {
        format!("{:.1} h", s / 3600.0)
    } else if s >= 90.0 {
        format!("{:.0} min", s / 60.0)
    } else {
        format!("{s:.0} s")
    }
}
