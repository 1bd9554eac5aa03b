//! The MAIC network (one set of parameters shared by all agents, the agent id one-hot in the
//! input). Per step, with n agents per environment and h_i agent i's GRU state:
//! - local     Q_i = W_out h_i,  h_i = GRU(relu(W_in u_i), h_i')          (pymarl's RNN agent)
//! - teammates (mu_i, log var_i) = E2 lrelu(BN(E1 h_i))                    [n * L each]
//!             z_ij = mu_ij (+ sqrt(var_ij) eps in training), var floored
//! - messages  m_ij = M2 lrelu(M1 [h_i | z_ij])                           (h_j with `receiver`)
//! - attention alpha_ij = softmax_{j != i}(W_q h_i . W_k z_ij / sqrt(att)), pruned outside training
//! - output    Q_j + sum_i alpha_ij m_ij
//! - inference q(z | h_i, a_j) = N(I2 lrelu(BN(I1 [h_i | onehot a_j])))   (training losses only)

use burn::module::{Module, Param, RunningState};
use burn::nn::Linear;
use burn::tensor::activation::{relu, softmax};
use burn::tensor::{Bool, Device, Int, Tensor, TensorData};

use super::{BatchNormMode, EntropyAttention, MaicConfig, MessageInput, MiAction, MiPairs};
use crate::agent::RnnAgent;
use crate::config::LearnConfig;
use crate::init::linear;
use crate::methods::{leaky_relu, linear_rows, standard_normal, AuxTerm, MethodHooks, TrainContext};
use crate::{InputLayout, LearnRng};

const LEAK: f64 = 0.01; // torch's LeakyReLU default
const BN_EPS: f32 = 1e-5;
const BN_MOMENTUM: f32 = 0.1;

/// Batch normalisation over the last dim whose training statistics can leave rows out (padded
/// steps), with torch's running statistics.
#[derive(Module, Debug)]
pub struct MaskedBatchNorm {
    pub gamma: Param<Tensor<1>>,
    pub beta: Param<Tensor<1>>,
    pub running_mean: RunningState<Tensor<1>>,
    pub running_var: RunningState<Tensor<1>>,
}

impl MaskedBatchNorm {
    pub fn new(features: usize, device: &Device) -> Self {
        MaskedBatchNorm {
            gamma: Param::from_tensor(Tensor::ones([features], device)),
            beta: Param::from_tensor(Tensor::zeros([features], device)),
            running_mean: RunningState::new(Tensor::zeros([features], device)),
            running_var: RunningState::new(Tensor::ones([features], device)),
        }
    }

    fn affine<const D: usize>(&self, x: Tensor<D>) -> Tensor<D> {
        x * self.gamma.val().unsqueeze::<D>() + self.beta.val().unsqueeze::<D>()
    }

    /// Training: x [T, R, F] normalised with the statistics of each step over the rows whose
    /// `mask` [T, R, 1] is 1 (biased variance, as torch), the other rows to 0 (before the
    /// affine map); `update` folds each step's statistics into the running ones, in step order.
    pub fn forward_masked(&self, x: Tensor<3>, mask: Tensor<3>, update: bool) -> Tensor<3> {
        let count = mask.clone().sum_dim(1); // [T, 1, 1]
        let denom = count.clone().clamp_min(1.0);
        let mean = (x.clone() * mask.clone()).sum_dim(1) / denom.clone();
        let centered = x - mean.clone();
        let var = (centered.clone().square() * mask.clone()).sum_dim(1) / denom;
        if update {
            self.update_running(mean.detach(), var.clone().detach(), count);
        }
        // Rows left out are set to the mean (normalised to 0): normalised with statistics they
        // took no part in, a padded row could reach any size, and an overflow further on would
        // reach the loss through `0 * inf`.
        self.affine(centered * mask / var.add_scalar(BN_EPS).sqrt())
    }

    /// Normalised with the statistics over `dim` (the released code's always-training mode for
    /// one forward pass's rows).
    pub fn forward_over<const D: usize>(&self, x: Tensor<D>, dim: usize) -> Tensor<D> {
        let mean = x.clone().mean_dim(dim);
        let centered = x - mean;
        let var = centered.clone().square().mean_dim(dim);
        self.affine(centered / var.add_scalar(BN_EPS).sqrt())
    }

    /// Normalised with the running statistics (torch's eval mode).
    pub fn forward_running<const D: usize>(&self, x: Tensor<D>) -> Tensor<D> {
        let mean = self.running_mean.value().unsqueeze::<D>();
        let var = self.running_var.value().unsqueeze::<D>();
        self.affine((x - mean) / var.add_scalar(BN_EPS).sqrt())
    }

    /// torch's update, once per step with rows: mean' = (1 - m) mean + m mean_t, and the same
    /// for the unbiased variance (steps with a single row leave the variance alone).
    fn update_running(&self, mean: Tensor<3>, var: Tensor<3>, count: Tensor<3>) {
        let f = mean.dims()[2];
        let host = |t: Tensor<3>| t.into_data().try_into_vec::<f32>().expect("f32 statistics");
        let (mean, var, count) = (host(mean), host(var), host(count));
        let rm_t = self.running_mean.value_sync();
        let device = rm_t.device();
        let mut rm = rm_t.into_data().try_into_vec::<f32>().expect("f32 running mean");
        let mut rv = self.running_var.value_sync().into_data().try_into_vec::<f32>().expect("f32 running var");
        for (t, &c) in count.iter().enumerate() {
            if c < 1.0 {
                continue;
            }
            for k in 0..f {
                rm[k] = (1.0 - BN_MOMENTUM) * rm[k] + BN_MOMENTUM * mean[t * f + k];
                if c > 1.0 {
                    rv[k] = (1.0 - BN_MOMENTUM) * rv[k] + BN_MOMENTUM * var[t * f + k] * c / (c - 1.0);
                }
            }
        }
        self.running_mean.update(Tensor::from_data(TensorData::new(rm, [f]), &device));
        self.running_var.update(Tensor::from_data(TensorData::new(rv, [f]), &device));
        // Fold the update in now, so a checkpoint written next holds it.
        let _ = (self.running_mean.value_sync(), self.running_var.value_sync());
    }
}

#[derive(Module, Debug)]
pub struct MaicAgent {
    pub agent: RnnAgent,
    pub embed1: Linear,
    pub embed_norm: MaskedBatchNorm,
    pub embed2: Linear,
    pub infer1: Linear,
    pub infer_norm: MaskedBatchNorm,
    pub infer2: Linear,
    pub msg1: Linear,
    pub msg2: Linear,
    pub query: Linear,
    pub key: Linear,
    #[module(skip)]
    pub cfg: MaicConfig,
    pub n_agents: usize,
}

/// What one forward pass after the GRU gives the losses (training only).
struct Internals {
    /// [T, B, n, n, L] latent means and variances of z_ij.
    mu: Tensor<5>,
    var: Tensor<5>,
    z: Tensor<5>,
    /// [T, B, n, n] attention weights (unpruned).
    alpha: Tensor<4>,
    /// [T, B, n, A] the incoming weighted messages.
    incoming: Tensor<4>,
}

impl MethodHooks for MaicAgent {
    fn rnn_agent_mut(&mut self) -> Option<&mut RnnAgent> {
        Some(&mut self.agent)
    }
}

impl MaicAgent {
    pub fn new(rng: &mut LearnRng, cfg: &MaicConfig, layout: &InputLayout, learn: &LearnConfig, device: &Device) -> Self {
        let s = &cfg.settings;
        let (n, a) = (layout.dims.n_agents, layout.dims.n_actions);
        let (h, k, l) = (learn.rnn_hidden_dim, s.hidden, s.latent_dim);
        MaicAgent {
            agent: RnnAgent::new(rng, layout.width(), h, a, device),
            embed1: linear(rng, h, k, device),
            embed_norm: MaskedBatchNorm::new(k, device),
            embed2: linear(rng, k, 2 * n * l, device),
            infer1: linear(rng, h + a, k, device),
            infer_norm: MaskedBatchNorm::new(k, device),
            infer2: linear(rng, k, 2 * l, device),
            msg1: linear(rng, h + l, k, device),
            msg2: linear(rng, k, a, device),
            query: linear(rng, h, s.attention_dim, device),
            key: linear(rng, l, s.attention_dim, device),
            cfg: cfg.clone(),
            n_agents: n,
        }
    }

    /// The agent GRU's hidden state.
    pub fn state_width(&self) -> usize {
        self.agent.hidden_dim
    }

    /// One acting step (test mode: latent means, pruned attention).
    pub fn step(&self, u: Tensor<2>, h: Tensor<2>) -> (Tensor<2>, Tensor<2>) {
        let [rows, hd] = h.dims();
        let h = self.agent.gru.forward(relu(self.agent.fc1.forward(u)), h);
        let (q, _) = self.heads(h.clone().reshape([1, rows, hd]), None);
        (q.reshape([rows, self.agent.n_actions]), h)
    }

    /// Unroll from zero states; in training (`train`) the latents are sampled with the update's
    /// seed and the MI and entropy losses are returned.
    pub fn unroll(&self, inputs: Vec<Tensor<2>>, train: Option<&TrainContext>) -> (Tensor<3>, Vec<AuxTerm>) {
        let hs = self.agent.hidden_states(&inputs);
        let mut rng = train.map(|c| LearnRng::seed_from(c.seed ^ 0x3A1C_0000_0000_0001));
        let (q, internals) = self.heads(hs.clone(), train.zip(rng.as_mut()));
        let aux = match (train, internals) {
            (Some(ctx), Some(int)) => self.losses(hs, q.clone(), int, ctx),
            _ => Vec::new(),
        };
        (q, aux)
    }

    /// Rows [T, N, 1] with the mask of their (t, b).
    fn row_mask(ctx: &TrainContext, t: usize, per_b: usize) -> Tensor<3> {
        ctx.mask.clone().reshape([t, ctx.b, 1]).expand([t, ctx.b, per_b]).reshape([t, ctx.b * per_b, 1])
    }

    /// Everything after the GRU, over all steps at once: h [T, N, H] -> Q [T, N, A]. `train`:
    /// sampled latents and training batch norm, and the internals the losses read.
    fn heads(&self, h: Tensor<3>, train: Option<(&TrainContext, &mut LearnRng)>) -> (Tensor<3>, Option<Internals>) {
        let [t, rows, hd] = h.dims();
        let s = &self.cfg.settings;
        let n = self.n_agents;
        let (b, l, a) = (rows / n, s.latent_dim, self.agent.n_actions);
        let device = h.device();
        let q_local = linear_rows(&self.agent.fc2, h.clone());

        // Teammate models.
        let e = linear_rows(&self.embed1, h.clone());
        let e = match (&train, s.batch_norm) {
            (Some((ctx, _)), mode) => self.embed_norm.forward_masked(e, Self::row_mask(ctx, t, n), mode == BatchNormMode::Running),
            (None, BatchNormMode::Running) => self.embed_norm.forward_running(e),
            (None, BatchNormMode::Batch) => self.embed_norm.forward_over(e.reshape([t, b, n, s.hidden]), 2).reshape([t, rows, s.hidden]),
        };
        let e = linear_rows(&self.embed2, leaky_relu(e, LEAK));
        let mu = e.clone().narrow(2, 0, n * l).reshape([t, b, n, n, l]);
        let var = e.narrow(2, n * l, n * l).exp().clamp_min(s.var_floor).reshape([t, b, n, n, l]);
        let (train, z) = match train {
            Some((ctx, rng)) => (Some(ctx), mu.clone() + var.clone().sqrt() * standard_normal(rng, [t, b, n, n, l], &device)),
            None => (None, mu.clone()),
        };

        // Messages m_ij from (h_i or h_j, z_ij): the first layer over [h | z_ij] is split into its
        // h part, computed once per agent and broadcast over the pairs, and its z part (the
        // same sums; n times fewer products than over the concatenated pair rows).
        let pair_axis = match s.message_input {
            MessageInput::Sender => 3,
            MessageInput::Receiver => 2,
        };
        let pre = pair_linear(&self.msg1, h.clone().reshape([t * b * n, hd]), z.clone(), [t, b, n], pair_axis);
        let msg = linear_rows(&self.msg2, leaky_relu(pre, LEAK)).reshape([t, b, n, n, a]);

        // Attention of each sender over its teammates.
        let alpha = self.attention(h.clone(), z.clone(), [t, b, n]);
        let used = match train {
            None => prune_attention(alpha.clone(), n, s.prune),
            Some(_) => alpha.clone(),
        };
        let incoming = (used.reshape([t, b, n, n, 1]) * msg).sum_dim(2).reshape([t, b, n, a]);
        let q = q_local + incoming.clone().reshape([t, rows, a]);
        let internals = train.map(|_| Internals { mu, var, z, alpha, incoming });
        (q, internals)
    }

    /// [T, B, n, n]: the unscaled scores W_q h_i . W_k z_ij.
    fn scores(&self, h: Tensor<3>, z: Tensor<5>, [t, b, n]: [usize; 3]) -> Tensor<4> {
        let att = self.cfg.settings.attention_dim;
        let query = linear_rows(&self.query, h).reshape([t, b, n, 1, att]);
        let key = linear_rows(&self.key, z);
        (query * key).sum_dim(4).reshape([t, b, n, n])
    }

    /// [T, B, n, n]: alpha_ij = softmax over j != i of W_q h_i . W_k z_ij / sqrt(att); 0 for j = i.
    fn attention(&self, h: Tensor<3>, z: Tensor<5>, [t, b, n]: [usize; 3]) -> Tensor<4> {
        let att = self.cfg.settings.attention_dim;
        let score = self.scores(h, z, [t, b, n]).div_scalar((att as f32).sqrt());
        let eye = eye_mask(n, &score.device()).reshape([1, 1, n, n]).expand([t, b, n, n]);
        // The explicit zero on the diagonal also covers n = 1 (no teammate: no message).
        let off: Tensor<4> = eye.clone().bool_not().float();
        softmax(score.mask_fill(eye, -1e9), 3) * off
    }

    fn losses(&self, h: Tensor<3>, q: Tensor<3>, int: Internals, ctx: &TrainContext) -> Vec<AuxTerm> {
        let [t, rows, hd] = h.dims();
        let s = &self.cfg.settings;
        let n = self.n_agents;
        assert_eq!(ctx.n_agents, n, "the context's agent count");
        let (b, l, a) = (ctx.b, s.latent_dim, self.agent.n_actions);
        assert_eq!(rows, b * n, "rows are batch x agents");
        let device = h.device();
        let pairs = (n * n.saturating_sub(1)).max(1) as f32;
        let off: Tensor<4> = eye_mask(n, &device).bool_not().float().reshape([1, 1, n, n]);
        let step_mask = ctx.mask.clone().reshape([t, b, 1, 1]);
        let scalar = |x: &Tensor<1>| x.clone().detach().into_scalar::<f32>();

        // MI: KL(N(mu, var) || q(z | h_i, a_j)) over the pairs i != j.
        let act: Tensor<2, Int> = match s.mi_action {
            MiAction::Taken => {
                ctx.actions.as_ref().expect("MAIC's MI loss reads the batch's actions (TrainContext::actions)").taken.clone()
            }
            MiAction::Greedy => q.detach().argmax(2).reshape([t, rows]),
        };
        let onehot = act.reshape([t * rows]).one_hot::<2>(a).float().reshape([t, b, 1, n, a]).expand([t, b, n, n, a]);
        let x = pair_linear(&self.infer1, h.clone().reshape([t * b * n, hd]), onehot, [t, b, n], 3).reshape([
            t,
            b * n * n,
            self.cfg.settings.hidden,
        ]);
        let x = self.infer_norm.forward_masked(x, Self::row_mask(ctx, t, n * n), s.batch_norm == BatchNormMode::Running);
        let x = linear_rows(&self.infer2, leaky_relu(x, LEAK)).reshape([t, b, n, n, 2 * l]);
        let mu2 = x.clone().narrow(4, 0, l);
        let var2 = x.narrow(4, l, l).exp().clamp_min(s.var_floor);
        let kl =
            (var2.clone().log() - int.var.clone().log()).mul_scalar(0.5) + (int.var + (int.mu - mu2).square()) / var2.mul_scalar(2.0) - 0.5;
        // The steps the losses average over: the trained ones, or (the released reduction)
        // every step of the batch.
        let (loss_steps, steps) =
            if s.mask_losses { (step_mask.clone(), ctx.mask_sum) } else { (Tensor::ones([t, b, 1, 1], &device), (t * b) as f32) };
        let kl = kl.sum_dim(4).reshape([t, b, n, n]);
        let (mi_pairs, mi_count) = match s.mi_pairs {
            MiPairs::Teammates => (off.clone(), pairs),
            MiPairs::All => (Tensor::ones([1, 1, n, n], &device), (n * n) as f32),
        };
        let mi = (kl * mi_pairs * loss_steps.clone()).sum().div_scalar(steps * mi_count);

        // Entropy (bits) of each agent's attention, from detached h and z (weights clamped at
        // 1e-4 before the log, as the released code).
        let (h_d, z_d) = (h.detach(), int.z.detach());
        let (alpha_d, over) = match s.entropy_attention {
            EntropyAttention::Used => (self.attention(h_d, z_d, [t, b, n]), off.clone()),
            EntropyAttention::Released => (softmax(self.scores(h_d, z_d, [t, b, n]), 3), Tensor::ones([1, 1, n, n], &device)),
        };
        let alpha_d = alpha_d.clamp_min(1e-4);
        let ent = (alpha_d.clone() * alpha_d.log()).mul_scalar(-1.0 / std::f32::consts::LN_2) * over;
        let ent = (ent.sum_dim(3) * loss_steps).sum().div_scalar(steps * n as f32);

        // Diagnostics: the share of teammate weights the test-time pruning would cut, and the
        // size of the incoming messages.
        let thr = s.prune / n as f32;
        let pruned = int.alpha.detach().lower_elem(thr).float() * off * step_mask.clone();
        let pruned = scalar(&pruned.sum()) / (ctx.mask_sum * pairs);
        let msg_abs = scalar(&(int.incoming.detach().abs() * step_mask).sum()) / (ctx.mask_sum * (n * a) as f32);
        vec![
            AuxTerm { name: "maic_mi", value: scalar(&mi), loss: Some(mi.mul_scalar(s.mi_weight)) },
            AuxTerm { name: "maic_entropy", value: scalar(&ent), loss: Some(ent.mul_scalar(s.entropy_weight)) },
            AuxTerm { name: "maic_pruned_share", value: pruned, loss: None },
            AuxTerm { name: "maic_msg_abs", value: msg_abs, loss: None },
        ]
    }
}

/// Test-time pruning: attention weights below `prune / n_agents` are set to 0 (the others are
/// not renormalised). `prune = 0` keeps everything.
pub fn prune_attention<const D: usize>(alpha: Tensor<D>, n_agents: usize, prune: f32) -> Tensor<D> {
    if prune <= 0.0 {
        return alpha;
    }
    alpha.clone() * alpha.greater_equal_elem(prune / n_agents as f32).float()
}

fn eye_mask(n: usize, device: &Device) -> Tensor<2, Bool> {
    let v: Vec<bool> = (0..n * n).map(|k| k / n == k % n).collect();
    Tensor::from_data(TensorData::new(v, [n, n]), device)
}

/// `lin` over [own_i | pair_ij] for every pair, without building the concatenated rows:
/// own [T * B * n, d_own] (one row per agent), pair [T, B, n, n, d_pair]; the own part of the
/// product is broadcast along `axis` (3: the row's agent is i, the first pair index; 2: it is
/// j, the second). Returns [T, B, n, n, out].
fn pair_linear(lin: &Linear, own: Tensor<2>, pair: Tensor<5>, [t, b, n]: [usize; 3], axis: usize) -> Tensor<5> {
    let d_own = own.dims()[1];
    let [.., d_pair] = pair.dims();
    let w = lin.weight.val();
    let out = w.dims()[1];
    let own_part = own.matmul(w.clone().narrow(0, 0, d_own));
    let own_part = match axis {
        3 => own_part.reshape([t, b, n, 1, out]),
        _ => own_part.reshape([t, b, 1, n, out]),
    };
    let pair_part = pair.reshape([t * b * n * n, d_pair]).matmul(w.narrow(0, d_own, d_pair)).reshape([t, b, n, n, out]);
    let sum = pair_part + own_part;
    match &lin.bias {
        Some(bias) => sum + bias.val().reshape([1, 1, 1, 1, out]),
        None => sum,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
        t.into_data().try_into_vec::<f32>().unwrap()
    }

    #[test]
    fn pruning_cuts_weights_below_a_quarter_of_uniform() {
        let device = Device::default();
        // n = 4: the threshold is 0.25 / 4 = 0.0625.
        let alpha: Tensor<2> = Tensor::from_data(TensorData::new(vec![0.0, 0.05, 0.5, 0.45, 0.0625, 0.0, 0.9, 0.0375], [2, 4]), &device);
        assert_eq!(values(prune_attention(alpha.clone(), 4, 0.25)), vec![0.0, 0.0, 0.5, 0.45, 0.0625, 0.0, 0.9, 0.0]);
        // n = 2 with prune 0.25: threshold 0.125; prune 0 keeps all.
        assert_eq!(values(prune_attention(alpha.clone(), 2, 0.25)), vec![0.0, 0.0, 0.5, 0.45, 0.0, 0.0, 0.9, 0.0]);
        assert_eq!(values(prune_attention(alpha.clone(), 4, 0.0)), values(alpha));
    }

    #[test]
    fn the_masked_batch_norm_follows_torch_on_the_rows_it_keeps() {
        let device = Device::default();
        let bn = MaskedBatchNorm::new(1, &device);
        // One step, three rows, the last left out: mean 1.5, biased variance 0.25.
        let x: Tensor<3> = Tensor::from_data(TensorData::new(vec![1.0, 2.0, 100.0], [1, 3, 1]), &device);
        let mask: Tensor<3> = Tensor::from_data(TensorData::new(vec![1.0, 1.0, 0.0], [1, 3, 1]), &device);
        let y = values(bn.forward_masked(x, mask, true));
        let s = (0.25f32 + 1e-5).sqrt();
        for (got, want) in y.iter().zip([-0.5 / s, 0.5 / s, 0.0]) {
            assert!((got - want).abs() < 1e-5, "{y:?}");
        }
        // Running statistics: 0.9 * 0 + 0.1 * 1.5 and 0.9 * 1 + 0.1 * 0.25 * 2 / (2 - 1).
        assert!((values(bn.running_mean.value())[0] - 0.15).abs() < 1e-6);
        assert!((values(bn.running_var.value())[0] - 0.95).abs() < 1e-6);
        let r = values(bn.forward_running::<1>(Tensor::from_data(TensorData::new(vec![1.5], [1]), &device)));
        assert!((r[0] - 1.35 / (0.95f32 + 1e-5).sqrt()).abs() < 1e-5, "{r:?}");
        // Over a dim (the released code's always-training mode): rows [1, 3] -> -1, +1.
        let g = values(bn.forward_over(Tensor::<2>::from_data(TensorData::new(vec![1.0, 3.0], [2, 1]), &device), 0));
        assert!((g[0] + 1.0).abs() < 1e-4 && (g[1] - 1.0).abs() < 1e-4, "{g:?}");
    }

    /// The split first layer equals the layer over the concatenated pair rows, for the row's
    /// agent as sender (axis 3) and as receiver (axis 2).
    #[test]
    fn pair_linear_equals_the_linear_layer_over_concatenated_rows() {
        let device = Device::default();
        let mut rng = LearnRng::seed_from(7);
        let (t, b, n, d_own, d_pair, out) = (3, 2, 4, 5, 3, 6);
        let lin = linear(&mut rng, d_own + d_pair, out, &device);
        let own: Tensor<2> = Tensor::random([t * b * n, d_own], burn::tensor::Distribution::Default, &device);
        let pair: Tensor<5> = Tensor::random([t, b, n, n, d_pair], burn::tensor::Distribution::Default, &device);
        for axis in [3, 2] {
            let own4 = own.clone().reshape([t, b, n, d_own]);
            let own_pair = match axis {
                3 => own4.reshape([t, b, n, 1, d_own]).expand([t, b, n, n, d_own]),
                _ => own4.reshape([t, b, 1, n, d_own]).expand([t, b, n, n, d_own]),
            };
            let rows = Tensor::cat(vec![own_pair, pair.clone()], 4).reshape([t * b * n * n, d_own + d_pair]);
            let want = lin.forward(rows).reshape([t, b, n, n, out]);
            let got = pair_linear(&lin, own.clone(), pair.clone(), [t, b, n], axis);
            let diff = (want - got).abs().max().into_scalar::<f32>();
            assert!(diff < 1e-5, "axis {axis}: {diff}");
        }
    }
}
