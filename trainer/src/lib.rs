//! lmac trainer: episode assembly from shared-memory slots, acting, learning, and the CLI.
pub mod dataset;
pub mod design;
pub mod episode;
pub mod faults;
pub mod learn;
pub mod pipeline;
pub mod run_dir;
pub mod stats;
pub mod supervisor;
pub mod tensorboard;
pub mod train;
