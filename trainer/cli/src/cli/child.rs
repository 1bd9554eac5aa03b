//! `lmac child`: the entry points of the processes `lmac` starts (protocol runner, trainer).

use anyhow::{Context, Result};
use clap::{Args, Subcommand};
use lmac_protocol_runner::runner::{self as prunner, RunnerArgs};
use lmac_run::pipeline::{self, MessageCheck, RandomActor, TrainerArgs, TrainerReport};
use lmac_run::supervisor::{TrainerJob, TrainerJobFile, TrainerWork};
use lmac_shm_schema::schema::load_env;
use std::io::Write;
use std::time::Duration;

#[derive(Args, Clone)]
pub(crate) struct ChildOpts {
    #[arg(long)]
    run: String,
    #[arg(long)]
    env: String,
    #[arg(long)]
    members: usize,
    #[arg(long)]
    slots: usize,
    #[arg(long)]
    protocol: lmac_protocol_runner::ProtocolSpec,
    #[arg(long, default_value_t = 60.0)]
    startup_timeout: f64,
}

#[derive(Subcommand)]
pub(crate) enum ChildCmd {
    Runner(ChildOpts),
    Trainer {
        #[command(flatten)]
        o: ChildOpts,
        /// The job the parent wrote for this process (`supervisor::TrainerJobFile`, JSON): env
        /// steps, seed, what to do (act randomly, train or evaluate a run directory), where to
        /// write the report.
        #[arg(long)]
        job: std::path::PathBuf,
    },
}

pub(crate) fn child(c: ChildCmd) -> Result<i32> {
    // Stop gracefully on SIGTERM/SIGINT: the waits return and the process cleans up.
    let _ = ctrlc::set_handler(lmac_shm_schema::ring::request_stop);
    let code = match c {
        ChildCmd::Runner(o) => {
            let schema = load_env(&o.env)?;
            // Compiled once; each ring member gets its own copy (its own history).
            let plan = lmac_protocol_runner::plan_for(&o.protocol, &schema)?;
            let mut plans: Vec<_> = (0..o.members).map(|_| plan.fresh()).collect();
            let args = RunnerArgs {
                run: o.run,
                schema,
                n_members: o.members,
                n_slots: o.slots,
                startup_timeout: Duration::from_secs_f64(o.startup_timeout),
            };
            match prunner::run(&args, &mut plans) {
                Ok(_) => 0,
                Err(prunner::RunnerError::Ring(lmac_shm_schema::RingError::Stopped))
                | Err(prunner::RunnerError::Slab(lmac_shm_schema::SlabError::Stopped { .. })) => 0,
                Err(e) => {
                    eprintln!("lmac: {e}");
                    3
                }
            }
        }
        ChildCmd::Trainer { o, job } => {
            let TrainerJobFile { steps, seed, report: report_to, job } = TrainerJobFile::load(&job)?;
            let TrainerJob { warmup, verify, episodes_out, progress, work } = job;
            let schema = load_env(&o.env)?;
            // The one compile in this process: training, evaluation and the message check all
            // read this.
            let compiled = lmac_protocol_runner::compile_for(&o.protocol, &schema)?;
            let check = match o.protocol {
                lmac_protocol_runner::ProtocolSpec::FullComm => MessageCheck::FullComm,
                lmac_protocol_runner::ProtocolSpec::None => MessageCheck::None,
                lmac_protocol_runner::ProtocolSpec::Files(_) => MessageCheck::Recompute,
            };
            let args = TrainerArgs {
                run: o.run,
                schema,
                n_members: o.members,
                n_slots: o.slots,
                compiled,
                env_steps: steps,
                warmup_slots: warmup,
                startup_timeout: Duration::from_secs_f64(o.startup_timeout),
                verify: verify.then_some(check),
                protocol: o.protocol.clone(),
                progress,
            };
            // Training and evaluation end the same way: a report for the parent, or the error.
            let finish = |r: Result<TrainerReport>| match r {
                Ok(report) => write_report(&report_to, &report).map(|()| 0),
                Err(e) if e.to_string().contains("stopped by request") => Ok(0),
                Err(e) => {
                    eprintln!("lmac: trainer: {e:#}");
                    Ok(4)
                }
            };
            match &work {
                TrainerWork::Evaluate { dir, spec } => {
                    return finish(lmac_run::train::evaluate::evaluate_in_child(dir, spec, &args).map(|_| TrainerReport::default()))
                }
                TrainerWork::Train { dir } => return finish(lmac_run::train::train_in_child(dir, &args, progress)),
                TrainerWork::Random => {}
            }
            let mut actor = RandomActor::new(seed);
            match pipeline::run(&args, &mut actor) {
                Ok(report) => {
                    if let Some(path) = episodes_out {
                        let mut f =
                            std::io::BufWriter::new(std::fs::File::create(&path).with_context(|| format!("creating {}", path.display()))?);
                        for e in &report.episode_log {
                            writeln!(f, "{}", serde_json::to_string(e)?)?;
                        }
                    }
                    write_report(&report_to, &report)?;
                    0
                }
                Err(pipeline::PipelineError::Ring(lmac_shm_schema::RingError::Stopped))
                | Err(pipeline::PipelineError::Slab(lmac_shm_schema::SlabError::Stopped { .. })) => 0,
                Err(e) => {
                    eprintln!("lmac: {e}");
                    3
                }
            }
        }
    };
    Ok(code)
}

/// Write the report atomically (the parent reads it once this process has exited), never
/// through a symlink planted at its temporary name.
fn write_report(path: &std::path::Path, report: &TrainerReport) -> Result<()> {
    lmac_run::safe_fs::write_replace(path, &serde_json::to_vec(report)?).with_context(|| format!("writing the report {}", path.display()))
}
