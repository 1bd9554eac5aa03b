//! `lmac train`: resolve the configs, create or resume the run directories, train each seed
//! through the pipeline, plot.

use super::parse_steps;
use anyhow::{Context, Result};
use clap::Args;
use lmac_run::workflow::{interrupt_flag, plot, seed_dirs, train_dirs_holding};

pub(crate) const TRAIN_AFTER_HELP: &str = "\
Update ratio: by default the learner follows the LMAC paper's schedule (the authors' EPyMARL
episode runner): run.updates_per_episode = 1 gradient update (of learn.batch_size = 32 episodes)
per collected episode once the buffer holds 32, the target network copied every 200 episodes =
200 updates, and each update on both cores (acting waits for the learner at this ratio): the
batch's halves on two threads (learn.data_parallel) or the target network unrolled on the second
(learn.parallel_target). --preset paper spells these defaults out, with the authors' time limit (a
termination) and, for LMAC, their GRU-gate encoder; --preset epymarl is the same
schedule on one core; --preset pymarl-parallel is pymarl's parallel runner with 8 environments,
0.125 updates per episode (8x fewer; the target copied every 25 updates), lmac's default before
the paper's schedule was affordable; --preset released is everything as the authors' released
code runs it (its runner, and for LMAC their module and reward handling). Each environment
switches to new weights when its next episode starts.

Resuming: --resume DIR continues every unfinished seed in DIR (a group or one seed) from its
last checkpoint (run.checkpoint_interval env steps apart, and one at the end). Without the saved
replay buffer (run.save_buffer = false) the learner refills learn.batch_size episodes before it
updates again. Metrics rows logged after that checkpoint are dropped, so curves continue
without a step backwards; each checkpoint is logged in metrics.jsonl.";

/// `--algo`'s values, with each method's line, from the method registry.
pub(crate) fn algo_names() -> clap::builder::PossibleValuesParser {
    clap::builder::PossibleValuesParser::new(
        lmac_run::learn::methods::REGISTRY.iter().map(|m| clap::builder::PossibleValue::new(m.name).help(m.about)),
    )
}

/// The presets with their meanings, for `--preset` (one list: `lmac_run::train::PRESETS`).
pub(crate) fn preset_names() -> clap::builder::PossibleValuesParser {
    clap::builder::PossibleValuesParser::new(
        lmac_run::train::PRESETS.iter().map(|(name, about)| clap::builder::PossibleValue::new(*name).help(*about)),
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
    /// A named bundle of settings, applied before --set.
    #[arg(long, value_parser = preset_names())]
    preset: Option<String>,
    /// Where run directories go.
    #[arg(long, default_value = "runs")]
    out: std::path::PathBuf,
    /// Continue the runs in this directory (a seed's directory or a group of seeds).
    #[arg(long, conflicts_with_all = ["env", "algo", "protocol", "config", "set", "steps", "preset"])]
    resume: Option<std::path::PathBuf>,
    /// With --resume: continue a run whose config.toml was edited since its last checkpoint,
    /// under the new settings (each change is printed). Without it such a resume is refused with
    /// the list of changes; the step target and the test, log and checkpoint cadence may always
    /// change.
    #[arg(long, requires = "resume")]
    allow_changed: bool,
}

pub(crate) fn train(a: TrainArgs) -> Result<i32> {
    use lmac_run::train::TrainConfig;
    let interrupted = interrupt_flag();
    // The seed directories to run, each with its resolved config.toml.
    // The locks of seed directories this command made (taken before anything was written in them).
    let mut held = Vec::new();
    // A new group's runs share the resolution made while checking its config (seeds apart).
    let mut resolved = None;
    let (group, dirs): (std::path::PathBuf, Vec<std::path::PathBuf>) = if let Some(r) = &a.resume {
        seed_dirs(r)?
    } else {
        let mut overrides = lmac_run::train::preset_then(a.preset.as_deref(), a.algo.as_deref(), &a.set)?;
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
        let (mut cfg, mut run) = TrainConfig::resolve_with_run(a.config.as_deref(), &overrides)?;
        // Protocol files by absolute path, so a resumed run finds them from anywhere. A paper
        // design (`paper`, `paper:<task>`) stays as named: it is found in the repository each time.
        let paper = lmac_run::train::resolve_paper_spec(&cfg.run.protocol, &cfg.run.env)? != cfg.run.protocol;
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
        // Valid but suspicious protocol files (another environment's, or an older schema's).
        for w in &run.compiled.warnings {
            eprintln!("lmac: warning: run.protocol: {w}");
        }
        // The same files, now by the absolute paths the children are given.
        run.protocol = cfg.protocol()?;
        // A group directory of this command's own (two launches in the same second get two),
        // and each seed's lock taken before its config is written: no other lmac ever trains a
        // directory with a config it did not write.
        let parent = a.out.join(lmac_run::run_dir::env_dir_name(&cfg.run.env)).join(&cfg.run.algo);
        let group = lmac_run::run_dir::create_unique_dir(&parent, &lmac_run::run_dir::stamp())?;
        let mut dirs = Vec::new();
        for &seed in &a.seeds {
            let mut c = cfg.clone();
            c.learn.seed = seed;
            let d = group.join(format!("seed{seed}"));
            std::fs::create_dir(&d).with_context(|| format!("creating {}", d.display()))?;
            held.push(Some(lmac_run::run_dir::lock(&d)?));
            c.save_new_run(&d)?;
            dirs.push(d);
        }
        resolved = Some(run);
        (group, dirs)
    };
    eprintln!("lmac: training {} run(s) in {}", dirs.len(), group.display());
    let per_dir: Vec<_> = dirs.iter().map(|_| resolved.as_ref()).collect();
    train_dirs_holding(&dirs, held, &per_dir, a.allow_changed, interrupted)?;
    plot("plot_runs", &group);
    Ok(0)
}
