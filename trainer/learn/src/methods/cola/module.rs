//! The COLA network (one set of parameters shared by all agents, the agent id one-hot in the
//! input). Per step, with u_i agent i's input row:
//! - recurrent  h_i = GRU(relu(W_in u_i), h_i')                         (pymarl's RNN agent)
//! - student    s_i = P2 relu(P1 V2 relu(V1 x_i)),  x_i = u_i (or detached h_i with `hidden`)
//! - class      c_i = argmax s_i, or K when agent i is dead (all-zero observation)
//! - output     Q_i = W_q [h_i | C2 relu(C1 E[c_i])]                   (E: (K + 1) x embed table)
//! - teacher    g_i: the student's shape, an EMA of its weights, in the training loss only
//!
//! Not trained by gradients (they do not require grad, so the optimizer leaves them alone; they
//! are saved in checkpoints and copied to the target network with the rest): the teacher, moved
//! towards the student in [`ColaAgent::after_update`]; the center, a [`RunningState`] moved there
//! too from the teacher logits the last training unroll left in `pending`.

use burn::module::{Module, Param, RunningState};
use burn::nn::Linear;
use burn::tensor::activation::{log_softmax, relu, softmax};
use burn::tensor::{Device, Tensor, TensorData};

use super::{agreement_and_entropy, classes, ColaConfig, ConsensusInput};
use crate::agent::{FusedGru, RnnAgent};
use crate::config::LearnConfig;
use crate::init::linear;
use crate::methods::{linear_rows, standard_normal, AuxTerm, MethodHooks, TrainContext};
use crate::{InputLayout, LearnRng};

/// The student's (or the teacher's) network: input -> 2W -> ReLU -> W ("view"), then W -> W ->
/// ReLU -> K ("projection"); no activation between the two, as in the released code.
#[derive(Module, Debug)]
pub struct ConsensusBuilder {
    pub view1: Linear,
    pub view2: Linear,
    pub proj1: Linear,
    pub proj2: Linear,
}

impl ConsensusBuilder {
    pub fn new(rng: &mut LearnRng, d_in: usize, width: usize, classes: usize, device: &Device) -> Self {
        ConsensusBuilder {
            view1: linear(rng, d_in, 2 * width, device),
            view2: linear(rng, 2 * width, width, device),
            proj1: linear(rng, width, width, device),
            proj2: linear(rng, width, classes, device),
        }
    }

    /// Logits [rows, K].
    pub fn forward(&self, x: Tensor<2>) -> Tensor<2> {
        let view = self.view2.forward(relu(self.view1.forward(x)));
        self.proj2.forward(relu(self.proj1.forward(view)))
    }

    /// `momentum * self + (1 - momentum) * student`, weight by weight; the result keeps this
    /// network's parameter ids and its training state (a teacher stays without gradients).
    pub fn ema(self, student: &ConsensusBuilder, momentum: f32) -> Self {
        let mix = |t: Linear, s: &Linear| Linear {
            weight: ema_param(t.weight, &s.weight, momentum),
            bias: match (t.bias, &s.bias) {
                (Some(tb), Some(sb)) => Some(ema_param(tb, sb, momentum)),
                (tb, _) => tb,
            },
        };
        ConsensusBuilder {
            view1: mix(self.view1, &student.view1),
            view2: mix(self.view2, &student.view2),
            proj1: mix(self.proj1, &student.proj1),
            proj2: mix(self.proj2, &student.proj2),
        }
    }
}

fn ema_param<const D: usize>(t: Param<Tensor<D>>, s: &Param<Tensor<D>>, momentum: f32) -> Param<Tensor<D>> {
    let s = s.val().detach();
    t.map(|t| (t.mul_scalar(momentum) + s.mul_scalar(1.0 - momentum)).detach())
}

/// DINO's cross-entropy between every teacher and every student of a group (one environment's
/// step): entry (g, i, j) of the result [G, n, n] is
/// `-sum_k softmax((teacher[g, i] - center) / teacher_temp)_k * log_softmax(student[g, j] / student_temp)_k`.
/// The teacher side carries no gradient.
pub fn dino_cross_entropy(student: Tensor<3>, teacher: Tensor<3>, center: Tensor<1>, teacher_temp: f32, student_temp: f32) -> Tensor<3> {
    let p = softmax((teacher - center.unsqueeze::<3>()).div_scalar(teacher_temp), 2).detach();
    let log_q = log_softmax(student.div_scalar(student_temp), 2);
    p.matmul(log_q.swap_dims(1, 2)).neg()
}

fn host<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().try_into_vec::<f32>().expect("f32 tensor")
}

#[derive(Module, Debug)]
pub struct ColaAgent {
    pub fc1: Linear,
    pub gru: FusedGru,
    /// The Q head on [h | consensus code].
    pub q: Linear,
    /// (K + 1) x embed_dim: one row per class, the last for dead agents (torch's N(0, 1) init).
    pub embedding: Param<Tensor<2>>,
    pub code1: Linear,
    pub code2: Linear,
    pub student: ConsensusBuilder,
    /// No gradients: an EMA of the student.
    pub teacher: ConsensusBuilder,
    /// [K], subtracted from the teacher logits.
    pub center: RunningState<Tensor<1>>,
    /// [K + 1]: the sums of the teacher logits over the alive trained rows of the last training
    /// unroll, and their count; folded into the center by the next `after_update`.
    pub pending: RunningState<Tensor<1>>,
    #[module(skip)]
    pub cfg: ColaConfig,
    pub n_agents: usize,
    /// Columns of the input row tested for the dead-agent zeros (the observation without its
    /// message columns; 0: every agent counts as alive).
    pub obs_cols: usize,
    pub hidden_dim: usize,
}

impl MethodHooks for ColaAgent {
    fn rnn_agent_mut(&mut self) -> Option<&mut RnnAgent> {
        None
    }

    /// Moves the EMA teacher and the center ([`ColaAgent::after_update`]).
    fn after_update(self) -> Self {
        ColaAgent::after_update(self)
    }
}

impl ColaAgent {
    pub fn new(rng: &mut LearnRng, cfg: &ColaConfig, layout: &InputLayout, learn: &LearnConfig, device: &Device) -> Self {
        let s = &cfg.settings;
        let (n, a, iw, h) = (layout.dims.n_agents, layout.dims.n_actions, layout.width(), learn.rnn_hidden_dim);
        let d_in = match s.input {
            ConsensusInput::Obs => iw,
            ConsensusInput::Hidden => h,
        };
        let k = s.classes;
        ColaAgent {
            fc1: linear(rng, iw, h, device),
            gru: FusedGru::new(rng, h, h, device),
            q: linear(rng, 2 * h, a, device),
            embedding: Param::from_tensor(standard_normal(rng, [k + 1, s.embed_dim], device)),
            code1: linear(rng, s.embed_dim, h, device),
            code2: linear(rng, h, h, device),
            student: ConsensusBuilder::new(rng, d_in, s.hidden, k, device),
            // Initialised on its own (not a copy of the student), as in the released code.
            teacher: ConsensusBuilder::new(rng, d_in, s.hidden, k, device).no_grad(),
            center: RunningState::new(Tensor::zeros([k], device)),
            pending: RunningState::new(Tensor::zeros([k + 1], device)),
            cfg: cfg.clone(),
            n_agents: n,
            obs_cols: layout.dims.obs_width.saturating_sub(cfg.msg_cols),
            hidden_dim: h,
        }
    }

    /// The agent GRU's hidden state (the class is made from the current step only).
    pub fn state_width(&self) -> usize {
        self.hidden_dim
    }

    /// Which rows of `x` [rows, in] are alive: a non-zero observation column.
    pub fn alive(&self, x: &Tensor<2>) -> Vec<bool> {
        let rows = x.dims()[0];
        if self.obs_cols == 0 {
            return vec![true; rows];
        }
        host(x.clone().narrow(1, 0, self.obs_cols).abs().sum_dim(1)).iter().map(|v| *v > 0.0).collect()
    }

    /// What the student and the teacher read: the input rows or the (detached) new GRU states.
    fn source(&self, x: Tensor<2>, h: &Tensor<2>) -> Tensor<2> {
        match self.cfg.settings.input {
            ConsensusInput::Obs => x,
            ConsensusInput::Hidden => h.clone().detach(),
        }
    }

    /// The encoded class of each row [rows, H]: the K + 1 codes are encoded once and each row
    /// picks its own (a one-hot product: exactly the row, and the gradient of the rows that use it).
    fn code(&self, cls: &[usize], device: &Device) -> Tensor<2> {
        let k1 = self.cfg.settings.classes + 1;
        let mut onehot = vec![0.0f32; cls.len() * k1];
        for (r, &c) in cls.iter().enumerate() {
            onehot[r * k1 + c.min(k1 - 1)] = 1.0;
        }
        let onehot: Tensor<2> = Tensor::from_data(TensorData::new(onehot, [cls.len(), k1]), device);
        let table = self.code2.forward(relu(self.code1.forward(self.embedding.val())));
        onehot.matmul(table)
    }

    /// The consensus classes of one step from GRU states `h` (K = dead), e.g. to inspect a
    /// trained network.
    pub fn consensus_classes(&self, x: Tensor<2>, h: Tensor<2>) -> Vec<usize> {
        let alive = self.alive(&x);
        let h = self.gru.forward(relu(self.fc1.forward(x.clone())), h);
        classes(&host(self.student.forward(self.source(x, &h))), self.cfg.settings.classes, &alive)
    }

    /// One acting step.
    pub fn step(&self, x: Tensor<2>, h: Tensor<2>) -> (Tensor<2>, Tensor<2>) {
        let alive = self.alive(&x);
        let device = x.device();
        let h = self.gru.forward(relu(self.fc1.forward(x.clone())), h);
        let cls = classes(&host(self.student.forward(self.source(x, &h))), self.cfg.settings.classes, &alive);
        let q = self.q.forward(Tensor::cat(vec![h.clone(), self.code(&cls, &device)], 1));
        (q, h)
    }

    /// Unroll from zero states; in training (`train`) the consensus loss is returned and the
    /// batch's teacher logits are left for the center (see [`after_update`](Self::after_update)).
    pub fn unroll(&self, inputs: Vec<Tensor<2>>, train: Option<&TrainContext>) -> (Tensor<3>, Vec<AuxTerm>) {
        assert!(!inputs.is_empty(), "unroll needs at least one step");
        let (t_len, rows) = (inputs.len(), inputs[0].dims()[0]);
        let hd = self.hidden_dim;
        let device = inputs[0].device();
        // Everything over all steps at once (time-major rows t * N + r), the recurrence as one
        // fused operation: the student's logits carry a gradient only into the consensus loss,
        // the classes none.
        let x_all = Tensor::cat(inputs, 0);
        let hs = self.gru.sequence(relu(self.fc1.forward(x_all.clone())), t_len);
        let alive = self.alive(&x_all);
        let src = match self.cfg.settings.input {
            ConsensusInput::Obs => x_all,
            ConsensusInput::Hidden => hs.clone().reshape([t_len * rows, hd]).detach(),
        };
        let logits = self.student.forward(src.clone());
        let cls = classes(&host(logits.clone().detach()), self.cfg.settings.classes, &alive);
        let code = self.code(&cls, &device).reshape([t_len, rows, hd]);
        let q = linear_rows(&self.q, Tensor::cat(vec![hs, code], 2));
        let aux = match train {
            Some(ctx) => self.losses(logits, src, &alive, &cls, ctx),
            None => Vec::new(),
        };
        (q, aux)
    }

    /// The consensus loss over the ordered pairs of alive agents of the trained steps, and the
    /// diagnostics; leaves the batch's teacher-logit sums in `pending`.
    fn losses(&self, logits: Tensor<2>, src: Tensor<2>, alive: &[bool], cls: &[usize], ctx: &TrainContext) -> Vec<AuxTerm> {
        let s = &self.cfg.settings;
        let (k, n) = (s.classes, self.n_agents);
        assert_eq!(ctx.n_agents, n, "the context's agent count");
        let rows = logits.dims()[0];
        let groups = rows / n;
        assert_eq!(groups * n, rows, "rows are steps x batch x agents");
        let device = logits.device();
        let step_mask = host(ctx.mask.clone());
        assert_eq!(step_mask.len(), groups, "one mask value per step of each episode");

        // Alive agent-rows of trained steps, and the ordered pairs i != j of them.
        let row_w: Vec<f32> = (0..rows).map(|r| if alive[r] && step_mask[r / n] > 0.0 { 1.0 } else { 0.0 }).collect();
        let mut pairs = vec![0.0f32; groups * n * n];
        for g in 0..groups {
            for i in 0..n {
                for j in (0..n).filter(|&j| j != i) {
                    pairs[(g * n + i) * n + j] = row_w[g * n + i] * row_w[g * n + j];
                }
            }
        }
        let pair_count: f32 = pairs.iter().sum();
        let pairs: Tensor<3> = Tensor::from_data(TensorData::new(pairs, [groups, n, n]), &device);

        let teacher = self.teacher.forward(src.detach()).detach();
        let cross = dino_cross_entropy(
            logits.reshape([groups, n, k]),
            teacher.clone().reshape([groups, n, k]),
            self.center.value(),
            s.teacher_temp,
            s.student_temp,
        );
        let loss = (cross * pairs).sum().div_scalar(pair_count.max(1.0));

        // The center's next step: the teacher logits of the alive trained rows.
        let count: f32 = row_w.iter().sum();
        let weights: Tensor<2> = Tensor::from_data(TensorData::new(row_w, [rows, 1]), &device);
        let sums = (teacher * weights).sum_dim(0).reshape([k]);
        let count: Tensor<1> = Tensor::from_data(TensorData::new(vec![count], [1]), &device);
        self.pending.update(Tensor::cat(vec![sums, count], 0));
        let _ = self.pending.value_sync();

        let (agreement, entropy) = agreement_and_entropy(cls, k, n, &step_mask);
        let value = loss.clone().detach().into_scalar::<f32>();
        vec![
            AuxTerm { name: "cola_consensus", value, loss: Some(loss.mul_scalar(s.consensus_weight)) },
            AuxTerm { name: "cola_agreement", value: agreement, loss: None },
            AuxTerm { name: "cola_class_entropy", value: entropy, loss: None },
        ]
    }

    /// After an optimizer step: the center moves towards the mean teacher logits of the last
    /// training unroll (if it had alive rows), then the teacher towards the student.
    pub fn after_update(self) -> Self {
        let s = &self.cfg.settings;
        let k = s.classes;
        let pending = host(self.pending.value_sync());
        if pending.len() == k + 1 && pending[k] > 0.0 {
            let center_t = self.center.value_sync();
            let device = center_t.device();
            let center = host(center_t);
            let m = s.center_momentum;
            let next: Vec<f32> = (0..k).map(|i| m * center[i] + (1.0 - m) * pending[i] / pending[k]).collect();
            self.center.update(Tensor::from_data(TensorData::new(next, [k]), &device));
            let _ = self.center.value_sync();
            self.pending.update(Tensor::zeros([k + 1], &device));
            let _ = self.pending.value_sync();
        }
        let teacher = self.teacher.clone().ema(&self.student, s.teacher_momentum);
        ColaAgent { teacher, ..self }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::episode::EpisodeDims;
    use crate::methods::cola::ColaSettings;

    fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
        t.into_data().try_into_vec::<f32>().unwrap()
    }

    fn tensor<const D: usize>(v: Vec<f32>, shape: [usize; D], device: &Device) -> Tensor<D> {
        Tensor::from_data(TensorData::new(v, shape), device)
    }

    fn agent(device: &Device) -> ColaAgent {
        let dims = EpisodeDims { n_agents: 2, obs_width: 3, state_dim: 1, n_actions: 2 };
        let learn = LearnConfig::default();
        let cfg = ColaConfig { settings: ColaSettings::default(), msg_cols: 1 };
        ColaAgent::new(&mut LearnRng::seed_from(3), &cfg, &InputLayout::new(dims, &learn), &learn, device)
    }

    #[test]
    fn the_dino_loss_matches_a_hand_computed_pair() {
        let device = Device::default();
        let (ts, tt) = (0.1f32, 0.04f32);
        let ln3 = 3f32.ln();
        // Students: agent 0 uniform, agent 1 with softmax(s / 0.1) = (3/4, 1/4).
        let student = tensor(vec![0.0, 0.0, ts * ln3, 0.0], [1, 2, 2], &device);
        // Teachers after subtracting the center (0.5, -0.2): agent 0 gives (3/4, 1/4), agent 1
        // uniform.
        let center = tensor(vec![0.5, -0.2], [2], &device);
        let teacher = tensor(vec![tt * ln3 + 0.5, -0.2, 0.5, -0.2], [1, 2, 2], &device);
        let m = values(dino_cross_entropy(student, teacher, center, tt, ts));
        let h34 = -(0.75f32 * 0.75f32.ln() + 0.25 * 0.25f32.ln());
        let ln2 = 2f32.ln();
        // (teacher i, student j): (0,0) = -(3/4 ln 1/2 + 1/4 ln 1/2) = ln 2; (0,1) = H(3/4, 1/4);
        // (1,0) = ln 2; (1,1) = -(1/2 ln 3/4 + 1/2 ln 1/4).
        let want = [ln2, h34, ln2, -(0.5 * 0.75f32.ln() + 0.5 * 0.25f32.ln())];
        for (got, want) in m.iter().zip(want) {
            assert!((got - want).abs() < 1e-5, "{m:?}");
        }
        // The loss averages the off-diagonal pairs: (H(3/4, 1/4) + ln 2) / 2 = 0.6277.
        assert!(((m[1] + m[2]) / 2.0 - 0.627_7).abs() < 1e-4);
    }

    #[test]
    fn after_an_update_the_teacher_and_the_center_take_their_moving_average_steps() {
        let device = Device::default().autodiff();
        let a = agent(&device);
        let (t0, s0) = (values(a.teacher.proj2.weight.val()), values(a.student.proj2.weight.val()));
        let tb0 = values(a.teacher.view1.bias.as_ref().unwrap().val());
        let sb0 = values(a.student.view1.bias.as_ref().unwrap().val());
        // What a training unroll leaves: sums of 2 rows of teacher logits.
        a.pending.update(tensor(vec![2.0, -4.0, 0.0, 6.0, 2.0], [5], &device));
        let a = a.after_update();
        let center = values(a.center.value());
        let want = [0.1 * 1.0, 0.1 * -2.0, 0.0, 0.1 * 3.0];
        for (g, w) in center.iter().zip(want) {
            assert!((g - w).abs() < 1e-6, "{center:?}");
        }
        for (got, (t, s)) in values(a.teacher.proj2.weight.val()).iter().zip(t0.iter().zip(&s0)) {
            assert!((got - (0.996 * t + 0.004 * s)).abs() < 1e-6);
        }
        for (got, (t, s)) in values(a.teacher.view1.bias.as_ref().unwrap().val()).iter().zip(tb0.iter().zip(&sb0)) {
            assert!((got - (0.996 * t + 0.004 * s)).abs() < 1e-6);
        }
        assert!(!a.teacher.proj2.weight.val().is_require_grad(), "the teacher stays out of the optimizer");
        assert!(a.student.proj2.weight.val().is_require_grad());
        // The pending sums were used up: a second hook call leaves the center alone.
        let a = a.after_update();
        assert_eq!(values(a.center.value()), center);
    }

    #[test]
    fn an_all_zero_observation_is_a_dead_agent_whatever_its_messages_and_ids() {
        let device = Device::default();
        let a = agent(&device);
        // Input rows: obs (2 columns + 1 message column) | last action (2) | agent id (2).
        let x = tensor(
            vec![
                0.0, 0.0, 0.9, 1.0, 0.0, 1.0, 0.0, // dead: zero observation, a message, ids
                0.0, 0.3, 0.0, 0.0, 0.0, 0.0, 1.0, // alive
            ],
            [2, 7],
            &device,
        );
        assert_eq!(a.alive(&x), vec![false, true]);
        let cls = a.consensus_classes(x, Tensor::zeros([2, 64], &device));
        assert_eq!(cls[0], 4, "the dead class");
        assert!(cls[1] < 4);
    }
}
