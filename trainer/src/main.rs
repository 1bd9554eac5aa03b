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
#[command(name = "lmac", version, about = "LLM-guided communication for cooperative multi-agent RL: a zero-copy shared-memory pipeline",
    long_about = "lmac runs batched environments in Python env servers that write straight into shared memory, a protocol runner that appends each agent's messages in place, and a trainer that consumes the batches with no serialization.")]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Run the pipeline: env servers -> protocol runner -> trainer (random policy until learning lands).
    Run(RunArgs),
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

#[derive(Subcommand)]
enum BenchCmd {
    /// Raw vectorized stepping in one Python process vs the full pipeline, in one run.
    Pipeline {
        #[command(flatten)]
        p: PipelineOpts,
        /// Alternate raw and pipeline runs this many times; report medians.
        #[arg(long, default_value_t = 3)]
        repeat: usize,
        /// Print JSON.
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
        Cmd::Bench(BenchCmd::Pipeline { p, repeat, json }) => bench_pipeline(p, repeat, json),
        Cmd::Child(c) => child(c),
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
        let v: Vec<_> = rows.iter().map(|s| serde_json::json!({
            "name": s.name, "n_agents": s.n_agents, "obs_dim": s.obs_dim, "state_dim": s.state_dim,
            "n_actions": s.n_actions, "episode_limit": s.episode_limit, "message_columns": s.message_columns, "alpha": s.alpha,
        })).collect();
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        println!("{:<42} {:>6} {:>5} {:>6} {:>7} {:>6} {:>5} {:>6}", "environment", "agents", "obs", "state", "actions", "limit", "msg", "alpha");
        for s in &rows {
            println!("{:<42} {:>6} {:>5} {:>6} {:>7} {:>6} {:>5} {:>6}", s.name, s.n_agents, s.obs_dim, s.state_dim, s.n_actions, s.episode_limit, s.message_columns, s.alpha);
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

/// Start the processes of one pipeline run and return the trainer's JSON report.
fn pipeline_report(p: &PipelineOpts, extra: Vec<String>, interrupted: Arc<AtomicBool>) -> Result<serde_json::Value> {
    let schema = load_env(&p.env).map_err(anyhow::Error::msg)?;
    let plan = lmac_protocol_runner::plan_for(&p.protocol, &schema).map_err(anyhow::Error::msg)?;
    if p.envs == 0 || p.servers == 0 || p.slots == 0 {
        bail!("--envs, --servers and --slots must be at least 1");
    }
    let rp = RunPlan {
        run: run_id(),
        env: p.env.clone(),
        servers: p.servers,
        envs_per_server: p.envs,
        slots: p.slots,
        msg_dim: schema.message_columns.max(plan.msg_dim()),
        protocol: p.protocol.clone(),
        seed: p.seed,
        startup_timeout_s: p.startup_timeout,
        trainer_args: [vec!["--steps".into(), p.steps.to_string()], extra].concat(),
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
        extra.push(std::fs::canonicalize(p.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(std::path::Path::new(".")))?.join(p.file_name().context("--episodes-out needs a file name")?).display().to_string());
    }
    let report = pipeline_report(&a.p, extra, interrupt_flag())?;
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
    if v.is_empty() { 0.0 } else { v[v.len() / 2] }
}

fn bench_pipeline(p: PipelineOpts, repeat: usize, json: bool) -> Result<i32> {
    let interrupted = interrupt_flag();
    let batched = (p.steps / (p.envs * p.servers) as u64).max(1);
    let (mut raws, mut pipes, mut trainer_us) = (Vec::new(), Vec::new(), Vec::new());
    // Alternate raw and pipeline runs so a change of machine load hits both alike.
    for _ in 0..repeat.max(1) {
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
        let pipe = pipeline_report(&p, vec![], interrupted.clone())?;
        pipes.push(pipe["env_steps_per_s"].as_f64().unwrap_or(0.0));
        trainer_us.push(pipe["trainer_us_per_slot"].as_f64().unwrap_or(0.0));
    }
    let ratios: Vec<f64> = raws.iter().zip(&pipes).map(|(r, q)| if *r > 0.0 { q / r } else { 0.0 }).collect();
    let (raw_rate, pipe_rate, ratio) = (median(raws.clone()), median(pipes.clone()), median(ratios.clone()));
    let v = serde_json::json!({
        "env": p.env, "envs_total": p.envs * p.servers, "servers": p.servers, "protocol": p.protocol,
        "env_steps": p.steps, "repeats": repeat,
        "raw_env_steps_per_s": raw_rate, "pipeline_env_steps_per_s": pipe_rate, "ratio": ratio,
        "raw_runs": raws, "pipeline_runs": pipes, "ratio_runs": ratios,
        "trainer_us_per_batched_step": median(trainer_us),
    });
    if json {
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        println!("{} ({} envs): raw {:.0} env-steps/s, pipeline {:.0} env-steps/s ({} servers, protocol {}), ratio {:.3} (median of {})",
            p.env, p.envs * p.servers, raw_rate, pipe_rate, p.servers, p.protocol, ratio, repeat);
    }
    Ok(0)
}

fn child(c: ChildCmd) -> Result<i32> {
    // Stop gracefully on SIGTERM/SIGINT: the waits return and the process cleans up.
    let _ = ctrlc::set_handler(lmac_shm_schema::ring::request_stop);
    let code = match c {
        ChildCmd::Runner(o) => {
            let schema = load_env(&o.env).map_err(anyhow::Error::msg)?;
            let mut plan = lmac_protocol_runner::plan_for(&o.protocol, &schema).map_err(anyhow::Error::msg)?;
            let args = RunnerArgs { run: o.run, schema, n_servers: o.servers, n_slots: o.slots, startup_timeout: Duration::from_secs_f64(o.startup_timeout) };
            match prunner::run(&args, plan.as_mut()) {
                Ok(_) => 0,
                Err(prunner::RunnerError::Ring(lmac_shm_schema::RingError::Stopped)) => 0,
                Err(e) => {
                    eprintln!("lmac: {e}");
                    3
                }
            }
        }
        ChildCmd::Trainer { o, steps, warmup, seed, verify, episodes_out, progress } => {
            let schema = load_env(&o.env).map_err(anyhow::Error::msg)?;
            let plan = lmac_protocol_runner::plan_for(&o.protocol, &schema).map_err(anyhow::Error::msg)?;
            let check = match o.protocol.as_str() {
                "fullcomm" => MessageCheck::FullComm,
                _ => MessageCheck::None,
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
                progress,
            };
            let mut actor = RandomActor::new(seed);
            match pipeline::run(&args, &mut actor, |_, _, _| {}) {
                Ok(report) => {
                    if let Some(path) = episodes_out {
                        let mut f = std::io::BufWriter::new(std::fs::File::create(&path).with_context(|| format!("creating {}", path.display()))?);
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
