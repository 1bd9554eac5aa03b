//! The published JSON Schema (`protocol-runner/protocol.schema.json`) is generated from the serde
//! types and kept in sync by this test. Regenerate it with
//! `LMAC_UPDATE_SCHEMA=1 cargo test -p lmac-protocol-runner --test protocol_schema`.

use lmac_protocol_runner::protocol::*;

#[test]
fn checked_in_schema_is_up_to_date() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("protocol.schema.json");
    let fresh = schema_json();
    if std::env::var_os("LMAC_UPDATE_SCHEMA").is_some() {
        std::fs::write(&path, &fresh).unwrap();
    }
    let on_disk = std::fs::read_to_string(&path).unwrap_or_default();
    assert!(
        on_disk == fresh,
        "{} is stale: regenerate it with LMAC_UPDATE_SCHEMA=1 cargo test -p lmac-protocol-runner --test protocol_schema",
        path.display()
    );
}

#[test]
fn schema_describes_the_language() {
    let s = schema_value();
    let text = s.to_string();
    for needle in [
        "message_design_instruction",
        "critical_state_dims",
        "obs_slice",
        "last_action",
        "sender_one_hot",
        "window",
        "broadcast",
        "peer",
        "clip",
        "delta",
    ] {
        assert!(text.contains(needle), "schema lacks {needle}");
    }
    assert_eq!(s["title"], "Protocol");
    let required: Vec<&str> = s["required"].as_array().unwrap().iter().map(|v| v.as_str().unwrap()).collect();
    assert!(required.contains(&"fields") && required.contains(&"message_design_instruction"));
}

#[test]
fn explain_says_who_sends_what_to_whom_and_why() {
    let env = ProtocolEnv::new(2, 27, 6, 300, 64);
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../prompts/examples");
    let p = parse_str(&std::fs::read_to_string(dir.join("lbf_8x8_phase2.json")).unwrap()).unwrap();
    let text = explain(&p, Some(&env));
    println!("{text}");
    assert!(text.contains("Protocol lbf_8x8_phase2 (phase 2: sharing enhancement)"));
    assert!(text.contains("Sharing enhancement: the agents recover"));
    assert!(text.contains("1. food_seen_10 (9 columns): Highest food level"));
    assert!(text.contains("who:   every agent -> every other agent (broadcast)"));
    assert!(text.contains("value: maximum over the last 10 steps of obs[9..18]"));
    assert!(text.contains("value: change of sum of the columns of obs[19, 21, 23, 25] over the last 3 steps (now minus 2 steps ago)"));
    assert!(text.contains("agent 0 (18 of 18 columns) receives from agent 1: food_seen_10, move_histogram_10, crowding_trend"));
    assert!(text.contains("each receiving agent gets 18 columns"));
    let flat = text.split_whitespace().collect::<Vec<_>>().join(" ");
    assert!(flat.contains("Layout (compact)"), "{text}");
    assert!(flat.contains("(18..18 columns used per receiver; the sender-blocks layout would need 18)"), "{text}");
    assert!(!text.contains("NOT VALID"));
    // Without an environment it still explains; with a too-small one it lists the errors.
    let bare = explain(&p, None);
    assert!(bare.contains("1. food_seen_10 (9 columns)"));
    let small = explain(&p, Some(&ProtocolEnv::new(2, 12, 6, 300, 64)));
    assert!(small.contains("NOT VALID for this environment"), "{small}");
    assert!(small.contains("fields[0].value.window.of.obs_slice (field \"food_seen_10\"): slice 9..18 is out of range"), "{small}");
}

#[test]
fn explain_phases_shows_where_each_phase_sits() {
    let env = ProtocolEnv::new(2, 27, 6, 300, 64);
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../prompts/examples");
    let ps: Vec<Protocol> = ["lbf_8x8_phase0.json", "lbf_8x8_phase2.json"]
        .iter()
        .map(|f| parse_str(&std::fs::read_to_string(dir.join(f)).unwrap()).unwrap())
        .collect();
    let text = explain_phases(&ps, Some(&env));
    assert!(text.contains("2 phase(s) in the compact layout"), "{text}");
    assert!(
        text.contains("  total: 37 columns per receiving agent (each phase on its own: 21 + 18; per receiver before padding: 37, 37)"),
        "{text}"
    );
    let old: Vec<Protocol> = ps
        .iter()
        .map(|p| {
            let mut p = p.clone();
            p.layout = MessageLayout::SenderBlocks;
            p
        })
        .collect();
    let text = explain_phases(&old, Some(&env));
    assert!(
        text.contains("  columns 0..21: lbf_8x8_phase0 (21 columns)\n  columns 21..39: lbf_8x8_phase2 (18 columns)\n  total: 39 columns"),
        "{text}"
    );
    assert!(text.contains("Protocol lbf_8x8_phase0 (phase 0: initialization)"));
    assert!(text.lines().filter(|l| !l.trim_start().starts_with("value:")).all(|l| l.chars().count() <= 100), "{text}");
}

#[test]
fn language_reference_states_the_environment_numbers() {
    let env = ProtocolEnv::new(3, 40, 9, 120, 150);
    let text = language_reference(Some(&env));
    assert!(text.contains("must not exceed 150 columns"));
    assert!(text.contains("(width 9; zeros on the first step)"));
    assert!(text.contains("dims 0..=39"));
    assert!(language_reference(None).contains("0..state_dim"));
}

#[test]
fn explain_shows_the_compact_layout_per_receiver() {
    let env = ProtocolEnv::new(3, 4, 3, 5, 100);
    let v = serde_json::json!({
        "message_design_instruction": "test", "critical_state_dims": [0],
        "fields": [
            {"name": "a", "description": "d", "value": {"obs": [1, 3]}},
            {"name": "b", "description": "d", "senders": [0], "receivers": {"agents": [2]}, "value": {"obs": [0, 1]}}
        ]
    });
    let text = explain(&parse_value(&v).unwrap(), Some(&env)).split_whitespace().collect::<Vec<_>>().join(" ");
    // Receivers: 0 gets [3 | a] from 1 and 2 (10); 1 the same (10); 2 gets [3 | a | b] from 0
    // and [3 | a] from 1 (12). Sender blocks: 2 x (3 + 4) = 14.
    assert!(text.contains("each receiving agent gets 12 columns"), "{text}");
    assert!(text.contains("(10..12 columns used per receiver; the sender-blocks layout would need 14)"), "{text}");
    assert!(text.contains("agent 1 (10 of 12 columns) receives from agent 0: a; from agent 2: a"), "{text}");
    let mut old = v.clone();
    old["layout"] = serde_json::json!("sender_blocks");
    let text = explain(&parse_value(&old).unwrap(), Some(&env)).split_whitespace().collect::<Vec<_>>().join(" ");
    assert!(text.contains("each receiving agent gets 14 columns"), "{text}");
    assert!(text.contains("Layout (sender_blocks)"), "{text}");
}

/// Where agents observe different things, a field every agent sends is explained in each
/// kind of sender's own meanings.
#[test]
fn explain_reads_each_senders_values_in_its_own_meanings() {
    let mut env = ProtocolEnv::new(2, 2, 3, 2, 8);
    env.obs_names = vec!["shared 0".into(), "shared 1".into()];
    env.agent_obs_names = vec![vec!["goal colour".into(), "padding".into()], vec!["own velocity".into(), "padding".into()]];
    let p = parse_str(
        r#"{"message_design_instruction": "x", "critical_state_dims": [0], "fields": [
            {"name": "first", "description": "the first value", "senders": "all", "receivers": "broadcast", "value": {"obs": [0]}}]}"#,
    )
    .unwrap();
    let text = explain(&p, Some(&env));
    assert!(
        text.contains("value from agent 0: obs[0] (goal colour)") && text.contains("value from agent 1: obs[0] (own velocity)"),
        "{text}"
    );
    // Agents that read alike: one value line, in the shared names.
    env.agent_obs_names.clear();
    let text = explain(&p, Some(&env));
    assert!(text.contains("value: obs[0] (shared 0)"), "{text}");
}
