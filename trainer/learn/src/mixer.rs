//! Mixers: VDN (sum), QMIX (monotonic hypernetwork mixer) and QPLEX (duplex dueling with
//! multi-head attention weights), following pymarl / the QPLEX reference code.

use burn::module::{Module, Param};
use burn::nn::Linear;
use burn::tensor::activation::{relu, sigmoid};
use burn::tensor::{Device, Tensor};

use super::config::{LearnConfig, MixerKind};
use super::dense::{dense, Activation};
use super::init::{linear, uniform};
use super::qmix_mix::qmix_mix;
use super::LearnRng;

/// A hypernetwork of 1 or 2 layers (pymarl `hypernet_layers`), ReLU between.
#[derive(Module, Debug)]
pub struct HyperNet {
    pub l1: Linear,
    pub l2: Option<Linear>,
}

impl HyperNet {
    pub fn new(rng: &mut LearnRng, input: usize, output: usize, layers: usize, embed: usize, device: &Device) -> Self {
        if layers >= 2 {
            HyperNet { l1: linear(rng, input, embed, device), l2: Some(linear(rng, embed, output, device)) }
        } else {
            HyperNet { l1: linear(rng, input, output, device), l2: None }
        }
    }

    /// Each layer with its ReLU is one fused operation (`dense`).
    pub fn forward(&self, x: Tensor<2>) -> Tensor<2> {
        match &self.l2 {
            Some(l2) => dense(l2, dense(&self.l1, x, None, Activation::Relu, None), None, Activation::Identity, None),
            None => dense(&self.l1, x, None, Activation::Identity, None),
        }
    }
}

/// QMIX: Q_tot = elu(q . |W1(s)| + b1(s)) . |W2(s)| + V(s); monotonic in every Q_i.
#[derive(Module, Debug)]
pub struct QmixMixer {
    pub hyper_w1: HyperNet,
    pub hyper_w_final: HyperNet,
    pub hyper_b1: Linear,
    pub v1: Linear,
    pub v2: Linear,
    pub n_agents: usize,
    pub embed: usize,
}

impl QmixMixer {
    pub fn new(rng: &mut LearnRng, n_agents: usize, state_dim: usize, cfg: &LearnConfig, device: &Device) -> Self {
        let e = cfg.mixing_embed_dim;
        QmixMixer {
            hyper_w1: HyperNet::new(rng, state_dim, e * n_agents, cfg.hypernet_layers, cfg.hypernet_embed, device),
            hyper_w_final: HyperNet::new(rng, state_dim, e, cfg.hypernet_layers, cfg.hypernet_embed, device),
            hyper_b1: linear(rng, state_dim, e, device),
            v1: linear(rng, state_dim, e, device),
            v2: linear(rng, e, 1, device),
            n_agents,
            embed: e,
        }
    }

    /// qs [N, n_agents], states [N, S] -> Q_tot [N]. The hypernetworks' layers are fused
    /// operations (`dense`), and so is the mixing of their outputs (`qmix_mix`).
    pub fn forward(&self, qs: Tensor<2>, states: Tensor<2>) -> Tensor<1> {
        let w1 = self.hyper_w1.forward(states.clone());
        let b1 = dense(&self.hyper_b1, states.clone(), None, Activation::Identity, None);
        let w_final = self.hyper_w_final.forward(states.clone());
        let v = dense(&self.v2, dense(&self.v1, states, None, Activation::Relu, None), None, Activation::Identity, None);
        qmix_mix(qs, w1, b1, w_final, v)
    }
}

/// K independent linear layers applied in one batched matmul: x [K, N, in] -> [K, N, out].
#[derive(Module, Debug)]
pub struct StackedLinear {
    pub weight: Param<Tensor<3>>,
    pub bias: Param<Tensor<3>>,
}

impl StackedLinear {
    pub fn new(rng: &mut LearnRng, k: usize, input: usize, output: usize, device: &Device) -> Self {
        let bound = 1.0 / (input as f32).sqrt();
        StackedLinear { weight: uniform(rng, [k, input, output], bound, device), bias: uniform(rng, [k, 1, output], bound, device) }
    }

    pub fn forward(&self, x: Tensor<3>) -> Tensor<3> {
        x.matmul(self.weight.val()) + self.bias.val()
    }
}

/// K independent MLPs (1..=3 layers, ReLU between) over the same input, as in QPLEX's
/// `DMAQ_SI_Weight` extractors. The first layer of all K is one wide Linear.
#[derive(Module, Debug)]
pub struct KernelMlp {
    pub first: Linear,
    pub mid: Option<StackedLinear>,
    pub last: Option<StackedLinear>,
    pub k: usize,
    pub first_out: usize,
}

impl KernelMlp {
    pub fn new(rng: &mut LearnRng, k: usize, input: usize, output: usize, layers: usize, embed: usize, device: &Device) -> Self {
        let first_out = if layers >= 2 { embed } else { output };
        KernelMlp {
            first: linear(rng, input, k * first_out, device),
            mid: (layers >= 3).then(|| StackedLinear::new(rng, k, embed, embed, device)),
            last: (layers >= 2).then(|| StackedLinear::new(rng, k, embed, output, device)),
            k,
            first_out,
        }
    }

    /// x [N, in] -> [K, N, out]
    pub fn forward(&self, x: Tensor<2>) -> Tensor<3> {
        let [n, _] = x.dims();
        let mut y: Tensor<3> = dense(&self.first, x, None, Activation::Identity, None).reshape([n, self.k, self.first_out]).swap_dims(0, 1);
        if let Some(mid) = &self.mid {
            y = mid.forward(relu(y));
        }
        if let Some(last) = &self.last {
            y = last.forward(relu(y));
        }
        y
    }
}

/// Checked against the QPLEX reference (wjh720/QPLEX `dmaq_general.py`, `dmaq_si_weight.py`,
/// `qplex.yaml`: `weighted_head` and `is_minus_one` on, 10 kernels of 3 layers; see
/// `docs/reference/fidelity.md`). One difference: the reference's w(s) and v(s) are always 2-layer
/// networks of width `hypernet_embed` (`dmaq_general.py:22-27`), here they follow
/// `learn.hypernet_layers` (2 by default, the same networks; 1 only if set).
///
/// QPLEX (DMAQ general): Q_tot = sum_i (w_i(s) Q_i + v_i(s))
///   + sum_i [(w_i Q_i + v_i) - (w_i max Q_i + v_i)]_detached * (lambda_i(s, a) - 1),
/// lambda_i = sum_k |key_k(s)| * sigmoid(agents_k(s))_i * sigmoid(action_k(s, a))_i.
#[derive(Module, Debug)]
pub struct QplexMixer {
    pub hyper_w_final: HyperNet,
    pub v: HyperNet,
    pub key: KernelMlp,
    pub agents: KernelMlp,
    pub action: KernelMlp,
    pub n_agents: usize,
}

impl QplexMixer {
    pub fn new(rng: &mut LearnRng, n_agents: usize, state_dim: usize, n_actions: usize, cfg: &LearnConfig, device: &Device) -> Self {
        let k = cfg.qplex_num_kernel;
        let (l, e) = (cfg.qplex_adv_hypernet_layers, cfg.qplex_adv_hypernet_embed);
        QplexMixer {
            hyper_w_final: HyperNet::new(rng, state_dim, n_agents, cfg.hypernet_layers, cfg.hypernet_embed, device),
            v: HyperNet::new(rng, state_dim, n_agents, cfg.hypernet_layers, cfg.hypernet_embed, device),
            key: KernelMlp::new(rng, k, state_dim, 1, l, e, device),
            agents: KernelMlp::new(rng, k, state_dim, n_agents, l, e, device),
            action: KernelMlp::new(rng, k, state_dim + n_agents * n_actions, n_agents, l, e, device),
            n_agents,
        }
    }

    /// qs [N, n] chosen utilities, states [N, S], actions_onehot [N, n*A] of the evaluated joint
    /// action, max_q [N, n] per-agent max utilities -> Q_tot [N].
    pub fn forward(&self, qs: Tensor<2>, states: Tensor<2>, actions_onehot: Tensor<2>, max_q: Tensor<2>) -> Tensor<1> {
        let [n, _] = qs.dims();
        let w = self.hyper_w_final.forward(states.clone()).abs().add_scalar(1e-10);
        let v = self.v.forward(states.clone());
        let q = w.clone() * qs + v.clone();
        let qmax = w * max_q + v;
        let adv_q = (q.clone() - qmax).detach();
        let key = self.key.forward(states.clone()).abs().add_scalar(1e-10); // [K, N, 1]
        let agents = sigmoid(self.agents.forward(states.clone())); // [K, N, n]
        let data = Tensor::cat(vec![states, actions_onehot], 1);
        let action = sigmoid(self.action.forward(data)); // [K, N, n]
        let lambda = (key * agents * action).sum_dim(0).reshape([n, self.n_agents]);
        let v_tot = q.sum_dim(1);
        let adv_tot = (adv_q * lambda.sub_scalar(1.0)).sum_dim(1);
        (v_tot + adv_tot).reshape([n])
    }
}

/// The mixer of a run: VDN when neither network is present.
#[derive(Module, Debug)]
pub struct Mixer {
    pub qmix: Option<QmixMixer>,
    pub qplex: Option<QplexMixer>,
}

/// Extra inputs QPLEX needs; other mixers ignore them.
pub struct QplexInputs {
    /// [N, n_agents * n_actions]
    pub actions_onehot: Tensor<2>,
    /// [N, n_agents]
    pub max_q: Tensor<2>,
}

impl Mixer {
    pub fn new(
        rng: &mut LearnRng,
        kind: MixerKind,
        n_agents: usize,
        state_dim: usize,
        n_actions: usize,
        cfg: &LearnConfig,
        device: &Device,
    ) -> Self {
        match kind {
            MixerKind::Vdn => Mixer { qmix: None, qplex: None },
            MixerKind::Qmix => Mixer { qmix: Some(QmixMixer::new(rng, n_agents, state_dim, cfg, device)), qplex: None },
            MixerKind::Qplex => Mixer { qmix: None, qplex: Some(QplexMixer::new(rng, n_agents, state_dim, n_actions, cfg, device)) },
        }
    }

    pub fn kind(&self) -> MixerKind {
        if self.qmix.is_some() {
            MixerKind::Qmix
        } else if self.qplex.is_some() {
            MixerKind::Qplex
        } else {
            MixerKind::Vdn
        }
    }

    /// qs [N, n_agents], states [N, S] -> Q_tot [N]. `extra` is required for QPLEX.
    pub fn forward(&self, qs: Tensor<2>, states: Tensor<2>, extra: Option<QplexInputs>) -> Tensor<1> {
        if let Some(m) = &self.qmix {
            m.forward(qs, states)
        } else if let Some(m) = &self.qplex {
            let extra = extra.expect("QPLEX mixer needs the joint action and per-agent max utilities");
            m.forward(qs, states, extra.actions_onehot, extra.max_q)
        } else {
            let [n, _] = qs.dims();
            qs.sum_dim(1).reshape([n])
        }
    }
}
