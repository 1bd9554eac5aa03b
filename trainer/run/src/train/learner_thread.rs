//! The learner thread: it takes episodes, checkpoint requests and best-test saves from the
//! actor over a channel, trains on the update schedule, and shares its newest acting weights,
//! statistics, written checkpoints and errors through `Shared`. It runs beside the actor so
//! acting and learning overlap on our two cores.

use super::checkpoints::{best_checkpoint_dir, write_best_test, BestTest};
use super::metrics::CheckpointWritten;
use super::schedule::UpdateSchedule;
use crate::episode::Episode;
use crate::learn::methods::AgentNet;
use crate::learn::Learner;
use parking_lot::Mutex;
use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::sync::Arc;

/// What the learner thread shares with the actor.
#[derive(Default)]
pub(super) struct Shared {
    /// Newest acting weights, taken by the actor.
    pub(super) agent: Option<AgentNet>,
    pub(super) updates: u64,
    /// The method's terms of the last update.
    pub(super) method: Vec<(&'static str, f32)>,
    pub(super) loss: Option<f32>,
    pub(super) grad_norm: Option<f32>,
    pub(super) q_taken_mean: Option<f32>,
    pub(super) error: Option<String>,
    pub(super) last_checkpoint: Option<PathBuf>,
    /// Checkpoints written and not yet logged to `metrics.jsonl`.
    pub(super) checkpoints: Vec<CheckpointWritten>,
}

pub(super) enum ToLearner {
    Episode(Episode),
    Checkpoint,
    /// A test phase scored better than any before: keep the learner's state as the best
    /// checkpoint (what a final evaluation reads).
    SaveBest(BestTest),
}

pub(super) fn learner_loop(
    mut learner: Learner,
    rx: mpsc::Receiver<ToLearner>,
    shared: Arc<Mutex<Shared>>,
    ck: PathBuf,
    run_dir: &Path,
    save_buffer: bool,
    schedule: UpdateSchedule,
) {
    // A checkpoint that cannot be written ends the run (its error names the file).
    let save = |learner: &Learner, shared: &Mutex<Shared>| -> bool {
        match learner.save_checkpoint(&ck, save_buffer) {
            Ok(()) => {
                let c = learner.counters();
                let mut s = shared.lock();
                s.last_checkpoint = Some(ck.clone());
                s.checkpoints.push(CheckpointWritten { t_env: c.t_env, episodes: c.episodes, updates: c.updates, path: ck.clone() });
                true
            }
            Err(e) => {
                shared.lock().error.get_or_insert(format!("writing the checkpoint failed: {e}"));
                false
            }
        }
    };
    let mut saved_at = None;
    let mut disconnected = false;
    while !disconnected {
        // Take everything that arrived; block briefly when idle.
        let first = rx.recv_timeout(std::time::Duration::from_millis(50));
        let mut msgs = Vec::new();
        match first {
            Ok(m) => msgs.push(m),
            Err(mpsc::RecvTimeoutError::Disconnected) => disconnected = true,
            Err(mpsc::RecvTimeoutError::Timeout) => {}
        }
        while let Ok(m) = rx.try_recv() {
            msgs.push(m);
        }
        for m in msgs {
            match m {
                ToLearner::Episode(ep) => {
                    if let Err(e) = learner.add_episode(ep) {
                        shared.lock().error = Some(format!("learner: {e}"));
                        return;
                    }
                }
                ToLearner::Checkpoint => {
                    if !save(&learner, &shared) {
                        return;
                    }
                    saved_at = Some(learner.counters());
                }
                ToLearner::SaveBest(best) => {
                    // The checkpoint first, then the record that names it: a crash between the
                    // two leaves an older record, never one without its checkpoint.
                    let saved = learner
                        .save_checkpoint(best_checkpoint_dir(run_dir), false)
                        .map_err(|e| e.to_string())
                        .and_then(|()| write_best_test(run_dir, &best));
                    if let Err(e) = saved {
                        shared.lock().error.get_or_insert(format!("writing the best checkpoint failed: {e}"));
                        return;
                    }
                }
            }
        }
        let due = schedule.due(learner.counters().episodes);
        let mut did = false;
        while learner.can_train() && learner.counters().updates < due {
            match learner.train_step() {
                Ok(st) => {
                    if !st.loss.is_finite() || !st.grad_norm.is_finite() {
                        let c = learner.counters();
                        let mut s = shared.lock();
                        s.error = Some(format!(
                            "the loss became {} at update {} (t_env {}); the last good checkpoint is {}",
                            st.loss,
                            c.updates,
                            c.t_env,
                            s.last_checkpoint.as_ref().map_or("none yet".into(), |p| p.display().to_string())
                        ));
                        return;
                    }
                    let mut s = shared.lock();
                    s.updates = learner.counters().updates;
                    s.loss = Some(st.loss);
                    s.grad_norm = Some(st.grad_norm);
                    s.q_taken_mean = Some(st.q_taken_mean);
                    s.method = st.method;
                    did = true;
                }
                Err(e) => {
                    shared.lock().error = Some(format!("learner: {e}"));
                    return;
                }
            }
        }
        if did {
            shared.lock().agent = Some(learner.acting_net().agent);
        }
    }
    // The last checkpoint, unless the one just written already holds this state.
    if saved_at != Some(learner.counters()) {
        save(&learner, &shared);
    }
}
