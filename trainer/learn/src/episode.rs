//! One finished episode of one environment, copied out of the slots step by step.
//! This is the only copy the trainer makes of slot data; the learner's replay buffer holds these.

/// Sizes shared by every episode of a run.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct EpisodeDims {
    pub n_agents: usize,
    /// Observation columns the agent network reads per agent: obs_dim + message columns in use.
    pub obs_width: usize,
    pub state_dim: usize,
    pub n_actions: usize,
}

/// `len` transitions t = 0..len. Step t holds what the agents saw (obs, state, available
/// actions) and what followed (action, team reward). When `terminated`, the last target is the
/// reward alone. When the time limit cut the episode (`truncated`), `next` holds what the agents
/// saw after the last action, and the learner bootstraps from it (pymarl treats a time limit as
/// "not terminated" in the same way); a truncated episode without `next` has its last
/// transition masked.
#[derive(Clone, Debug, Default)]
pub struct Episode {
    pub len: usize,
    /// len * n_agents * obs_width
    pub obs: Vec<f32>,
    /// len * state_dim
    pub state: Vec<f32>,
    /// len * n_agents * n_actions, 1 = available
    pub avail: Vec<u8>,
    /// len * n_agents
    pub actions: Vec<i32>,
    /// len
    pub reward: Vec<f32>,
    pub terminated: bool,
    pub truncated: bool,
    /// The step after the last one (truncated episodes).
    pub next: Option<NextStep>,
}

/// What the agents saw after a truncated episode's last action: one step of obs, state, avail.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct NextStep {
    /// n_agents * obs_width
    pub obs: Vec<f32>,
    /// state_dim
    pub state: Vec<f32>,
    /// n_agents * n_actions
    pub avail: Vec<u8>,
}

impl Episode {
    pub fn with_capacity(dims: &EpisodeDims, steps: usize) -> Self {
        Episode {
            len: 0,
            obs: Vec::with_capacity(steps * dims.n_agents * dims.obs_width),
            state: Vec::with_capacity(steps * dims.state_dim),
            avail: Vec::with_capacity(steps * dims.n_agents * dims.n_actions),
            actions: Vec::with_capacity(steps * dims.n_agents),
            reward: Vec::with_capacity(steps),
            terminated: false,
            truncated: false,
            next: None,
        }
    }

    /// An episode of `len` steps of uniform random values and actions, every action available:
    /// what the learner benchmarks train on (values do not change the cost of dense math).
    pub fn synthetic(dims: &EpisodeDims, len: usize, rng: &mut crate::LearnRng, terminated: bool) -> Episode {
        let mut ep = Episode::with_capacity(dims, len);
        ep.len = len;
        ep.obs = (0..len * dims.n_agents * dims.obs_width).map(|_| rng.uniform()).collect();
        ep.state = (0..len * dims.state_dim).map(|_| rng.uniform()).collect();
        ep.avail = vec![1; len * dims.n_agents * dims.n_actions];
        ep.actions = (0..len * dims.n_agents).map(|_| rng.below(dims.n_actions) as i32).collect();
        ep.reward = (0..len).map(|_| rng.uniform()).collect();
        (ep.terminated, ep.truncated) = (terminated, !terminated);
        ep
    }

    pub fn team_return(&self) -> f32 {
        self.reward.iter().sum()
    }

    /// Whether every array has the length `len` and `dims` imply (and actions are in range):
    /// `Err` says which does not.
    pub fn check(&self, d: &EpisodeDims) -> Result<(), String> {
        let l = self.len;
        let mut bad = Vec::new();
        let mut want = |what: &str, got: usize, expect: usize| {
            if got != expect {
                bad.push(format!("{what} {got} (expected {expect})"));
            }
        };
        want("obs", self.obs.len(), l * d.n_agents * d.obs_width);
        want("state", self.state.len(), l * d.state_dim);
        want("avail", self.avail.len(), l * d.n_agents * d.n_actions);
        want("actions", self.actions.len(), l * d.n_agents);
        want("reward", self.reward.len(), l);
        if let Some(n) = &self.next {
            want("next obs", n.obs.len(), d.n_agents * d.obs_width);
            want("next state", n.state.len(), d.state_dim);
            want("next avail", n.avail.len(), d.n_agents * d.n_actions);
        }
        if l == 0 {
            bad.push("no steps".into());
        }
        if let Some(a) = self.actions.iter().find(|&&a| a < 0 || a as usize >= d.n_actions) {
            bad.push(format!("action {a} outside 0..{}", d.n_actions));
        }
        if self.next.is_some() && self.terminated {
            bad.push("a terminated episode has a next step".into());
        }
        if bad.is_empty() {
            Ok(())
        } else {
            Err(format!("len {l}: {} (dims {d:?})", bad.join(", ")))
        }
    }
}
