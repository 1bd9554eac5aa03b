//! `EnvSchema::placeholders`: the generated `EDIT:` texts still in a schema, by field path
//! (`lmac envs --check` refuses them), and none left in the shipped schemas.
use lmac_shm_schema::schema::{all_envs, EnvSchema};
use std::path::Path;

const TOY: &str = r#"name = "toy:one"
task = "EDIT: what the team must do"
n_agents = 2
obs_dim = 3
state_dim = 4
n_actions = 2
episode_limit = 10
alpha = 0.1
reward = "1 per step."
actions = ["left", "  EDIT: action 1"]
[[obs_dims]]
count = 3
meaning = "position {k}"
[[state_dims]]
count = 2
repeat = 2
labels = ["row", "EDIT: a label"]
meaning = "EDIT: agent {r}'s {label}"
"#;

#[test]
fn each_placeholder_is_named_by_its_field() {
    let s = EnvSchema::parse(TOY, Path::new("toy/one.toml")).unwrap();
    assert_eq!(s.placeholders(), ["task", "actions[1]", "state_dims[0].meaning", "state_dims[0].labels[1]"]);
    let done = TOY.replace("EDIT: ", "");
    assert!(EnvSchema::parse(&done, Path::new("toy/one.toml")).unwrap().placeholders().is_empty());
}

#[test]
fn the_shipped_schemas_have_no_placeholders() {
    for (path, s) in all_envs().unwrap() {
        let s = s.unwrap_or_else(|e| panic!("{e}"));
        assert!(s.placeholders().is_empty(), "{}: {:?}", path.display(), s.placeholders());
    }
}
