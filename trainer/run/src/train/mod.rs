//! Training through the pipeline: the trainer child acts (epsilon-greedy with the learner's
//! latest weights) on the main thread while the learner trains on a second thread, so acting
//! and learning overlap on our two cores. One idea per file: `run.rs` (the trainer child's
//! entry point that wires the rest together), `schedule.rs` (updates owed per episode),
//! `actor.rs` (acting), `test_phases.rs` (when greedy test phases run and what they scored),
//! `run_log.rs` (metrics rows, checkpoints logged, progress), `learner_thread.rs` (the learning thread and
//! what it shares with the actor), `checkpoints.rs` (checkpoint places, the best test phase,
//! resume guard), `dataset_out.rs` (the trajectory dataset a run writes); the run's
//! configuration is `config.rs`, its metrics `metrics.rs`, the learning itself `learn/`.

mod actor;
pub mod budget;
pub mod build;
mod checkpoints;
pub mod config;
mod dataset_out;
pub mod evaluate;
mod learner_thread;
pub mod marl_eval;
pub mod metrics;
pub mod reference;
pub mod resume_check;
mod run;
mod run_log;
mod schedule;
mod test_phases;

pub use actor::TrainActor;
pub use checkpoints::{best_checkpoint_dir, checkpoint_dir, read_best_test, refuse_restart_over_metrics, BestTest};
pub use config::{
    paper_designs_dir, preset_overrides, preset_then, protocol_files, resolve_paper_spec, ResolvedRun, RunSection, TrainConfig, PRESETS,
};
pub use dataset_out::dataset_dir;
pub use metrics::{read_metrics, CheckpointWritten, Metrics, MetricsResume, MetricsRow};
pub use run::train_in_child;
pub use schedule::UpdateSchedule;
