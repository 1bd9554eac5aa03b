//! The commands. What they share here: the pipeline options and step and duration parsing; the
//! workflow they drive (starting pipelines, training and evaluating run directories) is the
//! library's [`lmac_run::workflow`].

pub(crate) mod bench;
pub(crate) mod campaign;
pub(crate) mod child;
pub(crate) mod clean;
pub(crate) mod design;
pub(crate) mod envs;
pub(crate) mod evaluate;
pub(crate) mod experiment;
pub(crate) mod faults;
pub(crate) mod protocol;
pub(crate) mod report;
pub(crate) mod run;
pub(crate) mod train;

use clap::Args;
use lmac_run::workflow::Pipeline;

#[derive(Args, Clone)]
pub(crate) struct PipelineOpts {
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
    /// Communication protocol applied by the runner: none | fullcomm | protocol files a.json+b.json.
    #[arg(long, default_value = "none")]
    protocol: lmac_protocol_runner::ProtocolSpec,
    /// Env steps to collect (after warm-up).
    #[arg(long, default_value_t = 20_000)]
    steps: u64,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Seconds the processes may take to find each other.
    #[arg(long, default_value_t = 60.0)]
    startup_timeout: f64,
}

pub(crate) fn parse_steps(s: &str) -> Result<u64, String> {
    let t = s.trim().to_ascii_lowercase();
    let (num, mul) = match t.chars().last() {
        Some('k') => (&t[..t.len() - 1], 1_000f64),
        Some('m') => (&t[..t.len() - 1], 1_000_000f64),
        _ => (&t[..], 1f64),
    };
    num.parse::<f64>().map(|v| (v * mul) as u64).map_err(|_| format!("{s:?} is not a step count (e.g. 2M, 500k, 20000)"))
}

pub(crate) fn parse_duration(s: &str) -> Result<f64, String> {
    let t = s.trim().to_ascii_lowercase();
    let (num, mul) = match t.chars().last() {
        Some('h') => (&t[..t.len() - 1], 3600.0),
        Some('m') => (&t[..t.len() - 1], 60.0),
        Some('s') => (&t[..t.len() - 1], 1.0),
        _ => (&t[..], 1.0),
    };
    num.parse::<f64>().ok().filter(|v| *v > 0.0).map(|v| v * mul).ok_or_else(|| format!("{s:?} is not a duration (e.g. 2h, 30m, 90s)"))
}

impl PipelineOpts {
    /// The pipeline these options describe.
    pub(crate) fn pipeline(&self) -> Pipeline {
        Pipeline {
            env: self.env.clone(),
            envs: self.envs,
            servers: self.servers,
            sub_batches: self.sub_batches,
            slots: self.slots,
            protocol: self.protocol.clone(),
            msg_dim: None,
            steps: self.steps,
            seed: self.seed,
            startup_timeout: self.startup_timeout,
        }
    }
}
