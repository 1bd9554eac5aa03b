//! The trajectory dataset a run writes once training is done (`run.dataset_episodes`): where it
//! goes in the run directory and how the actor's collected episodes are saved with their
//! header. Kept apart from acting so the dataset's format and place are in one file.

use super::actor::TrainActor;
use crate::dataset::{Dataset, DatasetHeader};
use anyhow::{Context, Result};
use std::path::{Path, PathBuf};

/// Where a run stores its trajectory dataset (`run.dataset_episodes`).
pub fn dataset_dir(run_dir: &Path) -> PathBuf {
    run_dir.join("dataset")
}

pub(super) fn save_dataset(run_dir: &Path, actor: &TrainActor, args: &crate::pipeline::TrainerArgs) -> Result<()> {
    let s = &args.schema;
    let eps = actor.epsilon();
    let header = DatasetHeader {
        env: actor.cfg.run.env.clone(),
        n_agents: s.n_agents,
        obs_dim: s.obs_dim,
        state_dim: s.state_dim,
        n_actions: s.n_actions,
        episode_limit: s.episode_limit,
        protocol: args.protocol.to_string(),
        policy: format!(
            "{} ({} mixer) after {} env steps, epsilon-greedy with epsilon {eps:.3}",
            actor.cfg.run.algo,
            format!("{:?}", actor.learn.mixer).to_lowercase(),
            actor.t_env
        ),
        seed: actor.learn.seed,
    };
    let ds = Dataset { header, episodes: actor.dataset.clone() };
    let dir = dataset_dir(run_dir);
    ds.save(&dir).with_context(|| format!("saving the dataset to {}", dir.display()))?;
    eprintln!("lmac: trainer: dataset of {} episodes saved in {}", ds.episodes.len(), dir.display());
    Ok(())
}
