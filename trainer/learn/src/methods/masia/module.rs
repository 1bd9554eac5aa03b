//! The MASIA network (one set of parameters shared by all agents). Per step, with u_i agent i's
//! input row without its last-action block (observation o_i, id e_i) and N = B * n batch-major
//! rows (an environment's n agents contiguous):
//! - encoder: [q_i | k_i | v_i] = W u_i, a_i = sum_j softmax_j(q_i . k_j / sqrt(d)) v_j,
//!   g_i = GRU(a_i, g_i'), z = [W_z g_1 | .. | W_z g_n] (one per environment);
//! - agent: x_i = [W_o o_i | sigmoid(W_g u_i) * z | e_i], Q_i = RNN(x_i) (pymarl's agent);
//! - training only: the decoder W_d z -> state; the transition ẑ' = ẑ + F([E_z(ẑ) | E_a(a_1 ..
//!   a_n)]); the projection P, prediction head C and reward head R; the target encoder and target
//!   projection, momentum copies of the encoder and of P (no gradient).
//!
//! The recurrent state of an agent-row is [g_i | h_i]: the encoder's GRU state, then the agent's.

use burn::module::{Module, ModuleMapper, ModuleVisitor, Param, ParamId};
use burn::nn::Linear;
use burn::tensor::activation::{relu, sigmoid, softmax};
use burn::tensor::{Device, Int, Tensor, TensorData};

use super::MasiaConfig;
use crate::agent::{FusedGru, RnnAgent};
use crate::config::LearnConfig;
use crate::init::linear;
use crate::methods::{linear_rows, AuxTerm, MethodHooks, TrainContext};
use crate::{InputLayout, LearnRng};

/// Linear -> ReLU -> Linear.
#[derive(Module, Debug)]
pub struct Mlp {
    pub l1: Linear,
    pub l2: Linear,
}

impl Mlp {
    pub fn new(rng: &mut LearnRng, d_in: usize, hidden: usize, d_out: usize, device: &Device) -> Self {
        Mlp { l1: linear(rng, d_in, hidden, device), l2: linear(rng, hidden, d_out, device) }
    }

    pub fn forward<const D: usize>(&self, x: Tensor<D>) -> Tensor<D> {
        linear_rows(&self.l2, relu(linear_rows(&self.l1, x)))
    }
}

/// The message encoder: self-attention over an environment's agents, a GRU per agent, and a
/// linear map of each agent's GRU state to its latent dims.
#[derive(Module, Debug)]
pub struct AttentionEncoder {
    /// The query, key and value maps, fused: output [query | key | value].
    pub qkv: Linear,
    pub gru: FusedGru,
    pub out: Linear,
    pub n_agents: usize,
    pub attention_dim: usize,
    pub latent_dim: usize,
}

impl AttentionEncoder {
    pub fn new(rng: &mut LearnRng, d_in: usize, attention: usize, hidden: usize, latent: usize, n: usize, device: &Device) -> Self {
        AttentionEncoder {
            qkv: linear(rng, d_in, 2 * attention + hidden, device),
            gru: FusedGru::new(rng, hidden, hidden, device),
            out: linear(rng, hidden, latent, device),
            n_agents: n,
            attention_dim: attention,
            latent_dim: latent,
        }
    }

    /// Self-attention over each environment's agents: u [N, in] (N a multiple of n, rows of one
    /// environment together) -> the attended values [N, H] the GRU reads.
    fn attend(&self, u: Tensor<2>) -> Tensor<2> {
        let rows = u.dims()[0];
        let (n, d, hd) = (self.n_agents, self.attention_dim, self.gru.hidden_dim);
        let qkv = self.qkv.forward(u).reshape([rows / n, n, 2 * d + hd]);
        let q = qkv.clone().narrow(2, 0, d);
        let k = qkv.clone().narrow(2, d, d);
        let v = qkv.narrow(2, 2 * d, hd);
        let score = softmax(q.matmul(k.swap_dims(1, 2)).div_scalar((d as f32).sqrt()), 2);
        score.matmul(v).reshape([rows, hd])
    }

    /// One step: u [N, in], g [N, H] -> (z [N / n, n * L], g' [N, H]).
    pub fn step(&self, u: Tensor<2>, g: Tensor<2>) -> (Tensor<2>, Tensor<2>) {
        let groups = u.dims()[0] / self.n_agents;
        let g = self.gru.forward(self.attend(u), g);
        let z = self.out.forward(g.clone()).reshape([groups, self.n_agents * self.latent_dim]);
        (z, g)
    }

    /// Every step at once: u [T * N, in] (time-major rows) -> z [T * N / n, n * L], what
    /// stepping `step` from zero states gives, with the recurrence as one fused operation.
    pub fn sequence(&self, u: Tensor<2>, steps: usize) -> Tensor<2> {
        let rows = u.dims()[0];
        let g = self.gru.sequence(self.attend(u), steps).reshape([rows, self.gru.hidden_dim]);
        self.out.forward(g).reshape([rows / self.n_agents, self.n_agents * self.latent_dim])
    }
}

#[derive(Module, Debug)]
pub struct MasiaAgent {
    pub encoder: AttentionEncoder,
    pub decoder: Linear,
    pub gate: Linear,
    pub obs_embed: Linear,
    pub agent: RnnAgent,
    pub projection: Mlp,
    pub predictor: Mlp,
    pub action_embed: Linear,
    pub joint_action: Mlp,
    pub latent_embed: Mlp,
    pub transition: Mlp,
    pub reward: Mlp,
    /// Momentum copy of `encoder` (no gradient; refreshed by [`MasiaAgent::after_update`]).
    pub target_encoder: AttentionEncoder,
    /// Momentum copy of `projection`.
    pub target_projection: Mlp,
    /// Optimizer steps since the momentum copies were last refreshed, [1].
    pub since_refresh: Param<Tensor<1, Int>>,
    #[module(skip)]
    pub cfg: MasiaConfig,
    pub n_agents: usize,
    /// Row columns before the last-action block (the observation).
    pub own_cols: usize,
    /// Width of the row's last-action block, dropped (0: the row has none).
    pub dropped_cols: usize,
    /// Row columns after the last-action block (the agent id).
    pub extra_cols: usize,
}

/// A copy of `m` with fresh parameter ids whose parameters do not require grad.
fn frozen_copy<M: Module>(m: &M) -> M {
    struct Fresh;
    impl ModuleMapper for Fresh {
        fn map_float<const D: usize>(&mut self, p: Param<Tensor<D>>) -> Param<Tensor<D>> {
            let (_, t, _) = p.consume();
            Param::initialized(ParamId::new(), t.detach()).set_require_grad(false)
        }
    }
    m.clone().map(&mut Fresh)
}

/// target <- tau * online + (1 - tau) * target, parameter by parameter (the two modules have
/// the same structure), keeping the target's ids and its no-gradient setting.
fn blend<M: Module>(target: M, online: &M, tau: f32) -> M {
    struct Collect(Vec<Tensor<1>>);
    impl ModuleVisitor for Collect {
        fn visit_float<const D: usize>(&mut self, p: &Param<Tensor<D>>) {
            let v = p.val().detach();
            let n = v.shape().num_elements();
            self.0.push(v.reshape([n]));
        }
    }
    struct Blend(std::vec::IntoIter<Tensor<1>>, f32);
    impl ModuleMapper for Blend {
        fn map_float<const D: usize>(&mut self, p: Param<Tensor<D>>) -> Param<Tensor<D>> {
            let src = self.0.next().expect("the momentum copy has the online module's structure");
            let tau = self.1;
            p.map(|t| {
                let src: Tensor<D> = src.reshape(t.dims());
                let v = if tau >= 1.0 { src } else { src.mul_scalar(tau) + t.detach().mul_scalar(1.0 - tau) };
                v.detach().set_require_grad(false)
            })
        }
    }
    let mut c = Collect(Vec::new());
    online.visit(&mut c);
    target.map(&mut Blend(c.0.into_iter(), tau))
}

/// What the unroll keeps for the losses (training only).
struct Trace {
    /// z [T, B, n * L]; the rows the encoder read [T * N, in'] and the gates [T * N, n * L]
    /// (detached), time-major.
    z: Tensor<3>,
    rows: Tensor<2>,
    gates: Tensor<2>,
}

impl MethodHooks for MasiaAgent {
    fn rnn_agent_mut(&mut self) -> Option<&mut RnnAgent> {
        Some(&mut self.agent)
    }

    /// Moves the momentum target encoder ([`MasiaAgent::after_update`]).
    fn after_update(self) -> Self {
        MasiaAgent::after_update(self)
    }
}

impl MasiaAgent {
    pub fn new(rng: &mut LearnRng, cfg: &MasiaConfig, layout: &InputLayout, learn: &LearnConfig, device: &Device) -> Self {
        let s = &cfg.settings;
        let d = &layout.dims;
        let (n, a) = (d.n_agents, d.n_actions);
        let dropped = if layout.last_action { a } else { 0 };
        let extra = layout.messages + if layout.agent_id { n } else { 0 };
        let own = layout.width() - dropped - extra;
        let iw = own + extra;
        let z = n * s.latent_dim;
        let (mh, ph) = (s.model_hidden, s.projection_hidden);
        let encoder = AttentionEncoder::new(rng, iw, s.attention_dim, s.encoder_hidden, s.latent_dim, n, device);
        let projection = Mlp::new(rng, z, ph, s.projection_dim, device);
        MasiaAgent {
            decoder: linear(rng, z, d.state_dim, device),
            gate: linear(rng, iw, z, device),
            obs_embed: linear(rng, own, s.obs_embed, device),
            agent: RnnAgent::new(rng, s.obs_embed + z + extra, learn.rnn_hidden_dim, a, device),
            predictor: Mlp::new(rng, s.projection_dim, ph, s.projection_dim, device),
            action_embed: linear(rng, a, s.action_embed, device),
            joint_action: Mlp::new(rng, n * s.action_embed, mh, mh, device),
            latent_embed: Mlp::new(rng, z, mh, mh, device),
            transition: Mlp::new(rng, 2 * mh, mh, z, device),
            reward: Mlp::new(rng, z, mh, 1, device),
            target_encoder: frozen_copy(&encoder),
            target_projection: frozen_copy(&projection),
            since_refresh: Param::initialized(ParamId::new(), Tensor::zeros([1], device)),
            encoder,
            projection,
            cfg: cfg.clone(),
            n_agents: n,
            own_cols: own,
            dropped_cols: dropped,
            extra_cols: extra,
        }
    }

    /// The encoder's GRU state, then the agent's.
    pub fn state_width(&self) -> usize {
        self.encoder.gru.hidden_dim + self.agent.hidden_dim
    }

    /// A row without its last-action block, and its two parts: (row, observation, id).
    pub fn split_row(&self, u: Tensor<2>) -> (Tensor<2>, Tensor<2>, Option<Tensor<2>>) {
        let own = u.clone().narrow(1, 0, self.own_cols);
        let extra = (self.extra_cols > 0).then(|| u.clone().narrow(1, self.own_cols + self.dropped_cols, self.extra_cols));
        let row = match (&extra, self.dropped_cols) {
            (_, 0) => u,
            (Some(e), _) => Tensor::cat(vec![own.clone(), e.clone()], 1),
            (None, _) => own.clone(),
        };
        (row, own, extra)
    }

    /// The agent network's input for one step: [W_o o_i | sigmoid(W_g u_i) * z | e_i], and the
    /// gate. z [B, n * L] is broadcast to the environment's n rows.
    fn agent_input(&self, row: Tensor<2>, own: Tensor<2>, extra: Option<Tensor<2>>, z: Tensor<2>) -> (Tensor<2>, Tensor<2>) {
        let [rows, _] = row.dims();
        let (b, w) = (z.dims()[0], z.dims()[1]);
        let gate = sigmoid(self.gate.forward(row));
        let z_rows = z.reshape([b, 1, w]).expand([b, self.n_agents, w]).reshape([rows, w]);
        let mut parts = vec![self.obs_embed.forward(own), gate.clone() * z_rows];
        parts.extend(extra);
        (Tensor::cat(parts, 1), gate)
    }

    /// One acting step: u [N, in], state [N, G + H] -> (q [N, A], state').
    pub fn step(&self, u: Tensor<2>, state: Tensor<2>) -> (Tensor<2>, Tensor<2>) {
        let [rows, _] = state.dims();
        let gw = self.encoder.gru.hidden_dim;
        let g = state.clone().narrow(1, 0, gw);
        let h = state.narrow(1, gw, self.agent.hidden_dim);
        let (row, own, extra) = self.split_row(u);
        let (z, g) = self.encoder.step(row.clone(), g);
        let (x, _) = self.agent_input(row, own, extra, z);
        let (q, h) = self.agent.step(x, h);
        debug_assert_eq!(q.dims()[0], rows);
        (q, Tensor::cat(vec![g, h], 1))
    }

    /// Unroll from zero states; in training (`train`) the self-supervised losses are returned.
    /// Every step at once (time-major rows): the encoder's and the agent's recurrences are each
    /// one fused operation, everything else one op over all steps.
    pub fn unroll(&self, inputs: Vec<Tensor<2>>, train: Option<&TrainContext>) -> (Tensor<3>, Vec<AuxTerm>) {
        assert!(!inputs.is_empty(), "unroll needs at least one step");
        let t_len = inputs.len();
        let (row, own, extra) = self.split_row(Tensor::cat(inputs, 0));
        let z = self.encoder.sequence(row.clone(), t_len);
        let (x, gate) = self.agent_input(row.clone(), own, extra, z.clone());
        let hs = self.agent.gru.sequence(relu(self.agent.fc1.forward(x)), t_len);
        let q = linear_rows(&self.agent.fc2, hs);
        let aux = match train {
            Some(ctx) => {
                let [groups, w] = z.dims();
                let trace = Trace { z: z.reshape([t_len, groups / t_len, w]), rows: row, gates: gate.detach() };
                self.losses(trace, ctx)
            }
            None => Vec::new(),
        };
        (q, aux)
    }

    /// The projections of the momentum target encoder's z' over the batch, [T, B, P]: constants,
    /// computed without autodiff (the copies do not train). `rows` [T * N, in'], time-major.
    fn target_projections(&self, rows: Tensor<2>, steps: usize) -> Tensor<3> {
        let (encoder, projection) = (self.target_encoder.valid(), self.target_projection.valid());
        let z = encoder.sequence(rows.inner(), steps);
        let [groups, w] = z.dims();
        projection.forward(z.reshape([steps, groups / steps, w]))
    }

    /// ẑ' = ẑ + F([E_z(ẑ) | E_a(a)]): z [T', B, n * L], actions one-hot [T', B, n, A].
    fn advance(&self, z: Tensor<3>, actions: Tensor<4>) -> Tensor<3> {
        let [t, b, n, _] = actions.dims();
        let ae = relu(linear_rows(&self.action_embed, actions)).reshape([t, b, n * self.cfg.settings.action_embed]);
        let x = Tensor::cat(vec![self.latent_embed.forward(z.clone()), self.joint_action.forward(ae)], 2);
        z + self.transition.forward(x)
    }

    fn losses(&self, tr: Trace, ctx: &TrainContext) -> Vec<AuxTerm> {
        let s = &self.cfg.settings;
        let (b, n) = (ctx.b, self.n_agents);
        assert_eq!(ctx.n_agents, n, "the context's agent count");
        let t = tr.z.dims()[0];
        let a = self.agent.n_actions;
        let scalar = |x: &Tensor<1>| x.clone().detach().into_scalar::<f32>();
        let mask_host: Vec<f32> = ctx.mask.clone().detach().into_data().iter::<f32>().collect();
        assert_eq!(mask_host.len(), t * b, "the mask is [T * B]");
        let mask: Tensor<3> = ctx.mask.clone().reshape([t, b, 1]);
        let z = tr.z;

        // Reconstruction of the state: squared error averaged over its dims.
        let sd = ctx.state.dims()[1];
        let state: Tensor<3> = ctx.state.clone().reshape([t, b, sd]);
        let recon = linear_rows(&self.decoder, z.clone()).sub(state).square().mean_dim(2);
        let recon = masked_mean(recon, &mask, &mask_host, b, 0);

        // Latent and reward prediction, k = 0 .. pred_len steps ahead.
        let reward = ctx.reward.as_ref().expect("MASIA's reward prediction reads the batch's rewards (TrainContext::reward)");
        let reward: Tensor<3> = reward.clone().reshape([t, b, 1]);
        let taken = ctx.actions.as_ref().expect("MASIA's transition model reads the batch's actions (TrainContext::actions)").taken.clone();
        let onehot: Tensor<4> = taken.reshape([t * b * n]).one_hot::<2>(a).float().reshape([t, b, n, a]);
        let target = self.target_projections(tr.rows, t);
        let predicted = rollout(z, s.pred_len, |cur, first, len| self.advance(cur, onehot.clone().narrow(0, first, len)));
        let mut latent: Option<Tensor<1>> = None;
        let mut rew: Option<Tensor<1>> = None;
        for (k, zk) in predicted.into_iter().enumerate() {
            let len = t - k;
            let p = self.predictor.forward(self.projection.forward(zk.clone()));
            let err = (p - target.clone().narrow(0, k, len)).square().sum_dim(2);
            let l = masked_mean(err, &mask, &mask_host, b, k);
            latent = Some(match latent {
                Some(acc) => acc + l,
                None => l,
            });
            let err = (self.reward.forward(zk) - reward.clone().narrow(0, k, len)).square();
            let l = masked_mean(err, &mask, &mask_host, b, k);
            rew = Some(match rew {
                Some(acc) => acc + l,
                None => l,
            });
        }
        let (latent, rew) = (latent.expect("k = 0 is always predicted"), rew.expect("k = 0 is always predicted"));

        // Diagnostic: the mean gate over the trained rows.
        let gates: Tensor<3> = tr.gates.reshape([t, b, n * n * s.latent_dim]);
        let gate_mean = scalar(&(gates.mean_dim(2) * mask).sum()) / ctx.mask_sum;
        vec![
            AuxTerm { name: "masia_recon", value: scalar(&recon), loss: Some(recon.mul_scalar(s.recon_weight)) },
            AuxTerm { name: "masia_latent", value: scalar(&latent), loss: Some(latent.mul_scalar(s.latent_weight)) },
            AuxTerm { name: "masia_reward", value: scalar(&rew), loss: Some(rew.mul_scalar(s.reward_weight)) },
            AuxTerm { name: "masia_gate_mean", value: gate_mean, loss: None },
        ]
    }

    /// After each optimizer step: count it, and every `momentum_interval` steps refresh the
    /// momentum copies, target <- tau * online + (1 - tau) * target.
    pub fn after_update(mut self) -> Self {
        let s = &self.cfg.settings;
        let device = self.since_refresh.val().device();
        let count = self.since_refresh.val().into_scalar::<i64>() + 1;
        let count = if count as u64 >= s.momentum_interval {
            let tau = s.momentum_tau;
            self.target_encoder = blend(self.target_encoder, &self.encoder, tau);
            self.target_projection = blend(self.target_projection, &self.projection, tau);
            0
        } else {
            count
        };
        let id = self.since_refresh.id;
        self.since_refresh = Param::initialized(id, Tensor::from_data(TensorData::new(vec![count], [1]), &device));
        self
    }
}

/// The latents predicted k = 0 ..= `steps` steps ahead (fewer when the batch is shorter than
/// `steps + 1`): element k is [T - k, B, L], its row t predicting step t + k from z_t and the
/// actions of steps t .. t + k - 1. `advance(z, first, len)` applies the transition model to
/// `len` latents with the actions of steps `first .. first + len`.
pub fn rollout(z: Tensor<3>, steps: usize, mut advance: impl FnMut(Tensor<3>, usize, usize) -> Tensor<3>) -> Vec<Tensor<3>> {
    let t = z.dims()[0];
    let mut out = vec![z];
    for k in 1..=steps.min(t.saturating_sub(1)) {
        // Row t of the previous element predicts step t + k - 1; the rows whose step t + k is
        // still in the batch are the first T - k, and they take the actions of steps k - 1 ..
        let len = t - k;
        let prev = out[k - 1].clone().narrow(0, 0, len);
        out.push(advance(prev, k - 1, len));
    }
    out
}

/// The masked mean of `err` [T - k, B, 1], whose row t is about step t + k: each row weighted by
/// the mask of its step t + k (`mask` [T, B, 1]; `mask_host` the same on the host), divided by
/// that mask's sum (at least 1). The mask is 1 on a prefix of each episode, so a trained step
/// t + k implies trained steps (and real actions) t .. t + k.
pub fn masked_mean(err: Tensor<3>, mask: &Tensor<3>, mask_host: &[f32], b: usize, k: usize) -> Tensor<1> {
    let len = err.dims()[0];
    let m = mask.clone().narrow(0, k, len);
    let denom = mask_host[k * b..(k + len) * b].iter().sum::<f32>().max(1.0);
    (err * m).sum().div_scalar(denom)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::episode::EpisodeDims;
    use crate::methods::masia::MasiaSettings;

    fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
        t.into_data().iter::<f32>().collect()
    }

    fn tensor<const D: usize>(v: Vec<f32>, shape: [usize; D]) -> Tensor<D> {
        Tensor::from_data(TensorData::new(v, shape), &Device::default())
    }

    #[test]
    fn the_k_step_predictions_line_up_with_their_targets_and_masks() {
        // T = 4 steps, B = 2 environments, one latent dim. Environment 0 trains all four steps,
        // environment 1 only its first two (its episode ended).
        let (t, b) = (4, 2);
        let z = tensor(vec![1.0, 10.0, 2.0, 20.0, 3.0, 30.0, 4.0, 40.0], [t, b, 1]);
        // "Actions" a[s, e]; the transition adds the action of the step it advances from.
        let act = tensor(vec![0.5, 5.0, 0.25, 2.5, 0.125, 1.25, 0.0, 0.0], [t, b, 1]);
        let preds = rollout(z, 2, |cur, first, len| cur + act.clone().narrow(0, first, len));
        assert_eq!(preds.len(), 3);
        // k = 1: row s predicts step s + 1 from z_s + a_s.
        assert_eq!(values(preds[1].clone()), vec![1.5, 15.0, 2.25, 22.5, 3.125, 31.25]);
        // k = 2: z_s + a_s + a_{s+1}.
        assert_eq!(values(preds[2].clone()), vec![1.75, 17.5, 2.375, 23.75]);
        // Only as many steps ahead as the batch holds.
        assert_eq!(rollout(tensor(vec![1.0, 2.0], [1, 2, 1]), 2, |c, _, _| c).len(), 1);

        let mask_host = vec![1.0, 1.0, 1.0, 1.0, 1.0, 0.0, 1.0, 0.0];
        let mask = tensor(mask_host.clone(), [t, b, 1]);
        // Targets: step s of environment e.
        let target = tensor(vec![1.0, 10.0, 2.0, 20.0, 3.0, 30.0, 4.0, 40.0], [t, b, 1]);
        let err = |k: usize, p: &Tensor<3>| (p.clone() - target.clone().narrow(0, k, t - k)).square();
        // k = 1: environment 0 errors (1.5-2)^2, (2.25-3)^2, (3.125-4)^2; environment 1 only its
        // step 1 ((15-20)^2): its steps 2 and 3 are not trained. 4 rows count.
        let want1 = (0.25 + 0.5625 + 0.765625 + 25.0) / 4.0;
        let got1 = values(masked_mean(err(1, &preds[1]), &mask, &mask_host, b, 1))[0];
        assert!((got1 - want1).abs() < 1e-6, "{got1} vs {want1}");
        // k = 2: environment 0 targets steps 2, 3 ((1.75-3)^2, (2.375-4)^2); environment 1 none.
        let want2 = (1.5625 + 2.640625) / 2.0;
        let got2 = values(masked_mean(err(2, &preds[2]), &mask, &mask_host, b, 2))[0];
        assert!((got2 - want2).abs() < 1e-6, "{got2} vs {want2}");
        // k = 0 is the plain masked mean over the 6 trained steps (all zero here).
        assert_eq!(values(masked_mean(err(0, &preds[0]), &mask, &mask_host, b, 0)), vec![0.0]);
        // A term without any trained target step is 0, not NaN.
        let none = vec![0.0; t * b];
        assert_eq!(values(masked_mean(err(2, &preds[2]), &tensor(none.clone(), [t, b, 1]), &none, b, 2)), vec![0.0]);
    }

    fn agent(settings: MasiaSettings, device: &Device) -> (MasiaAgent, InputLayout) {
        let dims = EpisodeDims { n_agents: 3, obs_width: 4, state_dim: 5, n_actions: 2 };
        let learn = LearnConfig::default();
        let layout = InputLayout::new(dims, &learn);
        (MasiaAgent::new(&mut LearnRng::seed_from(3), &super::super::MasiaConfig { settings }, &layout, &learn, device), layout)
    }

    fn first_weight(e: &AttentionEncoder) -> Vec<f32> {
        values(e.qkv.weight.val()).into_iter().take(4).collect()
    }

    #[test]
    fn the_momentum_copy_refreshes_on_its_schedule_and_trains_no_parameter() {
        let device = Device::default().autodiff();
        let settings = MasiaSettings { momentum_interval: 2, momentum_tau: 0.5, ..Default::default() };
        let (mut a, _) = agent(settings, &device);
        assert!(
            !a.target_encoder.qkv.weight.val().is_require_grad() && !a.target_projection.l1.bias.as_ref().unwrap().val().is_require_grad()
        );
        assert!(a.encoder.qkv.weight.val().is_require_grad());
        assert_ne!(a.target_encoder.qkv.weight.id, a.encoder.qkv.weight.id, "own parameter ids");
        let w0 = first_weight(&a.encoder);
        assert_eq!(first_weight(&a.target_encoder), w0, "starts as a copy");
        // Move the online encoder by +1 (as an optimizer step would), then two updates.
        struct Shift;
        impl ModuleMapper for Shift {
            fn map_float<const D: usize>(&mut self, p: Param<Tensor<D>>) -> Param<Tensor<D>> {
                p.map(|t| t.add_scalar(1.0))
            }
        }
        a.encoder = a.encoder.map(&mut Shift);
        a = a.after_update();
        assert_eq!(first_weight(&a.target_encoder), w0, "not refreshed after one update");
        a = a.after_update();
        for (got, w) in first_weight(&a.target_encoder).iter().zip(&w0) {
            assert!((got - (w + 0.5)).abs() < 1e-6, "half way: {got} vs {}", w + 0.5);
        }
        assert!(!a.target_encoder.qkv.weight.val().is_require_grad(), "still no gradient");
        assert_eq!(a.since_refresh.val().into_scalar::<i64>(), 0);
    }

    #[test]
    fn a_checkpoint_keeps_the_momentum_copy_and_its_count() {
        use crate::methods::{AgentConfig, AgentNet};
        use crate::Learner;
        let dims = EpisodeDims { n_agents: 2, obs_width: 3, state_dim: 4, n_actions: 3 };
        let learn = LearnConfig { batch_size: 4, buffer_size: 8, seed: 2, ..LearnConfig::default() };
        let settings = MasiaSettings { momentum_interval: 2, momentum_tau: 0.5, ..Default::default() };
        let mut l =
            Learner::with_agent(dims, learn, AgentConfig::Masia(super::super::MasiaConfig { settings }), Device::default()).unwrap();
        let mut rng = LearnRng::seed_from(4);
        for i in 0..6 {
            l.add_episode(crate::episode::Episode::synthetic(&dims, 2 + i % 3, &mut rng, false)).unwrap();
        }
        for _ in 0..3 {
            l.train_step().unwrap(); // refreshed after the second, one update counted since
        }
        let parts = |l: &Learner| match &l.online_net().agent {
            AgentNet::Masia(a) => (a.since_refresh.val().into_scalar::<i64>(), first_weight(&a.target_encoder), first_weight(&a.encoder)),
            _ => unreachable!("a MASIA learner"),
        };
        let before = parts(&l);
        assert_eq!(before.0, 1);
        assert_ne!(before.1, before.2, "the copy lags the online encoder");
        let dir = std::env::temp_dir().join(format!("lmac-masia-ck-{}", std::process::id()));
        l.save_checkpoint(&dir, true).unwrap();
        let mut r = Learner::load_checkpoint(&dir, Device::default()).unwrap();
        assert_eq!(parts(&r), before);
        // (A loaded network reads its tensors from the files lazily: the directory stays until the
        // end.) One more update refreshes the copy; saved again, it comes back as it was.
        r.train_step().unwrap();
        r.save_checkpoint(&dir, true).unwrap();
        r.save_checkpoint(&dir, true).unwrap();
        let r2 = Learner::load_checkpoint(&dir, Device::default()).unwrap();
        assert_eq!(parts(&r2), parts(&r));
        let _ = std::fs::remove_dir_all(&dir);
        match &r.online_net().agent {
            AgentNet::Masia(a) => {
                assert!(!a.target_encoder.out.weight.val().is_require_grad() && a.encoder.out.weight.val().is_require_grad())
            }
            _ => unreachable!("a MASIA learner"),
        }
    }

    #[test]
    fn the_last_action_columns_are_not_read() {
        let device = Device::default();
        let (a, layout) = agent(MasiaSettings::default(), &device);
        let (rows, iw) = (6, layout.width());
        assert_eq!((a.own_cols, a.dropped_cols, a.extra_cols), (4, 2, 3));
        let mut rng = LearnRng::seed_from(5);
        let x: Vec<f32> = (0..rows * iw).map(|_| rng.uniform()).collect();
        let mut y = x.clone();
        for r in 0..rows {
            y[r * iw + 4] += 3.0; // the last-action block: columns 4 and 5
            y[r * iw + 5] -= 2.0;
        }
        let h: Tensor<2> = Tensor::zeros([rows, a.state_width()], &device);
        let (q1, s1) = a.step(tensor(x, [rows, iw]), h.clone());
        let (q2, s2) = a.step(tensor(y, [rows, iw]), h);
        assert_eq!(values(q1), values(q2));
        assert_eq!(values(s1), values(s2));
    }

    #[test]
    fn each_environment_aggregates_only_its_own_agents() {
        let device = Device::default();
        let (a, layout) = agent(MasiaSettings::default(), &device);
        let (rows, iw) = (6, layout.width());
        let mut rng = LearnRng::seed_from(8);
        let x: Vec<f32> = (0..rows * iw).map(|_| rng.uniform()).collect();
        let mut y = x.clone();
        y[4 * iw] += 1.0; // an observation of environment 1's second agent
        let h: Tensor<2> = Tensor::zeros([rows, a.state_width()], &device);
        let q1 = values(a.step(tensor(x, [rows, iw]), h.clone()).0);
        let q2 = values(a.step(tensor(y, [rows, iw]), h).0);
        let per_env = 3 * 2;
        assert_eq!(q1[..per_env], q2[..per_env], "environment 0 is untouched");
        assert!(q1[per_env..].iter().zip(&q2[per_env..]).all(|(u, v)| u != v), "every agent of environment 1 hears it");
    }
}
