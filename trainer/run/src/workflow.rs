//! The workflow layer between the commands and the processes: start one pipeline run and read
//! its report ([`pipeline_report`]), train run directories to their step target with their
//! final evaluation ([`train_dirs`]), evaluate a trained run ([`evaluate_run`]), find the seeds
//! of a group ([`seed_dirs`]), draw figures ([`plot`]). `lmac train`, `lmac experiment`,
//! `lmac evaluate`, `lmac bench` and the design loop's dataset collection all go through here.

use crate::pipeline::TrainerReport;
use crate::supervisor::{self, RunPlan, TrainerJob, TrainerWork};
use crate::train::evaluate::{EvalResult, EvalSpec};
use crate::train::{ResolvedRun, TrainConfig};
use anyhow::{bail, Context, Result};
use lmac_shm_schema::schema::load_env;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

/// The seed offset of a final evaluation's environments (training's are `seed + t_env`).
pub const EVAL_SEED_OFFSET: u64 = 1_000_003;

/// One pipeline run: which environment, how many env servers and environments, the protocol
/// the runner applies, how many env steps the trainer takes.
#[derive(Clone, Debug)]
pub struct Pipeline {
    pub env: String,
    /// Environments per env server.
    pub envs: usize,
    pub servers: usize,
    /// Sub-batches per env server (None: the environment schema's default).
    pub sub_batches: Option<usize>,
    /// Slots in each server's shared-memory slab.
    pub slots: usize,
    pub protocol: lmac_protocol_runner::ProtocolSpec,
    /// The protocol's message columns when the run was resolved already ([`Pipeline::for_run`]);
    /// None: [`pipeline_report`] compiles the protocol to learn them.
    pub msg_dim: Option<usize>,
    /// Env steps the trainer takes (after warm-up).
    pub steps: u64,
    pub seed: u64,
    /// Seconds the processes may take to find each other.
    pub startup_timeout: f64,
}

impl Pipeline {
    /// The pipeline of a training run's config (its env, environments, servers and protocol,
    /// resolved in `run`), with the env servers seeded from `seed`; it runs until the trainer
    /// child ends it.
    pub fn for_run(cfg: &TrainConfig, run: &ResolvedRun, seed: u64) -> Self {
        Pipeline {
            env: cfg.run.env.clone(),
            envs: cfg.run.envs,
            servers: cfg.run.servers,
            // 0 = the default for the environment's schema (pipeline_report applies it).
            sub_batches: (cfg.run.sub_batches != 0).then_some(cfg.run.sub_batches),
            slots: 4,
            protocol: run.protocol.clone(),
            msg_dim: Some(run.msg_dim()),
            steps: u64::MAX / 4,
            seed,
            startup_timeout: 60.0,
        }
    }
}

/// A flag set by Ctrl-C (SIGINT, SIGTERM): every long step checks it and stops cleanly.
pub fn interrupt_flag() -> Arc<AtomicBool> {
    let flag = Arc::new(AtomicBool::new(false));
    let f = flag.clone();
    let _ = ctrlc::set_handler(move || f.store(true, Ordering::SeqCst));
    flag
}

/// Start the processes of one pipeline run and return the trainer's report. `job` says what the
/// trainer does, `env_extra` goes to the env servers' command line.
pub fn pipeline_report(p: &Pipeline, job: TrainerJob, env_extra: Vec<String>, interrupted: Arc<AtomicBool>) -> Result<TrainerReport> {
    let schema = load_env(&p.env)?;
    let msg_dim = match p.msg_dim {
        Some(m) => m,
        None => lmac_protocol_runner::plan_for(&p.protocol, &schema)?.msg_dim(),
    };
    if p.envs == 0 || p.servers == 0 || p.slots == 0 {
        bail!("--envs, --servers and --slots must be at least 1");
    }
    let sub_batches = p.sub_batches.unwrap_or_else(|| supervisor::default_sub_batches(&schema, p.envs));
    if sub_batches == 0 || p.envs % sub_batches != 0 {
        bail!("--sub-batches {sub_batches} must be at least 1 and divide --envs {}", p.envs);
    }
    let rp = RunPlan {
        run: crate::run_dir::run_id(),
        env: p.env.clone(),
        servers: p.servers,
        envs_per_server: p.envs,
        sub_batches,
        slots: p.slots,
        msg_dim,
        protocol: p.protocol.clone(),
        seed: p.seed,
        startup_timeout_s: p.startup_timeout,
        steps: p.steps,
        trainer: job,
        env_server_args: env_extra,
    };
    Ok(supervisor::run_pipeline(&rp, interrupted)?.report)
}

/// The seed directories of `r` (one seed's directory, or a group holding seeds) and their group.
pub fn seed_dirs(r: &Path) -> Result<(PathBuf, Vec<PathBuf>)> {
    if r.join("config.toml").exists() {
        return Ok((r.parent().unwrap_or(r).to_path_buf(), vec![r.to_path_buf()]));
    }
    let mut d: Vec<_> = std::fs::read_dir(r)
        .with_context(|| format!("reading {}", r.display()))?
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.join("config.toml").exists())
        .collect();
    d.sort();
    if d.is_empty() {
        bail!("{} holds no run (no config.toml in it or its subfolders)", r.display());
    }
    Ok((r.to_path_buf(), d))
}

/// Train each run directory (a resolved `config.toml` inside) in turn through the pipeline, to
/// its step target, then evaluate it once ([`final_evaluation`]). A finished run is skipped; an
/// unfinished one resumes from its checkpoint.
pub fn train_dirs(dirs: &[PathBuf], interrupted: Arc<AtomicBool>) -> Result<()> {
    train_dirs_holding(dirs, Vec::new(), &[], false, interrupted)
}

/// [`train_dirs`] with the locks of some directories already taken (`held[i]` is that of
/// `dirs[i]`; missing or None: taken here) and the resolutions the caller made when it wrote
/// the configs (`resolved[i]` that of `dirs[i]`; missing or None: resolved here), so each run
/// is resolved, and its protocol compiled, once per process. A
/// run whose `config.toml` differs from the one its checkpoint was trained with is refused with
/// the differences, unless `allow_changed`.
pub fn train_dirs_holding(
    dirs: &[PathBuf],
    mut held: Vec<Option<crate::run_dir::RunLock>>,
    resolved: &[Option<&ResolvedRun>],
    allow_changed: bool,
    interrupted: Arc<AtomicBool>,
) -> Result<()> {
    use crate::learn::checkpoint::{checkpoint_exists, peek_checkpoint};
    for (i, d) in dirs.iter().enumerate() {
        // One lmac at a time per run directory: a second one would interleave checkpoints and
        // metrics. The lock goes with the process (also when it is killed).
        let _lock = match held.get_mut(i).and_then(Option::take) {
            Some(l) => l,
            None => crate::run_dir::lock(d)?,
        };
        let cfg = TrainConfig::load(d)?;
        let own;
        let run = match resolved.get(i).copied().flatten() {
            Some(r) => r,
            None => {
                own = cfg.resolve_run()?;
                &own
            }
        };
        // Where the run stands: a checkpoint's step, or 0 for a fresh start.
        let ck = crate::train::checkpoint_dir(d);
        let done_t_env = if checkpoint_exists(&ck) {
            let info = peek_checkpoint(&ck).map_err(|e| anyhow::anyhow!("{}: {e}", d.display()))?;
            let mut changes = info.run_config.as_deref().map(|r| crate::train::resume_check::config_changes(r, &cfg)).unwrap_or_default();
            if let Some(recorded) = &cfg.run.protocol_sha256 {
                let now = cfg.protocol_digest().with_context(|| format!("{}: reading its protocol", d.display()))?;
                if now.as_ref() != Some(recorded) {
                    changes.push(format!(
                        "run.protocol's files now read differently (sha256 {recorded} -> {}; the run's copy is in {})",
                        now.as_deref().unwrap_or("none"),
                        d.join("protocol").display()
                    ));
                }
            }
            if !changes.is_empty() && !allow_changed {
                bail!(
                    "{}: config.toml differs from the configuration its checkpoint (t_env {}) was trained with:\n  {}\n\
                     Resuming would train one network under two settings. Undo the edits, train a new run, or resume with \
                     --allow-changed to continue under the new settings.",
                    d.display(),
                    info.counters.t_env,
                    changes.join("\n  ")
                );
            }
            for c in &changes {
                eprintln!("lmac: {}: warning: resuming with a changed setting (--allow-changed): {c}", d.display());
            }
            info.counters.t_env
        } else {
            // Said here, before any process starts (the trainer checks it again).
            crate::train::refuse_restart_over_metrics(d)?;
            0
        };
        let dataset_done = cfg.run.dataset_episodes == 0 || crate::train::dataset_dir(d).exists();
        if done_t_env >= cfg.run.steps && dataset_done {
            eprintln!("lmac: {} seed {}: already finished (t_env {done_t_env} of {})", d.display(), cfg.learn.seed, cfg.run.steps);
            final_evaluation(d, &cfg, run, interrupted.clone())?;
            continue;
        }
        eprintln!("lmac: {} {} seed {} -> {}", cfg.run.env, cfg.run.algo, cfg.learn.seed, d.display());
        // A resumed segment's environments start from other seeds than the first segment's (else
        // it would replay the same episodes).
        let p = Pipeline::for_run(&cfg, run, cfg.learn.seed + done_t_env);
        let job =
            TrainerJob { warmup: 1, progress: true, work: TrainerWork::Train { dir: std::fs::canonicalize(d)? }, ..Default::default() };
        pipeline_report(&p, job, vec![], interrupted.clone()).with_context(|| format!("run {}", d.display()))?;
        final_evaluation(d, &cfg, run, interrupted.clone())?;
    }
    Ok(())
}

/// A finished run's `marl_eval.json`, with its absolute metrics: the best test phase's
/// checkpoint evaluated greedily over `run.final_eval_episodes` episodes (10 x the test phase
/// by default). Done once; a rerun of a finished run finds the file and skips it. An evaluation
/// that fails (a dead env server, a checkpoint whose network the run's settings no longer
/// describe) is reported and leaves the file unwritten, so a rerun tries again; the training
/// itself is finished and intact, and the seeds after it go on. Ctrl-C still stops everything.
fn final_evaluation(d: &Path, cfg: &TrainConfig, run: &ResolvedRun, interrupted: Arc<AtomicBool>) -> Result<()> {
    match write_final_evaluation(d, cfg, run, interrupted.clone()) {
        Err(e) if !interrupted.load(Ordering::SeqCst) => {
            eprintln!(
                "lmac: warning: {}: the final evaluation failed, marl_eval.json not written (a rerun tries again): {e:#}",
                d.display()
            );
            Ok(())
        }
        other => other,
    }
}

fn write_final_evaluation(d: &Path, cfg: &TrainConfig, run: &ResolvedRun, interrupted: Arc<AtomicBool>) -> Result<()> {
    if d.join("marl_eval.json").exists() {
        return Ok(());
    }
    let episodes = cfg.run.final_eval_episodes.unwrap_or(10 * cfg.run.test_episodes);
    let result = if episodes == 0 {
        None
    } else {
        eprintln!("lmac: {} seed {}: final evaluation of the best checkpoint, {episodes} greedy episodes", cfg.run.env, cfg.learn.seed);
        let spec = EvalSpec { episodes, method: toml::Table::new(), best: true };
        let r = evaluate_run(d, cfg, run, &spec, "final", EVAL_SEED_OFFSET, interrupted)?;
        eprintln!(
            "lmac: {} seed {}: final evaluation ({} checkpoint, t_env {}): return {:.3}, win rate {:.3}",
            cfg.run.env, cfg.learn.seed, r.checkpoint, r.t_env, r.mean_return, r.win_rate
        );
        Some(r)
    };
    crate::train::marl_eval::write_marl_eval(d, cfg, result.as_ref())
}

/// One evaluation of the run in `d` (its config and its resolution) through the pipeline. The
/// spec and its result stay with the run: `<seed dir>/evaluations/<name>.json` and
/// `<name>.result.json`.
pub fn evaluate_run(
    d: &Path,
    cfg: &TrainConfig,
    run: &ResolvedRun,
    spec: &EvalSpec,
    name: &str,
    seed_offset: u64,
    interrupted: Arc<AtomicBool>,
) -> Result<EvalResult> {
    let evals = d.join("evaluations");
    // A folder of the run's own: a symlink planted in its place is refused, never written through.
    match std::fs::symlink_metadata(&evals) {
        Ok(m) if !m.is_dir() => {
            bail!("{}: not a directory (a symlink?); lmac writes evaluations only into a folder of the run's own", evals.display())
        }
        Ok(_) => {}
        Err(_) => std::fs::create_dir(&evals).with_context(|| format!("creating {}", evals.display()))?,
    }
    let spec_path = evals.join(format!("{name}.json"));
    crate::safe_fs::write_replace(&spec_path, &serde_json::to_vec(spec)?).context("writing the evaluation")?;
    let p = Pipeline::for_run(cfg, run, cfg.learn.seed + seed_offset);
    let work = TrainerWork::Evaluate { dir: std::fs::canonicalize(d)?, spec: std::fs::canonicalize(&spec_path)? };
    let job = TrainerJob { warmup: 1, work, ..Default::default() };
    pipeline_report(&p, job, vec![], interrupted).with_context(|| format!("evaluating {}", d.display()))?;
    let out = EvalSpec::result_path(&spec_path);
    Ok(serde_json::from_slice(&crate::safe_fs::read_capped(&out, crate::safe_fs::TEXT_CAP).context("reading the evaluation's result")?)?)
}

/// Draw a run's or a design's figures with one of the reporting package's matplotlib modules
/// (`python -m lmac_report.<module> DIR`, the project's Python); a failure is reported, not fatal.
pub fn plot(module: &str, dir: &Path) {
    let out = supervisor::python_command().and_then(|mut c| Ok(c.arg("-m").arg(format!("lmac_report.{module}")).arg(dir).output()?));
    match out {
        Ok(o) if o.status.success() => print!("{}", String::from_utf8_lossy(&o.stdout)),
        Ok(o) => eprintln!("lmac: lmac_report.{module} failed: {}", String::from_utf8_lossy(&o.stderr)),
        Err(e) => eprintln!("lmac: lmac_report.{module} failed: {e}"),
    }
}
