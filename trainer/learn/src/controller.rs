//! Acting: batched greedy / epsilon-greedy action selection for `n_envs` environments with the
//! agent network (no autodiff), keeping each environment's recurrent state (whatever the
//! method's `AgentNet::state_width` holds) between calls.

use burn::tensor::{Device, Tensor, TensorData};

use super::learner::Learner;
use super::methods::AgentNet;
use super::{InputLayout, LearnRng, RowParts};

pub struct Controller {
    /// Acting weights in use, oldest first; the last is the newest. Each env acts with one of
    /// them for a whole episode (`env_agent`), so new weights take effect between episodes.
    agents: Vec<AgentNet>,
    /// Per env: index into `agents`.
    env_agent: Vec<usize>,
    layout: InputLayout,
    device: Device,
    n_envs: usize,
    /// Recurrent state width per agent-row.
    hidden_dim: usize,
    /// [n_envs * n_agents * H]
    hidden: Vec<f32>,
    inputs: Vec<f32>,
    /// Q-values of the last call, [n_envs * n_agents * n_actions].
    last_q: Vec<f32>,
    /// The acting network's own random draws (LMAC's dropout with `dropout_when_acting`), apart
    /// from the exploration's so that turning it on does not move the epsilon draws.
    noise: LearnRng,
}

impl Controller {
    pub fn new(learner: &Learner, n_envs: usize) -> Self {
        let layout = *learner.layout();
        let agent = learner.acting_net().agent;
        let h = agent.state_width();
        let n = layout.dims.n_agents;
        Controller {
            agents: vec![agent],
            env_agent: vec![0; n_envs],
            layout,
            device: learner.device().clone(),
            n_envs,
            hidden_dim: h,
            hidden: vec![0.0; n_envs * n * h],
            inputs: Vec::new(),
            last_q: Vec::new(),
            noise: LearnRng::seed_from(learner.config().seed ^ 0xAC7D_0000_0000_0001),
        }
    }

    /// Take the learner's current online weights, for every env at once.
    pub fn sync_weights(&mut self, learner: &Learner) {
        self.set_agent(learner.acting_net().agent);
    }

    /// Act with `agent` in every env from the next step on (mid-episode).
    pub fn set_agent(&mut self, agent: AgentNet) {
        self.agents = vec![agent];
        self.env_agent.fill(0);
    }

    /// New weights for the episodes that start from now on; running episodes finish with the
    /// weights they started with (as pymarl's runners, which load new weights between episodes).
    pub fn offer_agent(&mut self, agent: AgentNet) {
        self.agents.push(agent);
        self.drop_unused();
    }

    /// Forget the versions no env acts with (the newest always stays).
    fn drop_unused(&mut self) {
        let newest = self.agents.len() - 1;
        let mut used = vec![false; self.agents.len()];
        used[newest] = true;
        for &k in &self.env_agent {
            used[k] = true;
        }
        if used.iter().all(|&u| u) {
            return;
        }
        let mut remap = vec![0; used.len()];
        let mut kept = 0;
        for (k, &u) in used.iter().enumerate() {
            remap[k] = kept;
            kept += u as usize;
        }
        let mut k = 0;
        self.agents.retain(|_| {
            k += 1;
            used[k - 1]
        });
        for e in &mut self.env_agent {
            *e = remap[*e];
        }
    }

    /// How many weight versions are acting right now (1 unless episodes straddle an update).
    pub fn versions_in_use(&self) -> usize {
        self.agents.len()
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
    /// last_actions: B*n (ignored where `first`); first[b]: env b starts an episode (hidden reset,
    /// and it takes the newest weights).
    pub fn q_values(&mut self, obs: &[f32], state: Option<&[f32]>, last_actions: &[i32], first: &[bool]) -> &[f32] {
        let d = self.layout.dims;
        let (b, n, h, iw, a) = (self.n_envs, d.n_agents, self.hidden_dim, self.layout.width(), d.n_actions);
        assert_eq!(obs.len(), b * n * d.obs_width, "obs length");
        assert_eq!(last_actions.len(), b * n, "last_actions length");
        assert_eq!(first.len(), b, "first length");
        if self.layout.state {
            let s = state.expect("agent_sees_state needs the global state");
            assert_eq!(s.len(), b * d.state_dim, "state length");
        }
        let newest = self.agents.len() - 1;
        self.inputs.resize(b * n * iw, 0.0);
        for e in 0..b {
            if first[e] {
                self.hidden[e * n * h..(e + 1) * n * h].fill(0.0);
                self.env_agent[e] = newest;
            }
            let st = state.map(|s| &s[e * d.state_dim..(e + 1) * d.state_dim]);
            for ag in 0..n {
                let row = e * n + ag;
                let last = if first[e] { -1 } else { last_actions[row] };
                let o = &obs[row * d.obs_width..(row + 1) * d.obs_width];
                self.layout.write(&mut self.inputs[row * iw..(row + 1) * iw], RowParts::step(o, st, last, ag));
            }
        }
        if self.env_agent.iter().all(|&k| k == newest) {
            // The usual case: one forward over every env.
            let x: Tensor<2> = Tensor::from_data(TensorData::new(self.inputs.clone(), [b * n, iw]), &self.device);
            let hs: Tensor<2> = Tensor::from_data(TensorData::new(self.hidden.clone(), [b * n, h]), &self.device);
            let (q, h_new) = self.agents[newest].step_drawing(x, hs, &mut self.noise);
            self.hidden = h_new.into_data().try_into_vec::<f32>().expect("f32 hidden");
            self.last_q = q.into_data().try_into_vec::<f32>().expect("f32 q");
        } else {
            // Episodes that straddle a weight update: one forward per version over its envs.
            self.last_q.resize(b * n * a, 0.0);
            for k in 0..self.agents.len() {
                let envs: Vec<usize> = (0..b).filter(|&e| self.env_agent[e] == k).collect();
                if envs.is_empty() {
                    continue;
                }
                let gather = |src: &[f32], w: usize| -> Vec<f32> {
                    envs.iter().flat_map(|&e| src[e * n * w..(e + 1) * n * w].iter().copied()).collect()
                };
                let rows = envs.len() * n;
                let x: Tensor<2> = Tensor::from_data(TensorData::new(gather(&self.inputs, iw), [rows, iw]), &self.device);
                let hs: Tensor<2> = Tensor::from_data(TensorData::new(gather(&self.hidden, h), [rows, h]), &self.device);
                let (q, h_new) = self.agents[k].step_drawing(x, hs, &mut self.noise);
                let (q, h_new) =
                    (q.into_data().try_into_vec::<f32>().expect("f32 q"), h_new.into_data().try_into_vec::<f32>().expect("f32 hidden"));
                for (j, &e) in envs.iter().enumerate() {
                    self.hidden[e * n * h..(e + 1) * n * h].copy_from_slice(&h_new[j * n * h..(j + 1) * n * h]);
                    self.last_q[e * n * a..(e + 1) * n * a].copy_from_slice(&q[j * n * a..(j + 1) * n * a]);
                }
            }
        }
        self.drop_unused();
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
            let act = if explore { nth_available(av, rng.below(n_av)) } else { greedy_available(q, av) };
            out.push(act.unwrap_or(0) as i32);
        }
        out
    }
}

/// The available action with the highest value, the first of equal ones (pymarl's argmax over
/// Q with unavailable actions masked); None when no action is available.
pub fn greedy_available(q: &[f32], avail: &[u8]) -> Option<usize> {
    let mut best: Option<usize> = None;
    for (i, (&v, &ok)) in q.iter().zip(avail).enumerate() {
        if ok != 0 && best.is_none_or(|b| v > q[b]) {
            best = Some(i);
        }
    }
    best
}

/// The `k`-th available action (0-based); None when fewer than k + 1 are available. With k
/// uniform over the count of available actions this is a uniformly random available action.
pub fn nth_available(avail: &[u8], k: usize) -> Option<usize> {
    avail.iter().enumerate().filter(|(_, &x)| x != 0).nth(k).map(|(i, _)| i)
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
        f.debug_struct("Controller").field("n_envs", &self.n_envs).field("versions", &self.agents.len()).finish()
    }
}
