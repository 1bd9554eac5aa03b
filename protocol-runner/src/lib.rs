//! The protocol runner: a process that owns the message columns of every slot and writes each
//! agent's received messages in place, next to its observation, before the trainer sees the step.
pub mod builtin;
pub mod plan;
pub mod protocol;
pub mod runner;
pub mod spec;

pub use spec::ProtocolSpec;

use lmac_shm_schema::EnvSchema;
use protocol::{ProtocolEnv, ValidatedProtocol, ValidationError};

/// Why a protocol could not be loaded or compiled for an environment; each names the file or the
/// budget at fault, and the validator's errors stay typed for callers that hand them back to an
/// LLM.
#[derive(Debug, thiserror::Error)]
pub enum ProtocolError {
    /// The file could not be read (missing, not a regular file, too large, not UTF-8).
    #[error("cannot read protocol file {0}")]
    Read(String),
    /// One phase's file does not parse or validate.
    #[error("{file}:\n{}", protocol::errors_to_text(.errors))]
    Invalid { file: String, errors: Vec<ValidationError> },
    /// The phases are valid one by one but do not compile together.
    #[error("{}", protocol::errors_to_text(.0))]
    Compile(Vec<ValidationError>),
    /// The plan writes more message columns than the environment reserves.
    #[error("protocol {protocol} writes {width} message columns but {env} allows {budget} (its message_columns budget)")]
    TooWide { protocol: String, width: usize, env: String, budget: usize },
}

/// What a protocol may use of an environment: its sizes, its message budget (the schema's
/// `message_columns`) and the meaning of every dimension (for error texts and explanations).
pub fn protocol_env(schema: &EnvSchema) -> ProtocolEnv {
    let mut env = ProtocolEnv::new(schema.n_agents, schema.obs_dim, schema.n_actions, schema.state_dim, schema.message_columns);
    env.obs_names = schema.obs_meanings();
    if schema.agents_differ() {
        env.agent_obs_names = (0..schema.n_agents).map(|j| schema.obs_meanings_of(j)).collect();
    }
    env.state_names = schema.state_meanings();
    env.action_names = schema.actions.clone();
    env.env_name = schema.name.clone();
    env.schema_fingerprint = schema.fingerprint();
    env
}

/// Validate protocol files as consecutive phases (each phase's width counts against the budget
/// left by the earlier ones). An invalid file's error names it.
pub fn load_phases(files: &[&str], env: &ProtocolEnv) -> Result<Vec<ValidatedProtocol>, ProtocolError> {
    let mut phases: Vec<ValidatedProtocol> = Vec::new();
    for f in files {
        let text = protocol::read_protocol_file(std::path::Path::new(f))?;
        let invalid = |errors| ProtocolError::Invalid { file: f.to_string(), errors };
        let p = protocol::parse_str(&text).map_err(invalid)?;
        let v = protocol::validate_phase(&p, env, &phases).map_err(invalid)?;
        phases.push(v);
    }
    Ok(phases)
}

/// A protocol compiled for an environment: its plan, never applied (each ring member takes
/// `plan.fresh()`), the task-critical state dims its phases name (sorted, each once) and what is
/// valid but suspicious about its files (another environment's, an older schema's), each
/// prefixed by its file.
pub struct CompiledProtocol {
    pub plan: Box<dyn plan::MessagePlan>,
    pub critical_dims: Vec<usize>,
    pub warnings: Vec<String>,
}

impl CompiledProtocol {
    /// Message columns the plan writes per agent.
    pub fn msg_dim(&self) -> usize {
        self.plan.msg_dim()
    }
}

/// Compile `protocol` for `schema`: a built-in, or the protocol files validated as phases and
/// compiled into one plan (the final protocol concatenates the phases). A plan wider than the
/// schema's message budget is refused here, the one width check every caller shares. Every
/// process of a run compiles the same spec the same way, once.
pub fn compile_for(protocol: &ProtocolSpec, schema: &EnvSchema) -> Result<CompiledProtocol, ProtocolError> {
    let (plan, critical_dims, warnings): (Box<dyn plan::MessagePlan>, Vec<usize>, Vec<String>) = match protocol {
        ProtocolSpec::None => (Box::new(builtin::NoMessages), Vec::new(), Vec::new()),
        ProtocolSpec::FullComm => {
            (Box::new(builtin::FullComm { n_agents: schema.n_agents, obs_dim: schema.obs_dim }), Vec::new(), Vec::new())
        }
        ProtocolSpec::Files(files) => {
            let env = protocol_env(schema);
            let names: Vec<&str> = files.iter().map(String::as_str).collect();
            let phases = load_phases(&names, &env)?;
            let critical: std::collections::BTreeSet<usize> = phases.iter().flat_map(|p| p.critical_dims.iter().copied()).collect();
            let warnings = names.iter().zip(&phases).flat_map(|(f, p)| p.warnings.iter().map(move |w| format!("{f}: {w}"))).collect();
            let plan = protocol::compile(&phases, &env).map_err(ProtocolError::Compile)?;
            (plan, critical.into_iter().collect(), warnings)
        }
    };
    if plan.msg_dim() > schema.message_columns {
        return Err(ProtocolError::TooWide {
            protocol: protocol.to_string(),
            width: plan.msg_dim(),
            env: schema.name.clone(),
            budget: schema.message_columns,
        });
    }
    Ok(CompiledProtocol { plan, critical_dims, warnings })
}

/// The message plan of `protocol` ([`compile_for`] without the critical dims).
pub fn plan_for(protocol: &ProtocolSpec, schema: &EnvSchema) -> Result<Box<dyn plan::MessagePlan>, ProtocolError> {
    compile_for(protocol, schema).map(|c| c.plan)
}
