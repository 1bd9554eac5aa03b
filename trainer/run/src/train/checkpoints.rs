//! Checkpoint handling of a run directory: where the latest checkpoint and the best test
//! phase's checkpoint live, the best test phase's record (`best_test.json`), and the refusal to
//! restart a run over its metrics when its checkpoint is gone. The learner thread writes
//! checkpoints, `evaluate.rs` and the command line read them: the places are named once, here.

use super::metrics;
use anyhow::{bail, Result};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// The best test phase so far, saved next to the best checkpoint (`best_test.json`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct BestTest {
    pub test_return: f64,
    pub t_env: u64,
}

/// The best test phase of a run so far, if one was saved. A file that cannot be read is
/// reported and treated as none (the next best test phase rewrites it).
pub fn read_best_test(run_dir: &Path) -> Option<BestTest> {
    let path = run_dir.join("best_test.json");
    let bytes = crate::safe_fs::read_capped(&path, crate::safe_fs::TEXT_CAP).ok()?;
    match serde_json::from_slice(&bytes) {
        Ok(b) => Some(b),
        Err(e) => {
            eprintln!("lmac: trainer: ignoring {}: {e}", path.display());
            None
        }
    }
}

/// Record `best` as the run's best test phase (`best_test.json`, written to a temporary file
/// and renamed over the old record). The error names the file.
pub(super) fn write_best_test(run_dir: &Path, best: &BestTest) -> std::result::Result<(), String> {
    let path = run_dir.join("best_test.json");
    crate::safe_fs::write_replace(&path, &serde_json::to_vec_pretty(best).expect("a plain struct")).map_err(|e| e.to_string())
}

/// Where the learner keeps its latest checkpoint inside a run directory.
pub fn checkpoint_dir(run_dir: &Path) -> PathBuf {
    run_dir.join("checkpoint")
}

/// Where the learner keeps the checkpoint of the best test phase so far (without the replay
/// buffer), with `best_test.json` beside it in the run directory.
pub fn best_checkpoint_dir(run_dir: &Path) -> PathBuf {
    run_dir.join("checkpoint_best")
}

/// Refuse to start `run_dir` from t_env 0 when it has no usable checkpoint but its metrics
/// show it trained before (its checkpoint was lost or moved): starting again would drop every
/// row. Says what to do instead.
pub fn refuse_restart_over_metrics(run_dir: &Path) -> Result<()> {
    let logged = metrics::logged_t_env(run_dir);
    if logged > 0 {
        let ck = checkpoint_dir(run_dir);
        // Why a checkpoint that is there is not usable: its state.json is not a regular file.
        let why = ["", ".old", ".tmp"]
            .iter()
            .map(|s| PathBuf::from(format!("{}{s}", ck.display())).join("state.json"))
            .find(|p| std::fs::symlink_metadata(p).is_ok() && !p.is_file())
            .map(|p| format!(" ({} is not a regular file)", p.display()))
            .unwrap_or_default();
        bail!(
            "{}: no usable checkpoint ({}, {}.old or a complete {}.tmp){why}, but its metrics go up to t_env {logged}: \
             refusing to train it again from t_env 0 over them. Restore the checkpoint, or move metrics.csv and \
             metrics.jsonl away to start this run afresh",
            run_dir.display(),
            ck.display(),
            ck.display(),
            ck.display()
        );
    }
    Ok(())
}
