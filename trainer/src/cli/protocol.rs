//! `lmac protocol`: check, explain, schema.

use anyhow::{Context, Result};
use clap::Subcommand;
use lmac_shm_schema::schema::load_env;

#[derive(Subcommand)]
pub(crate) enum ProtocolCmd {
    /// Validate protocol phase files (in order) against an environment; errors are the text an LLM gets back.
    Check {
        /// Protocol JSON files: phase 0, then phase 1, ... (concatenated in this order).
        #[arg(required = true)]
        files: Vec<String>,
        #[arg(long)]
        env: String,
        /// Also look for dead fields on this trajectory dataset (e.g. <design>/collect/dataset):
        /// links whose columns are constant or copy what the receiver already observes.
        #[arg(long, value_name = "DIR")]
        dataset: Option<std::path::PathBuf>,
    },
    /// Explain protocol files in plain words: who sends what to whom and why.
    Explain {
        #[arg(required = true)]
        files: Vec<String>,
        /// Name dimensions by their meaning in this environment.
        #[arg(long)]
        env: Option<String>,
        /// Also say which fields carry nothing on this trajectory dataset (needs --env).
        #[arg(long, value_name = "DIR", requires = "env")]
        dataset: Option<std::path::PathBuf>,
    },
    /// Print the protocol language's JSON Schema.
    Schema,
}

pub(crate) fn protocol_cmd(c: ProtocolCmd) -> Result<i32> {
    use lmac_protocol_runner::protocol;
    match c {
        ProtocolCmd::Schema => {
            println!("{}", protocol::schema_json());
            Ok(0)
        }
        ProtocolCmd::Check { files, env, dataset } => {
            let schema = load_env(&env).map_err(anyhow::Error::msg)?;
            let penv = lmac_protocol_runner::protocol_env(&schema);
            let refs: Vec<&str> = files.iter().map(|s| s.as_str()).collect();
            match lmac_protocol_runner::load_phases(&refs, &penv) {
                Ok(phases) => {
                    for (f, p) in files.iter().zip(&phases) {
                        println!("{f}: {}", protocol::check_summary(p));
                    }
                    let total = protocol::check_phases(&phases, &penv).map_err(|e| anyhow::anyhow!(protocol::errors_to_text(&e)))?;
                    println!("all phases: {total} message columns per agent (budget {})", schema.message_columns);
                    if let Some(d) = dataset {
                        let dead = dead_fields_on(&d, &env, &phases, &penv)?;
                        if !dead.is_empty() {
                            println!("{}", dead.join("\n"));
                        }
                    }
                    Ok(0)
                }
                Err(e) => {
                    eprintln!("{e}");
                    Ok(1)
                }
            }
        }
        ProtocolCmd::Explain { files, env, dataset } => {
            let mut ps = Vec::new();
            for f in &files {
                let text = std::fs::read_to_string(f).with_context(|| format!("reading {f}"))?;
                ps.push(protocol::parse_str(&text).map_err(|e| anyhow::anyhow!("{f}:\n{}", protocol::errors_to_text(&e)))?);
            }
            let penv = match &env {
                Some(e) => Some(lmac_protocol_runner::protocol_env(&load_env(e).map_err(anyhow::Error::msg)?)),
                None => None,
            };
            println!("{}", protocol::explain_phases(&ps, penv.as_ref()));
            if let (Some(d), Some(e), Some(penv)) = (dataset, env, penv) {
                let refs: Vec<&str> = files.iter().map(|s| s.as_str()).collect();
                let phases = lmac_protocol_runner::load_phases(&refs, &penv).map_err(anyhow::Error::msg)?;
                let dead = dead_fields_on(&d, &e, &phases, &penv)?;
                println!();
                println!("{}", dead.join("\n"));
            }
            Ok(0)
        }
    }
}

/// Lines describing the dead fields of `phases` on the dataset in `dir` (one line saying there
/// are none when so).
fn dead_fields_on(
    dir: &std::path::Path,
    env: &str,
    phases: &[lmac_protocol_runner::protocol::ValidatedProtocol],
    penv: &lmac_protocol_runner::protocol::ProtocolEnv,
) -> Result<Vec<String>> {
    let data = lmac_trainer::dataset::Dataset::load(dir).with_context(|| format!("loading the dataset {}", dir.display()))?;
    if data.header.env != env {
        anyhow::bail!("dataset {} was collected on {}, not {env}", dir.display(), data.header.env);
    }
    let steps: usize = data.episodes.iter().map(|e| e.len).sum();
    let dead = lmac_trainer::design::dead_fields::find(&data, phases, penv)?;
    if dead.is_empty() {
        return Ok(vec![format!("dead fields on {} ({steps} steps): none", dir.display())]);
    }
    let mut lines = vec![format!("dead fields on {} ({steps} steps): {}", dir.display(), dead.len())];
    lines.extend(dead.iter().map(|d| format!("warning: {}", d.describe())));
    Ok(lines)
}
