//! The shared-parameter RNN agent (pymarl `RNNAgent`): linear -> ReLU -> GRU cell -> linear,
//! one network for all agents (agent id one-hot in the input). The GRU cell is hand-written
//! with fused gates: one input and one hidden matmul of width 3H per step.

use burn::module::Module;
use burn::nn::Linear;
use burn::tensor::activation::{relu, sigmoid, tanh};
use burn::tensor::{Device, Tensor};

use super::dense::{dense, Activation};
use super::gru_sequence::{gru_sequence_projected, gru_sequence_projected_carry};
use super::init::linear;
use super::LearnRng;

/// GRU cell, torch conventions (gate order r, z, n; `n = tanh(W_in x + b_in + r * (W_hn h + b_hn))`,
/// `h' = (1 - z) * n + z * h`).
#[derive(Module, Debug)]
pub struct FusedGru {
    pub input: Linear,
    pub hidden: Linear,
    pub hidden_dim: usize,
}

impl FusedGru {
    pub fn new(rng: &mut LearnRng, input_dim: usize, hidden_dim: usize, device: &Device) -> Self {
        // Linear init is torch's U(-1/sqrt(fan_in), 1/sqrt(fan_in)); torch's GRUCell uses
        // U(-1/sqrt(H), 1/sqrt(H)) for both, identical here since the GRU reads fc1's H-wide output.
        FusedGru {
            input: linear(rng, input_dim, 3 * hidden_dim, device),
            hidden: linear(rng, hidden_dim, 3 * hidden_dim, device),
            hidden_dim,
        }
    }

    /// x: [N, in], h: [N, H] -> h': [N, H]
    pub fn forward(&self, x: Tensor<2>, h: Tensor<2>) -> Tensor<2> {
        let hd = self.hidden_dim;
        let n = x.dims()[0];
        let gi = self.input.forward(x);
        let gh = self.hidden.forward(h.clone());
        let rz = sigmoid(gi.clone().slice([0..n, 0..2 * hd]) + gh.clone().slice([0..n, 0..2 * hd]));
        let r = rz.clone().slice([0..n, 0..hd]);
        let z = rz.slice([0..n, hd..2 * hd]);
        let cand = tanh(gi.slice([0..n, 2 * hd..3 * hd]) + r * gh.slice([0..n, 2 * hd..3 * hd]));
        // (1 - z) * n + z * h = n + z * (h - n)
        cand.clone() + z * (h - cand)
    }

    /// The hidden states over a whole sequence from zero: `x` holds every step's input,
    /// time-major [T * N, in] -> [T, N, H]. One fused operation (`gru_sequence_projected`)
    /// computes each step's input projection and recurrence, equal to stepping `forward`.
    pub fn sequence(&self, x: Tensor<2>, steps: usize) -> Tensor<3> {
        let [total, width] = x.dims();
        let rows = total / steps.max(1);
        let (b_ih, b_hh) = (self.bias(&self.input, &x.device()), self.bias(&self.hidden, &x.device()));
        gru_sequence_projected(x.reshape([steps, rows, width]), self.input.weight.val(), b_ih, self.hidden.weight.val(), b_hh)
    }

    /// A projection's bias, zeros when it has none [3H].
    fn bias(&self, layer: &Linear, device: &Device) -> Tensor<1> {
        layer.bias.as_ref().map_or_else(|| Tensor::zeros([3 * self.hidden_dim], device), |b| b.val())
    }
}

impl FusedGru {
    /// [`sequence`](Self::sequence) with each step's input added to its new state before it is
    /// carried on: c_t = GRU(x_t, c_{t-1}) + x_t (input width = hidden width), [T, N, H].
    /// Like [`sequence`](Self::sequence), each step's input projection runs inside the loop
    /// (`gru_sequence_projected_carry`).
    pub fn sequence_carry(&self, x: Tensor<2>, steps: usize) -> Tensor<3> {
        let rows = x.dims()[0] / steps.max(1);
        let (b_ih, b_hh) = (self.bias(&self.input, &x.device()), self.bias(&self.hidden, &x.device()));
        let x = x.reshape([steps, rows, self.hidden_dim]);
        gru_sequence_projected_carry(x, self.input.weight.val(), b_ih, self.hidden.weight.val(), b_hh)
    }
}

#[derive(Module, Debug)]
pub struct RnnAgent {
    pub fc1: Linear,
    pub gru: FusedGru,
    pub fc2: Linear,
    pub input_dim: usize,
    pub hidden_dim: usize,
    pub n_actions: usize,
    /// Unroll the recurrence as one fused operation (`gru_sequence`); false: burn's per-step
    /// cell, the reference it is tested against (`learn.fused_gru`).
    pub fused: bool,
}

impl RnnAgent {
    pub fn new(rng: &mut LearnRng, input_dim: usize, hidden_dim: usize, n_actions: usize, device: &Device) -> Self {
        RnnAgent {
            fc1: linear(rng, input_dim, hidden_dim, device),
            gru: FusedGru::new(rng, hidden_dim, hidden_dim, device),
            fc2: linear(rng, hidden_dim, n_actions, device),
            input_dim,
            hidden_dim,
            n_actions,
            fused: true,
        }
    }

    /// One step for acting: x [N, in], h [N, H] -> (q [N, A], h' [N, H]).
    pub fn step(&self, x: Tensor<2>, h: Tensor<2>) -> (Tensor<2>, Tensor<2>) {
        let e = relu(self.fc1.forward(x));
        let h = self.gru.forward(e, h);
        (self.fc2.forward(h.clone()), h)
    }

    /// Unroll over time from a zero hidden state. `inputs[t]` is [N, in] (N = batch * agents);
    /// returns Q-values [T, N, A].
    pub fn unroll(&self, inputs: Vec<Tensor<2>>) -> Tensor<3> {
        crate::methods::linear_rows(&self.fc2, self.hidden_states(&inputs))
    }

    /// The GRU's hidden states over time from zero: `inputs[t]` [N, in] -> [T, N, H] (what
    /// `unroll` reads, and the methods whose heads read h). fc1 and the GRU's input projection
    /// do not depend on h, so they run once over all steps; only the recurrence is sequential,
    /// and it is one fused operation (per-step burn ops cost about 30 operations
    /// and allocations per step forward and backward, which dominated the update).
    pub fn hidden_states(&self, inputs: &[Tensor<2>]) -> Tensor<3> {
        assert!(!inputs.is_empty(), "unroll needs at least one step");
        if !self.fused {
            return self.hidden_states_stepwise(inputs);
        }
        let x = if inputs.len() == 1 { inputs[0].clone() } else { Tensor::cat(inputs.to_vec(), 0) };
        self.gru.sequence(dense(&self.fc1, x, None, Activation::Relu, None), inputs.len())
    }

    /// [`unroll`](Self::unroll) of inputs already stacked time-major: x [T * N, in] -> Q [T, N, A]
    /// (a method that builds its agents' inputs for all steps at once saves the per-step split
    /// and the concatenation).
    pub fn unroll_stacked(&self, x: Tensor<2>, steps: usize) -> Tensor<3> {
        assert!(steps > 0, "unroll needs at least one step");
        let hs = if self.fused {
            self.gru.sequence(dense(&self.fc1, x, None, Activation::Relu, None), steps)
        } else {
            let n = x.dims()[0] / steps;
            let inputs: Vec<Tensor<2>> = x.split(n.max(1), 0);
            self.hidden_states_stepwise(&inputs)
        };
        crate::methods::linear_rows(&self.fc2, hs)
    }

    /// The same hidden states with burn's per-step cell (the reference of the fused path).
    pub fn hidden_states_stepwise(&self, inputs: &[Tensor<2>]) -> Tensor<3> {
        let n = inputs[0].dims()[0];
        let mut h: Tensor<2> = Tensor::zeros([n, self.hidden_dim], &inputs[0].device());
        let mut hs = Vec::with_capacity(inputs.len());
        for x in inputs {
            let e = relu(self.fc1.forward(x.clone()));
            h = self.gru.forward(e, h);
            hs.push(h.clone());
        }
        Tensor::stack(hs, 0)
    }
}
