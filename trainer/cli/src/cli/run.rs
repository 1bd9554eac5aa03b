//! `lmac run`: the pipeline with a random policy (throughput, invariant checks).

use super::PipelineOpts;
use anyhow::{Context, Result};
use clap::Args;
use lmac_run::supervisor::TrainerJob;
use lmac_run::workflow::{interrupt_flag, pipeline_report};

#[derive(Args)]
pub(crate) struct RunArgs {
    #[command(flatten)]
    p: PipelineOpts,
    /// Check every slot: message columns, episode ids, steps and boundaries.
    #[arg(long)]
    verify: bool,
    /// Write one JSON line per finished episode to this file.
    #[arg(long)]
    episodes_out: Option<std::path::PathBuf>,
    /// Print the report as JSON.
    #[arg(long)]
    json: bool,
}

pub(crate) fn run(a: RunArgs) -> Result<i32> {
    let episodes_out = match &a.episodes_out {
        Some(p) => Some(
            std::fs::canonicalize(p.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(std::path::Path::new(".")))?
                .join(p.file_name().context("--episodes-out needs a file name")?),
        ),
        None => None,
    };
    let job = TrainerJob { verify: a.verify, episodes_out, progress: true, ..Default::default() };
    let report = pipeline_report(&a.p.pipeline(), job, vec![], interrupt_flag())?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        println!(
            "{}: {} env steps in {:.2} s = {:.0} env-steps/s through the pipeline ({} servers x {} envs, protocol {}); {} episodes, mean team return {:.3}{}",
            a.p.env, report.env_steps, report.seconds, report.env_steps_per_s,
            a.p.servers, a.p.envs, a.p.protocol, report.episodes, report.mean_return,
            if a.verify { format!("; {} invariant violations", report.violation_count) } else { String::new() }
        );
    }
    Ok(if report.violation_count > 0 { 1 } else { 0 })
}
