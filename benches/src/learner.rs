//! `lmac bench learner`: the cost of one learner update on a fixed shape, lmac's fused
//! recurrence against burn's per-step cell and (with `--against torch`) against the PyTorch
//! implementation of pymarl's QLearner in `benches/torch/qlearner.py`, alternating in one run,
//! with each figure's FLOP count and achieved GFLOP/s next to the machine's single-core sgemm.

use anyhow::{bail, Context, Result};
use lmac_run::episode::{Episode, EpisodeDims};
use lmac_run::learn::flops::UpdateShape;
use lmac_run::learn::methods::{self, MethodContext};
use lmac_run::learn::{AgentConfig, Device, LearnConfig, LearnRng, Learner, MixerKind};
use serde::Serialize;
use std::io::{BufRead, BufReader, Write};
use std::path::PathBuf;
use std::process::{Child, ChildStdin, ChildStdout, Command, Stdio};
use std::time::Instant;

use lmac_run::stats::median;

/// The update's shape (batch, steps, agents, input width, actions, state, hidden width): the
/// learner's own, which its FLOP counts take.
pub type Shape = UpdateShape;

/// Named shapes: `lbf8x8` (LBF 8x8 with the default QMIX settings) and `1o10b` (smaclite
/// 1o_10b_vs_1r with its designed protocol's messages).
pub fn named_shape(name: &str) -> Result<Shape> {
    Ok(match name {
        "lbf8x8" => Shape { batch: 32, steps: 25, agents: 2, input: 37, actions: 6, state: 300, hidden: 64 },
        "1o10b" => Shape { batch: 32, steps: 50, agents: 11, input: 108, actions: 16, state: 148, hidden: 64 },
        other => bail!("unknown shape {other:?} (lbf8x8, 1o10b, or give --batch/--steps/... yourself)"),
    })
}

/// The episode dims of `shape`: its input row holds the observation, the last action and the id.
fn dims(shape: &Shape) -> Result<EpisodeDims> {
    let obs = shape.input.checked_sub(shape.actions + shape.agents).filter(|&o| o > 0).with_context(|| {
        format!(
            "input width {} must exceed actions + agents ({}): it holds obs, last action and id",
            shape.input,
            shape.actions + shape.agents
        )
    })?;
    Ok(EpisodeDims { n_agents: shape.agents, obs_width: obs, state_dim: shape.state, n_actions: shape.actions })
}

/// The FLOPs one update of `method` (None: the plain agent) counts: every method has its count.
fn update_flops(shape: &Shape, mixer: MixerKind, cfg: &LearnConfig, method: Option<&MethodUnderTest>) -> f64 {
    let agent = method.map_or(&AgentConfig::Rnn, |m| &m.agent);
    agent.update_flops(shape, mixer, cfg, method.is_some_and(|m| m.agent_sees_state))
}

/// A method's agent network in place of the plain RNN agent (`--algo`): its configured agent
/// and what it fixes of the learner.
pub struct MethodUnderTest {
    pub name: String,
    pub agent: AgentConfig,
    pub mixer: Option<MixerKind>,
    pub agent_sees_state: bool,
    /// The command-line description, for the report.
    pub settings: serde_json::Value,
}

impl MethodUnderTest {
    /// `name` configured as `lmac train` would (`[method]` settings parsed by the same code),
    /// for an input whose last `messages` observation columns are messages and whose first
    /// `critical` state dims (default all) are task-critical.
    pub fn new(name: &str, messages: usize, critical: Option<usize>, settings: &[String], shape: &Shape) -> Result<Self> {
        let spec = methods::method(name).map_err(|e| anyhow::anyhow!("--algo: {e}"))?;
        let obs = dims(shape)?.obs_width;
        if messages >= obs {
            bail!("--messages {messages}: the observation has {obs} columns (--input minus actions and agents)");
        }
        let critical = critical.unwrap_or(shape.state);
        if critical == 0 || critical > shape.state {
            bail!("--critical {critical}: must be 1..={} (the state's dims)", shape.state);
        }
        let mut table = toml::Table::new();
        for kv in settings {
            let (key, value) =
                kv.split_once('=').with_context(|| format!("--method {kv:?}: expected KEY=VALUE, e.g. encoder='\"window\"'"))?;
            table.insert(key.trim().to_string(), lmac_run::train::config::override_value(value));
        }
        let ctx = MethodContext { msg_cols: messages, alpha: 0.05, critical_dims: (0..critical).collect(), state_dim: shape.state };
        let agent = (spec.configure)(&table, &ctx).map_err(|e| anyhow::anyhow!("--method: {name}: {e}"))?;
        let described = serde_json::json!({"algo": name, "messages": messages, "critical_dims": critical, "method": settings});
        Ok(MethodUnderTest { name: name.into(), agent, mixer: spec.mixer, agent_sees_state: spec.agent_sees_state, settings: described })
    }
}

/// The figure of the update on two cores (`--two-cores`).
const TWO_CORES: &str = "lmac-two-cores";

/// What one implementation measured: per-update milliseconds of every round, and the GFLOP/s
/// that makes of the update's counted FLOPs (see `update_flops`).
#[derive(Debug, Serialize)]
pub struct Figure {
    pub name: String,
    pub mixer: String,
    pub rounds_ms: Vec<f64>,
    pub median_ms: f64,
    pub gflops: f64,
}

fn mixer_name(m: MixerKind) -> &'static str {
    match m {
        MixerKind::Vdn => "vdn",
        MixerKind::Qmix => "qmix",
        MixerKind::Qplex => "qplex",
    }
}

/// A learner (the plain RNN agent, or `method`'s) with two batches of synthetic full-length
/// episodes of `shape` in its buffer; `two_cores`: the update as `--preset paper` runs it
/// (`learn.data_parallel` and `learn.parallel_target`).
fn filled_learner(shape: &Shape, mixer: MixerKind, fused: bool, two_cores: bool, method: Option<&MethodUnderTest>) -> Result<Learner> {
    let mut cfg = LearnConfig {
        mixer,
        rnn_hidden_dim: shape.hidden,
        batch_size: shape.batch,
        fused_gru: fused,
        data_parallel: two_cores,
        parallel_target: two_cores,
        ..LearnConfig::default()
    };
    let dims = dims(shape)?;
    let agent = match method {
        Some(m) => {
            cfg.agent_sees_state |= m.agent_sees_state;
            m.agent.clone()
        }
        None => AgentConfig::Rnn,
    };
    let mut learner = Learner::with_agent(dims, cfg, agent, Device::default())?;
    let mut rng = LearnRng::seed_from(0);
    for _ in 0..shape.batch * 2 {
        learner.add_episode(Episode::synthetic(&dims, shape.steps, &mut rng, false))?;
    }
    Ok(learner)
}

/// The PyTorch anchor as a child process in `--serve` mode.
struct Torch {
    child: Child,
    stdin: ChildStdin,
    stdout: BufReader<ChildStdout>,
    version: String,
}

impl Torch {
    fn start(python: &PathBuf, script: &PathBuf, shape: &Shape, mixer: MixerKind, threads: usize) -> Result<Torch> {
        let mut cmd = Command::new(python);
        cmd.arg(script).arg("--serve").arg("--mixer").arg(mixer_name(mixer));
        for (flag, v) in [
            ("--batch", shape.batch),
            ("--steps", shape.steps),
            ("--agents", shape.agents),
            ("--input", shape.input),
            ("--actions", shape.actions),
            ("--state", shape.state),
            ("--hidden", shape.hidden),
            ("--threads", threads),
        ] {
            cmd.arg(flag).arg(v.to_string());
        }
        let mut child = cmd
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .with_context(|| format!("starting {} {} (run benches/torch/setup.sh first)", python.display(), script.display()))?;
        let stdin = child.stdin.take().context("torch child stdin")?;
        let mut stdout = BufReader::new(child.stdout.take().context("torch child stdout")?);
        let ready = read_json(&mut stdout)?;
        if ready.get("ready").and_then(|v| v.as_bool()) != Some(true) {
            bail!("the torch anchor did not report ready: {ready}");
        }
        let version = ready.get("version").and_then(|v| v.as_str()).unwrap_or("?").to_string();
        Ok(Torch { child, stdin, stdout, version })
    }

    /// Run `k` updates; their milliseconds.
    fn run(&mut self, k: usize) -> Result<Vec<f64>> {
        writeln!(self.stdin, "run {k}")?;
        self.stdin.flush()?;
        let v = read_json(&mut self.stdout)?;
        let ms = v.get("ms").and_then(|m| m.as_array()).with_context(|| format!("torch anchor replied {v}"))?;
        Ok(ms.iter().filter_map(|x| x.as_f64()).collect())
    }
}

impl Drop for Torch {
    fn drop(&mut self) {
        let _ = writeln!(self.stdin, "quit");
        let _ = self.stdin.flush();
        let _ = self.child.wait();
    }
}

fn read_json(r: &mut impl BufRead) -> Result<serde_json::Value> {
    let mut line = String::new();
    if r.read_line(&mut line)? == 0 {
        bail!("the torch anchor exited (see its error output above)");
    }
    serde_json::from_str(line.trim()).with_context(|| format!("the torch anchor printed {line:?}, not JSON"))
}

/// Milliseconds of each of `k` updates.
fn time_updates(learner: &mut Learner, k: usize) -> Result<Vec<f64>> {
    let mut out = Vec::with_capacity(k);
    for _ in 0..k {
        let t0 = Instant::now();
        learner.train_step()?;
        out.push(t0.elapsed().as_secs_f64() * 1e3);
    }
    Ok(out)
}

/// Single-thread sgemm throughput through burn's backend (512^3, best of 20): the ceiling the
/// GFLOP/s figures are read against. Measured before and after the updates; the report keeps
/// the higher (a loaded machine only lowers it).
fn sgemm_gflops() -> f64 {
    use burn::tensor::{Distribution, Tensor};
    let dev = Device::default();
    let n = 512;
    let a: Tensor<2> = Tensor::random([n, n], Distribution::Default, &dev);
    let b: Tensor<2> = Tensor::random([n, n], Distribution::Default, &dev);
    let mut best = f64::INFINITY;
    for _ in 0..20 {
        let t0 = Instant::now();
        let c = a.clone().matmul(b.clone());
        let _ = c.into_data();
        best = best.min(t0.elapsed().as_secs_f64());
    }
    2.0 * (n * n * n) as f64 / best / 1e9
}

/// One matmul of an update: `reps` products of [m, k] x [k, n], the lhs read transposed when
/// `lhs_t` (a weight gradient reads the layer's input as [k, m]), `batch` of them at once (a
/// batched matmul, as the mixer's per-step [1, n] x [n, e]).
#[derive(Clone, Copy, Debug, Serialize)]
struct MatmulShape {
    what: &'static str,
    m: usize,
    k: usize,
    n: usize,
    batch: usize,
    reps: usize,
    lhs_t: bool,
}

/// The matmuls of a plain-agent update with the QMIX or VDN mixer, shape by shape, as
/// [`UpdateShape::plain`] counts them and the fused recurrence runs them: the agent's forward
/// (fc1; the GRU's input and hidden projections once per step on one step's rows; fc2), the
/// backward's input and
/// weight gradients (none into the first layers' inputs), the target network's forward, and
/// the mixer's hypernetworks and per-step mixing. QPLEX has no list (None).
fn update_matmuls(s: &Shape, mixer: MixerKind, cfg: &LearnConfig) -> Option<Vec<MatmulShape>> {
    let (h, a, n, st) = (s.hidden, s.actions, s.agents, s.state);
    let r = s.batch * s.steps * n;
    let step_rows = s.batch * n;
    let mm = |what, m, k, nn, reps| MatmulShape { what, m, k, n: nn, batch: 1, reps, lhs_t: false };
    let wg = |what, m, k, nn, reps| MatmulShape { what, m, k, n: nn, batch: 1, reps, lhs_t: true };
    // Forward of online and target (2x), input gradients, weight gradients.
    let mut v = vec![
        mm("agent fc1 (forward, online + target)", r, s.input, h, 2),
        mm("GRU input projection, one step (forward)", step_rows, h, 3 * h, 2 * s.steps),
        mm("GRU hidden projection, one step (forward)", step_rows, h, 3 * h, 2 * s.steps),
        mm("agent fc2 (forward)", r, h, a, 2),
        mm("fc2 input gradient", r, a, h, 1),
        mm("GRU input projection, one step, input gradient", step_rows, 3 * h, h, s.steps),
        mm("GRU hidden, one step, input gradient", step_rows, 3 * h, h, s.steps),
        wg("fc1 weight gradient", s.input, r, h, 1),
        wg("GRU input weight gradient, one step", h, step_rows, 3 * h, s.steps),
        // (the first step's is a product with h_{-1} = 0, skipped by the kernel but counted by
        // update_flops, which this list sums to exactly)
        wg("GRU hidden weight gradient, one step", h, step_rows, 3 * h, s.steps),
        wg("fc2 weight gradient", h, r, a, 1),
    ];
    match mixer {
        MixerKind::Vdn => {}
        MixerKind::Qmix => {
            let (e, he, m) = (cfg.mixing_embed_dim, cfg.hypernet_embed, s.batch * s.steps);
            // Each layer: forward twice (online, target), its weight gradient, and its input
            // gradient unless it reads the state.
            for (what, k, nn, first) in [
                ("hyper w1, first layer", st, he, true),
                ("hyper w1, second layer", he, e * n, false),
                ("hyper w_final, first layer", st, he, true),
                ("hyper w_final, second layer", he, e, false),
                ("hyper b1", st, e, true),
                ("V, first layer", st, e, true),
                ("V, second layer", e, 1, false),
            ] {
                v.push(mm(what, m, k, nn, 2));
                v.push(wg(what, k, m, nn, 1));
                if !first {
                    v.push(mm(what, m, nn, k, 1));
                }
            }
            // The per-step mixing: [1, n] x [n, e] then [1, e] x [e, 1], forward twice and
            // two gradients each.
            v.push(MatmulShape { what: "mixing, agents x w1 (batched)", m: 1, k: n, n: e, batch: m, reps: 4, lhs_t: false });
            v.push(MatmulShape { what: "mixing, hidden x w_final (batched)", m: 1, k: e, n: 1, batch: m, reps: 4, lhs_t: false });
        }
        MixerKind::Qplex => return None,
    }
    Some(v)
}

/// [`update_matmuls`] for LMAC (`l`: its settings): the plain agent's list with the agent's
/// first layer reading [own row | z], plus per agent-row the module's layers as
/// [`LmacConfig::update_flops`](lmac_run::learn::methods::lmac::LmacConfig::update_flops)
/// counts them, in the online and the target network (each forward twice, its weight gradient,
/// and its input gradient except the embedding's first layer, which reads the data): the
/// embedding and the encoder (window: q, k, v and the output layer; gru-gate: the GRU's input
/// projection over all steps, its hidden projection one step at a time as the fused recurrence
/// runs it, and the gate's query, key and value); the decoder and the cycle encoder in the
/// online network only. The window attention and the gate's dot product are not matmuls and
/// are left out (they are timed in `--profile`).
fn lmac_update_matmuls(
    s: &Shape,
    mixer: MixerKind,
    cfg: &LearnConfig,
    l: &lmac_run::learn::methods::lmac::LmacConfig,
) -> Option<Vec<MatmulShape>> {
    use lmac_run::learn::methods::lmac::{AuxLayout, EncoderKind};
    let st = &l.settings;
    let agent_in = s.input - if st.raw_messages { 0 } else { l.msg_cols } + st.latent_dim;
    let mut v = update_matmuls(&Shape { input: agent_in, ..*s }, mixer, cfg)?;
    let r = s.batch * s.steps * s.agents;
    let (e, lat, att, hd, dc) = (st.embed_dim, st.latent_dim, st.attention_dim, st.decoder_hidden, l.critical_dims.len());
    let mm = |what, m, k, n, reps| MatmulShape { what, m, k, n, batch: 1, reps, lhs_t: false };
    let wg = |what, m, k, n, reps| MatmulShape { what, m, k, n, batch: 1, reps, lhs_t: true };
    // (what, in, out, copies, in both networks, input gradient)
    let mut layers: Vec<(&'static str, usize, usize, usize, bool, bool)> =
        vec![("LMAC embedding, first layer", s.input, e, 1, true, false), ("LMAC embedding, second layer", e, e, 1, true, true)];
    match st.encoder {
        EncoderKind::Window => {
            layers.extend([("LMAC window q, k, v", e, att, 3, true, true), ("LMAC window output layer", att, lat, 1, true, true)])
        }
        EncoderKind::GruGate => {
            layers.extend([
                ("LMAC encoder GRU, input projection", e, 3 * e, 1, true, true),
                ("LMAC gate query", e, att, 1, true, true),
                ("LMAC gate key and value (one gemm)", e, att + lat, 1, true, true),
            ]);
            // The recurrence, one step's rows at a time: forward in both networks, the input
            // and weight gradients in the online one (the first step's weight gradient is a
            // product with c_{-1} = 0, skipped by the kernel but counted, as for the agent's GRU).
            let step_rows = s.batch * s.agents;
            v.push(mm("LMAC encoder GRU hidden projection, one step (forward)", step_rows, e, 3 * e, 2 * s.steps));
            v.push(mm("LMAC encoder GRU hidden, one step, input gradient", step_rows, 3 * e, e, s.steps));
            v.push(wg("LMAC encoder GRU hidden weight gradient, one step", e, step_rows, 3 * e, s.steps));
        }
    }
    layers.extend([
        ("LMAC decoder, first layer", lat, hd, 1, false, true),
        ("LMAC decoder, second layer", hd, hd, 1, false, true),
        ("LMAC decoder heads (state, reliability)", hd, dc, 2, false, true),
        ("LMAC cycle encoder, first layer", 2 * dc, hd, 1, false, true),
        ("LMAC cycle encoder, last layer", hd, lat, 1, false, true),
    ]);
    if st.aux_layout == AuxLayout::Released {
        layers.push(("LMAC cycle encoder, middle layer", hd, hd, 1, false, true));
    }
    for (what, k, n, copies, both, input_grad) in layers {
        v.push(mm(what, r, k, n, copies * if both { 2 } else { 1 }));
        v.push(wg(what, k, r, n, copies));
        if input_grad {
            v.push(mm(what, r, n, k, copies));
        }
    }
    Some(v)
}

impl MatmulShape {
    /// FLOPs of one of them (each of its `batch` products).
    fn flops(&self) -> f64 {
        2.0 * (self.batch * self.m * self.k * self.n) as f64
    }
}

/// The shape ceiling: each of the update's matmuls timed alone through burn on this thread
/// (best of 10 after a warm-up), and the update's time if every matmul ran at the rate gemm
/// reaches at its own shape with nothing else in between. Small per-step products reach far
/// less than the 512^3 rate, so this, not the 512^3 rate, bounds what the update can reach.
fn shape_ceiling(list: &[MatmulShape]) -> Vec<(MatmulShape, f64)> {
    use burn::tensor::{Distribution, Tensor};
    let dev = Device::default();
    list.iter()
        .map(|x| {
            let best = if x.batch > 1 {
                let l: Tensor<3> = Tensor::random([x.batch, x.m, x.k], Distribution::Default, &dev);
                let r: Tensor<3> = Tensor::random([x.batch, x.k, x.n], Distribution::Default, &dev);
                best_of(10, || {
                    let _ = l.clone().matmul(r.clone()).into_data();
                })
            } else {
                let l: Tensor<2> = if x.lhs_t {
                    Tensor::random([x.k, x.m], Distribution::Default, &dev)
                } else {
                    Tensor::random([x.m, x.k], Distribution::Default, &dev)
                };
                let r: Tensor<2> = Tensor::random([x.k, x.n], Distribution::Default, &dev);
                best_of(10, || {
                    let l = if x.lhs_t { l.clone().transpose() } else { l.clone() };
                    let _ = l.matmul(r.clone()).into_data();
                })
            };
            (*x, best * 1e3)
        })
        .collect()
}

/// Best wall time of `k` calls of `f` (seconds), after two unmeasured ones.
fn best_of(k: usize, mut f: impl FnMut()) -> f64 {
    f();
    f();
    (0..k)
        .map(|_| {
            let t0 = Instant::now();
            f();
            t0.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min)
}

/// Where one lmac update's time goes (median ms of `k` updates per phase): sampling the batch,
/// the target network's agent unroll, the online agents' forward, the rest of the loss (mixers,
/// targets, method terms), the backward pass, and clip + optimizer step.
fn profile_update(learner: &mut Learner, k: usize) -> Result<Vec<(&'static str, f64)>> {
    use burn::tensor::{Tensor, TensorData};
    let step_inputs = |batch: &lmac_run::learn::Batch, device: &Device| -> Vec<Tensor<2>> {
        let (b, n, iw) = (batch.b, batch.n_agents, batch.input_dim);
        (0..batch.t)
            .map(|ti| {
                Tensor::from_data(TensorData::new(batch.inputs[ti * b * n * iw..(ti + 1) * b * n * iw].to_vec(), [b * n, iw]), device)
            })
            .collect()
    };
    let ms = |t0: Instant| t0.elapsed().as_secs_f64() * 1e3;
    let mut phases: Vec<(&'static str, Vec<f64>)> = [
        "sample batch",
        "target agents (forward)",
        "online agents (forward)",
        "mixers, targets, loss",
        "backward",
        "clip + optimizer",
        "whole update",
    ]
    .into_iter()
    .map(|p| (p, Vec::new()))
    .collect();
    for _ in 0..k {
        let t0 = Instant::now();
        let batch = learner.sample_batch();
        phases[0].1.push(ms(t0));
        let dev = learner.device().clone();
        let t0 = Instant::now();
        let (q, _) = learner.target_net().agent.unroll(step_inputs(&batch, &dev), None);
        let _ = q.into_data();
        phases[1].1.push(ms(t0));
        let t0 = Instant::now();
        let (q, _) = learner.online_net().agent.unroll(step_inputs(&batch, &dev.clone().autodiff()), None);
        let _ = q.inner().into_data();
        phases[2].1.push(ms(t0));
        let t0 = Instant::now();
        let (loss, _) = learner.td_loss(&batch)?;
        let whole_loss = ms(t0);
        let agents = phases[1].1.last().copied().unwrap_or(0.0) + phases[2].1.last().copied().unwrap_or(0.0);
        phases[3].1.push((whole_loss - agents).max(0.0));
        let t0 = Instant::now();
        let _ = loss.backward();
        let backward = ms(t0);
        phases[4].1.push(backward);
        let (loss, stats) = learner.td_loss(&batch)?;
        let t0 = Instant::now();
        learner.apply_loss(loss, stats)?;
        phases[5].1.push((ms(t0) - backward).max(0.0));
        let t0 = Instant::now();
        learner.train_on(&batch)?;
        phases[6].1.push(ms(t0));
    }
    Ok(phases.into_iter().map(|(p, v)| (p, median(&v))).collect())
}

pub struct LearnerBenchOpts {
    pub shape: Shape,
    pub mixers: Vec<MixerKind>,
    pub method: Option<MethodUnderTest>,
    pub against_torch: bool,
    pub python: Option<PathBuf>,
    pub rounds: usize,
    pub updates: usize,
    pub stepwise: bool,
    /// Also time the update on two cores, as `--preset paper` runs it.
    pub two_cores: bool,
    pub profile: bool,
    pub json: bool,
    pub out: Option<PathBuf>,
}

pub fn bench_learner(o: LearnerBenchOpts) -> Result<i32> {
    // One thread for lmac as for torch: burn's flex backend parallelizes large matmuls on rayon's
    // global pool, which this sizes before its first use.
    if std::env::var_os("RAYON_NUM_THREADS").is_none() {
        std::env::set_var("RAYON_NUM_THREADS", "1");
    }
    let threads: usize = std::env::var("RAYON_NUM_THREADS").ok().and_then(|v| v.parse().ok()).unwrap_or(1);
    let root = lmac_run::supervisor::repo_root()?;
    let script = root.join("benches/torch/qlearner.py");
    let python = o.python.clone().unwrap_or_else(|| root.join("benches/torch/.venv/bin/python"));
    let peak_before = sgemm_gflops();
    let mut figures = Vec::new();
    let mut torch_version = None;
    let mut profiles = Vec::new();
    let method = o.method.as_ref();
    // An algorithm that names its backbone (qmix, vdn, qplex) runs on that one only.
    let mixers = match method.and_then(|m| m.mixer) {
        Some(fixed) => vec![fixed],
        None => o.mixers.clone(),
    };
    for &mixer in &mixers {
        let cfg = LearnConfig { mixer, ..LearnConfig::default() };
        let flops = update_flops(&o.shape, mixer, &cfg, method);
        let mut fused = filled_learner(&o.shape, mixer, true, false, method)?;
        let mut stepwise = if o.stepwise { Some(filled_learner(&o.shape, mixer, false, false, method)?) } else { None };
        let mut two_cores = if o.two_cores { Some(filled_learner(&o.shape, mixer, true, true, method)?) } else { None };
        let mut torch = if o.against_torch { Some(Torch::start(&python, &script, &o.shape, mixer, threads)?) } else { None };
        if let Some(t) = &torch {
            torch_version = Some(t.version.clone());
        }
        // warm-up (allocator, caches); torch warmed up before reporting ready
        time_updates(&mut fused, 3)?;
        if let Some(s) = stepwise.as_mut() {
            time_updates(s, 3)?;
        }
        if let Some(l) = two_cores.as_mut() {
            time_updates(l, 3)?;
        }
        let (mut f_rounds, mut s_rounds, mut t_rounds, mut c_rounds) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        for round in 0..o.rounds {
            f_rounds.push(median(&time_updates(&mut fused, o.updates)?));
            if let Some(s) = stepwise.as_mut() {
                s_rounds.push(median(&time_updates(s, o.updates)?));
            }
            if let Some(l) = two_cores.as_mut() {
                c_rounds.push(median(&time_updates(l, o.updates)?));
            }
            if let Some(t) = torch.as_mut() {
                t_rounds.push(median(&t.run(o.updates)?));
            }
            eprintln!(
                "lmac: {} round {}: lmac {:.1} ms{}{}{}",
                mixer_name(mixer),
                round + 1,
                f_rounds[round],
                s_rounds.get(round).map(|v| format!(", lmac stepwise {v:.1} ms")).unwrap_or_default(),
                c_rounds.get(round).map(|v| format!(", lmac on two cores {v:.1} ms")).unwrap_or_default(),
                t_rounds.get(round).map(|v| format!(", torch {v:.1} ms")).unwrap_or_default()
            );
        }
        for (name, rounds) in [("lmac", f_rounds), ("lmac-stepwise", s_rounds), (TWO_CORES, c_rounds), ("torch", t_rounds)] {
            if rounds.is_empty() {
                continue;
            }
            let m = median(&rounds);
            figures.push(Figure {
                name: name.into(),
                mixer: mixer_name(mixer).into(),
                rounds_ms: rounds,
                median_ms: m,
                gflops: flops / (m * 1e-3) / 1e9,
            });
        }
        drop(torch);
        if o.profile {
            for (name, l) in [("lmac", Some(&mut fused)), ("lmac-stepwise", stepwise.as_mut()), (TWO_CORES, two_cores.as_mut())] {
                let Some(l) = l else { continue };
                let p = profile_update(l, o.updates)?;
                for (phase, v) in &p {
                    eprintln!("lmac: profile {} {name}: {phase}: {v:.2} ms", mixer_name(mixer));
                }
                profiles.push(serde_json::json!({"mixer": mixer_name(mixer), "implementation": name,
                    "phases_ms": p.iter().map(|(k, v)| serde_json::json!({"phase": k, "ms": v})).collect::<Vec<_>>()}));
            }
        }
    }
    let peak = peak_before.max(sgemm_gflops());
    eprintln!("lmac: single-thread sgemm through burn (512^3): {peak:.1} GFLOP/s");
    // The update's matmuls at their own shapes: the plain agent's, and LMAC's (either encoder);
    // the other methods add modules no list covers yet.
    let ceilings: Vec<(MixerKind, Vec<(MatmulShape, f64)>)> = mixers
        .iter()
        .filter_map(|&m| {
            let cfg = LearnConfig { mixer: m, ..LearnConfig::default() };
            let list = match method.map(|x| &x.agent) {
                None | Some(AgentConfig::Rnn) => update_matmuls(&o.shape, m, &cfg),
                Some(AgentConfig::Lmac(l)) => lmac_update_matmuls(&o.shape, m, &cfg, l),
                Some(_) => None,
            };
            list.map(|l| (m, shape_ceiling(&l)))
        })
        .collect();
    let ceiling_ms = |c: &[(MatmulShape, f64)]| c.iter().map(|(x, ms)| x.reps as f64 * ms).sum::<f64>();
    let list_flops = |c: &[(MatmulShape, f64)]| c.iter().map(|(x, _)| x.reps as f64 * x.flops()).sum::<f64>();
    let ceiling_json: Vec<_> = ceilings
        .iter()
        .map(|(m, c)| {
            serde_json::json!({"mixer": mixer_name(*m), "ms_if_every_matmul_ran_alone": ceiling_ms(c), "gflop_of_these_matmuls": list_flops(c) / 1e9,
                "matmuls": c.iter().map(|(x, ms)| serde_json::json!({"what": x.what, "m": x.m, "k": x.k, "n": x.n, "batch": x.batch,
                    "lhs_transposed": x.lhs_t, "per_update": x.reps, "ms_each": ms,
                    "gflops": x.flops() / (ms * 1e-3) / 1e9})).collect::<Vec<_>>()})
        })
        .collect();
    let flops: Vec<_> = mixers
        .iter()
        .map(|&m| {
            let f = update_flops(&o.shape, m, &LearnConfig { mixer: m, ..LearnConfig::default() }, method);
            serde_json::json!({"mixer": mixer_name(m), "gflop_per_update": f / 1e9})
        })
        .collect();
    let report = serde_json::json!({
        "shape": o.shape, "threads": threads, "rounds": o.rounds, "updates_per_round": o.updates,
        "sgemm_gflops_single_thread": peak, "torch_version": torch_version, "flops": flops, "figures": figures, "profiles": profiles,
        "shape_ceiling": ceiling_json,
        "method": method.map(|m| m.settings.clone()),
    });
    if let Some(path) = &o.out {
        std::fs::write(path, serde_json::to_string_pretty(&report)?).with_context(|| format!("writing {}", path.display()))?;
    }
    if o.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
        return Ok(0);
    }
    let s = &o.shape;
    println!(
        "one update{}: {} episodes x {} steps x {} agents, input {}, {} actions, state {}, GRU {}; {} thread(s); median of {} rounds x {} updates",
        method.map(|m| format!(" of {} ({})", m.name, m.settings)).unwrap_or_default(),
        s.batch,
        s.steps,
        s.agents,
        s.input,
        s.actions,
        s.state,
        s.hidden,
        threads,
        o.rounds,
        o.updates
    );
    // The two-core figure is read against two cores' worth of the one-core sgemm rate.
    println!("| mixer | implementation | ms per update | GFLOP/s | of sgemm {peak:.0} GFLOP/s per core | torch / this |");
    println!("| --- | --- | --- | --- | --- | --- |");
    for f in &figures {
        let torch = figures.iter().find(|g| g.mixer == f.mixer && g.name == "torch").map(|g| g.median_ms);
        let cores = if f.name == TWO_CORES { 2.0 } else { 1.0 };
        println!(
            "| {} | {} | {:.1} | {:.1} | {:.0}% | {} |",
            f.mixer,
            f.name,
            f.median_ms,
            f.gflops,
            100.0 * f.gflops / (peak * cores),
            torch.map(|t| format!("{:.2}", t / f.median_ms)).unwrap_or_else(|| "-".into())
        );
    }
    for (m, c) in &ceilings {
        let ideal = ceiling_ms(c);
        // The list's own FLOPs: the update's count for the plain agent; LMAC's less its window
        // attention, which is no matmul.
        let flops = list_flops(c);
        let one = figures.iter().find(|f| f.mixer == mixer_name(*m) && f.name == "lmac").map(|f| f.median_ms);
        println!(
            "{}: its {} matmuls ({:.2} GFLOP), each timed alone at its own shape, take {ideal:.1} ms per update ({:.1} GFLOP/s, {:.0}% of the 512^3 rate){}",
            mixer_name(*m),
            c.iter().map(|(x, _)| x.reps).sum::<usize>(),
            flops / 1e9,
            flops / (ideal * 1e-3) / 1e9,
            100.0 * flops / (ideal * 1e-3) / 1e9 / peak,
            one.map(|u| format!("; the update on one thread takes {u:.1} ms, {:.0}% of that ceiling's speed", 100.0 * ideal / u)).unwrap_or_default()
        );
    }
    Ok(0)
}
