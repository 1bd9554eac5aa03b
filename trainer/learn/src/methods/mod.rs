//! The seam every method plugs into. A method is one file (or folder) here that gives a
//! [`MethodSpec`]: which messages the runner makes for it, its backbone and what its agents see,
//! and how its `[method]` settings become an [`AgentConfig`]. The agent network it builds is one
//! variant of [`AgentNet`], which offers the learner and the controller four things:
//!
//! - `state_width`: the per-agent recurrent state carried between acting steps (GRU hidden
//!   states, attention windows: whatever the method needs, as one flat row);
//! - `step`: acting, one step for N agent-rows;
//! - `unroll`: a batch over time, giving the Q-values handed to the mixer and, in training, the
//!   method's extra losses (named, each logged);
//! - its parameters, as a burn `Module` (optimizer, target copy, checkpoint).
//!
//! The learner (double Q, masking, mixers, target copies, clipping, optimizer) knows nothing
//! about any method. Adding one = a file or folder here, a variant of [`AgentConfig`] and
//! [`AgentNet`], and a line in [`REGISTRY`]; `tests/method_suite.rs` then checks it.

pub mod cola;
pub mod fullcomm;
pub mod lmac;
pub mod maic;
pub mod masia;
pub mod ndq;
pub mod qmix_state;
pub mod t2mac;
pub mod value_decomposition;

use std::sync::{Arc, OnceLock};

use burn::module::Module;
use burn::tensor::{Device, Int, Tensor};
use serde::{Deserialize, Serialize};

use super::agent::RnnAgent;
use super::config::{ConfigError, LearnConfig, MixerKind};
use super::{InputLayout, LearnRng};

/// Which messages the protocol runner writes for a method.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Messages {
    /// None unless `run.protocol` names protocol files (then "QMIX with messages").
    Optional,
    /// Every agent receives every other agent's full observation.
    FullComm,
    /// A designed protocol is required (`run.protocol`: a design directory or phase files).
    Designed,
}

/// What a run knows when it configures its method: resolved from the schema and the protocol.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MethodContext {
    /// Message columns after each agent's observation (the protocol's width).
    pub msg_cols: usize,
    /// The environment's recovery threshold alpha (a squared error in the state's units).
    pub alpha: f64,
    /// The union of the protocol phases' task-critical state dims (sorted); empty = none named.
    pub critical_dims: Vec<usize>,
    pub state_dim: usize,
}

/// One entry of the registry: everything a method decides outside its network.
pub struct MethodSpec {
    /// `--algo` name.
    pub name: &'static str,
    /// One line for `--help` and errors.
    pub about: &'static str,
    pub messages: Messages,
    /// The backbone this name fixes (`None`: `learn.mixer` decides).
    pub mixer: Option<MixerKind>,
    /// Agents also see the global state (QMIX+State, an upper bound).
    pub agent_sees_state: bool,
    /// Parse and check the `[method]` table (unknown keys are errors naming the field).
    pub configure: fn(&toml::Table, &MethodContext) -> Result<AgentConfig, ConfigError>,
    /// The JSON Schema of its `[method]` settings (their doc comments and defaults), for the
    /// configuration reference; `None`: the method has no settings.
    pub settings: Option<fn() -> schemars::Schema>,
}

/// Every method, by `--algo` name (pymarl's registry: one line each).
pub const REGISTRY: &[&MethodSpec] = &[
    &value_decomposition::QMIX,
    &value_decomposition::VDN,
    &value_decomposition::QPLEX,
    &fullcomm::FULLCOMM,
    &qmix_state::QMIX_STATE,
    &lmac::LMAC,
    &ndq::NDQ,
    &maic::MAIC,
    &t2mac::T2MAC,
    &cola::COLA,
    &masia::MASIA,
];

/// The method called `name`, or an error listing the known ones.
pub fn method(name: &str) -> Result<&'static MethodSpec, String> {
    REGISTRY
        .iter()
        .copied()
        .find(|m| m.name == name)
        .ok_or_else(|| format!("unknown algorithm {name:?}; known: {}", REGISTRY.iter().map(|m| m.name).collect::<Vec<_>>().join(", ")))
}

/// An error of a `[method]` setting, naming it (`method.<key>`).
pub fn bad(field: &'static str, reason: impl Into<String>) -> ConfigError {
    ConfigError { field, reason: reason.into() }
}

/// The `[method]` table as a method's settings (missing keys take their defaults; an unknown or
/// mistyped key is an error whose message names it).
pub fn parse_settings<T: serde::de::DeserializeOwned>(table: &toml::Table) -> Result<T, ConfigError> {
    toml::Value::Table(table.clone()).try_into().map_err(|e: toml::de::Error| bad("method", e.message().to_string()))
}

/// A method without settings: any key in `[method]` is an error.
pub fn no_settings(table: &toml::Table, _: &MethodContext) -> Result<AgentConfig, ConfigError> {
    match table.keys().next() {
        Some(k) => Err(ConfigError { field: "method", reason: format!("this algorithm has no settings, got `{k}`") }),
        None => Ok(AgentConfig::Rnn),
    }
}

/// Every method network, declared once: the `AgentConfig` variant a method's `configure` returns
/// (saved in checkpoints with the learner's config, tagged `agent = "<variant in kebab case>"`),
/// the `AgentNet` variant holding its burn module, and the dispatch over both. A method's module
/// gives its config a `validate`, its agent `new(rng, config, layout, learn, device)`,
/// `state_width`, `step` and `unroll`, a `STAT_NAMES` list and a [`MethodHooks`] impl; adding a
/// method is one line here (and one in [`REGISTRY`]).
macro_rules! method_networks {
    ($( $(#[$doc:meta])* $variant:ident => $module:ident :: { $config:ident, $agent:ident } ),* $(,)?) => {
        /// The agent network a method builds, saved in checkpoints with the learner's config.
        #[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
        #[serde(tag = "agent", rename_all = "kebab-case")]
        pub enum AgentConfig {
            /// pymarl's RNN agent (QMIX, VDN, QPLEX, FullComm, QMIX+State).
            #[default]
            Rnn,
            $( $(#[$doc])* $variant($module::$config), )*
        }

        /// One agent network for every method (burn modules are concrete types, so the seam is
        /// an enum).
        #[derive(Module, Debug)]
        pub enum AgentNet {
            Rnn(RnnAgent),
            $( $variant($module::$agent), )*
        }

        impl AgentConfig {
            pub fn validate(&self) -> Result<(), ConfigError> {
                match self {
                    AgentConfig::Rnn => Ok(()),
                    $( AgentConfig::$variant(c) => c.validate(), )*
                }
            }

            /// The extra numbers an update of this method logs, in order.
            pub fn stat_names(&self) -> &'static [&'static str] {
                match self {
                    AgentConfig::Rnn => &[],
                    $( AgentConfig::$variant(_) => $module::STAT_NAMES, )*
                }
            }

            /// Multiply-add FLOPs of one update of this agent at `shape` ([`crate::flops`]): the
            /// plain agent's, its input widened by the state where the method reads it, or the
            /// method's own count.
            pub fn update_flops(&self, shape: &crate::flops::UpdateShape, mixer: MixerKind, cfg: &LearnConfig, agent_sees_state: bool) -> f64 {
                match self {
                    AgentConfig::Rnn => {
                        let input = shape.input + if agent_sees_state { shape.state } else { 0 };
                        crate::flops::UpdateShape { input, ..*shape }.plain(mixer, cfg)
                    }
                    $( AgentConfig::$variant(c) => c.update_flops(shape, mixer, cfg), )*
                }
            }
        }

        impl AgentNet {
            /// The network of `agent`, weights drawn from `rng`.
            fn build(rng: &mut LearnRng, agent: &AgentConfig, layout: &InputLayout, cfg: &LearnConfig, device: &Device) -> Self {
                match agent {
                    AgentConfig::Rnn => {
                        AgentNet::Rnn(RnnAgent::new(rng, layout.width(), cfg.rnn_hidden_dim, layout.dims.n_actions, device))
                    }
                    $( AgentConfig::$variant(c) => AgentNet::$variant($module::$agent::new(rng, c, layout, cfg, device)), )*
                }
            }

            /// The method's pymarl RNN agent, for methods built around one (COLA has its own).
            pub fn rnn_agent_mut(&mut self) -> Option<&mut RnnAgent> {
                match self {
                    AgentNet::Rnn(a) => Some(a),
                    $( AgentNet::$variant(a) => a.rnn_agent_mut(), )*
                }
            }

            /// Width of the per-agent recurrent state the controller carries between steps.
            pub fn state_width(&self) -> usize {
                match self {
                    AgentNet::Rnn(a) => a.hidden_dim,
                    $( AgentNet::$variant(a) => a.state_width(), )*
                }
            }

            /// One acting step, deterministic (no dropout; see [`AgentNet::step_drawing`]): x [N, in], state [N, S] -> (q [N, A], state').
            pub fn step(&self, x: Tensor<2>, state: Tensor<2>) -> (Tensor<2>, Tensor<2>) {
                match self {
                    AgentNet::Rnn(a) => a.step(x, state),
                    $( AgentNet::$variant(a) => a.step(x, state), )*
                }
            }

            /// Unroll from zero states: `inputs[t]` is [N, in] with N = B * n_agents (batch-major
            /// rows). Returns Q [T, N, A] and, when `train` is given (the online network in an
            /// update), the method's extra loss terms. Without `train` the network is deterministic.
            pub fn unroll(&self, inputs: Vec<Tensor<2>>, train: Option<&TrainContext>) -> (Tensor<3>, Vec<AuxTerm>) {
                match self {
                    AgentNet::Rnn(a) => (a.unroll(inputs), Vec::new()),
                    $( AgentNet::$variant(a) => a.unroll(inputs, train), )*
                }
            }

            /// Whether every loss term of the method is a sum over the batch's steps divided by
            /// the whole batch's count (`TrainContext::mask_sum` for trained steps,
            /// `batch_episodes` for all steps), so that the terms of two halves of a batch add
            /// up to the whole batch's (`learn.data_parallel` splits only such methods' updates).
            pub fn losses_are_step_means(&self) -> bool {
                match self {
                    AgentNet::Rnn(_) => true,
                    $( AgentNet::$variant(a) => a.losses_are_step_means(), )*
                }
            }

            /// After every optimizer step of the online network: a method's updates that are not
            /// gradient steps (an EMA teacher, a momentum target encoder). Parameters it keeps
            /// this way do not require grad, so the optimizer leaves them alone; they are saved
            /// with the rest.
            pub fn after_update(self) -> Self {
                match self {
                    AgentNet::Rnn(a) => AgentNet::Rnn(a),
                    $( AgentNet::$variant(a) => AgentNet::$variant(MethodHooks::after_update(a)), )*
                }
            }
        }
    };
}

method_networks! {
    /// The LMAC agent: the meta-cognitive latent module in front of an RNN agent.
    Lmac => lmac::{LmacConfig, LmacAgent},
    /// NDQ: Gaussian messages to every teammate, an action-inference head (Wang et al. 2020).
    Ndq => ndq::{NdqConfig, NdqAgent},
    /// MAIC: teammate models and incentive messages added to the receivers' Q-values (Yuan et
    /// al. 2022).
    Maic => maic::{MaicConfig, MaicAgent},
    /// T2MAC: attention over teammates, evidential opinions sent to selected teammates and fused
    /// (Sun et al. 2024).
    T2mac => t2mac::{T2macConfig, T2macAgent},
    /// COLA: a consensus class per agent and step, learnt DINO-style so that agents agree, next
    /// to the GRU state (Xu et al. 2023).
    Cola => cola::{ColaConfig, ColaAgent},
    /// MASIA: every agent's input aggregated by a self-supervised attention encoder, gated per
    /// agent (Guan et al. 2022).
    Masia => masia::{MasiaConfig, MasiaAgent},
}

/// What a method's network offers beyond `new`, `state_width`, `step` and `unroll`, with the
/// defaults most methods need.
pub trait MethodHooks: Sized {
    /// The pymarl RNN agent the method is built around (its `fused` switch follows
    /// `learn.fused_gru`); `None` when it has its own recurrence.
    fn rnn_agent_mut(&mut self) -> Option<&mut RnnAgent>;
    /// Updates after each optimizer step that are not gradient steps; none by default.
    fn after_update(self) -> Self {
        self
    }
    /// Whether every loss term is a sum over the batch's steps divided by the whole batch's
    /// count (see `AgentNet::losses_are_step_means`); not by default, so a new method's update is
    /// never split unless it says so.
    fn losses_are_step_means(&self) -> bool {
        false
    }
}

impl AgentNet {
    /// [`step`](Self::step) with the method's acting randomness drawn from `noise`: LMAC's
    /// embedding dropout with `method.dropout_when_acting`. Every other method acts
    /// deterministically and draws nothing.
    pub fn step_drawing(&self, x: Tensor<2>, state: Tensor<2>, noise: &mut LearnRng) -> (Tensor<2>, Tensor<2>) {
        match self {
            AgentNet::Lmac(a) if a.drops_out_when_acting() => a.step_with(x, state, Some(noise)),
            _ => self.step(x, state),
        }
    }

    /// The target network's unroll, Q [T, N, A]: deterministic, except LMAC's embedding dropout
    /// with `method.dropout_when_acting`, drawn from `seed`.
    pub fn unroll_target(&self, inputs: Vec<Tensor<2>>, seed: u64) -> Tensor<3> {
        let steps = inputs.len();
        self.unroll_target_stacked(Tensor::cat(inputs, 0), steps, seed)
    }

    /// [`unroll`](Self::unroll) of the steps stacked time-major, x [T * N, in] (the batch's
    /// layout): the networks that read all steps at once (the plain agent, LMAC) take it as it
    /// is, saving a split into steps and the concatenation back; the others get its steps.
    pub fn unroll_stacked(&self, x: Tensor<2>, steps: usize, train: Option<&TrainContext>) -> (Tensor<3>, Vec<AuxTerm>) {
        match self {
            AgentNet::Rnn(a) => (a.unroll_stacked(x, steps), Vec::new()),
            AgentNet::Lmac(a) => a.unroll_stacked(x, steps, train),
            _ => self.unroll(split_steps(x, steps), train),
        }
    }

    /// [`unroll_target`](Self::unroll_target) of the steps stacked time-major, x [T * N, in].
    pub fn unroll_target_stacked(&self, x: Tensor<2>, steps: usize, seed: u64) -> Tensor<3> {
        match self {
            AgentNet::Lmac(a) => a.unroll_target_stacked(x, steps, seed),
            _ => self.unroll_stacked(x, steps, None).0,
        }
    }
}

impl AgentConfig {
    /// Whether the method's reference code standardises rewards (`learn.reward_standardisation
    /// = "method"`): LMAC's released config does; the baselines run EPyMARL's default (no).
    pub fn standardises_rewards(&self) -> bool {
        match self {
            AgentConfig::Lmac(c) => c.settings.standardise_rewards,
            _ => false,
        }
    }
}

/// What the online network's unroll needs in training, beyond its inputs. Tensors are on the
/// autodiff device; rows are time-major (`t * b + b_i`).
pub struct TrainContext {
    /// [T * B, state_dim]
    pub state: Tensor<2>,
    /// [T * B]: 1 on steps that are trained on.
    pub mask: Tensor<1>,
    /// The number of trained steps every mean over them divides by (at least 1): the sum of
    /// `mask`, or with `learn.data_parallel` the whole batch's while this context holds half of
    /// its episodes (the halves' terms then add up to the whole batch's).
    pub mask_sum: f32,
    pub b: usize,
    /// Episodes of the batch every mean over all its steps, padding included, divides by: `b`,
    /// or with `learn.data_parallel` the whole batch's while this context holds half of them.
    pub batch_episodes: usize,
    pub n_agents: usize,
    /// Seed of this update's random draws (dropout), so an update is reproducible and a resumed
    /// run draws what the uninterrupted one would have.
    pub seed: u64,
    /// The batch's actions and the target network's greedy ones, per step and agent-row. The
    /// learner always fills it; a context built by hand (a test of a method that reads no
    /// actions) may leave it out.
    pub actions: Option<StepActions>,
    /// [T * B]: the batch's reward of each step (0 on padded steps), for methods that predict
    /// it. The learner always fills it; a context built by hand may leave it out.
    pub reward: Option<Tensor<1>>,
}

/// Actions per step and agent-row, `[T, N]` with N = B * n_agents (batch-major, like the
/// unroll's inputs), on the autodiff device.
pub struct StepActions {
    /// The action each agent took (0 on padded steps).
    pub taken: Tensor<2, Int>,
    /// The target network's greedy action among the available ones. Filled by the target
    /// unroll, which may still be running on another thread: [`StepActions::target_greedy`]
    /// waits for it. `None` inside: the target unroll failed.
    target_greedy: Arc<OnceLock<Option<Tensor<2, Int>>>>,
}

impl StepActions {
    /// Both known now (tests, or a learner that unrolled the target first).
    pub fn new(taken: Tensor<2, Int>, target_greedy: Tensor<2, Int>) -> Self {
        let cell = OnceLock::new();
        let _ = cell.set(Some(target_greedy));
        StepActions { taken, target_greedy: Arc::new(cell) }
    }

    /// The target's greedy actions to come: the returned cell is filled by whoever unrolls the
    /// target network (with `Some`, or `None` if that failed).
    pub fn pending(taken: Tensor<2, Int>) -> (Self, Arc<OnceLock<Option<Tensor<2, Int>>>>) {
        let cell = Arc::new(OnceLock::new());
        (StepActions { taken, target_greedy: cell.clone() }, cell)
    }

    /// The target network's greedy actions `[T, N]`, waiting for the target unroll if needed.
    pub fn target_greedy(&self) -> Tensor<2, Int> {
        match self.target_greedy.wait() {
            Some(t) => t.clone(),
            None => panic!("the target network's unroll failed, so its greedy actions are unknown"),
        }
    }
}

/// A named term a method adds to the TD loss, or a diagnostic it logs.
pub struct AuxTerm {
    pub name: &'static str,
    /// Weighted and gradient-carrying; `None` for a logged diagnostic.
    pub loss: Option<Tensor<1>>,
    /// The logged value (unweighted).
    pub value: f32,
}

impl AgentNet {
    /// Build with weights drawn from `rng`. `layout` is what the learner writes per agent-row.
    pub fn new(rng: &mut LearnRng, agent: &AgentConfig, layout: &InputLayout, cfg: &LearnConfig, device: &Device) -> Self {
        let mut net = AgentNet::build(rng, agent, layout, cfg, device);
        if let Some(rnn) = net.rnn_agent_mut() {
            rnn.fused = cfg.fused_gru;
        }
        net
    }

    /// Change the test-time settings of a trained network from `from` to `to` (what
    /// `lmac evaluate --set method.KEY=VALUE` does): NDQ's message cut, MAIC's pruning. Any
    /// other difference would need other weights and is refused, naming what may change.
    pub fn retune(&mut self, from: &AgentConfig, to: &AgentConfig) -> Result<(), String> {
        if from == to {
            return Ok(());
        }
        match (self, from, to) {
            (AgentNet::Ndq(a), AgentConfig::Ndq(f), AgentConfig::Ndq(t))
                if ndq::NdqSettings { cut: f.settings.cut, ..t.settings.clone() } == f.settings =>
            {
                a.set_cut(t.settings.cut);
                Ok(())
            }
            (AgentNet::Maic(a), AgentConfig::Maic(f), AgentConfig::Maic(t))
                if maic::MaicSettings { prune: f.settings.prune, ..t.settings.clone() } == f.settings =>
            {
                a.cfg.settings.prune = t.settings.prune;
                Ok(())
            }
            (AgentNet::Lmac(a), AgentConfig::Lmac(f), AgentConfig::Lmac(t))
                if lmac::LmacSettings { dropout_when_acting: f.settings.dropout_when_acting, ..t.settings.clone() } == f.settings =>
            {
                a.cfg.settings.dropout_when_acting = t.settings.dropout_when_acting;
                Ok(())
            }
            _ => Err(format!(
                "the network in the checkpoint was built for other settings than the run's config now gives ({}); only \
                 test-time settings can change for a trained network: method.cut (ndq), method.prune (maic), \
                 method.dropout_when_acting (lmac)",
                config_differences(from, to)
            )),
        }
    }
}

/// Leaky ReLU as relu(x) (1 - slope) + slope x: the same values (to rounding) as burn's
/// `leaky_relu`, whose default form under autodiff selects with `mask_where`, a branch per
/// element that mispredicts on mixed signs (17% of MAIC's update at 1o_10b's shape); relu and
/// its backward are branch-free elementwise passes.
pub fn leaky_relu<const D: usize>(x: Tensor<D>, slope: f64) -> Tensor<D> {
    burn::tensor::activation::relu(x.clone()).mul_scalar(1.0 - slope) + x.mul_scalar(slope)
}

/// The steps of x [T * N, in] (time-major), each [N, in].
fn split_steps(x: Tensor<2>, steps: usize) -> Vec<Tensor<2>> {
    let rows = x.dims()[0] / steps.max(1);
    x.split(rows.max(1), 0)
}

/// `layer` applied to every row of `x` [.., in] as one [rows, in] x [in, out] matmul, the fused
/// [`dense`](crate::dense::dense) operation. burn's `Linear` on a 3-d input keeps the leading dim
/// as a batch when each batch's rows fill its row tiles (LMAC's [T = 50, N = 352, in]: 50 small
/// matmuls forward, and in the backward 50 weight products summed over a [T, in, out]
/// temporary); the rows of one matmul are what the weight sees either way, so the values are the
/// same up to float summation order.
pub fn linear_rows<const D: usize>(layer: &burn::nn::Linear, x: Tensor<D>) -> Tensor<D> {
    let dims = x.dims();
    if D < 2 {
        return layer.forward(x);
    }
    let d_in = dims[D - 1];
    let rows = dims[..D - 1].iter().product::<usize>();
    let y = crate::dense::dense(layer, x.reshape([rows, d_in]), None, crate::dense::Activation::Identity, None);
    let mut out = dims;
    out[D - 1] = y.dims()[1];
    y.reshape(out)
}

/// Dropout with a mask drawn on the host from `rng` (inverted: kept units scaled by 1/(1-p)),
/// so a seed fixes it exactly (burn's device RNG is process-global).
pub fn dropout<const D: usize>(x: Tensor<D>, p: f32, rng: &mut LearnRng) -> Tensor<D> {
    if p <= 0.0 {
        return x;
    }
    let shape = x.dims();
    let mask = crate::dense::dropout_mask(shape.iter().product(), p, rng);
    let m: Tensor<D> = Tensor::from_data(burn::tensor::TensorData::new(mask, shape), &x.device());
    x * m
}

/// Standard normal draws from `rng` (Box-Muller), as a tensor of `shape` on `device`: host-side
/// like [`dropout`], so a seed fixes every sample.
pub fn standard_normal<const D: usize>(rng: &mut LearnRng, shape: [usize; D], device: &Device) -> Tensor<D> {
    let n: usize = shape.iter().product();
    let mut v = Vec::with_capacity(n + 1);
    while v.len() < n {
        // 1 - u lies in (0, 1]: the logarithm stays finite.
        let (u1, u2) = (1.0 - rng.uniform() as f64, rng.uniform() as f64);
        let r = (-2.0 * u1.ln()).sqrt();
        let a = std::f64::consts::TAU * u2;
        v.push((r * a.cos()) as f32);
        v.push((r * a.sin()) as f32);
    }
    v.truncate(n);
    Tensor::from_data(burn::tensor::TensorData::new(v, shape), device)
}

/// What differs between two agent configs, as `path: trained -> now` (at most six), e.g.
/// `lmac.msg_cols: 450 -> 211` when a protocol's message layout changed since training.
fn config_differences(trained: &AgentConfig, now: &AgentConfig) -> String {
    fn walk(path: &str, a: &serde_json::Value, b: &serde_json::Value, out: &mut Vec<String>) {
        match (a, b) {
            (serde_json::Value::Object(x), serde_json::Value::Object(y)) => {
                let keys: std::collections::BTreeSet<&String> = x.keys().chain(y.keys()).collect();
                for k in keys {
                    let null = serde_json::Value::Null;
                    let sub = if path.is_empty() { k.clone() } else { format!("{path}.{k}") };
                    walk(&sub, x.get(k).unwrap_or(&null), y.get(k).unwrap_or(&null), out);
                }
            }
            _ if a != b => {
                let short = |v: &serde_json::Value| {
                    let t = v.to_string();
                    if t.chars().count() > 40 {
                        format!("{}...", t.chars().take(40).collect::<String>())
                    } else {
                        t
                    }
                };
                out.push(format!("{path}: {} -> {}", short(a), short(b)));
            }
            _ => {}
        }
    }
    let as_json = |c: &AgentConfig| serde_json::to_value(c).unwrap_or(serde_json::Value::Null);
    let mut out = Vec::new();
    walk("", &as_json(trained), &as_json(now), &mut out);
    let more = out.len().saturating_sub(6);
    out.truncate(6);
    if more > 0 {
        out.push(format!("{more} more"));
    }
    out.join(", ")
}
