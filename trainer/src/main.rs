//! `lmac`: the command line of the LMAC system.
use anyhow::{bail, Context, Result};
use clap::{Args, Parser, Subcommand};
use lmac_protocol_runner::runner::{self as prunner, RunnerArgs};
use lmac_shm_schema::schema::{all_envs, load_env};
use lmac_trainer::pipeline::{self, MessageCheck, RandomActor, TrainerArgs};
use lmac_trainer::supervisor::{self, RunPlan};
use std::io::Write;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

#[derive(Parser)]
#[command(
    name = "lmac",
    version,
    about = "LLM-guided communication for cooperative multi-agent RL: a zero-copy shared-memory pipeline",
    long_about = "lmac runs batched environments in Python env servers that write straight into shared memory, a protocol runner that appends each agent's messages in place, and a trainer that consumes the batches with no serialization."
)]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Run the pipeline with a random policy: env servers -> protocol runner -> trainer (throughput, checks).
    Run(RunArgs),
    /// Train VDN / QMIX / QPLEX and the baselines through the pipeline, over several seeds.
    #[command(after_long_help = TRAIN_AFTER_HELP)]
    Train(TrainArgs),
    /// Design a communication protocol in three phases (initialization, recognition enhancement,
    /// sharing enhancement) with an LLM or the embedded offline designer, checked on real data.
    Design(DesignArgs),
    /// Protocols: check a protocol file against an environment, explain it, print the JSON Schema.
    #[command(subcommand)]
    Protocol(ProtocolCmd),
    /// List the environments with their dimensions.
    Envs {
        /// Validate every schema file and fail on the first bad one.
        #[arg(long)]
        check: bool,
        /// Print JSON instead of a table.
        #[arg(long)]
        json: bool,
    },
    /// Benchmarks.
    #[command(subcommand)]
    Bench(BenchCmd),
    /// Fault injection: train, SIGKILL a random process of the run (an env server, the protocol
    /// runner, the trainer or the lmac parent) at a random moment, resume, repeat; report how fast
    /// each death was noticed, resumes that continued, steps lost and shared memory left behind.
    Chaos(ChaosArgs),
    /// Endurance: train for a long time and sample the run's memory, open files and shared-memory
    /// mappings; report their slopes once the replay buffer is full.
    Soak(SoakArgs),
    /// Internal: the child processes started by `lmac run`.
    #[command(subcommand, hide = true)]
    Child(ChildCmd),
}

#[derive(Args, Clone)]
struct PipelineOpts {
    /// Environment, e.g. lbf:8x8-2p-2f-s1-coop (see `lmac envs`).
    #[arg(long, default_value = "lbf:8x8-2p-2f-s1-coop")]
    env: String,
    /// Environments per env server.
    #[arg(long, default_value_t = 32)]
    envs: usize,
    /// Env server processes.
    #[arg(long, default_value_t = 1)]
    servers: usize,
    /// Sub-batches per env server: it steps one while the other's slot travels through the
    /// runner and the trainer (default: 2 when --envs is even, unless the environment's schema
    /// sets double_buffer = false; else 1).
    #[arg(long)]
    sub_batches: Option<usize>,
    /// Slots in each server's shared-memory slab.
    #[arg(long, default_value_t = 4)]
    slots: usize,
    /// Communication protocol applied by the runner: none | fullcomm.
    #[arg(long, default_value = "none")]
    protocol: String,
    /// Env steps to collect (after warm-up).
    #[arg(long, default_value_t = 20_000)]
    steps: u64,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Seconds the processes may take to find each other.
    #[arg(long, default_value_t = 60.0)]
    startup_timeout: f64,
}

#[derive(Args)]
struct RunArgs {
    #[command(flatten)]
    p: PipelineOpts,
    /// Check every slot: message columns, episode ids, steps and boundaries.
    #[arg(long)]
    verify: bool,
    /// Write one JSON line per finished episode to this file.
    #[arg(long)]
    episodes_out: Option<std::path::PathBuf>,
    /// Print the report as JSON.
    #[arg(long)]
    json: bool,
}

const TRAIN_AFTER_HELP: &str = "\
Update ratio: by default the learner does run.updates_per_episode = 0.125 gradient updates (of
learn.batch_size = 32 episodes) per collected episode, pymarl's parallel runner with 8
environments. That is 8x fewer updates per episode than EPyMARL's episode runner (1 per
episode), and the target network, copied every 200 episodes, is then copied every 25 updates.
--preset epymarl reproduces the episode runner's schedule: 1 update per episode from the 32nd
episode on, a target copy every 200 updates. Each environment switches to new weights when its
next episode starts.

Resuming: --resume DIR continues every unfinished seed in DIR (a group or one seed) from its
last checkpoint (run.checkpoint_interval env steps apart, and one at the end). Without the saved
replay buffer (run.save_buffer = false) the learner refills learn.batch_size episodes before it
updates again. Metrics rows logged after that checkpoint are dropped, so curves continue
without a step backwards; each checkpoint is logged in metrics.jsonl.";

#[derive(Args)]
struct TrainArgs {
    /// Environment (overrides run.env).
    #[arg(long)]
    env: Option<String>,
    /// qmix | vdn | qplex | fullcomm | qmix-state (overrides run.algo).
    #[arg(long)]
    algo: Option<String>,
    /// Seeds, comma separated: one run directory each, run one after the other.
    #[arg(long, default_value = "0", value_delimiter = ',')]
    seeds: Vec<u64>,
    /// Env steps per seed, e.g. 2M, 500k (overrides run.steps).
    #[arg(long, value_parser = parse_steps)]
    steps: Option<u64>,
    /// Config file (TOML with [run] and [learn] sections).
    #[arg(long)]
    config: Option<std::path::PathBuf>,
    /// Override a config value: --set learn.lr=0.001 --set run.envs=8
    #[arg(long = "set", value_name = "KEY=VALUE")]
    set: Vec<String>,
    /// A named bundle of settings, applied before --set: epymarl (EPyMARL's episode-runner
    /// learning schedule: 1 update per collected episode, target copy every 200 updates).
    #[arg(long)]
    preset: Option<String>,
    /// Where run directories go.
    #[arg(long, default_value = "runs")]
    out: std::path::PathBuf,
    /// Continue the runs in this directory (a seed's directory or a group of seeds).
    #[arg(long, conflicts_with_all = ["env", "algo", "config", "set", "steps", "preset"])]
    resume: Option<std::path::PathBuf>,
}

#[derive(Args)]
struct ChaosArgs {
    /// Kills (each followed by a resume).
    #[arg(long, default_value_t = 100)]
    kills: usize,
    #[arg(long, default_value = "lbf:8x8-2p-2f-s1-coop")]
    env: String,
    /// Env steps between checkpoints (at most this many are lost per crash).
    #[arg(long, default_value_t = 5000)]
    checkpoint_interval: u64,
    /// Seconds from each start or resume to the kill: drawn uniformly from MIN,MAX.
    #[arg(long, value_delimiter = ',', default_value = "3,12")]
    kill_after: Vec<f64>,
    /// Environments per env server and env servers.
    #[arg(long, default_value_t = 8)]
    envs: usize,
    #[arg(long, default_value_t = 2)]
    servers: usize,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Where the run goes (must be empty or absent; default: a temporary folder, removed after).
    #[arg(long)]
    out: Option<std::path::PathBuf>,
    /// Write the report (JSON) here.
    #[arg(long)]
    report: Option<std::path::PathBuf>,
}

#[derive(Args)]
struct SoakArgs {
    /// How long to train, e.g. 2h, 30m, 90s.
    #[arg(long, default_value = "2h", value_parser = parse_duration)]
    duration: f64,
    /// Seconds between samples.
    #[arg(long, default_value_t = 30.0)]
    interval: f64,
    #[arg(long, default_value = "lbf:8x8-2p-2f-s1-coop")]
    env: String,
    #[arg(long, default_value_t = 16)]
    envs: usize,
    #[arg(long, default_value_t = 2)]
    servers: usize,
    /// Store the replay buffer in checkpoints too (the largest thing a run writes).
    #[arg(long)]
    save_buffer: bool,
    /// Where the run goes (default: a temporary folder, removed after).
    #[arg(long)]
    out: Option<std::path::PathBuf>,
    /// Write the report (JSON, with every sample) here.
    #[arg(long)]
    report: Option<std::path::PathBuf>,
}

fn parse_duration(s: &str) -> Result<f64, String> {
    let t = s.trim().to_ascii_lowercase();
    let (num, mul) = match t.chars().last() {
        Some('h') => (&t[..t.len() - 1], 3600.0),
        Some('m') => (&t[..t.len() - 1], 60.0),
        Some('s') => (&t[..t.len() - 1], 1.0),
        _ => (&t[..], 1.0),
    };
    num.parse::<f64>().ok().filter(|v| *v > 0.0).map(|v| v * mul).ok_or_else(|| format!("{s:?} is not a duration (e.g. 2h, 30m, 90s)"))
}

#[derive(Args)]
struct DesignArgs {
    /// Environment, e.g. lbf:8x8-2p-2f-s1-coop.
    #[arg(long, default_value = "lbf:8x8-2p-2f-s1-coop")]
    env: String,
    /// Designer: `offline` (embedded, no network: builds each phase from the meta-information),
    /// or an LLM: `openai:MODEL` (any OpenAI-compatible server: OpenAI, vLLM, llama.cpp,
    /// Ollama; key from OPENAI_API_KEY), `anthropic:MODEL` (key from ANTHROPIC_API_KEY).
    #[arg(long, default_value = "offline")]
    llm: String,
    /// Base URL of an OpenAI-compatible server, e.g. http://127.0.0.1:8080/v1.
    #[arg(long)]
    base_url: Option<String>,
    /// live: ask the LLM (recording every exchange); replay: answer from the recordings only
    /// (offline, exact); replay-or-live: recordings first, then the LLM.
    #[arg(long, default_value = "live")]
    llm_mode: String,
    /// Where LLM exchanges are recorded and replayed from (default: <out>/llm-recordings).
    #[arg(long)]
    recordings: Option<std::path::PathBuf>,
    /// Corrections the LLM gets per reply (invalid JSON, validation errors) before the design fails.
    #[arg(long, default_value_t = 3)]
    max_retries: usize,
    /// Env steps of the QMIX run whose epsilon-greedy policy collects the dataset (paper: 200k).
    #[arg(long, default_value = "50k", value_parser = parse_steps)]
    pretrain_steps: u64,
    /// Episodes in the dataset (paper: 5000).
    #[arg(long, default_value_t = 1000)]
    dataset_episodes: usize,
    /// Epsilon while collecting (default: the schedule's value at the end of the QMIX run).
    #[arg(long)]
    dataset_epsilon: Option<f32>,
    /// Reuse a dataset directory (e.g. <design>/collect/dataset) instead of collecting one.
    #[arg(long)]
    dataset: Option<std::path::PathBuf>,
    /// Environments per env server and env servers for the collection run.
    #[arg(long, default_value_t = 16)]
    envs: usize,
    #[arg(long, default_value_t = 2)]
    servers: usize,
    /// Discriminator updates per training (paper: 1000 epochs x 10 iterations).
    #[arg(long)]
    disc_updates: Option<usize>,
    /// Design phases (paper: 3).
    #[arg(long, default_value_t = 3)]
    phases: usize,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Where design directories go.
    #[arg(long, default_value = "designs")]
    out: std::path::PathBuf,
}

fn parse_steps(s: &str) -> Result<u64, String> {
    let t = s.trim().to_ascii_lowercase();
    let (num, mul) = match t.chars().last() {
        Some('k') => (&t[..t.len() - 1], 1_000f64),
        Some('m') => (&t[..t.len() - 1], 1_000_000f64),
        _ => (&t[..], 1f64),
    };
    num.parse::<f64>().map(|v| (v * mul) as u64).map_err(|_| format!("{s:?} is not a step count (e.g. 2M, 500k, 20000)"))
}

#[derive(Subcommand)]
enum ProtocolCmd {
    /// Validate protocol phase files (in order) against an environment; errors are the text an LLM gets back.
    Check {
        /// Protocol JSON files: phase 0, then phase 1, ... (concatenated in this order).
        #[arg(required = true)]
        files: Vec<String>,
        #[arg(long)]
        env: String,
    },
    /// Explain protocol files in plain words: who sends what to whom and why.
    Explain {
        #[arg(required = true)]
        files: Vec<String>,
        /// Name dimensions by their meaning in this environment.
        #[arg(long)]
        env: Option<String>,
    },
    /// Print the protocol language's JSON Schema.
    Schema,
}

#[derive(Subcommand)]
enum BenchCmd {
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
        /// qmix | vdn | qplex | fullcomm | qmix-state
        #[arg(long, default_value = "qmix")]
        algo: String,
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
}

#[derive(Args, Clone)]
struct ChildOpts {
    #[arg(long)]
    run: String,
    #[arg(long)]
    env: String,
    #[arg(long)]
    servers: usize,
    #[arg(long)]
    slots: usize,
    #[arg(long)]
    protocol: String,
    #[arg(long, default_value_t = 60.0)]
    startup_timeout: f64,
}

#[derive(Subcommand)]
enum ChildCmd {
    Runner(ChildOpts),
    Trainer {
        #[command(flatten)]
        o: ChildOpts,
        #[arg(long)]
        steps: u64,
        #[arg(long, default_value_t = 10)]
        warmup: u64,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        #[arg(long)]
        verify: bool,
        #[arg(long)]
        episodes_out: Option<std::path::PathBuf>,
        #[arg(long)]
        progress: bool,
        /// Train with the run directory's config (instead of acting randomly).
        #[arg(long)]
        train_dir: Option<std::path::PathBuf>,
    },
}

fn main() {
    let cli = Cli::parse();
    let code = match dispatch(cli) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("lmac: error: {e:#}");
            2
        }
    };
    std::process::exit(code);
}

fn dispatch(cli: Cli) -> Result<i32> {
    match cli.cmd {
        Cmd::Envs { check, json } => envs(check, json),
        Cmd::Run(a) => run(a),
        Cmd::Train(a) => train(a),
        Cmd::Protocol(p) => protocol_cmd(p),
        Cmd::Design(d) => design(d),
        Cmd::Bench(BenchCmd::Pipeline { p, repeat, json }) => bench_pipeline(p, repeat, json),
        Cmd::Bench(BenchCmd::Train { env, algo, envs, steps, updates, json }) => bench_train(&env, &algo, &envs, steps, updates, json),
        Cmd::Chaos(a) => chaos(a),
        Cmd::Soak(a) => soak(a),
        Cmd::Child(c) => child(c),
    }
}

fn protocol_cmd(c: ProtocolCmd) -> Result<i32> {
    use lmac_protocol_runner::protocol;
    match c {
        ProtocolCmd::Schema => {
            println!("{}", protocol::schema_json());
            Ok(0)
        }
        ProtocolCmd::Check { files, env } => {
            let schema = load_env(&env).map_err(anyhow::Error::msg)?;
            let penv = lmac_protocol_runner::protocol_env(&schema);
            let refs: Vec<&str> = files.iter().map(|s| s.as_str()).collect();
            match lmac_protocol_runner::load_phases(&refs, &penv) {
                Ok(phases) => {
                    for (f, p) in files.iter().zip(&phases) {
                        println!("{f}: {}", protocol::check_summary(p));
                    }
                    let total = protocol::check_phases(&phases, &penv).map_err(|e| anyhow::anyhow!(protocol::errors_to_text(&e)))?;
                    println!("all phases: {total} message columns per agent (budget {})", schema.message_columns);
                    Ok(0)
                }
                Err(e) => {
                    eprintln!("{e}");
                    Ok(1)
                }
            }
        }
        ProtocolCmd::Explain { files, env } => {
            let mut ps = Vec::new();
            for f in &files {
                let text = std::fs::read_to_string(f).with_context(|| format!("reading {f}"))?;
                ps.push(protocol::parse_str(&text).map_err(|e| anyhow::anyhow!("{f}:\n{}", protocol::errors_to_text(&e)))?);
            }
            let penv = match env {
                Some(e) => Some(lmac_protocol_runner::protocol_env(&load_env(&e).map_err(anyhow::Error::msg)?)),
                None => None,
            };
            println!("{}", protocol::explain_phases(&ps, penv.as_ref()));
            Ok(0)
        }
    }
}

fn envs(check: bool, json: bool) -> Result<i32> {
    let mut rows = Vec::new();
    let mut bad = 0;
    for (path, r) in all_envs().map_err(anyhow::Error::msg)? {
        match r {
            Ok(s) => rows.push(s),
            Err(e) => {
                bad += 1;
                eprintln!("{e}");
                if check {
                    bail!("invalid schema {}", path.display());
                }
            }
        }
    }
    if json {
        let v: Vec<_> = rows
            .iter()
            .map(|s| {
                serde_json::json!({
                    "name": s.name, "n_agents": s.n_agents, "obs_dim": s.obs_dim, "state_dim": s.state_dim,
                    "n_actions": s.n_actions, "episode_limit": s.episode_limit, "message_columns": s.message_columns, "alpha": s.alpha,
                })
            })
            .collect();
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        println!(
            "{:<42} {:>6} {:>5} {:>6} {:>7} {:>6} {:>5} {:>6}",
            "environment", "agents", "obs", "state", "actions", "limit", "msg", "alpha"
        );
        for s in &rows {
            println!(
                "{:<42} {:>6} {:>5} {:>6} {:>7} {:>6} {:>5} {:>6}",
                s.name, s.n_agents, s.obs_dim, s.state_dim, s.n_actions, s.episode_limit, s.message_columns, s.alpha
            );
        }
    }
    Ok(if bad > 0 && check { 1 } else { 0 })
}

fn run_id() -> String {
    let t = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_nanos()).unwrap_or(0);
    format!("{:08x}", (t as u64 ^ ((std::process::id() as u64) << 32)) as u32)
}

fn interrupt_flag() -> Arc<AtomicBool> {
    let flag = Arc::new(AtomicBool::new(false));
    let f = flag.clone();
    let _ = ctrlc::set_handler(move || f.store(true, Ordering::SeqCst));
    flag
}

/// Start the processes of one pipeline run and return the trainer's JSON report. `extra` goes to
/// the trainer, `env_extra` to the env servers.
fn pipeline_report(
    p: &PipelineOpts,
    extra: Vec<String>,
    env_extra: Vec<String>,
    interrupted: Arc<AtomicBool>,
) -> Result<serde_json::Value> {
    let schema = load_env(&p.env).map_err(anyhow::Error::msg)?;
    let plan = lmac_protocol_runner::plan_for(&p.protocol, &schema).map_err(anyhow::Error::msg)?;
    if plan.msg_dim() > schema.message_columns {
        bail!(
            "protocol {} writes {} message columns but {} allows {} (its message_columns budget)",
            p.protocol,
            plan.msg_dim(),
            p.env,
            schema.message_columns
        );
    }
    if p.envs == 0 || p.servers == 0 || p.slots == 0 {
        bail!("--envs, --servers and --slots must be at least 1");
    }
    let sub_batches = p.sub_batches.unwrap_or_else(|| supervisor::default_sub_batches(&schema, p.envs));
    if sub_batches == 0 || p.envs % sub_batches != 0 {
        bail!("--sub-batches {sub_batches} must be at least 1 and divide --envs {}", p.envs);
    }
    let rp = RunPlan {
        run: run_id(),
        env: p.env.clone(),
        servers: p.servers,
        envs_per_server: p.envs,
        sub_batches,
        slots: p.slots,
        msg_dim: plan.msg_dim(),
        protocol: p.protocol.clone(),
        seed: p.seed,
        startup_timeout_s: p.startup_timeout,
        trainer_args: [vec!["--steps".into(), p.steps.to_string()], extra].concat(),
        env_server_args: env_extra,
    };
    let out = supervisor::run_pipeline(&rp, interrupted)?;
    let line = out.trainer_stdout.lines().rev().find(|l| l.starts_with('{')).context("the trainer printed no report")?;
    Ok(serde_json::from_str(line)?)
}

fn run(a: RunArgs) -> Result<i32> {
    let mut extra = vec!["--progress".to_string()];
    if a.verify {
        extra.push("--verify".into());
    }
    if let Some(p) = &a.episodes_out {
        extra.push("--episodes-out".into());
        extra.push(
            std::fs::canonicalize(p.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(std::path::Path::new(".")))?
                .join(p.file_name().context("--episodes-out needs a file name")?)
                .display()
                .to_string(),
        );
    }
    let report = pipeline_report(&a.p, extra, vec![], interrupt_flag())?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        println!(
            "{}: {} env steps in {:.2} s = {:.0} env-steps/s through the pipeline ({} servers x {} envs, protocol {}); {} episodes, mean team return {:.3}{}",
            a.p.env, report["env_steps"], report["seconds"].as_f64().unwrap_or(0.0), report["env_steps_per_s"].as_f64().unwrap_or(0.0),
            a.p.servers, a.p.envs, a.p.protocol, report["episodes"], report["mean_return"].as_f64().unwrap_or(0.0),
            if a.verify { format!("; {} invariant violations", report["violation_count"]) } else { String::new() }
        );
    }
    Ok(if report["violation_count"].as_u64().unwrap_or(0) > 0 { 1 } else { 0 })
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    if v.is_empty() {
        0.0
    } else {
        v[v.len() / 2]
    }
}

/// What `repeat` alternations of raw stepping and the pipeline measured.
struct Alternations {
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
fn bench_pipeline(p: PipelineOpts, repeat: usize, json: bool) -> Result<i32> {
    let interrupted = interrupt_flag();
    let repeat = repeat.max(1);
    let schema = load_env(&p.env).map_err(anyhow::Error::msg)?;
    let sub_batches = p.sub_batches.unwrap_or_else(|| supervisor::default_sub_batches(&schema, p.envs));
    let m = if p.servers == 1 { bench_interleaved(&p, repeat, interrupted)? } else { bench_separate_runs(&p, repeat, interrupted)? };
    let ratios: Vec<f64> = m.raws.iter().zip(&m.pipes).map(|(r, q)| if *r > 0.0 { q / r } else { 0.0 }).collect();
    // Rates over the whole measurement (harmonic means: total env steps over total time, the
    // same steps in every alternation); the ratio is the median over alternations, each a pair
    // measured back to back, which keeps one disturbed alternation from moving it.
    let overall = |rates: &[f64]| rates.len() as f64 / rates.iter().map(|r| 1.0 / r).sum::<f64>();
    let (raw_rate, pipe_rate, ratio) = (overall(&m.raws), overall(&m.pipes), median(ratios.clone()));
    let (lo, hi) = ratios.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), &r| (lo.min(r), hi.max(r)));
    let v = serde_json::json!({
        "env": p.env, "envs_total": p.envs * p.servers, "servers": p.servers, "protocol": p.protocol,
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
fn bench_interleaved(p: &PipelineOpts, repeat: usize, interrupted: Arc<AtomicBool>) -> Result<Alternations> {
    const WARMUP: u64 = 20; // batched steps each side takes before the first block
    let block = p.steps.div_ceil((p.envs * repeat) as u64).max(1);
    let out = std::env::temp_dir().join(format!("lmac-bench-pipeline-{}.json", run_id()));
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
    let report = pipeline_report(&trainer_p, vec![], env_extra, interrupted);
    let blocks = std::fs::read_to_string(&out);
    let _ = std::fs::remove_file(&out);
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
    let trainer_us = report["trainer_us_per_slot"].as_f64().unwrap_or(0.0);
    Ok(Alternations { raws, pipes, trainer_us, method: "interleaved block pairs", split: Some(split) })
}

/// Separate raw and pipeline runs, alternated so a change of machine load hits both alike.
fn bench_separate_runs(p: &PipelineOpts, repeat: usize, interrupted: Arc<AtomicBool>) -> Result<Alternations> {
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
        let pipe = pipeline_report(p, vec![], vec![], interrupted.clone())?;
        pipes.push(pipe["env_steps_per_s"].as_f64().unwrap_or(0.0));
        trainer_us.push(pipe["trainer_us_per_slot"].as_f64().unwrap_or(0.0));
    }
    Ok(Alternations { raws, pipes, trainer_us: median(trainer_us), method: "separate runs", split: None })
}

fn bench_train(env: &str, algo_name: &str, envs: &[usize], steps: u64, updates: usize, json: bool) -> Result<i32> {
    use lmac_trainer::episode::{Episode, EpisodeDims};
    use lmac_trainer::learn::{Device, LearnRng, Learner};
    use lmac_trainer::train::TrainConfig;
    let interrupted = interrupt_flag();
    let cfg = TrainConfig::resolve(None, &[format!("run.env={env:?}"), format!("run.algo={algo_name:?}")])?;
    let schema = load_env(env).map_err(anyhow::Error::msg)?;
    let msg = lmac_protocol_runner::plan_for(&cfg.protocol()?, &schema).map_err(anyhow::Error::msg)?.msg_dim();
    let dims = EpisodeDims {
        n_agents: schema.n_agents,
        obs_width: schema.obs_dim + msg,
        state_dim: schema.state_dim,
        n_actions: schema.n_actions,
    };
    // 1. One update on full-length episodes of this environment's sizes (values do not change
    //    the cost of dense math).
    let learn = cfg.effective_learn()?;
    let mut learner = Learner::new(dims, learn.clone(), Device::default())?;
    let mut rng = LearnRng::seed_from(0);
    let len = schema.episode_limit;
    for _ in 0..2 * learn.batch_size {
        let mut ep = Episode::with_capacity(&dims, len);
        ep.len = len;
        ep.obs = (0..len * dims.n_agents * dims.obs_width).map(|_| rng.uniform()).collect();
        ep.state = (0..len * dims.state_dim).map(|_| rng.uniform()).collect();
        ep.avail = vec![1; len * dims.n_agents * dims.n_actions];
        ep.actions = (0..len * dims.n_agents).map(|_| rng.below(dims.n_actions) as i32).collect();
        ep.reward = (0..len).map(|_| rng.uniform()).collect();
        ep.truncated = true;
        learner.add_episode(ep)?;
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
    let base = std::env::temp_dir().join(format!("lmac-bench-train-{}", run_id()));
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
        let csv = std::fs::read_to_string(d.join("metrics.csv"))?;
        let last = csv.lines().last().context("no metrics written")?;
        let cols: Vec<&str> = last.split(',').collect();
        let (t_env, wall): (f64, f64) = (cols[0].parse()?, cols[3].parse()?);
        let updates_done: f64 = cols[2].parse()?;
        let train_rate = t_env / wall.max(1e-9);
        let p = PipelineOpts {
            env: env.into(),
            envs: n / servers,
            servers,
            sub_batches: None,
            slots: 4,
            protocol: cfg.protocol()?,
            steps,
            seed: 0,
            startup_timeout: 60.0,
        };
        let rand_rate = pipeline_report(&p, vec![], vec![], interrupted.clone())?["env_steps_per_s"].as_f64().unwrap_or(0.0);
        eprintln!(
            "lmac: {n} envs: training {train_rate:.0} env-steps/s ({updates_done} updates), random acting {rand_rate:.0} env-steps/s"
        );
        rows.push(serde_json::json!({"envs": n, "servers": servers, "train_env_steps_per_s": train_rate, "updates": updates_done,
            "random_env_steps_per_s": rand_rate, "ratio": if rand_rate > 0.0 { train_rate / rand_rate } else { 0.0 }}));
    }
    let _ = std::fs::remove_dir_all(&base);
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

fn train(a: TrainArgs) -> Result<i32> {
    use lmac_trainer::train::TrainConfig;
    let interrupted = interrupt_flag();
    // The seed directories to run, each with its resolved config.toml.
    let (group, dirs): (std::path::PathBuf, Vec<std::path::PathBuf>) = if let Some(r) = &a.resume {
        if r.join("config.toml").exists() {
            (r.parent().unwrap_or(r).to_path_buf(), vec![r.clone()])
        } else {
            let mut d: Vec<_> = std::fs::read_dir(r)
                .with_context(|| format!("reading {}", r.display()))?
                .flatten()
                .map(|e| e.path())
                .filter(|p| p.join("config.toml").exists())
                .collect();
            d.sort();
            if d.is_empty() {
                bail!("{} holds no run (no config.toml in it or its subfolders)", r.display());
            }
            (r.clone(), d)
        }
    } else {
        let mut overrides = match &a.preset {
            Some(p) => lmac_trainer::train::preset_overrides(p)?,
            None => Vec::new(),
        };
        overrides.extend(a.set.iter().cloned());
        if let Some(e) = &a.env {
            overrides.push(format!("run.env={e:?}"));
        }
        if let Some(al) = &a.algo {
            overrides.push(format!("run.algo={al:?}"));
        }
        if let Some(st) = a.steps {
            overrides.push(format!("run.steps={st}"));
        }
        let mut cfg = TrainConfig::resolve(a.config.as_deref(), &overrides)?;
        // Protocol files by absolute path, so a resumed run finds them from anywhere.
        if !cfg.run.protocol.is_empty() {
            let files: Result<Vec<String>> = cfg
                .run
                .protocol
                .split('+')
                .map(|f| Ok(std::fs::canonicalize(f).with_context(|| format!("run.protocol: {f}"))?.display().to_string()))
                .collect();
            cfg.run.protocol = files?.join("+");
        }
        let stamp = chrono_stamp();
        let group = a.out.join(cfg.run.env.replace(':', "_")).join(&cfg.run.algo).join(stamp);
        let mut dirs = Vec::new();
        for &seed in &a.seeds {
            let mut c = cfg.clone();
            c.learn.seed = seed;
            let d = group.join(format!("seed{seed}"));
            std::fs::create_dir_all(&d).with_context(|| format!("creating {}", d.display()))?;
            std::fs::write(d.join("config.toml"), toml::to_string_pretty(&c)?)?;
            dirs.push(d);
        }
        (group, dirs)
    };
    eprintln!("lmac: training {} run(s) in {}", dirs.len(), group.display());
    train_dirs(&dirs, interrupted)?;
    plot_runs(&group);
    Ok(0)
}

/// Train each run directory (a resolved `config.toml` inside) in turn through the pipeline.
fn train_dirs(dirs: &[std::path::PathBuf], interrupted: Arc<AtomicBool>) -> Result<()> {
    use lmac_trainer::train::TrainConfig;
    for d in dirs {
        let cfg: TrainConfig = toml::from_str(&std::fs::read_to_string(d.join("config.toml"))?)
            .map_err(|e| anyhow::anyhow!("{}: {}", d.join("config.toml").display(), e.message()))?;
        cfg.check()?;
        // Where the run stands: a checkpoint's step, or 0 for a fresh start.
        let ck = lmac_trainer::train::checkpoint_dir(d);
        let done_t_env = match lmac_trainer::learn::checkpoint::peek_checkpoint(&ck) {
            Ok(info) => info.counters.t_env,
            Err(_) if !ck.exists() && !ck.with_extension("old").exists() => 0,
            Err(e) => bail!("{}: {e}", d.display()),
        };
        let dataset_done = cfg.run.dataset_episodes == 0 || lmac_trainer::train::dataset_dir(d).exists();
        if done_t_env >= cfg.run.steps && dataset_done {
            eprintln!("lmac: {} seed {}: already finished (t_env {done_t_env} of {})", d.display(), cfg.learn.seed, cfg.run.steps);
            continue;
        }
        eprintln!("lmac: {} {} seed {} -> {}", cfg.run.env, cfg.run.algo, cfg.learn.seed, d.display());
        let p = PipelineOpts {
            env: cfg.run.env.clone(),
            envs: cfg.run.envs,
            servers: cfg.run.servers,
            // 0 = the default for the environment's schema (pipeline_report applies it).
            sub_batches: (cfg.run.sub_batches != 0).then_some(cfg.run.sub_batches),
            slots: 4,
            protocol: cfg.protocol()?,
            steps: u64::MAX / 4,
            // A resumed segment's environments start from other seeds than the first segment's
            // (else it would replay the same episodes).
            seed: cfg.learn.seed + done_t_env,
            startup_timeout: 60.0,
        };
        let extra = vec![
            "--train-dir".to_string(),
            std::fs::canonicalize(d)?.display().to_string(),
            "--progress".into(),
            "--warmup".into(),
            "1".into(),
        ];
        pipeline_report(&p, extra, vec![], interrupted.clone()).with_context(|| format!("run {}", d.display()))?;
    }
    Ok(())
}

/// Plots and the multi-seed summary (matplotlib, in the project's Python).
fn plot_runs(group: &std::path::Path) {
    let script = supervisor::repo_root().map(|r| r.join("trainer/plot_runs.py"));
    let out = script.and_then(|s| Ok(supervisor::python_command()?.arg(s).arg(group).output()?));
    match out {
        Ok(o) if o.status.success() => print!("{}", String::from_utf8_lossy(&o.stdout)),
        Ok(o) => eprintln!("lmac: plotting failed: {}", String::from_utf8_lossy(&o.stderr)),
        Err(e) => eprintln!("lmac: plotting failed: {e}"),
    }
}

fn chrono_stamp() -> String {
    let secs = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs()).unwrap_or(0);
    let (d, s) = (secs / 86400, secs % 86400);
    // Civil date from days since 1970-01-01 (Howard Hinnant's algorithm).
    let z = d as i64 + 719468;
    let era = z.div_euclid(146097);
    let doe = z - era * 146097;
    let yoe = (doe - doe / 1460 + doe / 36524 - doe / 146096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + if month <= 2 { 1 } else { 0 };
    format!("{year:04}{month:02}{day:02}-{:02}{:02}{:02}", s / 3600, (s / 60) % 60, s % 60)
}

fn child(c: ChildCmd) -> Result<i32> {
    // Stop gracefully on SIGTERM/SIGINT: the waits return and the process cleans up.
    let _ = ctrlc::set_handler(lmac_shm_schema::ring::request_stop);
    let code = match c {
        ChildCmd::Runner(o) => {
            let schema = load_env(&o.env).map_err(anyhow::Error::msg)?;
            let mut plans = (0..o.servers)
                .map(|_| lmac_protocol_runner::plan_for(&o.protocol, &schema))
                .collect::<Result<Vec<_>, _>>()
                .map_err(anyhow::Error::msg)?;
            let args = RunnerArgs {
                run: o.run,
                schema,
                n_servers: o.servers,
                n_slots: o.slots,
                startup_timeout: Duration::from_secs_f64(o.startup_timeout),
            };
            match prunner::run(&args, &mut plans) {
                Ok(_) => 0,
                Err(prunner::RunnerError::Ring(lmac_shm_schema::RingError::Stopped)) => 0,
                Err(e) => {
                    eprintln!("lmac: {e}");
                    3
                }
            }
        }
        ChildCmd::Trainer { o, steps, warmup, seed, verify, episodes_out, progress, train_dir } => {
            let schema = load_env(&o.env).map_err(anyhow::Error::msg)?;
            let plan = lmac_protocol_runner::plan_for(&o.protocol, &schema).map_err(anyhow::Error::msg)?;
            let check = match o.protocol.as_str() {
                "fullcomm" => MessageCheck::FullComm,
                "none" => MessageCheck::None,
                _ => MessageCheck::Recompute,
            };
            let args = TrainerArgs {
                run: o.run,
                schema,
                n_servers: o.servers,
                n_slots: o.slots,
                msg_used: plan.msg_dim(),
                env_steps: steps,
                warmup_slots: warmup,
                startup_timeout: Duration::from_secs_f64(o.startup_timeout),
                verify: verify.then_some(check),
                protocol: o.protocol.clone(),
                progress,
            };
            if let Some(dir) = train_dir {
                return match lmac_trainer::train::train_in_child(&dir, &args, progress) {
                    Ok(report) => {
                        println!("{}", serde_json::to_string(&report)?);
                        Ok(0)
                    }
                    Err(e) if e.to_string().contains("stopped by request") => Ok(0),
                    Err(e) => {
                        eprintln!("lmac: trainer: {e:#}");
                        Ok(4)
                    }
                };
            }
            let mut actor = RandomActor::new(seed);
            match pipeline::run(&args, &mut actor) {
                Ok(report) => {
                    if let Some(path) = episodes_out {
                        let mut f =
                            std::io::BufWriter::new(std::fs::File::create(&path).with_context(|| format!("creating {}", path.display()))?);
                        for e in &report.episode_log {
                            writeln!(f, "{}", serde_json::to_string(e)?)?;
                        }
                    }
                    println!("{}", serde_json::to_string(&report)?);
                    0
                }
                Err(pipeline::PipelineError::Ring(lmac_shm_schema::RingError::Stopped)) => 0,
                Err(e) => {
                    eprintln!("lmac: {e}");
                    3
                }
            }
        }
    };
    Ok(code)
}

fn chaos(a: ChaosArgs) -> Result<i32> {
    use lmac_trainer::faults::{chaos, ChaosOptions};
    let [lo, hi] = a.kill_after[..] else { bail!("--kill-after: give MIN,MAX seconds, e.g. 3,12") };
    if !(lo > 0.0 && hi >= lo) {
        bail!("--kill-after: need 0 < MIN <= MAX, got {lo},{hi}");
    }
    let temp = a.out.is_none();
    let out = a.out.clone().unwrap_or_else(|| std::env::temp_dir().join(format!("lmac-chaos-{}", run_id())));
    let o = ChaosOptions {
        kills: a.kills,
        seed: a.seed,
        out: out.clone(),
        env: a.env,
        checkpoint_interval: a.checkpoint_interval,
        kill_after: (lo, hi),
        envs: a.envs,
        servers: a.servers,
    };
    let bar = indicatif::ProgressBar::new(a.kills as u64);
    bar.set_style(indicatif::ProgressStyle::with_template("[{elapsed_precise}] {bar:30} {pos}/{len} kills {msg}").expect("template"));
    let r = chaos(&o, |_, k| {
        bar.inc(1);
        bar.set_message(format!(
            "last: {} after {:.1} s, noticed in {}",
            k.victim.name(),
            k.after_s,
            k.detect_s.map_or("-".into(), |d| format!("{d:.2} s"))
        ));
    });
    bar.finish_and_clear();
    if temp {
        let _ = std::fs::remove_dir_all(&out);
    }
    let r = r?;
    let text = serde_json::to_string_pretty(&r)?;
    if let Some(p) = &a.report {
        std::fs::write(p, &text).with_context(|| format!("writing {}", p.display()))?;
    }
    println!(
        "{} kills in {:.0} s: deaths noticed in p50 {:.2} s, p99 {:.2} s (max {:.2} s, {} unnoticed); resumes that continued {}/{}; \
         checkpoints that failed to load {}; env steps lost per crash max {} (mean {:.0}, checkpoint interval {}); shared-memory files left {}; metrics monotone {}",
        r.kills, r.seconds, r.detect_p50_s, r.detect_p99_s, r.detect_max_s, r.undetected, r.resumes_continued, r.kills,
        r.checkpoint_load_failures, r.steps_lost_max, r.steps_lost_mean, r.checkpoint_interval, r.shm_files_left, r.metrics_monotone
    );
    for v in &r.by_victim {
        println!(
            "  {}: {} kills, noticed in p50 {:.2} s (max {:.2} s), steps lost max {}",
            v["victim"].as_str().unwrap_or(""),
            v["kills"],
            v["detect_p50_s"].as_f64().unwrap_or(f64::NAN),
            v["detect_max_s"].as_f64().unwrap_or(f64::NAN),
            v["steps_lost_max"]
        );
    }
    let ok = r.undetected == 0
        && r.checkpoint_load_failures == 0
        && r.resumes_continued == r.kills
        && r.shm_files_left == 0
        && r.metrics_monotone;
    Ok(if ok { 0 } else { 1 })
}

fn soak(a: SoakArgs) -> Result<i32> {
    let temp = a.out.is_none();
    let out = a.out.clone().unwrap_or_else(|| std::env::temp_dir().join(format!("lmac-soak-{}", run_id())));
    let mut args: Vec<String> = ["--env", &a.env, "--algo", "qmix", "--steps", "1000000000000"].iter().map(|s| s.to_string()).collect();
    for kv in [format!("run.envs={}", a.envs), format!("run.servers={}", a.servers), format!("run.save_buffer={}", a.save_buffer)] {
        args.extend(["--set".to_string(), kv]);
    }
    args.extend(["--out".to_string(), out.display().to_string()]);
    let buffer = lmac_trainer::learn::LearnConfig::default().buffer_size as u64;
    let bar = indicatif::ProgressBar::new(a.duration as u64);
    bar.set_style(indicatif::ProgressStyle::with_template("[{elapsed_precise}] {bar:30} {pos}/{len} s {msg}").expect("template"));
    let r = lmac_trainer::faults::soak(&args, &out, &a.env, a.duration, a.interval, buffer, |s| {
        bar.set_position(s.wall_s as u64);
        bar.set_message(format!("t_env {} RSS {:.0} MiB, {} fds, {} shm mappings", s.t_env, s.rss_mib, s.open_fds, s.shm_mappings));
    });
    bar.finish_and_clear();
    if temp {
        let _ = std::fs::remove_dir_all(&out);
    }
    let r = r?;
    if let Some(p) = &a.report {
        std::fs::write(p, serde_json::to_string_pretty(&r)?).with_context(|| format!("writing {}", p.display()))?;
    }
    println!(
        "{:.0} s, {} env steps: RSS {:.0} MiB when the buffer filled (at {:.0} s), {:.0} MiB at the end (max {:.0}); after it filled: \
         RSS {:+.1} MiB/h, open fds {:+.2}/h (range {}-{}), shm mappings {:+.2}/h (range {}-{})",
        r.seconds,
        r.t_env,
        r.rss_mib_at_buffer_full.unwrap_or(f64::NAN),
        r.buffer_full_at_s.unwrap_or(f64::NAN),
        r.rss_mib_end,
        r.rss_mib_max,
        r.rss_mib_per_hour,
        r.open_fds_per_hour,
        r.open_fds_range.0,
        r.open_fds_range.1,
        r.shm_mappings_per_hour,
        r.shm_mappings_range.0,
        r.shm_mappings_range.1
    );
    Ok(0)
}

fn design(a: DesignArgs) -> Result<i32> {
    use lmac_trainer::design::llm::LlmMode;
    use lmac_trainer::design::llm_designer::{LlmDesigner, LlmDesignerOptions};
    use lmac_trainer::design::meta::{self, MetaConfig};
    use lmac_trainer::design::offline::{OfflineConfig, OfflineDesigner};
    use lmac_trainer::design::run::{run_design, DesignOptions};
    use lmac_trainer::design::Designer;
    let interrupted = interrupt_flag();
    let opts = DesignOptions {
        env: a.env.clone(),
        out: a.out.clone(),
        seed: a.seed,
        pretrain_steps: a.pretrain_steps,
        dataset_episodes: a.dataset_episodes,
        dataset_epsilon: a.dataset_epsilon,
        envs: a.envs,
        servers: a.servers,
        dataset: a.dataset.clone(),
        phases: a.phases,
    };
    // One discriminator configuration for the offline designer's phase-0 measurement and for
    // every phase's meta-information.
    let mut meta_cfg = MetaConfig::default();
    if let Some(u) = a.disc_updates {
        meta_cfg.discriminator.updates = u;
    }
    meta_cfg.discriminator.validate()?;
    let mut designer: Box<dyn Designer> = if a.llm == "offline" {
        let cfg = OfflineConfig { discriminator: meta_cfg.discriminator.clone(), phases: a.phases, ..Default::default() };
        Box::new(OfflineDesigner::new(cfg))
    } else {
        let mode: LlmMode = a.llm_mode.parse().map_err(anyhow::Error::msg)?;
        let rec = a.recordings.clone().unwrap_or_else(|| a.out.join("llm-recordings"));
        std::fs::create_dir_all(&rec).with_context(|| format!("creating {}", rec.display()))?;
        let options = LlmDesignerOptions { max_retries: a.max_retries, ..Default::default() };
        Box::new(LlmDesigner::from_spec(&a.llm, a.base_url.as_deref(), mode, Some(rec), options)?)
    };
    let train = |dir: &std::path::Path| train_dirs(&[dir.to_path_buf()], interrupted.clone());
    let evaluate = |ctx: &lmac_trainer::design::DesignContext, phases: &[lmac_protocol_runner::protocol::ValidatedProtocol]| {
        meta::evaluate(ctx, phases, &meta_cfg)
    };
    let dir = run_design(&opts, designer.as_mut(), &train, &evaluate)?;
    plot_design(&dir);
    println!("design written to {}", dir.display());
    println!("final protocol: {}", std::fs::read_to_string(dir.join("final_protocol.txt"))?.trim());
    Ok(0)
}

/// The design's Figure 3 (matplotlib, in the project's Python).
fn plot_design(dir: &std::path::Path) {
    let script = supervisor::repo_root().map(|r| r.join("trainer/plot_design.py"));
    let out = script.and_then(|s| Ok(supervisor::python_command()?.arg(s).arg(dir).output()?));
    match out {
        Ok(o) if o.status.success() => print!("{}", String::from_utf8_lossy(&o.stdout)),
        Ok(o) => eprintln!("lmac: plotting the design failed: {}", String::from_utf8_lossy(&o.stderr)),
        Err(e) => eprintln!("lmac: plotting the design failed: {e}"),
    }
}
