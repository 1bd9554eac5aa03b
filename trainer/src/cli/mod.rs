//! What the commands share: the pipeline options, starting a pipeline run and reading its
//! report, step and duration parsing, Ctrl-C.

pub(crate) mod bench;
pub(crate) mod bench_learner;
pub(crate) mod child;
pub(crate) mod clean;
pub(crate) mod design;
pub(crate) mod envs;
pub(crate) mod evaluate;
pub(crate) mod experiment;
pub(crate) mod faults;
pub(crate) mod protocol;
pub(crate) mod report;
pub(crate) mod run;
pub(crate) mod train;

use anyhow::{bail, Result};
use clap::Args;
use lmac_shm_schema::schema::load_env;
use lmac_trainer::pipeline::TrainerReport;
use lmac_trainer::supervisor::{self, RunPlan};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

#[derive(Args, Clone)]
pub(crate) struct PipelineOpts {
    /// Environment, e.g. lbf:8x8-2p-2f-s1-coop (see `lmac envs`).
    #[arg(long, default_value = "lbf:8x8-2p-2f-s1-coop")]
    env: String,
    /// Environments per env server.
    #[arg(long, default_value_t = 32)]
    envs: usize,
    /// Env server processes.
    #[arg(long, default_value_t = 1)]
    servers: usize,
    /// Sub-batches per env server: it steps one while the other's slot travels through the
    /// runner and the trainer (default: 2 when --envs is even, unless the environment's schema
    /// sets double_buffer = false; else 1).
    #[arg(long)]
    sub_batches: Option<usize>,
    /// Slots in each server's shared-memory slab.
    #[arg(long, default_value_t = 4)]
    slots: usize,
    /// Communication protocol applied by the runner: none | fullcomm | protocol files a.json+b.json.
    #[arg(long, default_value = "none")]
    protocol: lmac_protocol_runner::ProtocolSpec,
    /// Env steps to collect (after warm-up).
    #[arg(long, default_value_t = 20_000)]
    steps: u64,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Seconds the processes may take to find each other.
    #[arg(long, default_value_t = 60.0)]
    startup_timeout: f64,
}

pub(crate) fn parse_steps(s: &str) -> Result<u64, String> {
    let t = s.trim().to_ascii_lowercase();
    let (num, mul) = match t.chars().last() {
        Some('k') => (&t[..t.len() - 1], 1_000f64),
        Some('m') => (&t[..t.len() - 1], 1_000_000f64),
        _ => (&t[..], 1f64),
    };
    num.parse::<f64>().map(|v| (v * mul) as u64).map_err(|_| format!("{s:?} is not a step count (e.g. 2M, 500k, 20000)"))
}

pub(crate) fn parse_duration(s: &str) -> Result<f64, String> {
    let t = s.trim().to_ascii_lowercase();
    let (num, mul) = match t.chars().last() {
        Some('h') => (&t[..t.len() - 1], 3600.0),
        Some('m') => (&t[..t.len() - 1], 60.0),
        Some('s') => (&t[..t.len() - 1], 1.0),
        _ => (&t[..], 1.0),
    };
    num.parse::<f64>().ok().filter(|v| *v > 0.0).map(|v| v * mul).ok_or_else(|| format!("{s:?} is not a duration (e.g. 2h, 30m, 90s)"))
}

impl PipelineOpts {
    /// The pipeline of a training run's config (its env, environments, servers and protocol),
    /// with the env servers seeded from `seed`; it runs until the trainer child ends it.
    pub(crate) fn for_run(cfg: &lmac_trainer::train::TrainConfig, seed: u64) -> Result<Self> {
        Ok(PipelineOpts {
            env: cfg.run.env.clone(),
            envs: cfg.run.envs,
            servers: cfg.run.servers,
            // 0 = the default for the environment's schema (pipeline_report applies it).
            sub_batches: (cfg.run.sub_batches != 0).then_some(cfg.run.sub_batches),
            slots: 4,
            protocol: cfg.protocol()?,
            steps: u64::MAX / 4,
            seed,
            startup_timeout: 60.0,
        })
    }
}

pub(crate) fn interrupt_flag() -> Arc<AtomicBool> {
    let flag = Arc::new(AtomicBool::new(false));
    let f = flag.clone();
    let _ = ctrlc::set_handler(move || f.store(true, Ordering::SeqCst));
    flag
}

/// Start the processes of one pipeline run and return the trainer's report. `extra` goes to the
/// trainer, `env_extra` to the env servers.
pub(crate) fn pipeline_report(
    p: &PipelineOpts,
    extra: Vec<String>,
    env_extra: Vec<String>,
    interrupted: Arc<AtomicBool>,
) -> Result<TrainerReport> {
    let schema = load_env(&p.env).map_err(anyhow::Error::msg)?;
    let plan = lmac_protocol_runner::plan_for(&p.protocol, &schema).map_err(anyhow::Error::msg)?;
    if plan.msg_dim() > schema.message_columns {
        bail!(
            "protocol {} writes {} message columns but {} allows {} (its message_columns budget)",
            p.protocol,
            plan.msg_dim(),
            p.env,
            schema.message_columns
        );
    }
    if p.envs == 0 || p.servers == 0 || p.slots == 0 {
        bail!("--envs, --servers and --slots must be at least 1");
    }
    let sub_batches = p.sub_batches.unwrap_or_else(|| supervisor::default_sub_batches(&schema, p.envs));
    if sub_batches == 0 || p.envs % sub_batches != 0 {
        bail!("--sub-batches {sub_batches} must be at least 1 and divide --envs {}", p.envs);
    }
    let rp = RunPlan {
        run: lmac_trainer::run_dir::run_id(),
        env: p.env.clone(),
        servers: p.servers,
        envs_per_server: p.envs,
        sub_batches,
        slots: p.slots,
        msg_dim: plan.msg_dim(),
        protocol: p.protocol.clone(),
        seed: p.seed,
        startup_timeout_s: p.startup_timeout,
        trainer_args: [vec!["--steps".into(), p.steps.to_string()], extra].concat(),
        env_server_args: env_extra,
    };
    Ok(supervisor::run_pipeline(&rp, interrupted)?.report)
}

/// Draw a run's or a design's figures with one of the reporting package's matplotlib modules
/// (`python -m lmac_report.<module> DIR`, the project's Python); a failure is reported, not fatal.
pub(crate) fn plot(module: &str, dir: &std::path::Path) {
    let out = supervisor::python_command().and_then(|mut c| Ok(c.arg("-m").arg(format!("lmac_report.{module}")).arg(dir).output()?));
    match out {
        Ok(o) if o.status.success() => print!("{}", String::from_utf8_lossy(&o.stdout)),
        Ok(o) => eprintln!("lmac: lmac_report.{module} failed: {}", String::from_utf8_lossy(&o.stderr)),
        Err(e) => eprintln!("lmac: lmac_report.{module} failed: {e}"),
    }
}

/// The curves of an experiment and, with the k ablations, its phase plot
/// (`lmac_report.plot_experiment`).
pub(crate) fn plot_experiment(dir: &std::path::Path) {
    plot("plot_experiment", dir);
}
