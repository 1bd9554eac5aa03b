//! `lmac envs`: the environments and their dimensions; `--check` validates every schema file
//! (bounds, its place, no `EDIT:` placeholders left) and compares it with what its environment
//! writes; `--generate FAMILY:VARIANT` writes a schema with the sizes the env gives.

use anyhow::{anyhow, bail, Context, Result};
use lmac_run::supervisor;
use lmac_shm_schema::schema::{all_envs, schema_dir, EnvSchema, PLACEHOLDER};
use std::path::Path;

/// The PettingZoo family: `--generate` reads its sizes from the env's spaces (env-server/lmac_env/pz.py).
const PZ: &str = "pz";

/// The name a schema file's place gives it: `<dir>/<family>/<variant>.toml` -> `family:variant`.
fn place_name(path: &Path) -> Option<String> {
    let variant = path.file_stem()?.to_str()?;
    let family = path.parent()?.file_name()?.to_str()?;
    Some(format!("{family}:{variant}"))
}

/// Build every schema's environment and compare what it writes with the schema
/// (`python -m lmac_env.sizes check`, one Python for all; the env servers run the same check on
/// their first reset and step). An env whose package or game is missing here is only noted.
/// Compare every schema's sizes with its environment; the number of environments that could not
/// be checked here (a game or package missing), each named in a note.
fn check_sizes(rows: &[EnvSchema]) -> Result<usize> {
    let mut c = supervisor::python_command()?;
    c.args(["-m", "lmac_env.sizes", "check"]).args(rows.iter().map(|s| s.name.as_str()));
    let out = c.output().context("starting Python (LMAC_PYTHON, else the repository's .venv)")?;
    let mut skipped = 0;
    for line in String::from_utf8_lossy(&out.stdout).lines() {
        if let Some(rest) = line.strip_prefix("skip ") {
            eprintln!("note: sizes not checked against the environment: {rest}");
            skipped += 1;
        }
    }
    if !out.status.success() {
        eprint!("{}", String::from_utf8_lossy(&out.stderr));
        bail!("a schema does not fit its environment (see above)");
    }
    Ok(skipped)
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
    for (path, r) in all_envs()? {
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
                if check {
                    let left = s.placeholders();
                    if !left.is_empty() {
                        let more = if left.len() > 4 { format!(" and {} more", left.len() - 4) } else { String::new() };
                        eprintln!(
                            "{}: {}{more}: still the generated {PLACEHOLDER:?} placeholder; write what it means \
                             (the LLM that designs protocols reads these texts)",
                            path.display(),
                            left[..left.len().min(4)].join(", ")
                        );
                        bail!("schema {} is not finished", path.display());
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
    if check && !rows.is_empty() {
        let skipped = check_sizes(&rows)?;
        // On stderr, so that --json keeps stdout one JSON document.
        eprintln!(
            "OK: {} {} valid and finished, each named by its place; sizes match the environment for {}{}",
            rows.len(),
            if rows.len() == 1 { "schema" } else { "schemas" },
            rows.len() - skipped,
            if skipped > 0 { format!(" ({skipped} not checked here, noted above)") } else { String::new() }
        );
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

/// `lmac envs --generate FAMILY:VARIANT`: the Python side writes `<schema dir>/<family>/<variant>.toml`
/// with every size it can measure and `EDIT:` placeholders for the texts (`lmac_env.pz generate`
/// from a PettingZoo env's spaces; `lmac_env.sizes generate` from the family module's
/// `sizes(variant)` for any other family); the file is then validated here like any schema.
pub(crate) fn generate(name: &str, force: bool, episode_limit: Option<usize>) -> Result<i32> {
    let (family, variant) = name
        .split_once(':')
        .filter(|(f, v)| !f.is_empty() && !v.is_empty() && !v.contains('/') && !f.contains('/'))
        .ok_or_else(|| anyhow!("{name:?} must look like FAMILY:VARIANT (e.g. pz:mpe2.simple_spread_v3 or rware:tiny-2ag)"))?;
    let dir = schema_dir().ok_or_else(|| anyhow!("cannot find env-server/schemas (set LMAC_SCHEMA_DIR)"))?;
    let path = dir.join(family).join(format!("{variant}.toml"));
    let mut c = if family == PZ {
        pz_command(&["generate", name, "--out"])?
    } else {
        let mut c = supervisor::python_command()?;
        c.args(["-m", "lmac_env.sizes", "generate", name, "--out"]);
        c
    };
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
