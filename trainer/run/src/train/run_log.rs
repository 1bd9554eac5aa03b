//! What a training run says about itself: the metrics rows (training rows every log interval,
//! a row per test phase), the checkpoints the learner wrote, the progress bar or progress lines,
//! and acting's latency. Apart from acting and from test scheduling, as pymarl keeps its logger.

use super::learner_thread::Shared;
use super::metrics::{Metrics, MetricsRow};
use parking_lot::Mutex;
use std::time::{Duration, Instant};

/// Where the run is, as the actor knows it, for a metrics row.
pub(super) struct RunPoint {
    pub t_env: u64,
    pub episodes: u64,
    pub epsilon: f32,
}

/// The log of one training run.
pub(super) struct RunLog {
    metrics: Metrics,
    steps: u64,
    seed: u64,
    log_interval: u64,
    /// The run has test phases (`run.test_episodes > 0`).
    tests: bool,
    next_log: u64,
    /// A row fell due during a test phase: the phase's row carries it, so no t_env gets two rows
    /// (a training row and a test row at the same step).
    log_due: bool,
    /// Training episodes' returns since the last row that reported them.
    train_returns: Vec<f32>,
    /// A metrics write that failed: it ends the run.
    pub(super) failed: Option<String>,
    started: Instant,
    /// `wall_s` already spent by earlier segments of a resumed run.
    wall_offset: f64,
    t_env_at_start: u64,
    pub(super) bar: Option<indicatif::ProgressBar>,
    /// Checkpoints asked of the learner and not yet logged.
    checkpoints_pending: u64,
    /// The controller's time per batched step (every env of one slab), microseconds: acting's
    /// latency, reported when the run ends (the learner shares the cores with it).
    act_us: Vec<f32>,
    /// Time acting spent waiting for the learner to catch up.
    learner_wait: Duration,
}

impl RunLog {
    pub(super) fn new(
        metrics: Metrics,
        run: &super::config::RunSection,
        seed: u64,
        t_env: u64,
        wall_offset: f64,
        bar: Option<indicatif::ProgressBar>,
    ) -> RunLog {
        RunLog {
            metrics,
            steps: run.steps,
            seed,
            log_interval: run.log_interval,
            tests: run.test_episodes > 0,
            next_log: super::budget::next_multiple(t_env, run.log_interval),
            log_due: false,
            train_returns: Vec::new(),
            failed: None,
            started: Instant::now(),
            wall_offset,
            t_env_at_start: t_env,
            bar,
            checkpoints_pending: 0,
            act_us: Vec::new(),
            learner_wait: Duration::ZERO,
        }
    }

    fn fail(&mut self, e: anyhow::Error) {
        if self.failed.is_none() {
            self.failed = Some(format!("{e:#}"));
        }
    }

    /// A checkpoint was asked of the learner; it is logged when written.
    pub(super) fn checkpoint_asked(&mut self) {
        self.checkpoints_pending += 1;
    }

    /// Log the checkpoints the learner wrote since the last call.
    pub(super) fn log_checkpoints(&mut self, shared: &Mutex<Shared>) {
        let written = std::mem::take(&mut shared.lock().checkpoints);
        self.checkpoints_pending = self.checkpoints_pending.saturating_sub(written.len() as u64);
        for c in &written {
            if let Err(e) = self.metrics.checkpoint(c) {
                self.fail(e);
            }
        }
    }

    /// A training episode ended with this team return (reported in the next row).
    pub(super) fn training_episode(&mut self, team_return: f32) {
        self.train_returns.push(team_return);
    }

    /// Training reached `at`: a row falls due every log interval, written now or, during a test
    /// phase, with the phase's row.
    pub(super) fn after_training(&mut self, at: &RunPoint, test_in_progress: bool, shared: &Mutex<Shared>) {
        if at.t_env < self.next_log {
            return;
        }
        self.next_log = super::budget::next_multiple(at.t_env, self.log_interval);
        if test_in_progress && self.tests {
            self.log_due = true;
        } else {
            self.write_row(at, None, shared);
        }
    }

    /// Write a metrics row at `at`: a training row, or a test phase's (mean return, win rate).
    pub(super) fn write_row(&mut self, at: &RunPoint, test: Option<(f64, f64)>, shared: &Mutex<Shared>) {
        // A checkpoint asked for at an earlier step is logged before this row, so metrics.jsonl
        // stays in t_env order even when the learner writes it late (behind a best-checkpoint
        // save or a backlog of updates). Checkpoints are rare: this waits at most once per one.
        let deadline = Instant::now() + Duration::from_secs(60);
        while self.checkpoints_pending > 0 && Instant::now() < deadline && shared.lock().error.is_none() {
            self.log_checkpoints(shared);
            if self.checkpoints_pending > 0 {
                std::thread::sleep(Duration::from_millis(2));
            }
        }
        let s = shared.lock();
        let secs = self.started.elapsed().as_secs_f64();
        let row = MetricsRow {
            t_env: at.t_env,
            episodes: at.episodes,
            updates: s.updates,
            wall_s: self.wall_offset + secs,
            env_steps_per_s: (at.t_env - self.t_env_at_start) as f64 / secs.max(1e-9),
            epsilon: at.epsilon,
            train_return_mean: ((test.is_none() || self.log_due) && !self.train_returns.is_empty())
                .then(|| self.train_returns.iter().map(|&r| r as f64).sum::<f64>() / self.train_returns.len() as f64),
            test_return_mean: test.map(|t| t.0),
            test_win_rate: test.map(|t| t.1),
            loss: s.loss,
            grad_norm: s.grad_norm,
            q_taken_mean: s.q_taken_mean,
            method: s.method.iter().map(|&(k, v)| (k.to_string(), v)).collect(),
        };
        drop(s);
        // Off a terminal the bar draws nothing: a line per test phase (per metrics row when the
        // run has no tests) keeps a long run from being an hour of silence in a log.
        let quiet = self.bar.as_ref().is_none_or(indicatif::ProgressBar::is_hidden);
        if quiet && (test.is_some() || !self.tests) {
            eprintln!("{}", progress_line(&row, self.steps, self.seed));
        }
        if test.is_none() || self.log_due {
            self.train_returns.clear();
        }
        self.log_due = false;
        if let Err(e) = self.metrics.write(&row) {
            self.fail(e);
        }
    }

    /// The progress bar's position and message.
    pub(super) fn progress(&self, t_env: u64, message: impl FnOnce() -> String) {
        if let Some(b) = &self.bar {
            b.set_position(t_env.min(self.steps));
            b.set_message(message());
        }
    }

    /// The controller took `us` microseconds for one batched step.
    pub(super) fn acted(&mut self, us: f32) {
        self.act_us.push(us);
    }

    /// Acting waited this long for the learner.
    pub(super) fn waited(&mut self, d: Duration) {
        self.learner_wait += d;
    }

    /// One line on acting for the run's log: the controller's latency per batched step (median
    /// and 99th percentile) and how long acting waited for the learner.
    pub(super) fn acting_summary(&self) -> Option<String> {
        if self.act_us.is_empty() {
            return None;
        }
        let mut us = self.act_us.clone();
        us.sort_by(f32::total_cmp);
        let at = |q: f64| us[((us.len() - 1) as f64 * q).round() as usize] / 1000.0;
        Some(format!(
            "acting: {} batched steps, the controller {:.2} ms median / {:.2} ms p99 per batched step; acting waited {:.1} s of {:.1} s for the learner",
            us.len(),
            at(0.5),
            at(0.99),
            self.learner_wait.as_secs_f64(),
            self.started.elapsed().as_secs_f64()
        ))
    }
}

/// One line of progress for a log: where the run is, how fast it goes, what it returns, and
/// roughly when it ends.
fn progress_line(row: &MetricsRow, steps: u64, seed: u64) -> String {
    let pct = 100.0 * row.t_env.min(steps) as f64 / steps.max(1) as f64;
    let eta = if row.env_steps_per_s > 0.0 {
        let s = (steps.saturating_sub(row.t_env) as f64 / row.env_steps_per_s) as u64;
        format!("{}h{:02}m", s / 3600, (s % 3600) / 60)
    } else {
        "-".into()
    };
    let opt = |v: Option<f64>, digits: usize| v.map_or("-".into(), |x| format!("{x:.digits$}"));
    format!(
        "lmac: seed {seed}: t_env {}/{steps} ({pct:.0}%), {} updates, {:.0} env steps/s, eps {:.2}, train return {}, test return {}, win rate {}, eta {eta}",
        row.t_env,
        row.updates,
        row.env_steps_per_s,
        row.epsilon,
        opt(row.train_return_mean, 3),
        opt(row.test_return_mean, 3),
        opt(row.test_win_rate, 3),
    )
}
