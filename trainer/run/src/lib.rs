//! lmac's runs: the pipeline's processes (the supervisor, the trainer's slot loop), training
//! runs, evaluation, metrics, datasets and run directories, and the workflow the commands and the
//! design loop drive ([`workflow`]); on the learning core [`lmac_learn`] (re-exported as
//! [`learn`], with its [`episode`] and [`stats`]).
pub use lmac_learn as learn;
pub use lmac_learn::{episode, stats, tune_allocator};

pub mod dataset;
pub mod pipeline;
pub mod run_dir;
pub use lmac_shm_schema::safe_fs;
pub mod supervisor;
pub mod tensorboard;
pub mod train;
pub mod workflow;
