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
/// actions) and what followed (action, team reward). The observation after the last action is
/// not kept: when `terminated` the last target is the reward alone; when the episode was cut by
/// the time limit (`truncated`) the last transition has no successor and the learner masks it.
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
        }
    }

    pub fn team_return(&self) -> f32 {
        self.reward.iter().sum()
    }
}
