//! `lmac evaluate`: greedy test episodes of trained runs (their last checkpoints) through the
//! pipeline, optionally with the method's test-time settings changed, e.g. NDQ's message cuts.

use anyhow::{bail, Context, Result};
use clap::Args;
use lmac_run::train::evaluate::{EvalResult, EvalSpec};
use lmac_run::train::TrainConfig;
use lmac_run::workflow::{evaluate_run, interrupt_flag, seed_dirs, EVAL_SEED_OFFSET};

pub(crate) const EVALUATE_AFTER_HELP: &str = "\
Each run is evaluated from its last checkpoint with the environments, protocol and settings of its
config.toml, every agent acting greedily. --set changes a test-time setting of the method for the
evaluation only: method.cut=P (NDQ: zero the bottom P% of message dims by |mean|), method.prune=P
(MAIC: drop attention weights below P / n), method.dropout_when_acting=B (LMAC: the embedding's
dropout on or off while acting). Several --set values of one key (e.g. --set
method.cut=0,90,95,98) evaluate each in turn. Results are printed, kept in each seed's
evaluations/ folder (the spec as <time>_<k>.json, the result as <time>_<k>.result.json) and, with
--json, written together.";

#[derive(Args)]
pub(crate) struct EvaluateArgs {
    /// Run directories: a seed's directory or a group of seeds (from `lmac train` or `lmac experiment`).
    #[arg(required = true)]
    runs: Vec<std::path::PathBuf>,
    /// Greedy test episodes per run and setting.
    #[arg(long, default_value_t = 100)]
    episodes: usize,
    /// A test-time method setting, KEY=VALUE or KEY=V1,V2,... (one evaluation per value).
    #[arg(long = "set", value_name = "method.KEY=VALUES")]
    set: Vec<String>,
    /// Seed offset of the evaluation environments (their seeds differ from training's).
    #[arg(long, default_value_t = EVAL_SEED_OFFSET)]
    seed: u64,
    /// Evaluate the checkpoint of each run's best test phase (`checkpoint_best/`) instead of its
    /// last one.
    #[arg(long)]
    best: bool,
    /// Write every result here (JSON).
    #[arg(long)]
    json: Option<std::path::PathBuf>,
}

/// `--set` values as the list of `[method]` tables to evaluate (one empty table without --set).
fn settings(set: &[String]) -> Result<Vec<toml::Table>> {
    let mut tables = vec![toml::Table::new()];
    for s in set {
        let (key, values) = s.split_once('=').with_context(|| format!("--set {s}: expected method.KEY=VALUE"))?;
        let Some(key) = key.trim().strip_prefix("method.") else {
            bail!("--set {s}: only method settings change at evaluation (method.KEY=VALUE)");
        };
        let mut next = Vec::new();
        for v in values.split(',') {
            let value = lmac_run::train::config::override_value(v.trim());
            for t in &tables {
                let mut t = t.clone();
                t.insert(key.to_string(), value.clone());
                next.push(t);
            }
        }
        tables = next;
    }
    Ok(tables)
}

pub(crate) fn evaluate(a: EvaluateArgs) -> Result<i32> {
    if a.episodes == 0 {
        bail!("--episodes must be at least 1");
    }
    let interrupted = interrupt_flag();
    let tables = settings(&a.set)?;
    let mut dirs = Vec::new();
    for r in &a.runs {
        dirs.extend(seed_dirs(r)?.1);
    }
    let stamp = lmac_run::run_dir::stamp();
    let mut results: Vec<EvalResult> = Vec::new();
    for d in &dirs {
        let cfg = TrainConfig::load(d)?;
        let run = cfg.resolve_run()?;
        for (k, method) in tables.iter().enumerate() {
            let spec = EvalSpec { episodes: a.episodes, method: method.clone(), best: a.best };
            let label = if method.is_empty() { "as trained".to_string() } else { method.to_string().trim().replace('\n', ", ") };
            eprintln!("lmac: evaluating {} ({label}), {} episodes", d.display(), a.episodes);
            let r = evaluate_run(d, &cfg, &run, &spec, &format!("{stamp}_{k}"), a.seed, interrupted.clone())?;
            println!(
                "{}  {}  {label}: return {:.3} +- {:.3}, win rate {:.3} ({} episodes, t_env {})",
                r.algo,
                d.display(),
                r.mean_return,
                r.std_return,
                r.win_rate,
                r.episodes,
                r.t_env
            );
            results.push(r);
        }
    }
    if let Some(path) = &a.json {
        std::fs::write(path, serde_json::to_vec_pretty(&results)?).with_context(|| format!("writing {}", path.display()))?;
        eprintln!("lmac: wrote {}", path.display());
    }
    Ok(0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn set_values_expand_into_one_table_per_combination() {
        assert_eq!(settings(&[]).unwrap(), vec![toml::Table::new()]);
        let t = settings(&["method.cut=0,90".into(), "method.x=\"a\"".into()]).unwrap();
        assert_eq!(t.len(), 2);
        assert_eq!(t[0].get("cut"), Some(&toml::Value::Integer(0)));
        assert_eq!(t[1].get("cut"), Some(&toml::Value::Integer(90)));
        assert_eq!(t[1].get("x"), Some(&toml::Value::String("a".into())));
        assert!(settings(&["learn.lr=0.1".into()]).unwrap_err().to_string().contains("only method settings"));
        assert!(settings(&["method.cut".into()]).is_err());
    }
}
