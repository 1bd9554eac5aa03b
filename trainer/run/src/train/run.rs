//! The trainer child's training run: build (or resume) the learner, start the learner thread,
//! run the pipeline with the training actor, save the dataset if one was asked for, and finish
//! with a checkpoint. The one place that wires the other rooms of `train/` together.

use super::actor::TrainActor;
use super::budget;
use super::checkpoints::{checkpoint_dir, read_best_test, refuse_restart_over_metrics};
use super::config::TrainConfig;
use super::dataset_out::save_dataset;
use super::learner_thread::{learner_loop, Shared, ToLearner};
use super::metrics::Metrics;
use super::run_log::RunLog;
use super::schedule::UpdateSchedule;
use super::test_phases::TestPhases;
use crate::episode::EpisodeDims;
use crate::learn::{Controller, LearnRng, Learner};
use anyhow::{bail, Result};
use parking_lot::Mutex;
use std::path::Path;
use std::sync::mpsc;
use std::sync::Arc;

/// The trainer child's training entry point: build (or resume) the learner, start its thread,
/// run the pipeline with the training actor, and finish with a checkpoint.
pub fn train_in_child(run_dir: &Path, args: &crate::pipeline::TrainerArgs, progress: bool) -> Result<crate::pipeline::TrainerReport> {
    let cfg = TrainConfig::load(run_dir)?;
    let learn = cfg.effective_learn()?;
    let schema = &args.schema;
    let dims = EpisodeDims {
        n_agents: schema.n_agents,
        obs_width: schema.obs_dim + args.msg_used(),
        state_dim: schema.state_dim,
        n_actions: schema.n_actions,
    };
    let device = crate::learn::Device::default();
    let ck = checkpoint_dir(run_dir);
    let agent_cfg = cfg.agent_config(schema, &args.compiled)?;
    let mut learner = if crate::learn::checkpoint::checkpoint_exists(&ck) {
        let info = crate::learn::checkpoint::peek_checkpoint(&ck).map_err(|e| anyhow::anyhow!("resuming: {e}"))?;
        if info.dims != dims {
            bail!("checkpoint {} was made for {:?}, this run has {:?}", info.dir.display(), info.dims, dims);
        }
        let l = Learner::load_checkpoint(&ck, device).map_err(|e| anyhow::anyhow!("resuming from {}: {e}", info.dir.display()))?;
        let c = l.counters();
        let buffer_note = if info.has_buffer {
            format!("with its replay buffer ({} episodes)", l.buffer().len())
        } else {
            format!(
                "without a replay buffer (run.save_buffer = false): the learner refills it with {} episodes before it updates again",
                learn.batch_size
            )
        };
        eprintln!("lmac: trainer: resuming from {} at t_env {} ({} updates), {buffer_note}", info.dir.display(), c.t_env, c.updates);
        if let Some(note) = cfg.build.as_ref().and_then(|b| b.difference(&super::build::BuildInfo::current())) {
            eprintln!("lmac: trainer: warning: {note}");
        }
        l
    } else {
        refuse_restart_over_metrics(run_dir)?;
        Learner::with_agent(dims, learn.clone(), agent_cfg, device)?
    };
    // Every checkpoint keeps the configuration it was trained with (a resume compares it).
    learner.set_run_config(toml::to_string_pretty(&cfg)?);
    let counters = learner.counters();
    let (metrics, earlier) = Metrics::open(run_dir, counters.t_env, learner.agent_config().stat_names())?;
    if earlier.dropped_rows > 0 {
        eprintln!(
            "lmac: trainer: dropped {} metrics rows logged after t_env {} (after the checkpoint, before the run stopped)",
            earlier.dropped_rows, counters.t_env
        );
    }
    if counters.t_env == 0 {
        for w in budget::warnings(&cfg, schema.episode_limit) {
            eprintln!("lmac: trainer: warning: {w}");
        }
    }
    let schedule =
        UpdateSchedule::new(cfg.run.updates_per_episode, learn.batch_size, counters.episodes, counters.updates, learner.buffer().len());
    // One controller per ring member (a sub-batch of an env server), each driving its environments.
    // The ring has env servers x sub-batches members (`args.n_members`).
    let envs_per_slab = cfg.run.envs * cfg.run.servers / args.n_members;
    let controllers = (0..args.n_members).map(|_| Controller::new(&learner, envs_per_slab)).collect();
    let shared = Arc::new(Mutex::new(Shared { updates: counters.updates, ..Default::default() }));
    let (tx, rx) = mpsc::channel::<ToLearner>();
    let learner_thread = {
        let shared = shared.clone();
        let ck = ck.clone();
        let run_dir = run_dir.to_path_buf();
        let save_buffer = cfg.run.save_buffer;
        std::thread::Builder::new()
            .name("learner".into())
            .spawn(move || learner_loop(learner, rx, shared, ck, &run_dir, save_buffer, schedule))?
    };
    let bar = progress.then(|| {
        let b = indicatif::ProgressBar::new(cfg.run.steps);
        b.set_style(
            indicatif::ProgressStyle::with_template("[{elapsed_precise}] {bar:30} {pos}/{len} env steps {per_sec} eta {eta} {msg}")
                .expect("template"),
        );
        b.set_position(counters.t_env);
        b
    });
    let tests = TestPhases::new(
        args.n_members,
        envs_per_slab,
        counters.t_env,
        cfg.run.test_episodes,
        cfg.run.test_interval,
        read_best_test(run_dir),
    );
    let log = RunLog::new(metrics, &cfg.run, learn.seed, counters.t_env, earlier.wall_s, bar);
    let mut actor = TrainActor {
        tests,
        log,
        next_checkpoint: budget::next_multiple(counters.t_env, cfg.run.checkpoint_interval),
        t_env: counters.t_env,
        episodes: counters.episodes,
        tx,
        shared: shared.clone(),
        episodes_sent: counters.episodes,
        schedule,
        scratch_first: Vec::new(),
        dataset: Vec::new(),
        obs_dim: schema.obs_dim,
        rng: LearnRng::seed_from(learn.seed ^ 0xAC70_0000 ^ counters.t_env),
        controllers,
        dims,
        learn,
        cfg,
    };
    let result = crate::pipeline::run(args, &mut actor);
    if let Some(b) = &actor.log.bar {
        b.finish_and_clear();
    }
    if let Some(line) = actor.log.acting_summary() {
        eprintln!("lmac: trainer: {line}");
    }
    if actor.cfg.run.dataset_episodes > 0 && actor.dataset.len() >= actor.cfg.run.dataset_episodes {
        save_dataset(run_dir, &actor, args)?;
    }
    // Final checkpoint, whatever happened to the pipeline: the learner thread saves on exit.
    drop(std::mem::replace(&mut actor.tx, mpsc::channel().0));
    let joined = learner_thread.join();
    actor.log.log_checkpoints(&actor.shared);
    if let Some(e) = &actor.log.failed {
        bail!("{e}");
    }
    let s = actor.shared.lock();
    if let Some(e) = &s.error {
        bail!("{e}");
    }
    if joined.is_err() {
        bail!("the learner thread panicked");
    }
    let ck_note = s.last_checkpoint.as_ref().map(|p| format!(" (last checkpoint: {})", p.display())).unwrap_or_default();
    match result {
        Ok(r) => Ok(r),
        Err(e) => bail!("{e}{ck_note}"),
    }
}
