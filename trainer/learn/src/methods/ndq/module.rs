//! The NDQ network (one set of parameters shared by all agents, the agent id one-hot in the
//! input). Per step, with u_i agent i's input row and N = B * n batch-major rows:
//! - encoder   mu_i = W3 relu(W2 relu(W1 u_i))                   [n * d]: block j is i's message to j
//! - message   m_ij = mu_ij + eps, eps ~ N(0, 1) in training; mu_ij (cut if set) when acting
//! - receiver  r_j = [m_1j | .. | m_nj];  Q_j = RNN([u_j | r_j])
//! - inference p_j = softmax(V3 relu(V2 relu(V1 [u_j | r_j])))  (training losses only)

use burn::module::Module;
use burn::nn::Linear;
use burn::tensor::activation::{relu, softmax};
use burn::tensor::{Device, Tensor, TensorData};

use super::{cut_mask, NdqConfig};
use crate::agent::RnnAgent;
use crate::config::LearnConfig;
use crate::init::linear;
use crate::methods::{standard_normal, AuxTerm, MethodHooks, TrainContext};
use crate::{InputLayout, LearnRng};

#[derive(Module, Debug)]
pub struct NdqAgent {
    pub enc1: Linear,
    pub enc2: Linear,
    pub enc3: Linear,
    pub infer1: Linear,
    pub infer2: Linear,
    pub infer3: Linear,
    pub agent: RnnAgent,
    #[module(skip)]
    pub cfg: NdqConfig,
    pub n_agents: usize,
}

impl MethodHooks for NdqAgent {
    fn rnn_agent_mut(&mut self) -> Option<&mut RnnAgent> {
        Some(&mut self.agent)
    }
}

impl NdqAgent {
    pub fn new(rng: &mut LearnRng, cfg: &NdqConfig, layout: &InputLayout, learn: &LearnConfig, device: &Device) -> Self {
        let s = &cfg.settings;
        let (n, a, iw) = (layout.dims.n_agents, layout.dims.n_actions, layout.width());
        let (h, nd) = (s.encoder_hidden, n * s.msg_dim);
        NdqAgent {
            enc1: linear(rng, iw, h, device),
            enc2: linear(rng, h, h, device),
            enc3: linear(rng, h, nd, device),
            infer1: linear(rng, iw + nd, 4 * nd, device),
            infer2: linear(rng, 4 * nd, 4 * nd, device),
            infer3: linear(rng, 4 * nd, a, device),
            agent: RnnAgent::new(rng, iw + nd, learn.rnn_hidden_dim, a, device),
            cfg: cfg.clone(),
            n_agents: n,
        }
    }

    /// The agent GRU's hidden state: messages are made from the current input only.
    pub fn state_width(&self) -> usize {
        self.agent.hidden_dim
    }

    /// Set the acting network's message cut (percent, 0 = none), e.g. to evaluate a trained
    /// network at NDQ's cuts.
    pub fn set_cut(&mut self, percent: f32) {
        self.cfg.settings.cut = percent;
    }

    /// The message means of every sender row, [N, n * d] (block j: to agent j).
    pub fn message_means(&self, u: Tensor<2>) -> Tensor<2> {
        self.enc3.forward(relu(self.enc2.forward(relu(self.enc1.forward(u)))))
    }

    /// Sender rows [N, n * d] to receiver rows [N, n * d]: receiver j's row holds the block
    /// for j of every sender of its environment, in sender order.
    pub fn route(&self, m: Tensor<2>) -> Tensor<2> {
        let [rows, nd] = m.dims();
        let n = self.n_agents;
        m.reshape([rows / n, n, n, nd / n]).swap_dims(1, 2).reshape([rows, nd])
    }

    /// The acting cut: zero the means of the dims in the bottom `cut` percent of each
    /// environment's n * n * d |means| (see [`cut_mask`]).
    pub fn cut(&self, mu: Tensor<2>) -> Tensor<2> {
        let p = self.cfg.settings.cut;
        if p <= 0.0 {
            return mu;
        }
        let [rows, nd] = mu.dims();
        let abs = mu.clone().abs().into_data().try_into_vec::<f32>().expect("f32 message means");
        let keep = cut_mask(&abs, self.n_agents * nd, p);
        let keep: Tensor<2> = Tensor::from_data(TensorData::new(keep, [rows, nd]), &mu.device());
        mu * keep
    }

    /// One acting step (deterministic: the message means, cut if set).
    pub fn step(&self, u: Tensor<2>, h: Tensor<2>) -> (Tensor<2>, Tensor<2>) {
        let mu = self.cut(self.message_means(u.clone()));
        self.agent.step(Tensor::cat(vec![u, self.route(mu)], 1), h)
    }

    /// Unroll from zero states. In training (`train`), messages are sampled with the update's
    /// seed and the communication losses are returned; without it, the means are sent (uncut:
    /// this is also the target network).
    pub fn unroll(&self, inputs: Vec<Tensor<2>>, train: Option<&TrainContext>) -> (Tensor<3>, Vec<AuxTerm>) {
        assert!(!inputs.is_empty(), "unroll needs at least one step");
        let mut rng = train.map(|c| LearnRng::seed_from(c.seed ^ 0x4E44_5100_0000_0001));
        let t_len = inputs.len();
        let (mut mus, mut msgs, mut xs) = (Vec::with_capacity(t_len), Vec::with_capacity(t_len), Vec::with_capacity(t_len));
        for u in inputs {
            // Per step (not once over all steps): the agent's GRU reads per-step inputs, and
            // slicing a gradient-carrying sequence costs a full-size zero tensor per slice in
            // the backward pass.
            let mu = self.message_means(u.clone());
            let m = match rng.as_mut() {
                Some(r) => mu.clone() + standard_normal(r, mu.dims(), &mu.device()),
                None => mu.clone(),
            };
            xs.push(Tensor::cat(vec![u, self.route(m.clone())], 1));
            if train.is_some() {
                mus.push(mu);
                msgs.push(m);
            }
        }
        let q = self.agent.unroll(xs.clone());
        let aux = match train {
            Some(ctx) => self.losses(Tensor::cat(mus, 0), Tensor::cat(msgs, 0), Tensor::cat(xs, 0), ctx),
            None => Vec::new(),
        };
        (q, aux)
    }

    /// The action-inference head's logits for receiver rows [.., input | received].
    pub fn infer(&self, x: Tensor<2>) -> Tensor<2> {
        self.infer3.forward(relu(self.infer2.forward(relu(self.infer1.forward(x)))))
    }

    /// mu, m [T * N, n * d] (sender rows), x [T * N, in + n * d] (receiver rows), time-major.
    fn losses(&self, mu: Tensor<2>, m: Tensor<2>, x: Tensor<2>, ctx: &TrainContext) -> Vec<AuxTerm> {
        let (rows, nd) = (mu.dims()[0], mu.dims()[1]);
        let (b, n) = (ctx.b, ctx.n_agents);
        assert_eq!(n, self.n_agents, "the context's agent count");
        let t = rows / (b * n);
        assert_eq!(rows, t * b * n, "rows are time x batch x agents");
        let s = &self.cfg.settings;
        let actions = ctx.actions.as_ref().expect("NDQ's inference loss reads the target network's greedy actions (TrainContext::actions)");
        let label = actions.target_greedy().reshape([rows, 1]);
        let per_row = |steps: Tensor<1>| steps.reshape([t * b, 1, 1]).expand([t * b, n, 1]).reshape([rows, 1]);
        let mask = per_row(ctx.mask.clone());
        // Which rows the losses sum over; either way they divide by the count of trained steps,
        // as the released learner does (`/ mask.sum()`).
        let loss_rows = if s.mask_losses { mask.clone() } else { per_row(released_rows(&ctx.mask, t, b)) };
        let denom = ctx.mask_sum;

        // Cross-entropy with the released code's floor: -log(p + 1e-6), summed over agents.
        let logits = self.infer(x);
        let p = softmax(logits.clone(), 1).gather(1, label.clone());
        let ce = (p.add_scalar(1e-6).log().neg() * loss_rows.clone()).sum().div_scalar(denom);
        // KL(N(mu, 1) || N(0, 1)) = mu^2 / 2 per dim.
        let kl = (mu.clone().square().sum_dim(1).mul_scalar(0.5) * loss_rows.clone()).sum().div_scalar(denom);
        // -log N(m; 0, 1) = m^2 / 2 + log(2 pi) / 2 per dim.
        let half_log_2pi = 0.5 * (2.0 * std::f32::consts::PI).ln();
        let ent = (m.square().mul_scalar(0.5).add_scalar(half_log_2pi).sum_dim(1) * loss_rows).sum().div_scalar(denom);

        let scalar = |x: &Tensor<1>| x.clone().detach().into_scalar::<f32>();
        let hit = logits.detach().argmax(1).equal(label).float();
        let acc = scalar(&(hit * mask.clone()).sum()) / (denom * n as f32);
        let mu_abs = scalar(&(mu.detach().abs().sum_dim(1) * mask).sum()) / (denom * (n * nd) as f32);
        let c = s.c_beta;
        vec![
            AuxTerm { name: "ndq_ce", value: scalar(&ce), loss: Some(ce.mul_scalar(c)) },
            AuxTerm { name: "ndq_kl", value: scalar(&kl), loss: Some(kl.mul_scalar(c * s.comm_beta)) },
            AuxTerm { name: "ndq_entropy", value: scalar(&ent), loss: Some(ent.mul_scalar(c * s.entropy_beta)) },
            AuxTerm { name: "ndq_infer_acc", value: acc, loss: None },
            AuxTerm { name: "ndq_mu_abs", value: mu_abs, loss: None },
        ]
    }
}

/// The steps the released learner's communication losses sum over, as 0/1 [T * B] (time-major
/// like `mask`): every (t, b) with t below the longest episode's count of trained steps, the
/// padded steps of shorter episodes included. Its batch is cut to the longest episode and the
/// losses read `[:, :-1]`, which drops only the row after that episode's last step.
pub fn released_rows(mask: &Tensor<1>, t: usize, b: usize) -> Tensor<1> {
    let host: Vec<f32> = mask.clone().detach().into_data().iter::<f32>().collect();
    assert_eq!(host.len(), t * b, "the mask is [T * B]");
    let longest = (0..t).rev().find(|&ti| host[ti * b..(ti + 1) * b].iter().any(|&m| m > 0.0)).map_or(0, |ti| ti + 1);
    let rows: Vec<f32> = (0..t * b).map(|r| if r / b < longest { 1.0 } else { 0.0 }).collect();
    Tensor::from_data(TensorData::new(rows, [t * b]), &mask.device())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::episode::EpisodeDims;
    use crate::methods::ndq::NdqSettings;

    fn agent(n_agents: usize, msg_dim: usize, cut: f32) -> NdqAgent {
        let dims = EpisodeDims { n_agents, obs_width: 2, state_dim: 1, n_actions: 2 };
        let learn = LearnConfig::default();
        let cfg = NdqConfig { settings: NdqSettings { msg_dim, cut, ..Default::default() } };
        NdqAgent::new(&mut LearnRng::seed_from(1), &cfg, &InputLayout::new(dims, &learn), &learn, &Device::default())
    }

    fn values(t: Tensor<2>) -> Vec<f32> {
        t.into_data().try_into_vec::<f32>().unwrap()
    }

    #[test]
    fn each_receiver_gets_the_block_every_sender_made_for_it() {
        let a = agent(2, 1, 0.0);
        // Two environments of two agents; sender row r holds [to agent 0, to agent 1].
        let m: Tensor<2> = Tensor::from_data(TensorData::new(vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0], [4, 2]), &Device::default());
        // Receiver 0 of env 0 gets (1 from agent 0, 3 from agent 1); receiver 1 gets (2, 4).
        assert_eq!(values(a.route(m)), vec![1.0, 3.0, 2.0, 4.0, 5.0, 7.0, 6.0, 8.0]);
    }

    #[test]
    fn the_acting_cut_ranks_within_each_environment() {
        let a = agent(2, 1, 50.0);
        // Env 0's four means and env 1's four: half of each (the two smallest |mu|) is cut.
        let mu: Tensor<2> =
            Tensor::from_data(TensorData::new(vec![0.1, -5.0, 0.3, -0.2, 10.0, 20.0, -30.0, 40.0], [4, 2]), &Device::default());
        assert_eq!(values(a.cut(mu)), vec![0.0, -5.0, 0.3, 0.0, 0.0, 0.0, -30.0, 40.0]);
    }
}
