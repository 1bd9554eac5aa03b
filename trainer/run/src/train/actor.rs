//! The actor side of training: epsilon-greedy acting with the learner's latest weights, greedy
//! test phases, the metrics rows, checkpoint requests and dataset collection. It runs on the
//! trainer child's main thread inside the pipeline and talks to the learner thread only through
//! the channel and `Shared` of `learner_thread.rs`.

use super::budget;
use super::checkpoints::BestTest;
use super::config::TrainConfig;
use super::learner_thread::{Shared, ToLearner};
use super::metrics::{Metrics, MetricsRow};
use super::schedule::UpdateSchedule;
use crate::dataset::Trajectory;
use crate::episode::{Episode, EpisodeDims};
use crate::learn::{Controller, LearnConfig, LearnRng};
use crate::pipeline::Actor;
use lmac_shm_schema::{Slot, FLAG_FIRST};
use parking_lot::Mutex;
use std::sync::mpsc;
use std::sync::Arc;
use std::time::Instant;

/// The actor side of training: epsilon-greedy acting, test episodes, metrics.
pub struct TrainActor {
    pub(super) cfg: TrainConfig,
    pub(super) learn: LearnConfig,
    pub(super) controllers: Vec<Controller>,
    pub(super) rng: LearnRng,
    pub(super) dims: EpisodeDims,
    /// Per member, per env: is the current episode a greedy test episode?
    pub(super) testing: Vec<Vec<bool>>,
    /// Per member, per env: whether each episode started and not yet reported done is a test
    /// episode, oldest first. `act` may see an env's next episode start before or after
    /// `episode_done` gets the one that ended, so the finished episode's own flag is looked up
    /// here, never in `testing` (which already belongs to the next episode).
    pub(super) started_tests: Vec<Vec<std::collections::VecDeque<bool>>>,
    pub(super) test_pending: usize,
    pub(super) test_returns: Vec<(f32, bool)>,
    /// The run reached its step budget and asked for its final test phase (a run always ends
    /// with a test at its last step, so its final return is measured there).
    pub(super) final_test: bool,
    pub(super) next_test: u64,
    pub(super) next_log: u64,
    /// A metrics row fell due during a test phase: the test phase's row carries it, so no t_env
    /// gets two rows (a training row and a test row at the same step).
    pub(super) log_due: bool,
    pub(super) next_checkpoint: u64,
    pub(super) t_env: u64,
    pub(super) episodes: u64,
    pub(super) train_returns: Vec<f32>,
    pub(super) tx: mpsc::Sender<ToLearner>,
    pub(super) shared: Arc<Mutex<Shared>>,
    pub(super) episodes_sent: u64,
    pub(super) schedule: UpdateSchedule,
    pub(super) metrics: Metrics,
    /// A metrics write that failed: it ends the run.
    pub(super) failed: Option<String>,
    pub(super) started: Instant,
    /// `wall_s` already spent by earlier segments of a resumed run.
    pub(super) wall_offset: f64,
    pub(super) t_env_at_start: u64,
    pub(super) scratch_first: Vec<bool>,
    pub(super) bar: Option<indicatif::ProgressBar>,
    pub(super) last_test_return: Option<f64>,
    /// The best test phase so far (its checkpoint is in `best_checkpoint_dir`).
    pub(super) best_test: Option<BestTest>,
    /// Checkpoints asked of the learner and not yet logged.
    pub(super) checkpoints_pending: u64,
    /// The trajectory dataset being collected once training is done (`run.dataset_episodes`).
    pub(super) dataset: Vec<Trajectory>,
    /// Observation columns without messages (what the dataset keeps).
    pub(super) obs_dim: usize,
    /// The controller's time per batched step (every env of one slab), microseconds: acting's
    /// latency, reported when the run ends (the learner shares the cores with it).
    pub(super) act_us: Vec<f32>,
    /// Time acting spent waiting for the learner to catch up (`wait_for_learner`).
    pub(super) learner_wait: std::time::Duration,
}

impl TrainActor {
    /// A test phase is asked for or under way (a running test episode is in `started_tests`
    /// until it is reported done).
    fn test_in_progress(&self) -> bool {
        self.test_pending > 0 || !self.test_returns.is_empty() || self.started_tests.iter().flatten().any(|q| q.contains(&true))
    }

    /// Training is done and the dataset is being collected (no learning, no test phases).
    fn collecting(&self) -> bool {
        self.t_env >= self.cfg.run.steps && self.cfg.run.dataset_episodes > 0
    }

    pub(super) fn epsilon(&self) -> f32 {
        match self.cfg.run.dataset_epsilon {
            Some(e) if self.collecting() => e,
            _ => self.learn.epsilon_at(self.t_env),
        }
    }

    fn wait_for_learner(&mut self) {
        // Keep updates per episode at the configured ratio: acting waits while the learner lags
        // by more than two updates.
        let due = self.schedule.due(self.episodes_sent);
        let start = Instant::now();
        loop {
            let s = self.shared.lock();
            if s.error.is_some() || s.updates + 2 >= due {
                break;
            }
            drop(s);
            std::thread::sleep(std::time::Duration::from_micros(500));
        }
        self.learner_wait += start.elapsed();
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

    fn fail(&mut self, e: anyhow::Error) {
        if self.failed.is_none() {
            self.failed = Some(format!("{e:#}"));
        }
    }

    /// Log the checkpoints the learner wrote since the last call.
    pub(super) fn log_checkpoints(&mut self) {
        let written = std::mem::take(&mut self.shared.lock().checkpoints);
        self.checkpoints_pending = self.checkpoints_pending.saturating_sub(written.len() as u64);
        for c in &written {
            if let Err(e) = self.metrics.checkpoint(c) {
                self.fail(e);
            }
        }
    }

    fn log(&mut self, test: Option<(f64, f64)>) {
        // A checkpoint asked for at an earlier step is logged before this row, so metrics.jsonl
        // stays in t_env order even when the learner writes it late (behind a best-checkpoint
        // save or a backlog of updates). Checkpoints are rare: this waits at most once per one.
        let deadline = Instant::now() + std::time::Duration::from_secs(60);
        while self.checkpoints_pending > 0 && Instant::now() < deadline && self.shared.lock().error.is_none() {
            self.log_checkpoints();
            if self.checkpoints_pending > 0 {
                std::thread::sleep(std::time::Duration::from_millis(2));
            }
        }
        let s = self.shared.lock();
        let secs = self.started.elapsed().as_secs_f64();
        let row = MetricsRow {
            t_env: self.t_env,
            episodes: self.episodes,
            updates: s.updates,
            wall_s: self.wall_offset + secs,
            env_steps_per_s: (self.t_env - self.t_env_at_start) as f64 / secs.max(1e-9),
            epsilon: self.epsilon(),
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
        if quiet && (test.is_some() || self.cfg.run.test_episodes == 0) {
            eprintln!("{}", progress_line(&row, self.cfg.run.steps, self.cfg.learn.seed));
        }
        if test.is_none() || self.log_due {
            self.train_returns.clear();
        }
        self.log_due = false;
        if let Err(e) = self.metrics.write(&row) {
            self.fail(e);
        }
    }
}

impl Actor for TrainActor {
    fn act(&mut self, member: usize, slot: &Slot<'_>, obs_width: usize, actions: &mut [i32]) {
        if let Some(agent) = self.shared.lock().agent.take() {
            // Each env switches to these weights when its next episode starts.
            for c in &mut self.controllers {
                c.offer_agent(agent.clone());
            }
        }
        let l = slot.layout();
        assert_eq!(l.row_width, obs_width, "the slab reserves exactly the protocol's message columns");
        self.scratch_first.clear();
        for e in 0..l.num_envs {
            let first = slot.env_meta(e).2 & FLAG_FIRST != 0;
            self.scratch_first.push(first);
            if first {
                // Start a greedy test episode here if a test phase wants more.
                self.testing[member][e] = self.test_pending > 0;
                self.started_tests[member][e].push_back(self.testing[member][e]);
                if self.test_pending > 0 {
                    self.test_pending -= 1;
                }
            }
        }
        let state = if self.learn.agent_sees_state { Some(slot.state()) } else { None };
        let eps = self.epsilon();
        let acting = Instant::now();
        let acts = self.controllers[member].select_actions(
            slot.obs(),
            state,
            slot.last_actions(),
            slot.avail(),
            &self.scratch_first,
            eps,
            &mut self.rng,
        );
        actions.copy_from_slice(&acts);
        // Test envs act greedily on the same Q-values.
        let (n, a) = (self.dims.n_agents, self.dims.n_actions);
        let q = self.controllers[member].last_q();
        let avail = slot.avail();
        for e in (0..l.num_envs).filter(|&e| self.testing[member][e]) {
            for ag in 0..n {
                let r = e * n + ag;
                let (qs, av) = (&q[r * a..(r + 1) * a], &avail[r * a..(r + 1) * a]);
                actions[r] = crate::learn::controller::greedy_available(qs, av).unwrap_or(0) as i32;
            }
        }
        self.act_us.push(acting.elapsed().as_secs_f32() * 1e6);
    }

    fn episode_done(&mut self, member: usize, env: usize, ep: Episode, won: bool) {
        if self.started_tests[member][env].pop_front().unwrap_or(false) {
            self.test_returns.push((ep.team_return(), won));
            if self.test_returns.len() >= self.cfg.run.test_episodes {
                let n = self.test_returns.len() as f64;
                let ret = self.test_returns.iter().map(|x| x.0 as f64).sum::<f64>() / n;
                let win = self.test_returns.iter().filter(|x| x.1).count() as f64 / n;
                self.test_returns.clear();
                self.last_test_return = Some(ret);
                self.log(Some((ret, win)));
                if self.best_test.is_none_or(|b| ret > b.test_return) {
                    let best = BestTest { test_return: ret, t_env: self.t_env };
                    self.best_test = Some(best);
                    let _ = self.tx.send(ToLearner::SaveBest(best));
                }
            }
            return;
        }
        if self.collecting() {
            if self.dataset.len() < self.cfg.run.dataset_episodes {
                self.dataset.push(Trajectory::from_episode(&ep, self.dims.n_agents, self.obs_dim));
                if let Some(b) = &self.bar {
                    b.set_message(format!("collecting the dataset: {}/{} episodes", self.dataset.len(), self.cfg.run.dataset_episodes));
                }
            }
            return;
        }
        if self.t_env >= self.cfg.run.steps {
            // Past the budget, waiting for the final test phase: not trained on, not counted.
            return;
        }
        self.t_env += ep.len as u64;
        self.episodes += 1;
        self.train_returns.push(ep.team_return());
        if self.tx.send(ToLearner::Episode(ep)).is_ok() {
            self.episodes_sent += 1;
        }
        if self.t_env >= self.next_test {
            self.next_test = budget::next_multiple(self.t_env, self.cfg.run.test_interval);
            self.test_pending = self.cfg.run.test_episodes;
        }
        if self.t_env >= self.cfg.run.steps && !self.final_test {
            self.final_test = true;
            if !self.test_in_progress() {
                self.test_pending = self.cfg.run.test_episodes;
            }
        }
        if self.t_env >= self.next_log {
            self.next_log = budget::next_multiple(self.t_env, self.cfg.run.log_interval);
            if self.test_in_progress() && self.cfg.run.test_episodes > 0 {
                self.log_due = true; // written with the test phase's row, at its t_env
            } else {
                self.log(None);
            }
        }
        if self.t_env >= self.next_checkpoint {
            self.next_checkpoint = budget::next_multiple(self.t_env, self.cfg.run.checkpoint_interval);
            if self.tx.send(ToLearner::Checkpoint).is_ok() {
                self.checkpoints_pending += 1;
            }
        }
        self.log_checkpoints();
        if let Some(b) = &self.bar {
            b.set_position(self.t_env.min(self.cfg.run.steps));
            let upd = self.shared.lock().updates;
            b.set_message(format!(
                "eps {:.2} updates {upd} test return {}",
                self.epsilon(),
                self.last_test_return.map_or("-".into(), |r| format!("{r:.3}"))
            ));
        }
        self.wait_for_learner();
    }

    fn finished(&self) -> bool {
        (self.t_env >= self.cfg.run.steps && self.dataset.len() >= self.cfg.run.dataset_episodes && !self.test_in_progress())
            || self.failed.is_some()
            || self.shared.lock().error.is_some()
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
