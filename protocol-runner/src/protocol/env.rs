//! The environment facts a protocol is checked against.

/// The environment facts validation needs (the lead maps the environment schema onto this).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ProtocolEnv {
    pub n_agents: usize,
    pub obs_dim: usize,
    pub n_actions: usize,
    pub state_dim: usize,
    /// Most message columns one receiving agent may get (all phases together).
    pub message_budget: usize,
    /// Optional names of the observation dims (for error messages and `explain`); empty = unknown.
    pub obs_names: Vec<String>,
    /// Per agent, its own names of the observation dims where agents observe different things
    /// (the schema's `agent_obs`); empty = every agent reads `obs_names`.
    pub agent_obs_names: Vec<Vec<String>>,
    /// Optional names of the state dims; empty = unknown.
    pub state_names: Vec<String>,
    /// Optional names of the actions; empty = unknown.
    pub action_names: Vec<String>,
    /// The environment's name and schema fingerprint; empty = unknown (no identity check).
    pub env_name: String,
    pub schema_fingerprint: String,
}

impl ProtocolEnv {
    pub fn new(n_agents: usize, obs_dim: usize, n_actions: usize, state_dim: usize, message_budget: usize) -> Self {
        ProtocolEnv { n_agents, obs_dim, n_actions, state_dim, message_budget, ..Default::default() }
    }
    /// The name of observation dim `d` as agent `agent` sees it (its own meanings where agents
    /// differ; the shared names otherwise, or when the agent is not known).
    pub fn obs_name_of(&self, agent: Option<usize>, d: usize) -> Option<&str> {
        let names = agent.and_then(|j| self.agent_obs_names.get(j)).filter(|v| !v.is_empty()).unwrap_or(&self.obs_names);
        names.get(d).map(|s| s.as_str()).filter(|s| !s.is_empty())
    }
    pub(crate) fn state_name(&self, d: usize) -> Option<&str> {
        self.state_names.get(d).map(|s| s.as_str()).filter(|s| !s.is_empty())
    }
}
