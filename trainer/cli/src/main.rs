//! `lmac`: the command line of the LMAC system. This file only parses and dispatches; each
//! command is a module of `cli/`, and the work of each process lives in its crate.
mod cli;

use anyhow::Result;
use clap::{Parser, Subcommand};
use cli::bench::BenchCmd;
use cli::child::ChildCmd;
use cli::design::DesignArgs;
use cli::evaluate::{EvaluateArgs, EVALUATE_AFTER_HELP};
use cli::experiment::ExperimentArgs;
use cli::faults::{ChaosArgs, SoakArgs};
use cli::protocol::ProtocolCmd;
use cli::run::RunArgs;
use cli::train::{TrainArgs, TRAIN_AFTER_HELP};

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
enum ConfigCmd {
    /// Print the configuration reference (Markdown): every key of [run], [learn] and each
    /// method's [method] with its default and meaning, generated from the code (the guide's
    /// docs/reference/configuration.md is this output).
    Reference,
    /// Print the resolved configuration (TOML) that a file, a preset and `--set` overrides give,
    /// as `lmac train` would save it, without training.
    Show {
        /// A config file (TOML) to start from.
        #[arg(long)]
        config: Option<std::path::PathBuf>,
        /// A preset, applied before the overrides.
        #[arg(long, value_parser = cli::train::preset_names())]
        preset: Option<String>,
        /// Overrides: --set learn.lr=0.001 --set run.envs=8.
        #[arg(long = "set", value_name = "KEY=VALUE")]
        set: Vec<String>,
    },
}

#[derive(Subcommand)]
enum Cmd {
    /// Run the pipeline with a random policy: env servers -> protocol runner -> trainer (throughput, checks).
    Run(RunArgs),
    /// Train a method (a backbone, a baseline, LMAC or a communication baseline: `lmac train --help` lists them) through the pipeline, over several seeds.
    #[command(after_long_help = TRAIN_AFTER_HELP)]
    Train(TrainArgs),
    /// Greedy test episodes of trained runs from their last checkpoints, optionally with a
    /// method's test-time settings changed (e.g. NDQ's message cuts).
    #[command(after_long_help = EVALUATE_AFTER_HELP)]
    Evaluate(EvaluateArgs),
    /// Design a communication protocol in three phases (initialization, recognition enhancement,
    /// sharing enhancement) with an LLM or the embedded offline designer, checked on real data.
    Design(DesignArgs),
    /// The paper's Algorithm 1 end to end: one protocol design, then LMAC and the baselines over
    /// seeds with the same settings, then a comparison table and curves (rerun to resume).
    Experiment(ExperimentArgs),
    /// A grid of training runs (stages x tasks x methods x seeds) from one campaign file, in one
    /// results tree: trained in order and resumably on this machine or as Ray tasks on a
    /// cluster, with its status, time left and a results page beside published values.
    #[command(subcommand)]
    Campaign(cli::campaign::CampaignCmd),
    /// Merge training runs: IQM, median and mean with stratified-bootstrap CIs (rliable's
    /// method), performance profile and sample-efficiency plots, marl-eval JSON (`lmac report --help`).
    Report(cli::report::ReportArgs),
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
        /// Write the schema of an environment with the sizes it gives and placeholder descriptions
        /// to edit: pz:<module>[,key=value]... from a PettingZoo env's spaces, any other family
        /// from its module's sizes(variant) (e.g. rware:tiny-2ag).
        #[arg(long, value_name = "ENV", conflicts_with_all = ["check", "json"])]
        generate: Option<String>,
        /// With --generate: overwrite an existing schema file.
        #[arg(long, requires = "generate")]
        force: bool,
        /// With --generate: the episode limit, when the environment gives none (no max_cycles).
        #[arg(long, requires = "generate", value_name = "STEPS")]
        episode_limit: Option<usize>,
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
    /// Remove what dead lmac runs left in shared memory (slabs in /dev/shm, iceoryx2 nodes and
    /// services): this user's only, never a live run's. Every start does it too.
    Clean(cli::clean::CleanArgs),
    /// The configuration: every key with its default and meaning, or the resolved config of a
    /// preset and overrides.
    #[command(subcommand)]
    Config(ConfigCmd),
    /// Internal: the child processes started by `lmac run`.
    #[command(subcommand, hide = true)]
    Child(ChildCmd),
}

fn main() {
    lmac_run::tune_allocator();
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
        Cmd::Envs { generate: Some(name), force, episode_limit, .. } => cli::envs::generate(&name, force, episode_limit),
        Cmd::Envs { check, json, .. } => cli::envs::envs(check, json),
        Cmd::Run(a) => cli::run::run(a),
        Cmd::Config(ConfigCmd::Reference) => {
            print!("{}", lmac_run::train::reference::markdown());
            Ok(0)
        }
        Cmd::Config(ConfigCmd::Show { config, preset, set }) => {
            let overrides = lmac_run::train::preset_then(preset.as_deref(), None, &set)?;
            let cfg = lmac_run::train::TrainConfig::resolve(config.as_deref(), &overrides)?;
            print!("{}", toml::to_string_pretty(&cfg)?);
            Ok(0)
        }
        Cmd::Train(a) => cli::train::train(a),
        Cmd::Evaluate(a) => cli::evaluate::evaluate(a),
        Cmd::Protocol(p) => cli::protocol::protocol_cmd(p),
        Cmd::Design(d) => cli::design::design(d),
        Cmd::Experiment(e) => cli::experiment::experiment(e),
        Cmd::Campaign(c) => cli::campaign::campaign(c),
        Cmd::Report(a) => cli::report::report(a),
        Cmd::Bench(BenchCmd::Pipeline { p, repeat, json }) => cli::bench::bench_pipeline(p, repeat, json),
        Cmd::Bench(BenchCmd::Train { env, algo, protocol, envs, steps, updates, json }) => {
            cli::bench::bench_train(&env, &algo, protocol.as_deref(), &envs, steps, updates, json)
        }
        Cmd::Bench(BenchCmd::Learner {
            shape,
            batch,
            steps,
            agents,
            input,
            actions,
            state,
            mixers,
            algo,
            messages,
            critical,
            method_settings,
            against,
            python,
            rounds,
            updates,
            no_stepwise,
            two_cores,
            profile,
            out,
            json,
        }) => (|| {
            let mut s = lmac_benches::learner::named_shape(&shape)?;
            s.batch = batch.unwrap_or(s.batch);
            s.steps = steps.unwrap_or(s.steps);
            s.agents = agents.unwrap_or(s.agents);
            s.input = input.unwrap_or(s.input);
            s.actions = actions.unwrap_or(s.actions);
            s.state = state.unwrap_or(s.state);
            let mixers = mixers
                .iter()
                .map(|m| {
                    serde_json::from_value(serde_json::Value::String(m.clone()))
                        .map_err(|_| anyhow::anyhow!("--mixers: unknown mixer {m:?} (vdn, qmix, qplex)"))
                })
                .collect::<Result<Vec<lmac_run::learn::MixerKind>>>()?;
            let against_torch = match against.as_deref() {
                None => false,
                Some("torch") => true,
                Some(other) => anyhow::bail!("--against {other:?}: only torch is known"),
            };
            if against_torch && algo.is_some() {
                anyhow::bail!("--against torch: the PyTorch anchor is pymarl's plain RNN agent; drop --algo to compare with it");
            }
            let method = match algo {
                Some(name) => Some(lmac_benches::learner::MethodUnderTest::new(&name, messages, critical, &method_settings, &s)?),
                None if messages > 0 || critical.is_some() || !method_settings.is_empty() => {
                    anyhow::bail!("--messages, --critical and --method describe a method's input: give --algo")
                }
                None => None,
            };
            lmac_benches::learner::bench_learner(lmac_benches::learner::LearnerBenchOpts {
                shape: s,
                mixers,
                method,
                against_torch,
                python,
                rounds,
                updates,
                stepwise: !no_stepwise,
                two_cores,
                profile,
                json,
                out,
            })
        })(),
        Cmd::Clean(a) => cli::clean::clean(a),
        Cmd::Chaos(a) => cli::faults::chaos(a),
        Cmd::Soak(a) => cli::faults::soak(a),
        Cmd::Child(c) => cli::child::child(c),
    }
}
