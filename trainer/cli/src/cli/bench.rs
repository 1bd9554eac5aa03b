//! `lmac bench`: the pipeline against raw stepping, and the learner's cost.

use super::{parse_steps, PipelineOpts};
use anyhow::{bail, Context, Result};
use clap::Subcommand;
use lmac_run::stats::median;
use lmac_run::supervisor;
use lmac_run::supervisor::TrainerJob;
use lmac_run::workflow::{interrupt_flag, pipeline_report, train_dirs, Pipeline};
use lmac_shm_schema::schema::load_env;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

#[derive(Subcommand)]
pub(crate) enum BenchCmd {
    /// Raw vectorized stepping in one Python process vs the full pipeline, in one run.
    Pipeline {
        #[command(flatten)]
        p: PipelineOpts,
        /// Alternate raw and pipeline this many times (blocks inside one env server, or
        /// separate runs with --servers above 1); report medians.
        #[arg(long, default_value_t = 21)]
        repeat: usize,
        /// Print JSON.
        #[arg(long)]
        json: bool,
    },
    /// The learner's cost (ms per update on this build's burn backend) and env-steps/s of real
    /// training runs through the pipeline, against the same pipeline acting randomly.
    Train {
        #[arg(long, default_value = "lbf:8x8-2p-2f-s1-coop")]
        env: String,
        /// qmix | vdn | qplex | fullcomm | qmix-state | lmac | ndq | maic | masia | t2mac | cola
        #[arg(long, default_value = "qmix")]
        algo: String,
        /// Protocol (a design directory or phase files; lmac needs one).
        #[arg(long)]
        protocol: Option<String>,
        /// Total environments of each training run (split over 2 env servers), comma separated.
        #[arg(long, value_delimiter = ',', default_value = "8,32")]
        envs: Vec<usize>,
        /// Env steps of each training run.
        #[arg(long, default_value_t = 20_000, value_parser = parse_steps)]
        steps: u64,
        /// Timed learner updates (after 3 warm-up updates).
        #[arg(long, default_value_t = 20)]
        updates: usize,
        #[arg(long)]
        json: bool,
    },
    /// One learner update on a fixed shape: lmac (fused recurrence), burn's per-step cell and,
    /// with --against torch, pymarl's QLearner in PyTorch (benches/torch/qlearner.py, set up by
    /// benches/torch/setup.sh), alternating in one run, one thread each, with FLOPs and GFLOP/s.
    Learner {
        /// Named shape: lbf8x8 (32 episodes x 25 steps x 2 agents, input 37, state 300) or
        /// 1o10b (32 x 50 x 11 agents, input 108, 16 actions, state 148).
        #[arg(long, default_value = "lbf8x8")]
        shape: String,
        /// Override the named shape's sizes.
        #[arg(long)]
        batch: Option<usize>,
        #[arg(long)]
        steps: Option<usize>,
        #[arg(long)]
        agents: Option<usize>,
        /// Agent input width (observation + last action one-hot + agent id one-hot).
        #[arg(long)]
        input: Option<usize>,
        #[arg(long)]
        actions: Option<usize>,
        #[arg(long)]
        state: Option<usize>,
        /// Mixers, comma separated (--algo qmix, vdn or qplex runs on that mixer only).
        #[arg(long, value_delimiter = ',', default_value = "qmix,vdn,qplex")]
        mixers: Vec<String>,
        /// A method's agent network instead of the plain RNN agent: lmac, ndq, maic, masia,
        /// t2mac, cola, qmix-state, ... (`lmac train --help`); its update's FLOPs are counted
        /// (the method's networks on top of the agent), so GFLOP/s is reported for every method.
        #[arg(long)]
        algo: Option<String>,
        /// Message columns at the end of each agent's observation (what the method reads as
        /// messages; they count in --input).
        #[arg(long, default_value_t = 0)]
        messages: usize,
        /// State dims a designed protocol names as task-critical: the first N (default: all).
        #[arg(long)]
        critical: Option<usize>,
        /// A `[method]` setting, KEY=VALUE in TOML (repeatable): --method encoder='"gru-gate"'.
        #[arg(long = "method", value_name = "KEY=VALUE")]
        method_settings: Vec<String>,
        /// Also run the PyTorch anchor (`torch`).
        #[arg(long)]
        against: Option<String>,
        /// Python of the PyTorch anchor (default: benches/torch/.venv/bin/python).
        #[arg(long)]
        python: Option<std::path::PathBuf>,
        /// Alternating rounds.
        #[arg(long, default_value_t = 3)]
        rounds: usize,
        /// Timed updates per implementation and round (the round's figure is their median).
        #[arg(long, default_value_t = 10)]
        updates: usize,
        /// Skip burn's per-step GRU cell (the reference of the fused recurrence).
        #[arg(long)]
        no_stepwise: bool,
        /// Also time the update on two cores as `--preset paper` runs it (the batch's two halves
        /// on two threads, or the target unroll on the second for methods whose losses do not
        /// split), alternating with the one-thread update.
        #[arg(long)]
        two_cores: bool,
        /// Also time the phases of an update (target unroll, online forward, mixers and loss,
        /// backward, optimizer).
        #[arg(long)]
        profile: bool,
        /// Write the report as JSON to this file too.
        #[arg(long)]
        out: Option<std::path::PathBuf>,
        #[arg(long)]
        json: bool,
    },
}

/// What `repeat` alternations of raw stepping and the pipeline measured.
pub(crate) struct Alternations {
    raws: Vec<f64>,
    pipes: Vec<f64>,
    trainer_us: f64,
    method: &'static str,
    /// Interleaved blocks only: where the pipeline's time went.
    split: Option<serde_json::Value>,
}

/// Raw stepping against the pipeline, `repeat` alternations. One env server: interleaved blocks
/// inside it (see `lmac_env.server._compare`), so each pipeline block is compared with a raw
/// block run right after it on the same machine. Several env servers: separate raw and pipeline
/// runs, alternated (their raw baseline is one process stepping all their environments).
pub(crate) fn bench_pipeline(p: PipelineOpts, repeat: usize, json: bool) -> Result<i32> {
    let p = p.pipeline();
    let interrupted = interrupt_flag();
    let repeat = repeat.max(1);
    let schema = load_env(&p.env)?;
    let sub_batches = p.sub_batches.unwrap_or_else(|| supervisor::default_sub_batches(&schema, p.envs));
    let m = if p.servers == 1 { bench_interleaved(&p, repeat, interrupted)? } else { bench_separate_runs(&p, repeat, interrupted)? };
    let ratios: Vec<f64> = m.raws.iter().zip(&m.pipes).map(|(r, q)| if *r > 0.0 { q / r } else { 0.0 }).collect();
    // Rates over the whole measurement (harmonic means: total env steps over total time, the
    // same steps in every alternation); the ratio is the median over alternations, each a pair
    // measured back to back, which keeps one disturbed alternation from moving it.
    let overall = |rates: &[f64]| rates.len() as f64 / rates.iter().map(|r| 1.0 / r).sum::<f64>();
    let (raw_rate, pipe_rate, ratio) = (overall(&m.raws), overall(&m.pipes), median(&ratios));
    let (lo, hi) = ratios.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), &r| (lo.min(r), hi.max(r)));
    let v = serde_json::json!({
        "env": p.env, "envs_total": p.envs * p.servers, "servers": p.servers, "protocol": p.protocol.to_string(),
        "sub_batches": sub_batches,
        "env_steps": p.steps, "repeats": repeat, "method": m.method,
        "raw_env_steps_per_s": raw_rate, "pipeline_env_steps_per_s": pipe_rate, "ratio": ratio,
        "ratio_of_rates": pipe_rate / raw_rate, "ratio_min": lo, "ratio_max": hi,
        "raw_runs": m.raws, "pipeline_runs": m.pipes, "ratio_runs": ratios,
        "trainer_us_per_batched_step": m.trainer_us, "pipeline_time": m.split,
    });
    if json {
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        println!(
            "{} ({} envs): raw {:.0} env-steps/s, pipeline {:.0} env-steps/s ({} servers, protocol {}): ratio {:.3} \
             overall, {:.3} median of {} {} (range {:.3}-{:.3})",
            p.env,
            p.envs * p.servers,
            raw_rate,
            pipe_rate,
            p.servers,
            p.protocol,
            pipe_rate / raw_rate,
            ratio,
            repeat,
            m.method,
            lo,
            hi
        );
        if let Some(t) = &m.split {
            println!(
                "  the pipeline's time: {:.1}% hand-over (taking, returning, waiting for slots); its stepping cost {:.3}x raw's",
                100.0 * t["handover_share"].as_f64().unwrap_or(0.0),
                t["stepping_vs_raw"].as_f64().unwrap_or(0.0)
            );
        }
    }
    Ok(0)
}

/// Per-block raw and pipeline rates from one env server alternating blocks of both.
pub(crate) fn bench_interleaved(p: &Pipeline, repeat: usize, interrupted: Arc<AtomicBool>) -> Result<Alternations> {
    const WARMUP: u64 = 20; // batched steps each side takes before the first block
    let block = p.steps.div_ceil((p.envs * repeat) as u64).max(1);
    // The env server writes its timings here: a private directory, not a guessable name in /tmp.
    let scratch = lmac_run::safe_fs::PrivateDir::new("bench-pipeline").context("creating a private temporary directory")?;
    let out = scratch.path().join("blocks.json");
    let env_extra = vec![
        "--compare-raw".to_string(),
        block.to_string(),
        "--compare-blocks".into(),
        repeat.to_string(),
        "--compare-out".into(),
        out.display().to_string(),
        "--warmup".into(),
        WARMUP.to_string(),
    ];
    // The trainer stays until every block is done: it counts the blocks' env steps plus the
    // warm-up's (and takes fewer warm-up slots than the env server's warm-up gives it).
    let mut trainer_p = p.clone();
    trainer_p.steps = (repeat as u64 * block + WARMUP) * p.envs as u64;
    let report = pipeline_report(&trainer_p, TrainerJob::default(), env_extra, interrupted);
    let blocks = std::fs::read_to_string(&out);
    let report = report?;
    let blocks: serde_json::Value =
        serde_json::from_str(&blocks.with_context(|| format!("the env server wrote no block timings ({})", out.display()))?)?;
    let per_block = (block * p.envs as u64) as f64;
    let (mut raws, mut pipes) = (Vec::new(), Vec::new());
    let (mut pipe_s, mut step_s, mut raw_s) = (0.0, 0.0, 0.0);
    for b in blocks["blocks"].as_array().into_iter().flatten() {
        let secs = |k: &str| b[k].as_f64().unwrap_or(f64::NAN);
        raws.push(per_block / secs("raw_s"));
        pipes.push(per_block / secs("pipeline_s"));
        (pipe_s, step_s, raw_s) = (pipe_s + secs("pipeline_s"), step_s + secs("stepping_s"), raw_s + secs("raw_s"));
    }
    if raws.len() < repeat {
        bail!("the env server finished {} of {repeat} block pairs", raws.len());
    }
    // Where the pipeline's time goes, summed over the blocks: stepping (against the same steps
    // in the raw baseline) and the rest (taking slots, handing them over, waiting).
    let split = serde_json::json!({
        "block_env_steps": per_block,
        "stepping_vs_raw": step_s / raw_s,
        "handover_share": 1.0 - step_s / pipe_s,
    });
    let trainer_us = report.trainer_us_per_slot;
    Ok(Alternations { raws, pipes, trainer_us, method: "interleaved block pairs", split: Some(split) })
}

/// Separate raw and pipeline runs, alternated so a change of machine load hits both alike.
pub(crate) fn bench_separate_runs(p: &Pipeline, repeat: usize, interrupted: Arc<AtomicBool>) -> Result<Alternations> {
    let batched = (p.steps / (p.envs * p.servers) as u64).max(1);
    let (mut raws, mut pipes, mut trainer_us) = (Vec::new(), Vec::new(), Vec::new());
    for _ in 0..repeat {
        // 1. Raw: the same environments stepped in one Python process, no pipeline.
        let out = supervisor::python_command()?
            .args(["-m", "lmac_env.server", "--raw", "--env", &p.env, "--envs", &(p.envs * p.servers).to_string()])
            .args(["--steps", &batched.to_string(), "--seed", &p.seed.to_string()])
            .output()
            .context("running the raw baseline (python -m lmac_env.server --raw)")?;
        if !out.status.success() {
            bail!("raw baseline failed: {}", String::from_utf8_lossy(&out.stderr));
        }
        let raw: serde_json::Value = serde_json::from_slice(&out.stdout).context("raw baseline output")?;
        raws.push(raw["env_steps_per_s"].as_f64().unwrap_or(0.0));
        // 2. The full pipeline on the same number of env steps.
        let pipe = pipeline_report(p, TrainerJob::default(), vec![], interrupted.clone())?;
        pipes.push(pipe.env_steps_per_s);
        trainer_us.push(pipe.trainer_us_per_slot);
    }
    Ok(Alternations { raws, pipes, trainer_us: median(&trainer_us), method: "separate runs", split: None })
}

pub(crate) fn bench_train(
    env: &str,
    algo_name: &str,
    protocol: Option<&str>,
    envs: &[usize],
    steps: u64,
    updates: usize,
    json: bool,
) -> Result<i32> {
    use lmac_run::episode::{Episode, EpisodeDims};
    use lmac_run::learn::{Device, LearnRng, Learner};
    use lmac_run::train::TrainConfig;
    let interrupted = interrupt_flag();
    let mut overrides = vec![format!("run.env={env:?}"), format!("run.algo={algo_name:?}")];
    if let Some(p) = protocol {
        overrides
            .push(format!("run.protocol={:?}", std::fs::canonicalize(p).with_context(|| format!("--protocol {p}"))?.display().to_string()));
    }
    let cfg = TrainConfig::resolve(None, &overrides)?;
    let run = cfg.resolve_run()?;
    let (schema, msg) = (&run.schema, run.msg_dim());
    let dims = EpisodeDims {
        n_agents: schema.n_agents,
        obs_width: schema.obs_dim + msg,
        state_dim: schema.state_dim,
        n_actions: schema.n_actions,
    };
    // 1. One update on full-length episodes of this environment's sizes (values do not change
    //    the cost of dense math).
    let learn = cfg.effective_learn()?;
    let mut learner = Learner::with_agent(dims, learn.clone(), run.agent.clone(), Device::default())?;
    let mut rng = LearnRng::seed_from(0);
    let len = schema.episode_limit;
    for _ in 0..2 * learn.batch_size {
        learner.add_episode(Episode::synthetic(&dims, len, &mut rng, false))?;
    }
    for _ in 0..3 {
        learner.train_step()?;
    }
    let t0 = std::time::Instant::now();
    for _ in 0..updates.max(1) {
        learner.train_step()?;
    }
    let ms_per_update = t0.elapsed().as_secs_f64() * 1e3 / updates.max(1) as f64;
    let backend = if cfg!(feature = "ndarray") && !cfg!(feature = "flex") { "ndarray" } else { "flex" };
    eprintln!("lmac: {env} {algo_name}: {ms_per_update:.1} ms per update ({} episodes x {len} steps, {backend} backend)", learn.batch_size);
    // 2. Training runs through the pipeline, and the same pipeline acting randomly.
    let scratch = lmac_run::safe_fs::PrivateDir::new("bench-train").context("creating a private temporary directory")?;
    let base = scratch.path().to_path_buf();
    let mut rows = Vec::new();
    for &n in envs {
        let servers = if n >= 2 { 2 } else { 1 };
        let d = base.join(format!("envs{n}"));
        std::fs::create_dir_all(&d)?;
        let c = TrainConfig::resolve(
            None,
            &[
                format!("run.env={env:?}"),
                format!("run.algo={algo_name:?}"),
                format!("run.steps={steps}"),
                format!("run.envs={}", n / servers),
                format!("run.servers={servers}"),
                "run.test_episodes=0".into(),
                format!("run.log_interval={}", (steps / 10).max(1)),
                format!("run.checkpoint_interval={}", steps * 10),
            ],
        )?;
        std::fs::write(d.join("config.toml"), toml::to_string_pretty(&c)?)?;
        train_dirs(std::slice::from_ref(&d), interrupted.clone())?;
        let last = lmac_run::train::read_metrics(&d)?.pop().context("no metrics written")?;
        let (t_env, wall, updates_done) = (last.t_env as f64, last.wall_s, last.updates);
        let train_rate = t_env / wall.max(1e-9);
        let p = Pipeline {
            env: env.into(),
            envs: n / servers,
            servers,
            sub_batches: None,
            slots: 4,
            protocol: run.protocol.clone(),
            msg_dim: Some(msg),
            steps,
            seed: 0,
            startup_timeout: 60.0,
        };
        let rand_rate = pipeline_report(&p, TrainerJob::default(), vec![], interrupted.clone())?.env_steps_per_s;
        eprintln!(
            "lmac: {n} envs: training {train_rate:.0} env-steps/s ({updates_done} updates), random acting {rand_rate:.0} env-steps/s"
        );
        rows.push(serde_json::json!({"envs": n, "servers": servers, "train_env_steps_per_s": train_rate, "updates": updates_done,
            "random_env_steps_per_s": rand_rate, "ratio": if rand_rate > 0.0 { train_rate / rand_rate } else { 0.0 }}));
    }
    drop(scratch);
    let v = serde_json::json!({"env": env, "algo": algo_name, "backend": backend, "ms_per_update": ms_per_update,
        "batch_episodes": learn.batch_size, "episode_len": len, "updates_per_episode": cfg.run.updates_per_episode, "runs": rows});
    if json {
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        println!("{env} {algo_name} ({backend}): {ms_per_update:.1} ms per update");
        for r in &rows {
            println!(
                "  {} envs: {:.0} env-steps/s training, {:.0} random, ratio {:.2}",
                r["envs"],
                r["train_env_steps_per_s"].as_f64().unwrap_or(0.0),
                r["random_env_steps_per_s"].as_f64().unwrap_or(0.0),
                r["ratio"].as_f64().unwrap_or(0.0)
            );
        }
    }
    Ok(0)
}
