//! Acting: batched greedy / epsilon-greedy action selection for `n_envs` environments with the
//! agent network (no autodiff), keeping each environment's GRU hidden state between calls.

use burn::module::Module;
use burn::tensor::{Device, Tensor, TensorData};

use super::agent::RnnAgent;
use super::learner::Learner;
use super::{InputLayout, LearnRng};

pub struct Controller {
    agent: RnnAgent,
    layout: InputLayout,
    device: Device,
    n_envs: usize,
    hidden_dim: usize,
    /// [n_envs * n_agents * H]
    hidden: Vec<f32>,
    inputs: Vec<f32>,
    /// Q-values of the last call, [n_envs * n_agents * n_actions].
    last_q: Vec<f32>,
}

impl Controller {
    pub fn new(learner: &Learner, n_envs: usize) -> Self {
        let layout = *learner.layout();
        let h = learner.config().rnn_hidden_dim;
        let n = layout.dims.n_agents;
        Controller {
            agent: learner.acting_net().agent,
            layout,
            device: learner.device().clone(),
            n_envs,
            hidden_dim: h,
            hidden: vec![0.0; n_envs * n * h],
            inputs: Vec::new(),
            last_q: Vec::new(),
        }
    }

    /// Take the learner's current online weights.
    pub fn sync_weights(&mut self, learner: &Learner) {
        self.agent = learner.acting_net().agent;
    }

    /// Take new acting weights (from the learner thread).
    pub fn set_agent(&mut self, agent: RnnAgent) {
        self.agent = agent;
    }

    pub fn n_envs(&self) -> usize {
        self.n_envs
    }

    /// Reset every environment's hidden state.
    pub fn reset_all(&mut self) {
        self.hidden.fill(0.0);
    }

    /// Q-values computed by the last `select_actions`/`q_values` call.
    pub fn last_q(&self) -> &[f32] {
        &self.last_q
    }

    /// Advance the recurrent state one step and return Q-values [B * n * A] (B = n_envs).
    /// obs: B*n*obs_width; state: B*state_dim (needed only when agents see the state);
    /// last_actions: B*n (ignored where `first`); first[b]: env b starts an episode (hidden reset).
    pub fn q_values(&mut self, obs: &[f32], state: Option<&[f32]>, last_actions: &[i32], first: &[bool]) -> &[f32] {
        let d = self.layout.dims;
        let (b, n, h, iw) = (self.n_envs, d.n_agents, self.hidden_dim, self.layout.width());
        assert_eq!(obs.len(), b * n * d.obs_width, "obs length");
        assert_eq!(last_actions.len(), b * n, "last_actions length");
        assert_eq!(first.len(), b, "first length");
        if self.layout.state {
            let s = state.expect("agent_sees_state needs the global state");
            assert_eq!(s.len(), b * d.state_dim, "state length");
        }
        self.inputs.resize(b * n * iw, 0.0);
        for e in 0..b {
            if first[e] {
                self.hidden[e * n * h..(e + 1) * n * h].fill(0.0);
            }
            let st = state.map(|s| &s[e * d.state_dim..(e + 1) * d.state_dim]);
            for ag in 0..n {
                let row = e * n + ag;
                let last = if first[e] { -1 } else { last_actions[row] };
                self.layout.write(
                    &mut self.inputs[row * iw..(row + 1) * iw],
                    &obs[row * d.obs_width..(row + 1) * d.obs_width],
                    st,
                    last,
                    ag,
                );
            }
        }
        let x: Tensor<2> = Tensor::from_data(TensorData::new(self.inputs.clone(), [b * n, iw]), &self.device);
        let hs: Tensor<2> = Tensor::from_data(TensorData::new(self.hidden.clone(), [b * n, h]), &self.device);
        let (q, h_new) = self.agent.step(x, hs);
        self.hidden = h_new.into_data().try_into_vec::<f32>().expect("f32 hidden");
        self.last_q = q.into_data().try_into_vec::<f32>().expect("f32 q");
        &self.last_q
    }

    /// Epsilon-greedy over available actions (pymarl `EpsilonGreedyActionSelector`): with
    /// probability epsilon a uniformly random available action, else the greedy one (first
    /// maximum). `epsilon = 0` is greedy. avail: B*n*A (1 = available). Returns B*n actions.
    #[allow(clippy::too_many_arguments)]
    pub fn select_actions(
        &mut self,
        obs: &[f32],
        state: Option<&[f32]>,
        last_actions: &[i32],
        avail: &[u8],
        first: &[bool],
        epsilon: f32,
        rng: &mut LearnRng,
    ) -> Vec<i32> {
        let a = self.layout.dims.n_actions;
        self.q_values(obs, state, last_actions, first);
        let rows = self.last_q.len() / a;
        assert_eq!(avail.len(), rows * a, "avail length");
        let mut out = Vec::with_capacity(rows);
        for r in 0..rows {
            let av = &avail[r * a..(r + 1) * a];
            let q = &self.last_q[r * a..(r + 1) * a];
            let n_av = av.iter().filter(|&&x| x != 0).count();
            if n_av == 0 {
                out.push(0);
                continue;
            }
            let explore = epsilon > 0.0 && rng.uniform() < epsilon;
            let act = if explore {
                let k = rng.below(n_av);
                av.iter().enumerate().filter(|(_, &x)| x != 0).nth(k).map(|(i, _)| i).unwrap()
            } else {
                let mut best = usize::MAX;
                for i in 0..a {
                    if av[i] != 0 && (best == usize::MAX || q[i] > q[best]) {
                        best = i;
                    }
                }
                best
            };
            out.push(act as i32);
        }
        out
    }
}

impl Controller {
    /// Greedy actions (epsilon 0), for evaluation and tests.
    pub fn greedy_actions(&mut self, obs: &[f32], state: Option<&[f32]>, last_actions: &[i32], avail: &[u8], first: &[bool]) -> Vec<i32> {
        // epsilon = 0 never draws from the RNG.
        let mut rng = LearnRng::seed_from(0);
        self.select_actions(obs, state, last_actions, avail, first, 0.0, &mut rng)
    }
}

impl std::fmt::Debug for Controller {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Controller").field("n_envs", &self.n_envs).field("params", &self.agent.num_params()).finish()
    }
}
