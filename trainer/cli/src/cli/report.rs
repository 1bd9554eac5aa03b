//! `lmac report`: the project's Python module `lmac_report` (env-server/lmac_report/) does the
//! work; its argparse is the one definition of the options, so everything after `report`,
//! `--help` included, is passed through.

use anyhow::{Context, Result};
use clap::Args;
use lmac_run::supervisor;

#[derive(Args)]
#[command(disable_help_flag = true)]
pub(crate) struct ReportArgs {
    /// RUNS... [--out DIR] [--reps N] [--seed S] [--metric return|win_rate] [--normalise min-max]
    /// (see `lmac report --help`).
    #[arg(trailing_var_arg = true, allow_hyphen_values = true, value_name = "ARGS")]
    args: Vec<String>,
}

pub(crate) fn report(a: ReportArgs) -> Result<i32> {
    let status = supervisor::python_command()?
        .args(["-m", "lmac_report"])
        .args(&a.args)
        .env("LMAC_REPORT_PROG", "lmac report")
        .status()
        .context("starting python -m lmac_report")?;
    Ok(status.code().unwrap_or(1))
}
