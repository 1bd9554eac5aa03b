//! The meta-cognitive latent module and the agent it feeds (one set of parameters shared by all
//! agents, the agent id one-hot in the input).
//!
//! Per agent-row and step, with u = [observation | messages | last action | agent id]:
//! - embedding  x = dropout(relu(W2 LayerNorm(relu(W1 u))))          (dropout in training only,
//!              or in every forward with `dropout_when_acting`)
//! - encoder    z = Enc(x, trajectory):
//!     `gru-gate`: c = GRU(x, c_prev) + x (carried to the next step, as the released code);
//!                 z = sigmoid(W_q x . W_k c) * W_v c
//!     `window`:   multi-head softmax(W_q x_t . W_k x_{t-o} / sqrt(d)) over o < W, values W_v x_{t-o},
//!                 then a linear map to the latent width (steps before the episode are masked)
//! - decoder    (s_hat, xi_hat) = Dec(z): z -> H (-> dropout) -> H -> (|critical dims| values,
//!              as many logits)
//! - cycle      z_hat = Enc_c(s_hat, sigmoid(xi_hat)): `released` layout
//!              -> H -> LayerNorm -> H -> dropout -> latent; `compact` -> H -> latent
//! - agent      Q = RNN([observation (| messages) | last action | id | z])
//!
//! Losses (means over the trained steps, agents and dims):
//! L_recon = (s_hat - s)^2 + lambda_meta BCE(xi_hat, xi), xi = 1[(s_hat - s)^2 <= alpha]
//! (no gradient through xi); L_cons = (z_hat - z)^2 averaged over the latent's dims too (the
//! released code's `F.mse_loss`; `consistency_over_latent = "sum"` sums over them), weighted by
//! lambda_cons. Logged besides: the share of (agent, dim, step) recovered within alpha, the mean
//! predicted reliability, and the mean ||z||^2.

use burn::module::Module;
use burn::nn::{LayerNorm, LayerNormConfig, Linear};
use burn::tensor::activation::{relu, sigmoid, softmax};
use burn::tensor::{Bool, Device, Int, Tensor, TensorData};

use super::{AuxLayout, EncoderKind, LatentReduction, LmacConfig};
use crate::agent::{FusedGru, RnnAgent};
use crate::agent_input::agent_input;
use crate::config::LearnConfig;
use crate::dense::{dense, dense_with, Activation, LAYER_NORM_EPSILON};
use crate::init::linear;
use crate::latent_gate::latent_gate;
use crate::methods::{linear_rows, AuxTerm, MethodHooks, TrainContext};
use crate::window_attention::window_attention;
use crate::{InputLayout, LearnRng};

/// The `gru-gate` encoder (the authors' code).
#[derive(Module, Debug)]
pub struct GruGateEncoder {
    pub gru: FusedGru,
    pub query: Linear,
    pub key: Linear,
    pub value: Linear,
}

/// The `window` encoder (the paper's wording).
#[derive(Module, Debug)]
pub struct WindowEncoder {
    pub query: Linear,
    pub key: Linear,
    pub value: Linear,
    pub out: Linear,
    pub heads: usize,
    pub window: usize,
}

#[derive(Module, Debug)]
pub enum Encoder {
    GruGate(GruGateEncoder),
    Window(WindowEncoder),
}

#[derive(Module, Debug)]
pub struct LmacAgent {
    pub embed1: Linear,
    pub norm: LayerNorm,
    pub embed2: Linear,
    pub encoder: Encoder,
    pub dec1: Linear,
    pub dec2: Linear,
    pub dec_state: Linear,
    pub dec_meta: Linear,
    pub cycle1: Linear,
    /// `released` layout only: the cycle encoder's LayerNorm and middle layer.
    pub cycle_norm: Option<LayerNorm>,
    pub cycle_mid: Option<Linear>,
    pub cycle2: Linear,
    pub agent: RnnAgent,
    #[module(skip)]
    pub cfg: LmacConfig,
    /// Observation columns before the messages.
    pub obs_dim: usize,
    /// Width of the learner's input row.
    pub in_width: usize,
}

impl MethodHooks for LmacAgent {
    fn rnn_agent_mut(&mut self) -> Option<&mut RnnAgent> {
        Some(&mut self.agent)
    }

    /// Reconstruction, meta and consistency terms are masked means over the trained steps, and
    /// the released code's unmasked consistency mean (`mask_consistency = false`) divides by the
    /// whole batch's steps.
    fn losses_are_step_means(&self) -> bool {
        true
    }
}

impl LmacAgent {
    pub fn new(rng: &mut LearnRng, cfg: &LmacConfig, layout: &InputLayout, learn: &LearnConfig, device: &Device) -> Self {
        let s = &cfg.settings;
        let in_width = layout.width();
        let (e, l, hd, dc) = (s.embed_dim, s.latent_dim, s.decoder_hidden, cfg.critical_dims.len());
        let embed1 = linear(rng, in_width, e, device);
        let embed2 = linear(rng, e, e, device);
        let encoder = match s.encoder {
            EncoderKind::GruGate => Encoder::GruGate(GruGateEncoder {
                gru: FusedGru::new(rng, e, e, device),
                query: linear(rng, e, s.attention_dim, device),
                key: linear(rng, e, s.attention_dim, device),
                value: linear(rng, e, l, device),
            }),
            EncoderKind::Window => Encoder::Window(WindowEncoder {
                query: linear(rng, e, s.attention_dim, device),
                key: linear(rng, e, s.attention_dim, device),
                value: linear(rng, e, s.attention_dim, device),
                out: linear(rng, s.attention_dim, l, device),
                heads: s.heads,
                window: s.window,
            }),
        };
        let agent_in = in_width - if s.raw_messages { 0 } else { cfg.msg_cols } + l;
        let released = s.aux_layout == AuxLayout::Released;
        LmacAgent {
            embed1,
            norm: LayerNormConfig::new(e).with_epsilon(LAYER_NORM_EPSILON as f64).init(device),
            embed2,
            encoder,
            dec1: linear(rng, l, hd, device),
            dec2: linear(rng, hd, hd, device),
            dec_state: linear(rng, hd, dc, device),
            dec_meta: linear(rng, hd, dc, device),
            cycle1: linear(rng, 2 * dc, hd, device),
            cycle_norm: released.then(|| LayerNormConfig::new(hd).with_epsilon(LAYER_NORM_EPSILON as f64).init(device)),
            cycle_mid: released.then(|| linear(rng, hd, hd, device)),
            cycle2: linear(rng, hd, l, device),
            agent: RnnAgent::new(rng, agent_in, learn.rnn_hidden_dim, layout.dims.n_actions, device),
            cfg: cfg.clone(),
            obs_dim: layout.dims.obs_width - cfg.msg_cols,
            in_width,
        }
    }

    fn embed_dim(&self) -> usize {
        self.cfg.settings.embed_dim
    }

    /// Encoder state per row: the GRU's hidden state, or the last W-1 embeddings plus a count of
    /// how many of them belong to this episode.
    fn encoder_state_width(&self) -> usize {
        match &self.encoder {
            Encoder::GruGate(_) => self.embed_dim(),
            Encoder::Window(w) => (w.window - 1) * self.embed_dim() + 1,
        }
    }

    /// [encoder state | agent GRU hidden state]
    pub fn state_width(&self) -> usize {
        self.encoder_state_width() + self.agent.hidden_dim
    }

    /// Each layer with its LayerNorm, ReLU and dropout is one fused operation (`dense`).
    fn embed(&self, u: Tensor<2>, rng: Option<&mut LearnRng>) -> Tensor<2> {
        let h = dense(&self.embed1, u, None, Activation::Relu, None);
        dense(&self.embed2, h, Some(&self.norm), Activation::Relu, rng.map(|r| (self.cfg.settings.dropout, r)))
    }

    /// The agent network's own input: the row without the message columns (unless it reads
    /// them), then z; one pass over the rows (`agent_input`).
    fn agent_input(&self, u: Tensor<2>, z: Tensor<2>) -> Tensor<2> {
        let m = if self.cfg.settings.raw_messages { 0 } else { self.cfg.msg_cols };
        let z = if self.cfg.settings.td_to_encoder { z } else { z.detach() };
        agent_input(u, self.obs_dim..self.obs_dim + m, z)
    }

    /// One acting step (deterministic).
    pub fn step(&self, u: Tensor<2>, state: Tensor<2>) -> (Tensor<2>, Tensor<2>) {
        self.step_with(u, state, None)
    }

    /// Whether the embedding's dropout acts outside training updates too (`dropout_when_acting`).
    pub fn drops_out_when_acting(&self) -> bool {
        self.cfg.settings.dropout_when_acting && self.cfg.settings.dropout > 0.0
    }

    /// One acting step; the embedding's dropout draws from `rng` when given.
    pub fn step_with(&self, u: Tensor<2>, state: Tensor<2>, rng: Option<&mut LearnRng>) -> (Tensor<2>, Tensor<2>) {
        let n = u.dims()[0];
        let es = self.encoder_state_width();
        let enc_state = state.clone().slice([0..n, 0..es]);
        let h_agent = state.slice([0..n, es..es + self.agent.hidden_dim]);
        let x = self.embed(u.clone(), rng);
        let (z, enc_next) = match &self.encoder {
            Encoder::GruGate(g) => {
                // The released code carries c = h + x to the next step, not h.
                let c = g.gru.forward(x.clone(), enc_state) + x.clone();
                (gate(g, x, c.clone()), c)
            }
            Encoder::Window(w) => {
                let e = self.embed_dim();
                let past = w.window - 1;
                let count = enc_state.clone().slice([0..n, past * e..past * e + 1]);
                // Window entries, newest first: the current embedding, then the stored ones.
                let mut entries = vec![x.clone()];
                entries.extend((0..past).map(|o| enc_state.clone().slice([0..n, o * e..(o + 1) * e])));
                // Entry o (o >= 1) is from this episode when o <= count.
                let valid: Vec<Tensor<2, Bool>> = (0..w.window).map(|o| count.clone().greater_equal_elem(o as f32)).collect();
                let z = window_attend(w, x.clone(), &entries, &valid);
                let mut next: Vec<Tensor<2>> = entries[..past].to_vec();
                next.push(count.add_scalar(1.0).clamp_max(past as f32));
                (z, Tensor::cat(next, 1))
            }
        };
        let (q, h_agent) = self.agent.step(self.agent_input(u, z), h_agent);
        (q, Tensor::cat(vec![enc_next, h_agent.clone()], 1))
    }

    /// Unroll from zero states; in training also the module's losses (see the file's header).
    /// The steps are stacked once ([T * N, in], time-major) and every part that does not depend
    /// on a recurrence runs over all of them at once; the agents' input is built in one
    /// concatenation for all steps.
    pub fn unroll(&self, inputs: Vec<Tensor<2>>, train: Option<&TrainContext>) -> (Tensor<3>, Vec<AuxTerm>) {
        assert!(!inputs.is_empty(), "unroll needs at least one step");
        let steps = inputs.len();
        self.unroll_stacked(Tensor::cat(inputs, 0), steps, train)
    }

    /// [`unroll`](Self::unroll) of the steps stacked time-major, u [T * N, in].
    pub fn unroll_stacked(&self, u: Tensor<2>, steps: usize, train: Option<&TrainContext>) -> (Tensor<3>, Vec<AuxTerm>) {
        let mut rng = train.map(|c| LearnRng::seed_from(c.seed ^ 0xD80F_0000_0000_0001));
        let (q, z) = self.unroll_latents(u, steps, rng.as_mut());
        let aux = match train {
            Some(ctx) => self.losses(z, ctx),
            None => Vec::new(),
        };
        (q, aux)
    }

    /// The target network's unroll: Q [T, N, A], the embedding's dropout drawn from `seed`
    /// when it acts outside training updates (`dropout_when_acting`), else deterministic.
    pub fn unroll_target(&self, inputs: Vec<Tensor<2>>, seed: u64) -> Tensor<3> {
        let steps = inputs.len();
        self.unroll_target_stacked(Tensor::cat(inputs, 0), steps, seed)
    }

    /// [`unroll_target`](Self::unroll_target) of the steps stacked time-major, u [T * N, in].
    pub fn unroll_target_stacked(&self, u: Tensor<2>, steps: usize, seed: u64) -> Tensor<3> {
        let mut rng = self.drops_out_when_acting().then(|| LearnRng::seed_from(seed ^ 0x7A56_0000_0000_0001));
        self.unroll_latents(u, steps, rng.as_mut()).0
    }

    /// Q [T, N, A] and the latents z [T, N, L] of an unroll from zero states, u [T * N, in]
    /// time-major.
    fn unroll_latents(&self, u: Tensor<2>, t_len: usize, rng: Option<&mut LearnRng>) -> (Tensor<3>, Tensor<3>) {
        assert!(t_len > 0, "unroll needs at least one step");
        let z = self.latents_stacked(u.clone(), t_len, rng);
        let [_, n, l] = z.dims();
        let q = self.agent.unroll_stacked(self.agent_input(u, z.clone().reshape([t_len * n, l])), t_len);
        (q, z)
    }

    /// The latent z of every step, one tensor per step (`rng`: dropout, in training).
    pub fn latent(&self, inputs: &[Tensor<2>], rng: Option<&mut LearnRng>) -> Vec<Tensor<2>> {
        let z = self.latents(inputs, rng);
        let [_, n, l] = z.dims();
        z.split(1, 0).into_iter().map(|z_t| z_t.reshape([n, l])).collect()
    }

    /// The latent z of every step, [T, N, L] (`rng`: dropout, in training).
    pub fn latents(&self, inputs: &[Tensor<2>], rng: Option<&mut LearnRng>) -> Tensor<3> {
        self.latents_stacked(Tensor::cat(inputs.to_vec(), 0), inputs.len(), rng)
    }

    /// [`latents`](Self::latents) of the steps stacked time-major, u [T * N, in]. The embedding
    /// and everything else that does not depend on the encoder's recurrence is one matmul per
    /// layer over all steps; dropout draws in the per-step order, since rows are time-major.
    fn latents_stacked(&self, u: Tensor<2>, t_len: usize, rng: Option<&mut LearnRng>) -> Tensor<3> {
        let n = u.dims()[0] / t_len;
        let e = self.embed_dim();
        let x = self.embed(u, rng);
        let z = match &self.encoder {
            // The recurrence is one fused operation over all steps, and the gate reads only x
            // and h, so it runs once after it.
            Encoder::GruGate(g) => {
                let cs = g.gru.sequence_carry(x.clone(), t_len).reshape([t_len * n, e]);
                gate(g, x, cs)
            }
            // No recurrence: the attention runs over all steps at once.
            Encoder::Window(w) => window_attend_all(w, x.reshape([t_len, n, e])),
        };
        let l = z.dims()[1];
        z.reshape([t_len, n, l])
    }

    /// Decode the latent: (s_hat, xi_hat logits), each [.., critical dims] (deterministic).
    pub fn decode(&self, z: Tensor<3>) -> (Tensor<3>, Tensor<3>) {
        self.decode_with(z, None)
    }

    /// [`decode`](Self::decode) with the `released` layout's dropout when `rng` is given.
    fn decode_with(&self, z: Tensor<3>, rng: Option<&mut LearnRng>) -> (Tensor<3>, Tensor<3>) {
        let [t, n, l] = z.dims();
        let drop = rng.filter(|_| self.cfg.settings.aux_layout == AuxLayout::Released).map(|r| (self.cfg.settings.dropout, r));
        let h1 = dense(&self.dec1, z.reshape([t * n, l]), None, Activation::Relu, drop);
        let h = dense(&self.dec2, h1, None, Activation::Relu, None);
        let dc = self.cfg.critical_dims.len();
        let s_hat = dense(&self.dec_state, h.clone(), None, Activation::Identity, None).reshape([t, n, dc]);
        (s_hat, dense(&self.dec_meta, h, None, Activation::Identity, None).reshape([t, n, dc]))
    }

    /// The cycle encoder: z_hat from (s_hat, sigmoid(xi_hat)) (deterministic).
    pub fn cycle(&self, s_hat: Tensor<3>, xi_logit: Tensor<3>) -> Tensor<3> {
        self.cycle_with(s_hat, xi_logit, None)
    }

    /// [`cycle`](Self::cycle) with the `released` layout's dropout when `rng` is given.
    fn cycle_with(&self, s_hat: Tensor<3>, xi_logit: Tensor<3>, rng: Option<&mut LearnRng>) -> Tensor<3> {
        let [t, n, dc] = s_hat.dims();
        let h = dense(&self.cycle1, Tensor::cat(vec![s_hat, sigmoid(xi_logit)], 2).reshape([t * n, 2 * dc]), None, Activation::Relu, None);
        let h = match (&self.cycle_norm, &self.cycle_mid) {
            (Some(norm), Some(mid)) => dense(mid, h, Some(norm), Activation::Relu, rng.map(|r| (self.cfg.settings.dropout, r))),
            _ => h,
        };
        let z_hat = dense(&self.cycle2, h, None, Activation::Identity, None);
        let l = z_hat.dims()[1];
        z_hat.reshape([t, n, l])
    }

    /// z [T, N, L] with N = B * n (batch-major rows); the context's state and mask are per
    /// (t, b) row.
    pub fn losses(&self, z: Tensor<3>, ctx: &TrainContext) -> Vec<AuxTerm> {
        let [t, n_rows, _] = z.dims();
        let (b, n) = (ctx.b, ctx.n_agents);
        assert_eq!(n_rows, b * n, "rows are batch x agents");
        let dc = self.cfg.critical_dims.len();
        let device = z.device();
        let s = &self.cfg.settings;
        // The decoder's and cycle encoder's dropout draws (released layout), apart from the
        // embedding's so either can change without moving the other.
        let mut rng = LearnRng::seed_from(ctx.seed ^ 0xDEC0_0000_0000_0001);
        let (s_hat, xi_logit) = self.decode_with(z.clone(), Some(&mut rng));
        let s_hat = s_hat.reshape([t, b, n, dc]);
        let xi_logit = xi_logit.reshape([t, b, n, dc]);
        let idx: Tensor<1, Int> =
            Tensor::from_data(TensorData::new(self.cfg.critical_dims.iter().map(|&d| d as i64).collect::<Vec<_>>(), [dc]), &device);
        let target = ctx.state.clone().select(1, idx).reshape([t, b, 1, dc]).expand([t, b, n, dc]);
        let mask = ctx.mask.clone().reshape([t, b, 1, 1]);
        let denom = ctx.mask_sum * (n * dc) as f32;

        let sq = (s_hat.clone() - target).square();
        let mse = (sq.clone() * mask.clone()).sum().div_scalar(denom);
        // xi = 1[(s_hat - s)^2 <= alpha], a target without gradient.
        let xi = sq.detach().lower_equal_elem(self.cfg.alpha as f32).float();
        // BCE with logits, stable: max(l, 0) - l * xi + log(1 + exp(-|l|)).
        let bce = relu(xi_logit.clone()) - xi_logit.clone() * xi.clone() + xi_logit.clone().abs().neg().exp().log1p();
        let bce = (bce * mask.clone()).sum().div_scalar(denom);
        let recon = mse.clone() + bce.clone().mul_scalar(s.lambda_meta);

        let z_hat = self.cycle_with(s_hat.reshape([t, n_rows, dc]), xi_logit.clone().reshape([t, n_rows, dc]), Some(&mut rng));
        // The latent's size: the consistency loss alone is smallest for a z shrunk towards 0,
        // so its value only means something next to ||z||^2.
        let z_sq = (z.clone().detach().square().sum_dim(2).reshape([t, b, n, 1]) * mask.clone()).sum().div_scalar(ctx.mask_sum * n as f32);
        let z_target = if s.detach_consistency_target { z.detach() } else { z };
        let sq_z = (z_hat - z_target).square();
        let cyc = match s.consistency_over_latent {
            LatentReduction::Mean => sq_z.mean_dim(2),
            LatentReduction::Sum => sq_z.sum_dim(2),
        }
        .reshape([t, b, n, 1]);
        // Unmasked, the mean over every step of the whole batch, padding included (the released
        // code's `mean()`), as a sum over this context's episodes over the whole batch's count.
        let cons = if s.mask_consistency {
            (cyc * mask.clone()).sum().div_scalar(ctx.mask_sum * n as f32)
        } else {
            cyc.sum().div_scalar((t * ctx.batch_episodes * n) as f32)
        };

        let scalar = |x: &Tensor<1>| x.clone().detach().into_scalar::<f32>();
        let recovered = scalar(&(xi * mask.clone()).sum().div_scalar(denom));
        let reliability = scalar(&(sigmoid(xi_logit.detach()) * mask).sum().div_scalar(denom));
        vec![
            AuxTerm { name: "lmac_recon_mse", value: scalar(&mse), loss: Some(recon) },
            AuxTerm { name: "lmac_meta_bce", value: scalar(&bce), loss: None },
            AuxTerm { name: "lmac_cons", value: scalar(&cons), loss: Some(cons.mul_scalar(s.lambda_cons)) },
            AuxTerm { name: "lmac_recovered", value: recovered, loss: None },
            AuxTerm { name: "lmac_reliability", value: reliability, loss: None },
            AuxTerm { name: "lmac_z_sq", value: z_sq.into_scalar::<f32>(), loss: None },
        ]
    }
}

/// z = sigmoid(W_q x . W_k c) * W_v c, c = h + x the carried state. The key and value are one
/// gemm (both read c), and the gate's arithmetic one operation (`latent_gate`).
fn gate(g: &GruGateEncoder, x: Tensor<2>, c: Tensor<2>) -> Tensor<2> {
    let q = dense(&g.query, x, None, Activation::Identity, None);
    let bias = |l: &Linear| l.bias.as_ref().expect("the gate's layers have biases").val();
    let w_kv = Tensor::cat(vec![g.key.weight.val(), g.value.weight.val()], 1);
    let b_kv = Tensor::cat(vec![bias(&g.key), bias(&g.value)], 0);
    latent_gate(q, dense_with(w_kv, b_kv, c, None, Activation::Identity, None))
}

/// Multi-head scaled dot-product attention from `x` (the current embedding) to `entries`
/// (newest first); `valid[o]` [N, 1] says which rows have entry o.
fn window_attend(w: &WindowEncoder, x: Tensor<2>, entries: &[Tensor<2>], valid: &[Tensor<2, Bool>]) -> Tensor<2> {
    let n = x.dims()[0];
    let a = w.query.weight.dims()[1];
    let (h, dh) = (w.heads, a / w.heads);
    let q = w.query.forward(x).reshape([n, h, dh]);
    let stacked = Tensor::cat(entries.to_vec(), 0); // [W * N, E]: one matmul for all entries
    let k = w.key.forward(stacked.clone()).reshape([w.window, n, h, dh]);
    let v = w.value.forward(stacked).reshape([w.window, n, h, dh]);
    let scores = (k * q.unsqueeze_dim::<4>(0)).sum_dim(3).reshape([w.window, n, h]).div_scalar((dh as f32).sqrt());
    let valid: Tensor<3, Bool> = Tensor::stack::<3>(valid.to_vec(), 0).expand([w.window, n, h]);
    let scores = scores.mask_fill(valid.bool_not(), -1e9);
    let att = softmax(scores, 0).reshape([w.window, n, h, 1]);
    let out = (att * v).sum_dim(0).reshape([n, a]);
    w.out.forward(out)
}

/// [`window_attend`] for all T steps of an unroll at once: x [T, N, E] (time-major) ->
/// z [T * N, L]. Query, key and value are one matmul each over all steps; the windowed
/// attention itself is one operation with a hand-written backward (`learn::window_attention`;
/// entries older than the unroll's first step are not attended to, as the per-step form masks
/// them).
fn window_attend_all(w: &WindowEncoder, x: Tensor<3>) -> Tensor<2> {
    let [t, n, _] = x.dims();
    let a = w.query.weight.dims()[1];
    let q = linear_rows(&w.query, x.clone());
    let k = linear_rows(&w.key, x.clone());
    let v = linear_rows(&w.value, x);
    let out = window_attention(q, k, v, w.heads, w.window);
    w.out.forward(out.reshape([t * n, a]))
}
