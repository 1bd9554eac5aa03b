//! A run's results in marl-eval's JSON shape (InstaDeep's `marl-eval`, the format the field's
//! tools read), written as `<seed dir>/marl_eval.json`:
//!
//! ```text
//! {env family: {task: {algo: {"seed_<k>": {
//!     "step_<i>": {"step_count": t_env, "return": [mean test return], "win_rate": [rate]},
//!     ...,
//!     "absolute_metrics": {"return": [per-episode returns], "win_rate": [rate]},
//!     "absolute_metrics_source": {"checkpoint": "best", "t_env": step of that checkpoint}}}}}}
//! ```
//!
//! Every entry of `absolute_metrics` is a list of numbers, as marl-eval reads them; which
//! checkpoint was evaluated is said beside it (runs written before 2026-12-04 carry
//! `checkpoint` and `t_env` inside `absolute_metrics`, which `lmac report` skips).
//!
//! The env family and the task are the env name split at its first ':' (`lbf` /
//! `8x8-2p-2f-s1-coop`); step i is the run's i-th test phase (each a mean over
//! `run.test_episodes` greedy episodes); `absolute_metrics` is the final evaluation of the best
//! test phase's checkpoint (absent when the run has none).

use std::path::Path;

use anyhow::{Context, Result};
use serde_json::{json, Map, Value};

use super::evaluate::EvalResult;
use super::{read_metrics, TrainConfig};

/// The run's marl-eval document from its metrics (test rows) and its final evaluation.
pub fn marl_eval_json(run_dir: &Path, cfg: &TrainConfig, final_eval: Option<&EvalResult>) -> Result<Value> {
    let (family, task) = cfg.run.env.split_once(':').unwrap_or((cfg.run.env.as_str(), cfg.run.env.as_str()));
    let mut seed = Map::new();
    let tests = read_metrics(run_dir)?.into_iter().filter_map(|r| Some((r.t_env, r.test_return_mean?, r.test_win_rate.unwrap_or(0.0))));
    for (i, (t_env, ret, win)) in tests.enumerate() {
        seed.insert(format!("step_{i}"), json!({"step_count": t_env, "return": [ret], "win_rate": [win]}));
    }
    if let Some(e) = final_eval {
        seed.insert("absolute_metrics".into(), json!({"return": e.returns, "win_rate": [e.win_rate]}));
        seed.insert("absolute_metrics_source".into(), json!({"checkpoint": e.checkpoint, "t_env": e.t_env}));
    }
    Ok(json!({family: {task: {cfg.run.algo.clone(): {format!("seed_{}", cfg.learn.seed): Value::Object(seed)}}}}))
}

/// Write `marl_eval.json` in the run directory (atomically).
pub fn write_marl_eval(run_dir: &Path, cfg: &TrainConfig, final_eval: Option<&EvalResult>) -> Result<()> {
    let doc = marl_eval_json(run_dir, cfg, final_eval)?;
    let path = run_dir.join("marl_eval.json");
    crate::safe_fs::write_replace(&path, &serde_json::to_vec_pretty(&doc)?).context("writing the marl-eval record")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn test_rows_become_steps_and_the_final_evaluation_absolute_metrics() {
        let dir = std::env::temp_dir().join(format!("lmac-marl-eval-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let rows = [
            r#"{"t_env":0,"episodes":0,"updates":0,"wall_s":0.1,"env_steps_per_s":0.0,"epsilon":1.0,"test_return_mean":0.0,"test_win_rate":0.0}"#,
            r#"{"t_env":5000,"episodes":200,"updates":19,"wall_s":1.0,"env_steps_per_s":5000.0,"epsilon":0.9,"train_return_mean":0.01}"#,
            r#"{"t_env":10010,"episodes":400,"updates":44,"wall_s":2.0,"env_steps_per_s":5000.0,"epsilon":0.8,"test_return_mean":0.25,"test_win_rate":0.5}"#,
        ];
        std::fs::write(dir.join("metrics.jsonl"), rows.join("\n") + "\n").unwrap();
        let mut cfg = TrainConfig::default();
        cfg.run.env = "lbf:8x8-2p-2f-s1-coop".into();
        cfg.run.algo = "ndq".into();
        cfg.learn.seed = 3;
        let eval = EvalResult { returns: vec![1.0, 0.5], win_rate: 0.5, checkpoint: "best".into(), t_env: 10010, ..Default::default() };
        let v = marl_eval_json(&dir, &cfg, Some(&eval)).unwrap();
        let seed = &v["lbf"]["8x8-2p-2f-s1-coop"]["ndq"]["seed_3"];
        assert_eq!(seed["step_0"], json!({"step_count": 0, "return": [0.0], "win_rate": [0.0]}));
        assert_eq!(seed["step_1"], json!({"step_count": 10010, "return": [0.25], "win_rate": [0.5]}));
        assert!(seed.get("step_2").is_none(), "a training row is not a step");
        assert_eq!(seed["absolute_metrics"]["return"], json!([1.0, 0.5]));
        assert_eq!(seed["absolute_metrics_source"], json!({"checkpoint": "best", "t_env": 10010}));
        // Only lists of numbers in absolute_metrics (what marl-eval and lmac report read).
        assert!(seed["absolute_metrics"].as_object().unwrap().values().all(|v| v.is_array()), "{seed}");
        write_marl_eval(&dir, &cfg, None).unwrap();
        let back: Value = serde_json::from_slice(&std::fs::read(dir.join("marl_eval.json")).unwrap()).unwrap();
        assert!(back["lbf"]["8x8-2p-2f-s1-coop"]["ndq"]["seed_3"].get("absolute_metrics").is_none());
        let _ = std::fs::remove_dir_all(&dir);
    }
}
