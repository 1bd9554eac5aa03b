//! Agents that observe different things: per-kind observation meanings and entities
//! (`agent_obs`), read for each agent, and refused with the field named when they do not fit.
use lmac_shm_schema::schema::EnvSchema;
use std::path::Path;

const TOY: &str = include_str!("data/toy.toml");
const FILE: &str = "schemas/toy/one.toml";

/// The toy schema with agent 0 a speaker that sees a colour and nothing else.
fn with_speaker(agents: &str, counts: (usize, usize)) -> String {
    format!(
        "{TOY}\n[[agent_obs]]\nname = \"speaker\"\nagents = {agents}\n[[agent_obs.obs_dims]]\ncount = {}\nmeaning = \"colour channel {{k}} of the goal\"\n[[agent_obs.obs_dims]]\ncount = {}\nmeaning = \"padding: always 0\"\n",
        counts.0, counts.1
    )
}

#[test]
fn each_agent_reads_its_own_meanings() {
    let s = EnvSchema::parse(&with_speaker("[0]", (1, 2)), Path::new(FILE)).unwrap();
    assert!(s.agents_differ());
    assert_eq!(s.obs_meanings_of(0), ["colour channel 0 of the goal", "padding: always 0", "padding: always 0"]);
    assert_eq!(s.obs_meanings_of(1), s.obs_meanings(), "an agent not listed reads obs_dims");
    assert_eq!(s.obs_meanings_of(1)[0], "position 0");
    assert_eq!(s.agent_kind(0).map(|k| k.name.as_str()), Some("speaker"));
    // Its entities are its own groups': the colour alone, then the padding.
    assert_eq!(s.obs_entities_of(0), vec![0..1, 1..3]);
    assert_eq!(s.obs_entities_of(1), s.obs_entities(), "an agent not listed has obs_dims' entities");
    // A schema without agent_obs reads as before, and writes no agent_obs back.
    let plain = EnvSchema::parse(TOY, Path::new(FILE)).unwrap();
    assert!(!plain.agents_differ() && !toml::to_string(&plain).unwrap().contains("agent_obs"));
}

#[test]
fn agent_obs_that_do_not_fit_are_refused_naming_the_field() {
    let refused = |text: String| EnvSchema::parse(&text, Path::new(FILE)).expect_err("must be refused").to_string();
    let e = refused(with_speaker("[0]", (1, 1)));
    assert!(e.contains("agent_obs[0].obs_dims: the groups describe 2 dimensions but obs_dim = 3"), "{e}");
    let e = refused(with_speaker("[2]", (1, 2)));
    assert!(e.contains("agent_obs[0].agents: agent 2 does not exist (n_agents = 2)"), "{e}");
    let e = refused(with_speaker("[0, 0]", (1, 2)));
    assert!(e.contains("agent 0 is already described by agent_obs[0]"), "{e}");
    let e = refused(with_speaker("[]", (1, 2)));
    assert!(e.contains("agent_obs[0].agents: lists no agent"), "{e}");
}

#[test]
fn generated_placeholders_in_agent_obs_are_named() {
    let text = with_speaker("[0]", (1, 2)).replace("name = \"speaker\"", "name = \"EDIT: what agent 0 is\"");
    let s = EnvSchema::parse(&text, Path::new(FILE)).unwrap();
    assert_eq!(s.placeholders(), ["agent_obs[0].name"]);
}
