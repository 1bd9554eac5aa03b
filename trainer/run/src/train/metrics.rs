//! The metrics of a training run: CSV, JSON lines and TensorBoard scalars side by side in its
//! directory, trimmed on resume so no curve steps backwards.

use anyhow::{Context, Result};
use lmac_shm_schema::safe_fs::{open_append, read_capped, read_text_capped, write_replace, TEXT_CAP};
use serde::{Deserialize, Serialize};
use std::io::Write;
use std::path::{Path, PathBuf};

/// One metrics row; empty fields are written as blanks in the CSV.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct MetricsRow {
    pub t_env: u64,
    pub episodes: u64,
    pub updates: u64,
    pub wall_s: f64,
    pub env_steps_per_s: f64,
    pub epsilon: f32,
    pub train_return_mean: Option<f64>,
    pub test_return_mean: Option<f64>,
    pub test_win_rate: Option<f64>,
    pub loss: Option<f32>,
    pub grad_norm: Option<f32>,
    pub q_taken_mean: Option<f32>,
    /// The method's extra losses and diagnostics of the last update (LMAC's, for example).
    #[serde(flatten, default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub method: std::collections::BTreeMap<String, f32>,
}

const CSV_HEADER: &str =
    "t_env,episodes,updates,wall_s,env_steps_per_s,epsilon,train_return_mean,test_return_mean,test_win_rate,loss,grad_norm,q_taken_mean";

/// The metrics of a run: CSV, JSON lines and TensorBoard scalars, side by side in its directory.
pub struct Metrics {
    /// The method's columns after the common ones (`AgentConfig::stat_names`).
    method_columns: Vec<String>,
    csv: std::fs::File,
    jsonl: std::fs::File,
    tb: crate::tensorboard::EventWriter,
    dir: PathBuf,
}

fn opt<T: std::fmt::Display>(v: &Option<T>) -> String {
    v.as_ref().map(|x| x.to_string()).unwrap_or_default()
}

/// The metrics rows of a run directory, from `metrics.jsonl` (checkpoint lines skipped).
pub fn read_metrics(dir: &Path) -> Result<Vec<MetricsRow>> {
    let path = dir.join("metrics.jsonl");
    let text = read_text_capped(&path, TEXT_CAP).with_context(|| format!("reading {}", path.display()))?;
    let mut rows = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let v: serde_json::Value = serde_json::from_str(line).with_context(|| format!("{} line {}", path.display(), i + 1))?;
        if v.get("checkpoint").is_none() {
            rows.push(serde_json::from_value(v).with_context(|| format!("{} line {}", path.display(), i + 1))?);
        }
    }
    Ok(rows)
}

/// The largest `t_env` of any row in the run's `metrics.csv` or `metrics.jsonl` (0 for none).
/// Unreadable lines are skipped: this only asks whether the run has trained before.
pub fn logged_t_env(dir: &Path) -> u64 {
    let read = |name: &str| {
        let p = dir.join(name);
        // Only regular files, bounded (a device would never end).
        String::from_utf8_lossy(&read_capped(&p, TEXT_CAP).unwrap_or_default()).into_owned()
    };
    let csv = read("metrics.csv");
    let from_csv = csv.lines().skip(1).filter_map(|l| l.split(',').next()?.parse::<u64>().ok());
    let jsonl = read("metrics.jsonl");
    let from_json = jsonl.lines().filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok()?["t_env"].as_u64());
    from_csv.chain(from_json).max().unwrap_or(0)
}

/// What [`Metrics::open`] found of an earlier segment of the run.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct MetricsResume {
    /// Rows dropped because they were logged after the checkpoint the run continues from (or
    /// were cut off by the crash).
    pub dropped_rows: usize,
    /// `wall_s` of the last row kept: the resumed segment's clock continues from it.
    pub wall_s: f64,
}

/// Keep the lines of `path` that `keep` accepts (the first `header` lines always), rewriting
/// the file atomically when any is dropped; returns (dropped, kept lines).
fn keep_lines(path: &Path, header: usize, keep: impl Fn(&str) -> bool) -> Result<(usize, Vec<String>)> {
    // Only regular files are read, bounded (a device such as /dev/full would never end).
    if std::fs::metadata(path).is_ok_and(|m| !m.is_file()) {
        return Ok((0, Vec::new()));
    }
    let text = match read_capped(path, TEXT_CAP) {
        Ok(b) => String::from_utf8_lossy(&b).into_owned(),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok((0, Vec::new())),
        Err(e) => return Err(anyhow::anyhow!("reading {e}")),
    };
    // A last line without its newline was cut off by the crash: never kept.
    let complete = if text.ends_with('\n') { &text[..] } else { &text[..text.rfind('\n').map_or(0, |i| i + 1)] };
    let mut kept = Vec::new();
    let mut dropped = usize::from(complete.len() < text.len());
    for (i, line) in complete.lines().enumerate() {
        if i < header || keep(line) {
            kept.push(line.to_string());
        } else {
            dropped += 1;
        }
    }
    if dropped > 0 {
        let mut body = kept.join("\n");
        if !body.is_empty() {
            body.push('\n');
        }
        write_replace(path, body.as_bytes()).with_context(|| format!("replacing {}", path.display()))?;
    }
    Ok((dropped, kept))
}

impl Metrics {
    /// Open the run's metrics for appending. `resume_t_env` is the step of the checkpoint the run
    /// continues from (0 for a fresh start): rows logged after it are dropped from the CSV and
    /// the JSON lines, and TensorBoard is told to discard its later events, so no curve steps
    /// backwards.
    pub fn open(dir: &Path, resume_t_env: u64, method_columns: &[&str]) -> Result<(Metrics, MetricsResume)> {
        let csv_path = dir.join("metrics.csv");
        let jsonl_path = dir.join("metrics.jsonl");
        // A run resumed by a build whose method logs other terms keeps the columns its file has.
        let existing = read_text_capped(&csv_path, TEXT_CAP).ok().and_then(|t| t.lines().next().map(str::to_string));
        let header: String = match existing.filter(|h| h.starts_with(CSV_HEADER)) {
            Some(h) => h,
            None => std::iter::once(CSV_HEADER).chain(method_columns.iter().copied()).collect::<Vec<_>>().join(","),
        };
        let method_columns: Vec<String> = header.split(',').skip(CSV_HEADER.split(',').count()).map(str::to_string).collect();
        let columns = header.split(',').count();
        let t_env_of_csv = |line: &str| line.split(',').next().and_then(|v| v.parse::<u64>().ok());
        let ok_csv = |line: &str| line.split(',').count() == columns && t_env_of_csv(line).is_some_and(|t| t <= resume_t_env);
        let (dropped_csv, kept) = keep_lines(&csv_path, 1, ok_csv)?;
        let wall_s = kept.iter().skip(1).last().and_then(|l| l.split(',').nth(3)).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
        let ok_json = |line: &str| {
            serde_json::from_str::<serde_json::Value>(line).ok().and_then(|v| v["t_env"].as_u64()).is_some_and(|t| t <= resume_t_env)
        };
        let (dropped_json, _) = keep_lines(&jsonl_path, 0, ok_json)?;
        let open = |p: &Path| open_append(p).context("opening the run's metrics");
        let new = kept.is_empty();
        let mut csv = open(&csv_path)?;
        if new {
            writeln!(csv, "{header}").with_context(|| format!("writing {}", csv_path.display()))?;
        }
        let jsonl = open(&jsonl_path)?;
        let mut tb =
            crate::tensorboard::EventWriter::create(dir).with_context(|| format!("creating TensorBoard events in {}", dir.display()))?;
        if resume_t_env > 0 {
            tb.session_start(resume_t_env + 1).with_context(|| format!("writing {}", tb.path().display()))?;
        }
        Ok((
            Metrics { method_columns, csv, jsonl, tb, dir: dir.to_path_buf() },
            MetricsResume { dropped_rows: dropped_csv.max(dropped_json), wall_s },
        ))
    }

    pub fn write(&mut self, r: &MetricsRow) -> Result<()> {
        let csv_err = |e: std::io::Error| anyhow::anyhow!("writing {}: {e}", self.dir.join("metrics.csv").display());
        let method: String = self.method_columns.iter().map(|c| format!(",{}", opt(&r.method.get(c)))).collect();
        writeln!(
            self.csv,
            "{},{},{},{:.2},{:.1},{:.4},{},{},{},{},{},{}{method}",
            r.t_env,
            r.episodes,
            r.updates,
            r.wall_s,
            r.env_steps_per_s,
            r.epsilon,
            opt(&r.train_return_mean),
            opt(&r.test_return_mean),
            opt(&r.test_win_rate),
            opt(&r.loss),
            opt(&r.grad_norm),
            opt(&r.q_taken_mean)
        )
        .and_then(|_| self.csv.flush())
        .map_err(csv_err)?;
        self.json_line(&serde_json::to_value(r)?)?;
        let f = |v: Option<f64>| v.unwrap_or(f64::NAN);
        let mut scalars = vec![
            ("env_steps_per_s", r.env_steps_per_s),
            ("epsilon", r.epsilon as f64),
            ("train_return_mean", f(r.train_return_mean)),
            ("test_return_mean", f(r.test_return_mean)),
            ("test_win_rate", f(r.test_win_rate)),
            ("loss", f(r.loss.map(f64::from))),
            ("grad_norm", f(r.grad_norm.map(f64::from))),
            ("q_taken_mean", f(r.q_taken_mean.map(f64::from))),
        ];
        scalars.extend(self.method_columns.iter().map(|c| (c.as_str(), f(r.method.get(c).map(|&v| f64::from(v))))));
        self.tb.scalars(r.t_env, &scalars).map_err(|e| anyhow::anyhow!("writing {}: {e}", self.tb.path().display()))?;
        Ok(())
    }

    /// A checkpoint was written: its path and step go into `metrics.jsonl` (so a scheduler
    /// following the run knows where to resume from).
    pub fn checkpoint(&mut self, c: &CheckpointWritten) -> Result<()> {
        self.json_line(&serde_json::json!({"t_env": c.t_env, "episodes": c.episodes, "updates": c.updates, "checkpoint": c.path}))
    }

    fn json_line(&mut self, v: &serde_json::Value) -> Result<()> {
        writeln!(self.jsonl, "{v}")
            .and_then(|_| self.jsonl.flush())
            .map_err(|e| anyhow::anyhow!("writing {}: {e}", self.dir.join("metrics.jsonl").display()))
    }
}

/// A checkpoint the learner wrote.
#[derive(Clone, Debug)]
pub struct CheckpointWritten {
    pub t_env: u64,
    pub episodes: u64,
    pub updates: u64,
    pub path: PathBuf,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resuming_drops_the_metrics_rows_after_the_checkpoint_and_a_cut_off_line() {
        let dir = std::env::temp_dir().join(format!("lmac-metrics-trim-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let row = |t: u64, wall: f64| format!("{t},1,0,{wall:.2},1.0,1.0,,,,,,\n");
        let csv = format!("{CSV_HEADER}\n{}{}{}12", row(100, 1.0), row(200, 2.0), row(300, 3.0));
        std::fs::write(dir.join("metrics.csv"), csv).unwrap();
        std::fs::write(dir.join("metrics.jsonl"), "{\"t_env\":100}\n{\"t_env\":200,\"checkpoint\":\"x\"}\n{\"t_env\":300}\n{\"t_e")
            .unwrap();
        let (mut m, r) = Metrics::open(&dir, 200, &[]).unwrap();
        assert_eq!(r, MetricsResume { dropped_rows: 2, wall_s: 2.0 }, "row 300 and the cut-off line go");
        m.write(&MetricsRow { t_env: 250, ..Default::default() }).unwrap();
        let csv = std::fs::read_to_string(dir.join("metrics.csv")).unwrap();
        let t: Vec<&str> = csv.lines().skip(1).map(|l| l.split(',').next().unwrap()).collect();
        assert_eq!(t, ["100", "200", "250"]);
        let json = std::fs::read_to_string(dir.join("metrics.jsonl")).unwrap();
        assert_eq!(json.lines().count(), 3, "{json}");
        assert!(json.lines().all(|l| serde_json::from_str::<serde_json::Value>(l).is_ok()));
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_resumed_run_keeps_the_method_columns_its_metrics_file_has() {
        let dir = std::env::temp_dir().join(format!("lmac-metrics-cols-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let (mut m, _) = Metrics::open(&dir, 0, &["a", "b"]).unwrap();
        let row = |t| MetricsRow { t_env: t, method: [("a".to_string(), 1.5), ("b".to_string(), 2.5)].into(), ..Default::default() };
        m.write(&row(100)).unwrap();
        drop(m);
        // A newer build logs a third term: the file keeps its two, and no row is dropped.
        let (mut m, r) = Metrics::open(&dir, 100, &["a", "b", "c"]).unwrap();
        assert_eq!(r.dropped_rows, 0);
        m.write(&row(200)).unwrap();
        let csv = std::fs::read_to_string(dir.join("metrics.csv")).unwrap();
        assert!(csv.lines().next().unwrap().ends_with(",a,b"), "{csv}");
        assert!(csv.lines().skip(1).all(|l| l.ends_with(",1.5,2.5")), "{csv}");
        assert_eq!(read_metrics(&dir).unwrap()[1].method["b"], 2.5);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn metrics_that_cannot_be_written_name_the_file() {
        let dir = std::env::temp_dir().join(format!("lmac-metrics-full-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        // A link to /dev/full (where every write fails) is refused at the open, naming the file.
        std::os::unix::fs::symlink("/dev/full", dir.join("metrics.jsonl")).unwrap();
        let err = format!("{:#}", Metrics::open(&dir, 0, &[]).err().expect("refused"));
        assert!(err.contains("metrics.jsonl") && err.contains("symlink"), "{err}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
