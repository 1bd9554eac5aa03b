//! The actor side of training: epsilon-greedy acting with the learner's latest weights (greedy
//! in test episodes), the run's step and episode counts, checkpoint requests and dataset
//! collection. When tests run is `test_phases.rs`; what the run logs, `run_log.rs`. It runs on
//! the trainer child's main thread inside the pipeline and talks to the learner thread only
//! through the channel and `Shared` of `learner_thread.rs`.

use super::budget;
use super::config::TrainConfig;
use super::learner_thread::{Shared, ToLearner};
use super::run_log::{RunLog, RunPoint};
use super::schedule::UpdateSchedule;
use super::test_phases::TestPhases;
use crate::dataset::Trajectory;
use crate::episode::{Episode, EpisodeDims};
use crate::learn::{Controller, LearnConfig, LearnRng};
use crate::pipeline::Actor;
use lmac_shm_schema::{Slot, FLAG_FIRST};
use parking_lot::Mutex;
use std::sync::mpsc;
use std::sync::Arc;
use std::time::Instant;

/// The actor side of training: epsilon-greedy acting and the run's clock; test scheduling is
/// `tests`, what the run logs is `log`.
pub struct TrainActor {
    pub(super) cfg: TrainConfig,
    pub(super) learn: LearnConfig,
    pub(super) controllers: Vec<Controller>,
    pub(super) rng: LearnRng,
    pub(super) dims: EpisodeDims,
    pub(super) tests: TestPhases,
    pub(super) log: RunLog,
    pub(super) next_checkpoint: u64,
    pub(super) t_env: u64,
    pub(super) episodes: u64,
    pub(super) tx: mpsc::Sender<ToLearner>,
    pub(super) shared: Arc<Mutex<Shared>>,
    pub(super) episodes_sent: u64,
    pub(super) schedule: UpdateSchedule,
    pub(super) scratch_first: Vec<bool>,
    /// The trajectory dataset being collected once training is done (`run.dataset_episodes`).
    pub(super) dataset: Vec<Trajectory>,
    /// Observation columns without messages (what the dataset keeps).
    pub(super) obs_dim: usize,
}

impl TrainActor {
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

    fn point(&self) -> RunPoint {
        RunPoint { t_env: self.t_env, episodes: self.episodes, epsilon: self.epsilon() }
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
        self.log.waited(start.elapsed());
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
                self.tests.episode_starts(member, e);
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
        for e in (0..l.num_envs).filter(|&e| self.tests.is_test(member, e)) {
            for ag in 0..n {
                let r = e * n + ag;
                let (qs, av) = (&q[r * a..(r + 1) * a], &avail[r * a..(r + 1) * a]);
                actions[r] = crate::learn::controller::greedy_available(qs, av).unwrap_or(0) as i32;
            }
        }
        self.log.acted(acting.elapsed().as_secs_f32() * 1e6);
    }

    fn episode_done(&mut self, member: usize, env: usize, ep: Episode, won: bool) {
        if self.tests.episode_ends(member, env) {
            if let Some((ret, win)) = self.tests.record(ep.team_return(), won) {
                self.log.write_row(&self.point(), Some((ret, win)), &self.shared);
                if let Some(best) = self.tests.improved(ret, self.t_env) {
                    let _ = self.tx.send(ToLearner::SaveBest(best));
                }
            }
            return;
        }
        if self.collecting() {
            if self.dataset.len() < self.cfg.run.dataset_episodes {
                self.dataset.push(Trajectory::from_episode(&ep, self.dims.n_agents, self.obs_dim));
                let (n, of) = (self.dataset.len(), self.cfg.run.dataset_episodes);
                self.log.progress(self.t_env, || format!("collecting the dataset: {n}/{of} episodes"));
            }
            return;
        }
        if self.t_env >= self.cfg.run.steps {
            // Past the budget, waiting for the final test phase: not trained on, not counted.
            return;
        }
        self.t_env += ep.len as u64;
        self.episodes += 1;
        self.log.training_episode(ep.team_return());
        if self.tx.send(ToLearner::Episode(ep)).is_ok() {
            self.episodes_sent += 1;
        }
        self.tests.after_training(self.t_env, self.cfg.run.steps);
        self.log.after_training(&self.point(), self.tests.in_progress(), &self.shared);
        if self.t_env >= self.next_checkpoint {
            self.next_checkpoint = budget::next_multiple(self.t_env, self.cfg.run.checkpoint_interval);
            if self.tx.send(ToLearner::Checkpoint).is_ok() {
                self.log.checkpoint_asked();
            }
        }
        self.log.log_checkpoints(&self.shared);
        // The bar's message is built (and the learner's count read) only where a bar is shown.
        let (eps, last, shared) = (self.epsilon(), self.tests.last_return, &self.shared);
        self.log.progress(self.t_env, || {
            let upd = shared.lock().updates;
            format!("eps {eps:.2} updates {upd} test return {}", last.map_or("-".into(), |r| format!("{r:.3}")))
        });
        self.wait_for_learner();
    }

    fn finished(&self) -> bool {
        (self.t_env >= self.cfg.run.steps && self.dataset.len() >= self.cfg.run.dataset_episodes && !self.tests.in_progress())
            || self.log.failed.is_some()
            || self.shared.lock().error.is_some()
    }
}
