//! `lmac envs`: the environments and their dimensions; `--check` validates every schema file,
//! `--generate pz:...` writes the schema of a PettingZoo environment.

use anyhow::{anyhow, bail, Context, Result};
use lmac_shm_schema::schema::{all_envs, schema_dir, EnvSchema};
use lmac_trainer::supervisor;
use std::path::Path;

/// The family whose schemas `--generate` writes and `--check` compares with the environment
/// itself (env-server/lmac_env/pz.py).
const PZ: &str = "pz";

/// The name a schema file's place gives it: `<dir>/<family>/<variant>.toml` -> `family:variant`.
fn place_name(path: &Path) -> Option<String> {
    let variant = path.file_stem()?.to_str()?;
    let family = path.parent()?.file_name()?.to_str()?;
    Some(format!("{family}:{variant}"))
}

/// `python -m lmac_env.pz <args>` with the project's Python (as env servers are started).
fn pz_command(args: &[&str]) -> Result<std::process::Command> {
    let mut c = supervisor::python_command()?;
    c.args(["-m", "lmac_env.pz"]).args(args);
    Ok(c)
}

pub(crate) fn envs(check: bool, json: bool) -> Result<i32> {
    let mut rows = Vec::new();
    let mut bad = 0;
    for (path, r) in all_envs().map_err(anyhow::Error::msg)? {
        match r {
            Ok(s) => {
                if check && place_name(&path).as_deref() != Some(s.name.as_str()) {
                    eprintln!(
                        "{}: name: {:?} does not match the file's place ({:?}); `--env` finds a schema by its place",
                        path.display(),
                        s.name,
                        place_name(&path).unwrap_or_default()
                    );
                    bail!("invalid schema {}", path.display());
                }
                if check && s.name.starts_with("pz:") {
                    // The dims must also fit the environment (the env server refuses it otherwise).
                    let out = pz_command(&["check", s.name.as_str(), "--schema"])?.arg(&path).output().context("starting Python")?;
                    if !out.status.success() {
                        eprint!("{}", String::from_utf8_lossy(&out.stderr));
                        bail!("schema {} does not fit its environment", path.display());
                    }
                }
                rows.push(s)
            }
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
                    "n_actions": s.n_actions, "episode_limit": s.episode_limit, "message_columns": s.message_columns,
                    "fullcomm_columns": s.fullcomm_columns(), "alpha": s.alpha,
                })
            })
            .collect();
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        println!(
            "{:<42} {:>6} {:>5} {:>6} {:>7} {:>6} {:>5} {:>8} {:>6}",
            "environment", "agents", "obs", "state", "actions", "limit", "msg", "fullcomm", "alpha"
        );
        for s in &rows {
            println!(
                "{:<42} {:>6} {:>5} {:>6} {:>7} {:>6} {:>5} {:>8} {:>6}",
                s.name,
                s.n_agents,
                s.obs_dim,
                s.state_dim,
                s.n_actions,
                s.episode_limit,
                s.message_columns,
                s.fullcomm_columns(),
                s.alpha
            );
        }
    }
    Ok(if bad > 0 && check { 1 } else { 0 })
}

/// `lmac envs --generate pz:<module>[,key=value]...`: the Python side (`lmac_env.pz generate`)
/// reads the environment's spaces and writes `<schema dir>/pz/<variant>.toml` with placeholder
/// descriptions; the file is then validated here like any schema.
pub(crate) fn generate(name: &str, force: bool, episode_limit: Option<usize>) -> Result<i32> {
    let (family, variant) = name
        .split_once(':')
        .filter(|(f, v)| !f.is_empty() && !v.is_empty() && !v.contains('/'))
        .ok_or_else(|| anyhow!("{name:?} must look like pz:<module>[,key=value]... (e.g. pz:mpe2.simple_spread_v3)"))?;
    if family != PZ {
        bail!(
            "--generate writes schemas of PettingZoo environments (pz:<module>[,key=value]...), not {name:?}; \
             for another family write env-server/schemas/{family}/{variant}.toml by hand (shm-schema/SCHEMA.md)"
        );
    }
    let dir = schema_dir().ok_or_else(|| anyhow!("cannot find env-server/schemas (set LMAC_SCHEMA_DIR)"))?;
    let path = dir.join(family).join(format!("{variant}.toml"));
    let mut c = pz_command(&["generate", name, "--out"])?;
    c.arg(&path);
    if force {
        c.arg("--force");
    }
    if let Some(n) = episode_limit {
        c.arg("--episode-limit").arg(n.to_string());
    }
    let status = c.status().context("starting Python (LMAC_PYTHON, else the repository's .venv)")?;
    if !status.success() {
        return Ok(status.code().unwrap_or(1));
    }
    let s = EnvSchema::load(&path).map_err(|e| anyhow!("the generated schema is invalid: {e}"))?;
    println!(
        "{}: {} agents, obs {}, state {}, actions {}, episode limit {}, message columns {}",
        s.name, s.n_agents, s.obs_dim, s.state_dim, s.n_actions, s.episode_limit, s.message_columns
    );
    Ok(0)
}
