//! When greedy test phases fall due, which episodes belong to one, and what each phase scored:
//! the test scheduling of a training run, apart from acting and from the run's log.

use super::budget;
use super::checkpoints::BestTest;
use std::collections::VecDeque;

/// The test phases of one training run.
pub(super) struct TestPhases {
    /// Episodes per test phase (`run.test_episodes`; 0: no tests).
    episodes: usize,
    /// Env steps between test phases (`run.test_interval`).
    interval: u64,
    /// Per member, per env: is the current episode a greedy test episode?
    testing: Vec<Vec<bool>>,
    /// Per member, per env: whether each episode started and not yet reported done is a test
    /// episode, oldest first. An env's next episode may start before or after the one that ended
    /// is reported, so a finished episode's own flag is looked up here, never in `testing`
    /// (which already belongs to the next episode).
    started: Vec<Vec<VecDeque<bool>>>,
    /// Test episodes the current phase still wants started.
    pending: usize,
    /// The current phase's finished episodes: (team return, won).
    results: Vec<(f32, bool)>,
    /// The run reached its step budget and asked for its final test phase (a run always ends
    /// with a test at its last step, so its final return is measured there).
    final_asked: bool,
    next: u64,
    /// The last finished phase's mean return.
    pub(super) last_return: Option<f64>,
    /// The best phase so far (its checkpoint is in `best_checkpoint_dir`).
    pub(super) best: Option<BestTest>,
}

impl TestPhases {
    /// Test phases for `members` ring members of `envs` envs each, from step `t_env`: a fresh run
    /// tests before it trains; a resumed one at its next interval.
    pub(super) fn new(members: usize, envs: usize, t_env: u64, episodes: usize, interval: u64, best: Option<BestTest>) -> TestPhases {
        TestPhases {
            episodes,
            interval,
            testing: vec![vec![false; envs]; members],
            started: vec![vec![VecDeque::new(); envs]; members],
            pending: if t_env == 0 { episodes } else { 0 },
            results: Vec::new(),
            final_asked: false,
            next: budget::next_multiple(t_env, interval),
            last_return: None,
            best,
        }
    }

    /// A phase is asked for or under way (a running test episode stays in `started` until it is
    /// reported done).
    pub(super) fn in_progress(&self) -> bool {
        self.pending > 0 || !self.results.is_empty() || self.started.iter().flatten().any(|q| q.contains(&true))
    }

    /// An env of `member` starts an episode: a greedy test episode if the phase wants more.
    pub(super) fn episode_starts(&mut self, member: usize, env: usize) {
        let test = self.pending > 0;
        self.testing[member][env] = test;
        self.started[member][env].push_back(test);
        self.pending = self.pending.saturating_sub(1);
    }

    /// Whether the env's current episode is a test episode (it acts greedily).
    pub(super) fn is_test(&self, member: usize, env: usize) -> bool {
        self.testing[member][env]
    }

    /// The env's oldest running episode ended: whether it was a test episode.
    pub(super) fn episode_ends(&mut self, member: usize, env: usize) -> bool {
        self.started[member][env].pop_front().unwrap_or(false)
    }

    /// A test episode's result; when it completes its phase, the phase's mean return and win
    /// rate.
    pub(super) fn record(&mut self, team_return: f32, won: bool) -> Option<(f64, f64)> {
        self.results.push((team_return, won));
        if self.results.len() < self.episodes {
            return None;
        }
        let n = self.results.len() as f64;
        let ret = self.results.iter().map(|x| x.0 as f64).sum::<f64>() / n;
        let win = self.results.iter().filter(|x| x.1).count() as f64 / n;
        self.results.clear();
        self.last_return = Some(ret);
        Some((ret, win))
    }

    /// A phase's return: the new best when it beats the best so far.
    pub(super) fn improved(&mut self, test_return: f64, t_env: u64) -> Option<BestTest> {
        if self.best.is_some_and(|b| test_return <= b.test_return) {
            return None;
        }
        let best = BestTest { test_return, t_env };
        self.best = Some(best);
        Some(best)
    }

    /// Training reached `t_env` of `steps`: a phase falls due every interval, and once at the
    /// end unless one is already under way.
    pub(super) fn after_training(&mut self, t_env: u64, steps: u64) {
        if t_env >= self.next {
            self.next = budget::next_multiple(t_env, self.interval);
            self.pending = self.episodes;
        }
        if t_env >= steps && !self.final_asked {
            self.final_asked = true;
            if !self.in_progress() {
                self.pending = self.episodes;
            }
        }
    }
}
