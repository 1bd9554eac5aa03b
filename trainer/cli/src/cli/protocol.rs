//! `lmac protocol`: check, explain, schema.

use anyhow::{Context, Result};
use clap::Subcommand;
use lmac_shm_schema::schema::load_env;

#[derive(Subcommand)]
pub(crate) enum ProtocolCmd {
    /// Validate protocol phase files (in order) against an environment; errors are the text an LLM gets back.
    Check {
        /// Protocol JSON files: phase 0, then phase 1, ... (concatenated in this order). A design
        /// directory, `paper` (the authors' design for --env) or `paper:<task>` stands for its phase files.
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
        /// Protocol JSON files, a design directory, `paper` (with --env) or `paper:<task>`.
        #[arg(required = true)]
        files: Vec<String>,
        /// Name dimensions by their meaning in this environment.
        #[arg(long)]
        env: Option<String>,
        /// Also say which fields carry nothing on this trajectory dataset (needs --env).
        #[arg(long, value_name = "DIR", requires = "env")]
        dataset: Option<std::path::PathBuf>,
    },
    /// Measure what protocol phases tell each agent on a trajectory dataset, as the design loop
    /// does for its own phases: for phases 0..=k (each k), per agent and state dim, how often a
    /// discriminator recovers the state with the messages and without them (both definitions),
    /// against a constant guess; dead fields too. Writes <out>/phase<k>/{meta,recovery}.json and
    /// <out>/summary.json.
    Measure {
        /// Protocol JSON files: phase 0, then phase 1, ...; a design directory, `paper` or `paper:<task>`.
        #[arg(required = true)]
        files: Vec<String>,
        #[arg(long)]
        env: String,
        /// A trajectory dataset of this environment (e.g. <design>/collect/dataset).
        #[arg(long, value_name = "DIR")]
        dataset: std::path::PathBuf,
        /// Where the results go.
        #[arg(long, value_name = "DIR")]
        out: std::path::PathBuf,
        /// The dims the trend is summarised on (default: phase 0's critical dims, all when none).
        #[arg(long, value_delimiter = ',', value_name = "D,D,...")]
        dims: Vec<usize>,
        /// Discriminator updates per training (default: the design loop's).
        #[arg(long)]
        disc_updates: Option<usize>,
        /// Seed of the held-out split and the discriminators.
        #[arg(long, default_value_t = 0)]
        seed: u64,
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
            let files = expand_specs(&files, Some(&env))?;
            let schema = load_env(&env)?;
            let penv = lmac_protocol_runner::protocol_env(&schema);
            let refs: Vec<&str> = files.iter().map(|s| s.as_str()).collect();
            match lmac_protocol_runner::load_phases(&refs, &penv) {
                Ok(phases) => {
                    for (f, p) in files.iter().zip(&phases) {
                        println!("{f}: {}", protocol::check_summary(p));
                        for w in &p.warnings {
                            println!("{f}: warning: {w}");
                        }
                    }
                    let total = protocol::check_phases(&phases, &penv).map_err(|e| anyhow::anyhow!(protocol::errors_to_text(&e)))?;
                    println!("all phases: {total} message columns per agent (budget {})", schema.message_columns);
                    let plain: Vec<protocol::Protocol> = phases.iter().map(|v| v.protocol.clone()).collect();
                    for line in protocol::constant_fields_report(&plain, &penv) {
                        println!("{line}");
                    }
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
        ProtocolCmd::Measure { files, env, dataset, out, dims, disc_updates, seed } => {
            let files = expand_specs(&files, Some(&env))?;
            measure(&files, &env, &dataset, &out, dims, disc_updates, seed)
        }
        ProtocolCmd::Explain { files, env, dataset } => {
            let files = expand_specs(&files, env.as_deref())?;
            let mut ps = Vec::new();
            for f in &files {
                let text = protocol::read_protocol_file(std::path::Path::new(f))?;
                ps.push(protocol::parse_str(&text).map_err(|e| anyhow::anyhow!("{f}:\n{}", protocol::errors_to_text(&e)))?);
            }
            let penv = match &env {
                Some(e) => Some(lmac_protocol_runner::protocol_env(&load_env(e)?)),
                None => None,
            };
            println!("{}", protocol::explain_phases(&ps, penv.as_ref()));
            if let Some(penv) = &penv {
                let constant = protocol::constant_fields_report(&ps, penv);
                if !constant.is_empty() {
                    println!("Constant by construction (found without a dataset):\n{}", constant.join("\n"));
                }
            }
            if let (Some(d), Some(e), Some(penv)) = (dataset, env, penv) {
                let refs: Vec<&str> = files.iter().map(|s| s.as_str()).collect();
                let phases = lmac_protocol_runner::load_phases(&refs, &penv)?;
                let dead = dead_fields_on(&d, &e, &phases, &penv)?;
                println!();
                println!("{}", dead.join("\n"));
            }
            Ok(0)
        }
    }
}

/// The phase files of each protocol argument, in order: a file as it is; a design directory
/// (from `lmac design`), `paper` (the authors' design for `env`) or `paper:<task>` as its phase
/// files, every form `lmac train --protocol` accepts.
fn expand_specs(args: &[String], env: Option<&str>) -> Result<Vec<String>> {
    let mut files = Vec::new();
    for a in args {
        let named = a == "paper" || a.starts_with("paper:") || std::path::Path::new(a).is_dir();
        if !named {
            files.push(a.clone());
            continue;
        }
        if a == "paper" && env.is_none() {
            anyhow::bail!("`paper` names the authors' design for --env: give --env, or name the task (paper:<task>)");
        }
        let spec = lmac_run::train::resolve_paper_spec(a, env.unwrap_or_default())?;
        files.extend(lmac_run::train::protocol_files(&spec, None)?);
    }
    Ok(files)
}

/// Lines describing the dead fields of `phases` on the dataset in `dir` (one line saying there
/// are none when so).
fn dead_fields_on(
    dir: &std::path::Path,
    env: &str,
    phases: &[lmac_protocol_runner::protocol::ValidatedProtocol],
    penv: &lmac_protocol_runner::protocol::ProtocolEnv,
) -> Result<Vec<String>> {
    let data = lmac_run::dataset::Dataset::load(dir).with_context(|| format!("loading the dataset {}", dir.display()))?;
    if data.header.env != env {
        anyhow::bail!("dataset {} was collected on {}, not {env}", dir.display(), data.header.env);
    }
    let steps: usize = data.episodes.iter().map(|e| e.len).sum();
    let dead = lmac_design::dead_fields::find(&data, phases, penv)?;
    if dead.is_empty() {
        return Ok(vec![format!("dead fields on {} ({steps} steps): none", dir.display())]);
    }
    let mut lines = vec![format!("dead fields on {} ({steps} steps): {}", dir.display(), dead.len())];
    lines.extend(dead.iter().map(|d| format!("warning: {}", d.describe())));
    Ok(lines)
}

/// `lmac protocol measure`.
fn measure(
    files: &[String],
    env: &str,
    dataset: &std::path::Path,
    out: &std::path::Path,
    dims: Vec<usize>,
    disc_updates: Option<usize>,
    seed: u64,
) -> Result<i32> {
    use lmac_design::{meta, run, DesignContext};
    let schema = load_env(env)?;
    let penv = lmac_protocol_runner::protocol_env(&schema);
    let refs: Vec<&str> = files.iter().map(|s| s.as_str()).collect();
    let phases = lmac_protocol_runner::load_phases(&refs, &penv)?;
    let data = lmac_run::dataset::Dataset::load(dataset).with_context(|| format!("loading the dataset {}", dataset.display()))?;
    if data.header.env != env {
        anyhow::bail!("dataset {} was collected on {}, not {env}", dataset.display(), data.header.env);
    }
    if let Some(&d) = dims.iter().find(|&&d| d >= schema.state_dim) {
        anyhow::bail!("--dims: state dim {d} is out of range (state_dim {})", schema.state_dim);
    }
    let mut cfg = meta::MetaConfig::default();
    if let Some(u) = disc_updates {
        cfg.discriminator.updates = u;
    }
    cfg.discriminator.validate()?;
    let ctx = DesignContext { env_name: env, schema: &schema, env: &penv, dataset: Some(&data), seed };
    let (fixed, source) = if dims.is_empty() { run::fixed_dims(&phases[0]) } else { (dims, "--dims") };
    let mut evaluations = Vec::new();
    for k in 0..phases.len() {
        let (_, ev) = run::evaluate_phase(&ctx, &phases[..=k], k, &fixed, &cfg, &out.join(format!("phase{k}")))?;
        evaluations.push(ev);
    }
    let summary = serde_json::json!({
        "env": env,
        "designer": "given protocol",
        "protocol": files,
        "alpha": schema.alpha,
        "dataset": dataset.display().to_string(),
        "dataset_episodes": data.episodes.len(),
        "fixed_dims": fixed,
        "fixed_dims_source": source,
        "evaluations": evaluations,
    });
    std::fs::write(out.join("summary.json"), serde_json::to_string_pretty(&summary)?)?;
    for e in &evaluations {
        println!("phases 0..={} ({} message columns), fixed dims {}", e.phase, e.message_columns, e.fixed_dims.summary_line());
    }
    lmac_run::workflow::plot("plot_design", out);
    println!("written: {}/summary.json, recovery.png, phase<k>/{{meta,recovery}}.json", out.display());
    Ok(0)
}
