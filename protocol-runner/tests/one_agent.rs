//! One agent is a valid environment: the schema validates, fullcomm has no message columns, and
//! neither the protocol validator nor the compiled plans divide by (or underflow on) n_agents - 1.
use lmac_protocol_runner::builtin::FullComm;
use lmac_protocol_runner::plan::StepView;
use lmac_protocol_runner::protocol::{self, ProtocolEnv};
use lmac_protocol_runner::{plan_for, protocol_env};
use lmac_shm_schema::EnvSchema;
use serde_json::json;
use std::path::Path;

const ONE: &str = r#"name = "toy:solo"
task = "One agent walks to the goal."
n_agents = 1
obs_dim = 3
state_dim = 4
n_actions = 2
episode_limit = 10
message_columns = 0
alpha = 0.1
reward = "1 at the goal."
actions = ["left", "right"]
[[obs_dims]]
count = 3
meaning = "position {k}"
[[state_dims]]
count = 4
meaning = "cell {k}"
"#;

fn schema() -> EnvSchema {
    EnvSchema::parse(ONE, Path::new("schemas/toy/solo.toml")).expect("a schema with one agent validates")
}

#[test]
fn fullcomm_with_one_agent_has_no_columns_and_leaves_the_rows_alone() {
    let s = schema();
    assert_eq!(s.fullcomm_columns(), 0);
    assert_eq!(FullComm::columns(1, s.obs_dim), 0);
    for name in ["fullcomm", "none"] {
        let mut plan = plan_for(&name.parse().unwrap(), &s).unwrap();
        assert_eq!(plan.msg_dim(), 0, "{name}");
        let mut rows: Vec<f32> = (0..2 * s.obs_dim).map(|x| x as f32).collect();
        let before = rows.clone();
        let (first, la) = (vec![true, false], vec![0i32; 2]);
        let mut view =
            StepView { num_envs: 2, n_agents: 1, obs_dim: s.obs_dim, msg_dim: 0, rows: &mut rows, first: &first, last_actions: &la };
        plan.apply(&mut view);
        assert_eq!(rows, before, "{name}");
    }
}

#[test]
fn protocol_validator_does_not_panic_with_one_agent() {
    let env = protocol_env(&schema());
    let p = json!({
        "name": "solo",
        "message_design_instruction": "share the position",
        "critical_state_dims": [0, 1],
        "fields": [
            {"name": "pos", "description": "where the agent is", "value": {"obs_slice": {"start": 0, "end": 3}}}
        ]
    });
    let p = protocol::parse_value(&p).map_err(|e| format!("{e:?}")).unwrap();
    // With no one to send to, a protocol is refused with a reason (not a division by zero).
    let errors = protocol::validate(&p, &env).err().expect("a protocol needs two agents");
    let text = protocol::errors_to_text(&errors);
    assert!(text.contains("1 agent(s)") && text.contains("at least 2 agents"), "{text}");
    // The budget and widths of the validator are 0 with one agent.
    assert_eq!(protocol::message_width(&p, &env, &[3]), 0);
    // A zero-agent environment (never a valid schema) does not underflow either.
    assert!(protocol::validate(&p, &ProtocolEnv::new(0, 3, 2, 4, 0)).is_err());
    assert_eq!(protocol::message_width(&p, &ProtocolEnv::new(0, 3, 2, 4, 0), &[3]), 0);
}
