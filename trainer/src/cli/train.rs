//! `lmac train`: resolve the configs, create or resume the run directories, train each seed
//! through the pipeline, plot.

use super::{interrupt_flag, parse_steps, pipeline_report, PipelineOpts};
use anyhow::{bail, Context, Result};
use clap::Args;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

pub(crate) const TRAIN_AFTER_HELP: &str = "\
Update ratio: by default the learner does run.updates_per_episode = 0.125 gradient updates (of
learn.batch_size = 32 episodes) per collected episode, pymarl's parallel runner with 8
environments. That is 8x fewer updates per episode than EPyMARL's episode runner (1 per
episode), and the target network, copied every 200 episodes, is then copied every 25 updates.
--preset paper reproduces the paper's schedule (EPyMARL's episode runner): 1 update per episode
from the 32nd episode on, a target copy every 200 updates, the target network unrolled on the
second core (acting waits for the learner at this ratio); --preset epymarl is the same on one
core, --preset pymarl-parallel the default's 0.125. Each environment switches to new weights when its
next episode starts.

Resuming: --resume DIR continues every unfinished seed in DIR (a group or one seed) from its
last checkpoint (run.checkpoint_interval env steps apart, and one at the end). Without the saved
replay buffer (run.save_buffer = false) the learner refills learn.batch_size episodes before it
updates again. Metrics rows logged after that checkpoint are dropped, so curves continue
without a step backwards; each checkpoint is logged in metrics.jsonl.";

/// `--algo`'s values, with each method's line, from the method registry.
pub(crate) fn algo_names() -> clap::builder::PossibleValuesParser {
    clap::builder::PossibleValuesParser::new(
        lmac_trainer::learn::methods::REGISTRY.iter().map(|m| clap::builder::PossibleValue::new(m.name).help(m.about)),
    )
}

#[derive(Args)]
pub(crate) struct TrainArgs {
    /// Environment (overrides run.env).
    #[arg(long)]
    env: Option<String>,
    /// The method to train (overrides run.algo).
    #[arg(long, value_parser = algo_names())]
    algo: Option<String>,
    /// Protocol: a design directory (from `lmac design`), phase files a.json+b.json, or the LMAC
    /// authors' design shipped in protocols/paper/: `paper` (for --env) or `paper:<task>`
    /// (overrides run.protocol; lmac needs one).
    #[arg(long)]
    protocol: Option<String>,
    /// Seeds, comma separated: one run directory each, run one after the other.
    #[arg(long, default_value = "0", value_delimiter = ',')]
    seeds: Vec<u64>,
    /// Env steps per seed, e.g. 2M, 500k (overrides run.steps).
    #[arg(long, value_parser = parse_steps)]
    steps: Option<u64>,
    /// Config file (TOML with [run], [learn] and [method] sections).
    #[arg(long)]
    config: Option<std::path::PathBuf>,
    /// Override a config value: --set learn.lr=0.001 --set run.envs=8
    #[arg(long = "set", value_name = "KEY=VALUE")]
    set: Vec<String>,
    /// A named bundle of settings, applied before --set: paper (the LMAC paper's schedule: 1
    /// update per collected episode, target copy every 200 updates, target unrolled on the
    /// second core), epymarl (the same schedule on one core), pymarl-parallel (0.125 updates
    /// per episode).
    #[arg(long)]
    preset: Option<String>,
    /// Where run directories go.
    #[arg(long, default_value = "runs")]
    out: std::path::PathBuf,
    /// Continue the runs in this directory (a seed's directory or a group of seeds).
    #[arg(long, conflicts_with_all = ["env", "algo", "protocol", "config", "set", "steps", "preset"])]
    resume: Option<std::path::PathBuf>,
}

pub(crate) fn train(a: TrainArgs) -> Result<i32> {
    use lmac_trainer::train::TrainConfig;
    let interrupted = interrupt_flag();
    // The seed directories to run, each with its resolved config.toml.
    // The locks of seed directories this command made (taken before anything was written in them).
    let mut held = Vec::new();
    let (group, dirs): (std::path::PathBuf, Vec<std::path::PathBuf>) = if let Some(r) = &a.resume {
        seed_dirs(r)?
    } else {
        let mut overrides = lmac_trainer::train::preset_then(a.preset.as_deref(), &a.set)?;
        if let Some(e) = &a.env {
            overrides.push(format!("run.env={e:?}"));
        }
        if let Some(al) = &a.algo {
            overrides.push(format!("run.algo={al:?}"));
        }
        if let Some(p) = &a.protocol {
            overrides.push(format!("run.protocol={p:?}"));
        }
        if let Some(st) = a.steps {
            overrides.push(format!("run.steps={st}"));
        }
        let mut cfg = TrainConfig::resolve(a.config.as_deref(), &overrides)?;
        // Protocol files by absolute path, so a resumed run finds them from anywhere. A paper
        // design (`paper`, `paper:<task>`) stays as named: it is found in the repository each time.
        let paper = lmac_trainer::train::resolve_paper_spec(&cfg.run.protocol, &cfg.run.env)? != cfg.run.protocol;
        if !cfg.run.protocol.is_empty() && !paper {
            let absolute = |f: &str| -> Result<String> {
                Ok(std::fs::canonicalize(f).with_context(|| format!("run.protocol: {f}"))?.display().to_string())
            };
            // Protocol files (or a built-in), else a design directory.
            cfg.run.protocol = match cfg.run.protocol.parse::<lmac_protocol_runner::ProtocolSpec>() {
                Ok(spec) => spec.map_files(absolute)?.to_string(),
                Err(_) => absolute(&cfg.run.protocol)?,
            };
        }
        // Valid but suspicious protocol files (another environment's, or an older schema's); an
        // invalid protocol is reported by the config check below.
        for w in cfg.protocol_warnings().unwrap_or_default() {
            eprintln!("lmac: warning: run.protocol: {w}");
        }
        // A group directory of this command's own (two launches in the same second get two),
        // and each seed's lock taken before its config is written: no other lmac ever trains a
        // directory with a config it did not write.
        let parent = a.out.join(cfg.run.env.replace(':', "_")).join(&cfg.run.algo);
        let group = lmac_trainer::run_dir::create_unique_dir(&parent, &lmac_trainer::run_dir::stamp())?;
        let mut dirs = Vec::new();
        for &seed in &a.seeds {
            let mut c = cfg.clone();
            c.learn.seed = seed;
            let d = group.join(format!("seed{seed}"));
            std::fs::create_dir(&d).with_context(|| format!("creating {}", d.display()))?;
            held.push(Some(lmac_trainer::run_dir::lock(&d)?));
            let p = d.join("config.toml");
            std::fs::write(&p, toml::to_string_pretty(&c)?).with_context(|| format!("writing {}", p.display()))?;
            dirs.push(d);
        }
        (group, dirs)
    };
    eprintln!("lmac: training {} run(s) in {}", dirs.len(), group.display());
    train_dirs_holding(&dirs, held, interrupted)?;
    super::plot("plot_runs", &group);
    Ok(0)
}

/// Train each run directory (a resolved `config.toml` inside) in turn through the pipeline.
/// The seed directories of `r` (one seed's directory, or a group holding seeds) and their group.
pub(crate) fn seed_dirs(r: &std::path::Path) -> Result<(std::path::PathBuf, Vec<std::path::PathBuf>)> {
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

pub(crate) fn train_dirs(dirs: &[std::path::PathBuf], interrupted: Arc<AtomicBool>) -> Result<()> {
    train_dirs_holding(dirs, Vec::new(), interrupted)
}

/// [`train_dirs`] with the locks of some directories already taken (`held[i]` is that of
/// `dirs[i]`; missing or None: taken here).
fn train_dirs_holding(
    dirs: &[std::path::PathBuf],
    mut held: Vec<Option<lmac_trainer::run_dir::RunLock>>,
    interrupted: Arc<AtomicBool>,
) -> Result<()> {
    use lmac_trainer::train::TrainConfig;
    for (i, d) in dirs.iter().enumerate() {
        // One lmac at a time per run directory: a second one would interleave checkpoints and
        // metrics. The lock goes with the process (also when it is killed).
        let _lock = match held.get_mut(i).and_then(Option::take) {
            Some(l) => l,
            None => lmac_trainer::run_dir::lock(d)?,
        };
        let cfg = TrainConfig::load(d)?;
        cfg.check()?;
        // Where the run stands: a checkpoint's step, or 0 for a fresh start.
        let ck = lmac_trainer::train::checkpoint_dir(d);
        use lmac_trainer::learn::checkpoint::{checkpoint_exists, peek_checkpoint};
        let done_t_env = if checkpoint_exists(&ck) {
            peek_checkpoint(&ck).map_err(|e| anyhow::anyhow!("{}: {e}", d.display()))?.counters.t_env
        } else {
            // Said here, before any process starts (the trainer checks it again).
            lmac_trainer::train::refuse_restart_over_metrics(d)?;
            0
        };
        let dataset_done = cfg.run.dataset_episodes == 0 || lmac_trainer::train::dataset_dir(d).exists();
        if done_t_env >= cfg.run.steps && dataset_done {
            eprintln!("lmac: {} seed {}: already finished (t_env {done_t_env} of {})", d.display(), cfg.learn.seed, cfg.run.steps);
            final_evaluation(d, &cfg, interrupted.clone())?;
            continue;
        }
        eprintln!("lmac: {} {} seed {} -> {}", cfg.run.env, cfg.run.algo, cfg.learn.seed, d.display());
        // A resumed segment's environments start from other seeds than the first segment's (else
        // it would replay the same episodes).
        let p = PipelineOpts::for_run(&cfg, cfg.learn.seed + done_t_env)?;
        let extra = vec![
            "--train-dir".to_string(),
            std::fs::canonicalize(d)?.display().to_string(),
            "--progress".into(),
            "--warmup".into(),
            "1".into(),
        ];
        pipeline_report(&p, extra, vec![], interrupted.clone()).with_context(|| format!("run {}", d.display()))?;
        final_evaluation(d, &cfg, interrupted.clone())?;
    }
    Ok(())
}

/// A finished run's `marl_eval.json`, with its absolute metrics: the best test phase's
/// checkpoint evaluated greedily over `run.final_eval_episodes` episodes (10 x the test phase
/// by default). Done once; a rerun of a finished run finds the file and skips it. An evaluation
/// that fails (a dead env server, a checkpoint whose network the run's settings no longer
/// describe) is reported and leaves the file unwritten, so a rerun tries again; the training
/// itself is finished and intact, and the seeds after it go on. Ctrl-C still stops everything.
fn final_evaluation(d: &std::path::Path, cfg: &lmac_trainer::train::TrainConfig, interrupted: Arc<AtomicBool>) -> Result<()> {
    match write_final_evaluation(d, cfg, interrupted.clone()) {
        Err(e) if !interrupted.load(std::sync::atomic::Ordering::SeqCst) => {
            eprintln!(
                "lmac: warning: {}: the final evaluation failed, marl_eval.json not written (a rerun tries again): {e:#}",
                d.display()
            );
            Ok(())
        }
        other => other,
    }
}

fn write_final_evaluation(d: &std::path::Path, cfg: &lmac_trainer::train::TrainConfig, interrupted: Arc<AtomicBool>) -> Result<()> {
    use lmac_trainer::train::evaluate::EvalSpec;
    if d.join("marl_eval.json").exists() {
        return Ok(());
    }
    let episodes = cfg.run.final_eval_episodes.unwrap_or(10 * cfg.run.test_episodes);
    let result = if episodes == 0 {
        None
    } else {
        eprintln!("lmac: {} seed {}: final evaluation of the best checkpoint, {episodes} greedy episodes", cfg.run.env, cfg.learn.seed);
        let spec = EvalSpec { episodes, method: toml::Table::new(), best: true };
        let r = super::evaluate::evaluate_run(d, cfg, &spec, "final", super::evaluate::EVAL_SEED_OFFSET, interrupted)?;
        eprintln!(
            "lmac: {} seed {}: final evaluation ({} checkpoint, t_env {}): return {:.3}, win rate {:.3}",
            cfg.run.env, cfg.learn.seed, r.checkpoint, r.t_env, r.mean_return, r.win_rate
        );
        Some(r)
    };
    lmac_trainer::train::marl_eval::write_marl_eval(d, cfg, result.as_ref())
}
