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
    },
    /// Explain protocol files in plain words: who sends what to whom and why.
    Explain {
        #[arg(required = true)]
        files: Vec<String>,
        /// Name dimensions by their meaning in this environment.
        #[arg(long)]
        env: Option<String>,
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
        ProtocolCmd::Check { files, env } => {
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
                    Ok(0)
                }
                Err(e) => {
                    eprintln!("{e}");
                    Ok(1)
                }
            }
        }
        ProtocolCmd::Explain { files, env } => {
            let mut ps = Vec::new();
            for f in &files {
                let text = std::fs::read_to_string(f).with_context(|| format!("reading {f}"))?;
                ps.push(protocol::parse_str(&text).map_err(|e| anyhow::anyhow!("{f}:\n{}", protocol::errors_to_text(&e)))?);
            }
            let penv = match env {
                Some(e) => Some(lmac_protocol_runner::protocol_env(&load_env(&e).map_err(anyhow::Error::msg)?)),
                None => None,
            };
            println!("{}", protocol::explain_phases(&ps, penv.as_ref()));
            Ok(0)
        }
    }
}
