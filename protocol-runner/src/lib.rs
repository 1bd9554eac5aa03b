//! The protocol runner: a process that owns the message columns of every slot and writes each
//! agent's received messages in place, next to its observation, before the trainer sees the step.
pub mod builtin;
pub mod plan;
pub mod protocol;
pub mod runner;

use lmac_shm_schema::EnvSchema;

/// The message plan named on the command line: a built-in (`none`, `fullcomm`) for now.
/// Every process of a run resolves the same name the same way.
pub fn plan_for(protocol: &str, schema: &EnvSchema) -> Result<Box<dyn plan::MessagePlan>, String> {
    builtin::builtin(protocol, schema.n_agents, schema.obs_dim)
        .ok_or_else(|| format!("unknown protocol {protocol:?}: use 'none' or 'fullcomm'"))
}
