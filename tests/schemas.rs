//! Schema validation: every shipped schema is valid, and bad schemas give errors that name the
//! file, the field and the problem.
use lmac_shm_schema::layout::{LayoutParams, SlotLayout, ALIGN};
use lmac_shm_schema::schema::{all_envs, EnvSchema};
use std::path::Path;

/// The small valid schema of the schema parser's own tests.
const GOOD: &str = include_str!("../shm-schema/tests/data/toy.toml");

fn errors(text: &str) -> String {
    EnvSchema::parse(text, Path::new("schemas/toy/one.toml")).expect_err("must be rejected").to_string()
}

#[test]
fn shipped_schemas_are_valid() {
    let all = all_envs().expect("schema directory");
    assert!(all.len() >= 2, "at least the two LBF schemas");
    for (path, r) in all {
        let s = r.unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        assert_eq!(s.obs_meanings().len(), s.obs_dim);
        assert_eq!(s.state_meanings().len(), s.state_dim);
        assert!(s.message_columns >= s.fullcomm_columns(), "{}: reserves too few message columns for fullcomm", s.name);
    }
}

#[test]
fn good_schema_expands_meanings() {
    let s = EnvSchema::parse(GOOD, Path::new("x.toml")).unwrap();
    assert_eq!(s.obs_meanings(), vec!["position 0", "position 1", "speed"]);
    assert_eq!(s.state_meanings()[3], "cell (1, 1)");
}

#[test]
fn a_repeated_group_describes_one_block_per_entity() {
    // Two agents x (row, col, level): one group with labels and repeat = 2 instead of six.
    let text = GOOD.replace("state_dim = 4", "state_dim = 6").replace(
        "count = 4\nshape = [2, 2]\nmeaning = \"cell ({i0}, {i1})\"",
        "count = 3\nrepeat = 2\nlabels = [\"row\", \"col\", \"level\"]\nmeaning = \"agent {r}'s {label} ({k})\"",
    );
    let s = EnvSchema::parse(&text, Path::new("x.toml")).unwrap();
    assert_eq!(
        s.state_meanings(),
        vec![
            "agent 0's row (0)",
            "agent 0's col (1)",
            "agent 0's level (2)",
            "agent 1's row (0)",
            "agent 1's col (1)",
            "agent 1's level (2)"
        ]
    );
    // The dims it covers are count x repeat; {r} without repeat and repeat = 0 are named.
    let e = errors(&text.replace("state_dim = 6", "state_dim = 3"));
    assert!(e.contains("state_dims: the groups describe 6 dimensions but state_dim = 3"), "{e}");
    let e = errors(&text.replace("repeat = 2", "repeat = 0"));
    assert!(e.contains("state_dims[0].repeat: must be at least 1"), "{e}");
    let e = errors(&GOOD.replace("meaning = \"speed\"", "meaning = \"speed of {r}\""));
    assert!(e.contains("obs_dims[1]: meaning uses {r} but the group has no repeat"), "{e}");
}

/// The observation's entities follow the schema's groups: on 1o_10b the four move features
/// are one, the Roach's eight values one, each of the ten teammate slots (a [10, 7] block) one,
/// the own features one; every shipped schema's entities cover its observation once, in order.
#[test]
fn observation_entities_follow_the_schema_groups() {
    let s = lmac_shm_schema::schema::load_env("smaclite:1o_10b_vs_1r").unwrap();
    let e = s.obs_entities();
    assert_eq!(e.len(), 1 + 1 + 10 + 1);
    assert_eq!((e[0].clone(), e[1].clone(), e[2].clone(), e[11].clone(), e[12].clone()), (0..4, 4..12, 12..19, 75..82, 82..85));
    for (path, r) in all_envs().unwrap() {
        let s = r.unwrap();
        let e = s.obs_entities();
        assert!(!e.is_empty(), "{}", path.display());
        assert!(e.windows(2).all(|w| w[0].end == w[1].start && !w[0].is_empty()), "{}: {e:?}", path.display());
        assert_eq!((e[0].start, e[e.len() - 1].end), (0, s.obs_dim), "{}", path.display());
    }
    // A repeated group is one entity per repetition; a group without shape or repeat is one.
    let text = GOOD.replace("count = 2\nmeaning = \"position {k}\"", "count = 1\nrepeat = 2\nmeaning = \"position {r}\"");
    let s = EnvSchema::parse(&text, Path::new("x.toml")).unwrap();
    assert_eq!(s.obs_entities(), vec![0..1, 1..2, 2..3]);
    assert_eq!(EnvSchema::parse(GOOD, Path::new("x.toml")).unwrap().obs_entities(), vec![0..2, 2..3]);
}

#[test]
fn missing_field_names_file_and_field() {
    let e = errors(&GOOD.replace("n_agents = 2\n", ""));
    assert!(e.contains("schemas/toy/one.toml") && e.contains("n_agents") && e.contains("missing"), "{e}");
}

#[test]
fn zero_agents_is_rejected() {
    let e = errors(&GOOD.replace("n_agents = 2", "n_agents = 0"));
    assert!(e.contains("schemas/toy/one.toml: n_agents: must be at least 1"), "{e}");
}

#[test]
fn dims_that_disagree_with_descriptions_are_rejected() {
    let e = errors(&GOOD.replace("obs_dim = 3", "obs_dim = 4"));
    assert!(e.contains("obs_dims: the groups describe 3 dimensions but obs_dim = 4"), "{e}");
    let e = errors(&GOOD.replace("shape = [2, 2]", "shape = [2, 3]"));
    assert!(e.contains("state_dims[0]: shape [2, 3] holds 6 dimensions but count = 4"), "{e}");
    let e = errors(&GOOD.replace("actions = [\"left\", \"right\"]", "actions = [\"left\"]"));
    assert!(e.contains("actions: lists 1 action names but n_actions = 2"), "{e}");
}

#[test]
fn several_problems_are_reported_together() {
    let e = errors(&GOOD.replace("n_actions = 2", "n_actions = 0").replace("alpha = 0.1", "alpha = -1.0"));
    assert!(e.contains("n_actions: must be at least 1") && e.contains("alpha: must be a positive number"), "{e}");
}

#[test]
fn unknown_fields_and_type_errors_are_named() {
    let e = errors(&GOOD.replace("alpha = 0.1", "alpha = 0.1\nalpah = 3"));
    assert!(e.contains("alpah"), "{e}");
    let e = errors(&GOOD.replace("obs_dim = 3", "obs_dim = \"three\""));
    assert!(e.contains("obs_dim") || e.contains("line"), "{e}");
}

#[test]
fn layout_sections_are_aligned_and_disjoint() {
    let s = EnvSchema::parse(GOOD, Path::new("x.toml")).unwrap();
    let l = SlotLayout::new(&s, LayoutParams { num_envs: 5, msg_dim: 7, n_slots: 3 });
    let secs = [l.env_meta, l.obs, l.state, l.avail, l.reward, l.terminated, l.truncated, l.last_actions, l.actions];
    for w in secs.windows(2) {
        assert_eq!(w[0].offset % ALIGN, 0);
        assert!(w[0].offset + w[0].bytes <= w[1].offset);
    }
    assert_eq!(l.obs.bytes, 5 * 2 * (3 + 7) * 4);
    assert_eq!(l.slot_stride % ALIGN, 0);
    let other = SlotLayout::new(&s, LayoutParams { num_envs: 5, msg_dim: 8, n_slots: 3 });
    assert_ne!(l.hash, other.hash, "the hash covers the layout parameters");
}
