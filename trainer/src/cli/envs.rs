//! `lmac envs`: the environments and their dimensions.

use anyhow::{bail, Result};
use lmac_shm_schema::schema::all_envs;

pub(crate) fn envs(check: bool, json: bool) -> Result<i32> {
    let mut rows = Vec::new();
    let mut bad = 0;
    for (path, r) in all_envs().map_err(anyhow::Error::msg)? {
        match r {
            Ok(s) => rows.push(s),
            Err(e) => {
                bad += 1;
                eprintln!("{e}");
                if check {
                    bail!("invalid schema {}", path.display());
                }
            }
        }
    }
    if json {
        let v: Vec<_> = rows
            .iter()
            .map(|s| {
                serde_json::json!({
                    "name": s.name, "n_agents": s.n_agents, "obs_dim": s.obs_dim, "state_dim": s.state_dim,
                    "n_actions": s.n_actions, "episode_limit": s.episode_limit, "message_columns": s.message_columns, "alpha": s.alpha,
                })
            })
            .collect();
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        println!(
            "{:<42} {:>6} {:>5} {:>6} {:>7} {:>6} {:>5} {:>6}",
            "environment", "agents", "obs", "state", "actions", "limit", "msg", "alpha"
        );
        for s in &rows {
            println!(
                "{:<42} {:>6} {:>5} {:>6} {:>7} {:>6} {:>5} {:>6}",
                s.name, s.n_agents, s.obs_dim, s.state_dim, s.n_actions, s.episode_limit, s.message_columns, s.alpha
            );
        }
    }
    Ok(if bad > 0 && check { 1 } else { 0 })
}
