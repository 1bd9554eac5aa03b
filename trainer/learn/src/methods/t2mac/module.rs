//! The T2MAC network (one set of parameters shared by all agents, the agent id one-hot in the
//! input). Per step, with n agents per environment, u_i agent i's input row and h_i its GRU
//! state:
//! - state      h_i = GRU(relu(W_in u_i), h_i')                            (pymarl's RNN agent)
//! - attention  w_i = softmax(W_att [W_q h_i | W_k h_1 .. W_k h_n])        [n]
//!              c_i = relu(W_c [sum_j w_ij W_v h_j | h_i]),  e_i = softplus(W_out c_i) (or relu)
//! - selector   p_i = softmax(S2 relu(S1 u_i))                             [n]
//! - utility    Q_i = own_weight e_i + fusion_weight fused_i               (`fusion.rs`)
//!
//! Everything after the GRU runs over all steps at once; the fusion is one host pass.

use burn::module::Module;
use burn::nn::Linear;
use burn::tensor::activation::{log_softmax, relu, softmax, softplus};
use burn::tensor::{Device, Int, Tensor, TensorData};

use super::fusion::{fuse, Fused};
use super::{Evidence, Selector, T2macConfig};
use crate::agent::RnnAgent;
use crate::config::LearnConfig;
use crate::init::linear;
use crate::methods::{linear_rows, AuxTerm, MethodHooks, TrainContext};
use crate::{InputLayout, LearnRng};

#[derive(Module, Debug)]
pub struct T2macAgent {
    /// fc1, GRU, and fc2 as the evidence head (H -> A).
    pub agent: RnnAgent,
    pub key: Linear,
    pub value: Linear,
    pub query: Linear,
    /// [query | n keys] -> n attention logits.
    pub attend: Linear,
    /// [attended value | h] -> H.
    pub merge: Linear,
    pub select1: Linear,
    pub select2: Linear,
    #[module(skip)]
    pub cfg: T2macConfig,
    pub n_agents: usize,
}

impl MethodHooks for T2macAgent {
    fn rnn_agent_mut(&mut self) -> Option<&mut RnnAgent> {
        Some(&mut self.agent)
    }
}

impl T2macAgent {
    pub fn new(rng: &mut LearnRng, cfg: &T2macConfig, layout: &InputLayout, learn: &LearnConfig, device: &Device) -> Self {
        let s = &cfg.settings;
        let (n, a) = (layout.dims.n_agents, layout.dims.n_actions);
        let (h, k) = (learn.rnn_hidden_dim, s.attention_dim);
        let (mut select1, mut select2) =
            (linear(rng, layout.width(), s.selector_hidden, device), linear(rng, s.selector_hidden, n, device));
        if s.selector == Selector::Frozen {
            (select1, select2) = (select1.no_grad(), select2.no_grad());
        }
        T2macAgent {
            agent: RnnAgent::new(rng, layout.width(), h, a, device),
            key: linear(rng, h, k, device),
            value: linear(rng, h, k, device),
            query: linear(rng, h, k, device),
            attend: linear(rng, k * (n + 1), n, device),
            merge: linear(rng, k + h, h, device),
            select1,
            select2,
            cfg: cfg.clone(),
            n_agents: n,
        }
    }

    /// The agent GRU's hidden state.
    pub fn state_width(&self) -> usize {
        self.agent.hidden_dim
    }

    /// One acting step (the same computation as a training step).
    pub fn step(&self, u: Tensor<2>, h: Tensor<2>) -> (Tensor<2>, Tensor<2>) {
        let [rows, in_w] = u.dims();
        let hd = self.agent.hidden_dim;
        let h = self.agent.gru.forward(relu(self.agent.fc1.forward(u.clone())), h);
        let (q, _, _) = self.heads(h.clone().reshape([1, rows, hd]), u.reshape([1, rows, in_w]), false);
        (q.reshape([rows, self.agent.n_actions]), h)
    }

    /// Unroll from zero states; in training (`train`) the selector's loss and the diagnostics.
    pub fn unroll(&self, inputs: Vec<Tensor<2>>, train: Option<&TrainContext>) -> (Tensor<3>, Vec<AuxTerm>) {
        let hs = self.agent.hidden_states(&inputs);
        let (q, logits, fused) = self.heads(hs, Tensor::stack(inputs, 0), train.is_some());
        let aux = match train {
            Some(ctx) => self.losses(logits, &fused, ctx),
            None => Vec::new(),
        };
        (q, aux)
    }

    /// Everything after the GRU over all steps: h [T, N, H], u [T, N, in] -> (Q [T, N, A], the
    /// selector's logits [T, B, n, n], the fusion; with the selector's labels when `labels`).
    fn heads(&self, h: Tensor<3>, u: Tensor<3>, labels: bool) -> (Tensor<3>, Tensor<4>, Fused) {
        let [t, rows, hd] = h.dims();
        let s = &self.cfg.settings;
        let (n, a, k) = (self.n_agents, self.agent.n_actions, s.attention_dim);
        let b = rows / n;
        let device = h.device();

        // Attention over all agents' values (keys of every agent concatenated to each query).
        let keys = linear_rows(&self.key, h.clone()).reshape([t, b, 1, n * k]).expand([t, b, n, n * k]);
        let query = linear_rows(&self.query, h.clone()).reshape([t, b, n, k]);
        let w = softmax(linear_rows(&self.attend, Tensor::cat(vec![query, keys], 3)), 3); // [t, b, n, n]
        let attended = w.matmul(linear_rows(&self.value, h.clone()).reshape([t, b, n, k]));
        let merged = relu(linear_rows(&self.merge, Tensor::cat(vec![attended, h.reshape([t, b, n, hd])], 3)));
        let q_raw = linear_rows(&self.agent.fc2, merged);
        let own = match s.evidence {
            Evidence::Relu => relu(q_raw),
            Evidence::Softplus => softplus(q_raw, 1.0),
        }; // [t, b, n, a]

        // Selector and fusion (no gradient through either's decisions).
        let logits = linear_rows(&self.select2, relu(linear_rows(&self.select1, u))).reshape([t, b, n, n]);
        let host = |x: Tensor<4>| x.detach().into_data().try_into_vec::<f32>().expect("f32 values");
        let min_drop = labels.then_some(s.min_uncertainty_drop);
        let fused = fuse(&host(own.clone()), &host(softmax(logits.clone(), 3)), n, a, s.send_threshold, min_drop);
        let received: Tensor<4> = Tensor::from_data(TensorData::new(fused.evidence.clone(), [t, b, n, a]), &device);
        let q = own.mul_scalar(s.own_weight) + received.mul_scalar(s.fusion_weight);
        (q.reshape([t, rows, a]), logits, fused)
    }

    fn losses(&self, logits: Tensor<4>, fused: &Fused, ctx: &TrainContext) -> Vec<AuxTerm> {
        let [t, b, n, _] = logits.dims();
        assert_eq!(ctx.n_agents, n, "the context's agent count");
        assert_eq!(ctx.b, b, "the context's batch size");
        let s = &self.cfg.settings;
        let device = logits.device();
        let scalar = |x: &Tensor<1>| x.clone().detach().into_scalar::<f32>();
        let targets: Tensor<4, Int> = Tensor::from_data(TensorData::new(fused.targets.clone(), [t, b, n, 1]), &device);
        let step_mask = ctx.mask.clone().reshape([t, b, 1, 1]);
        let nll = log_softmax(logits, 3).gather(3, targets).neg();
        let ce = (nll * step_mask).sum().div_scalar(ctx.mask_sum * n as f32);

        // Diagnostics over the trained steps, on the host.
        let mask = ctx.mask.clone().detach().into_data().try_into_vec::<f32>().expect("f32 mask");
        let (mut sends, mut labels, mut unc, mut drop, mut drops) = (0.0f64, 0.0f64, 0.0f64, 0.0f64, 0usize);
        for (g, &m) in mask.iter().enumerate().filter(|(_, &m)| m > 0.0) {
            for i in 0..n {
                let r = g * n + i;
                sends += m as f64 * fused.sends[r] as u8 as f64;
                labels += m as f64 * (fused.targets[r] != i as i64) as u8 as f64;
                unc += m as f64 * fused.uncertainty[r] as f64;
                if let Some(d) = fused.drop[r] {
                    drop += d as f64;
                    drops += 1;
                }
            }
        }
        let per = (ctx.mask_sum as f64 * n as f64).max(1.0);
        let loss = match s.selector {
            Selector::Learnt => Some(ce.clone().mul_scalar(s.selector_weight)),
            Selector::Frozen => None,
        };
        vec![
            AuxTerm { name: "t2mac_selector_ce", value: scalar(&ce), loss },
            AuxTerm { name: "t2mac_send_rate", value: (sends / per) as f32, loss: None },
            AuxTerm { name: "t2mac_label_send_rate", value: (labels / per) as f32, loss: None },
            AuxTerm { name: "t2mac_uncertainty", value: (unc / per) as f32, loss: None },
            AuxTerm { name: "t2mac_fused_drop", value: if drops > 0 { (drop / drops as f64) as f32 } else { 0.0 }, loss: None },
        ]
    }
}
