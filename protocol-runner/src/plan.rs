//! What the runner executes: a message plan applied in place to one batched step.
//!
//! A plan is compiled once (from a built-in protocol or a validated protocol description) and
//! then applied to every slot. It only ever writes the message columns of the observation rows.

/// One batched step as the runner sees it: the observation rows of every env and agent, each
/// `row_width = obs_dim + msg_dim` floats long, with the message columns right after the
/// observation. Everything else in the slot is read-only here.
pub struct StepView<'a> {
    pub num_envs: usize,
    pub n_agents: usize,
    pub obs_dim: usize,
    /// Reserved message columns per row (the slab layout's width; a plan may use fewer).
    pub msg_dim: usize,
    /// `num_envs * n_agents * (obs_dim + msg_dim)` floats, row-major by env, then agent.
    pub rows: &'a mut [f32],
    /// Per env: true when this step is the first of a new episode (history must restart).
    pub first: &'a [bool],
    /// `num_envs * n_agents` actions applied on the previous step (-1 on a first step).
    pub last_actions: &'a [i32],
}

impl StepView<'_> {
    pub fn row_width(&self) -> usize {
        self.obs_dim + self.msg_dim
    }
}

/// A compiled protocol. `apply` fills (only) the message columns of every row.
pub trait MessagePlan: Send {
    /// Message columns this plan writes per agent (must be <= the slab's reserved columns).
    fn msg_dim(&self) -> usize;
    /// Human-readable name for logs (`none`, `fullcomm`, a protocol file's name).
    fn name(&self) -> String;
    fn apply(&mut self, step: &mut StepView<'_>);
    /// The same plan with no history: what compiling the protocol again would give. A process
    /// compiles its protocol once and gives each ring member it serves a fresh copy.
    fn fresh(&self) -> Box<dyn MessagePlan>;
}
