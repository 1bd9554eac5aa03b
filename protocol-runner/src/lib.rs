//! The protocol runner: a process that owns the message columns of every slot and writes each
//! agent's received messages in place, next to its observation, before the trainer sees the step.
pub mod builtin;
pub mod plan;
pub mod protocol;
pub mod runner;

use lmac_shm_schema::EnvSchema;
use protocol::{ProtocolEnv, ValidatedProtocol};

/// What a protocol may use of an environment: its sizes, its message budget (the schema's
/// `message_columns`) and the meaning of every dimension (for error texts and explanations).
pub fn protocol_env(schema: &EnvSchema) -> ProtocolEnv {
    let mut env = ProtocolEnv::new(schema.n_agents, schema.obs_dim, schema.n_actions, schema.state_dim, schema.message_columns);
    env.obs_names = schema.obs_meanings();
    env.state_names = schema.state_meanings();
    env.action_names = schema.actions.clone();
    env
}

/// Validate protocol files as consecutive phases (each phase's width counts against the budget
/// left by the earlier ones). Errors are the validator's text, prefixed by the file.
pub fn load_phases(files: &[&str], env: &ProtocolEnv) -> Result<Vec<ValidatedProtocol>, String> {
    let mut phases: Vec<ValidatedProtocol> = Vec::new();
    for f in files {
        let text = protocol::read_protocol_file(std::path::Path::new(f)).map_err(|e| format!("{f}: {e}"))?;
        let p = protocol::parse_str(&text).map_err(|e| format!("{f}:\n{}", protocol::errors_to_text(&e)))?;
        let v = protocol::validate_phase(&p, env, &phases).map_err(|e| format!("{f}:\n{}", protocol::errors_to_text(&e)))?;
        phases.push(v);
    }
    Ok(phases)
}

/// The message plan named on the command line: a built-in (`none`, `fullcomm`) or protocol
/// files joined by '+' (`phase0.json+phase1.json+phase2.json`: the final protocol concatenates
/// the phases). Every process of a run resolves the same name the same way; each call returns
/// a fresh plan (its own observation history), so use one per env server.
pub fn plan_for(protocol: &str, schema: &EnvSchema) -> Result<Box<dyn plan::MessagePlan>, String> {
    if let Some(p) = builtin::builtin(protocol, schema.n_agents, schema.obs_dim) {
        return Ok(p);
    }
    let files: Vec<&str> = protocol.split('+').collect();
    if !files.iter().all(|f| f.ends_with(".json")) {
        return Err(format!("unknown protocol {protocol:?}: use 'none', 'fullcomm' or protocol files (a.json or a.json+b.json)"));
    }
    let env = protocol_env(schema);
    let phases = load_phases(&files, &env)?;
    protocol::compile(&phases, &env).map_err(|e| protocol::errors_to_text(&e))
}
