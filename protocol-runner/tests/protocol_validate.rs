//! Validation errors are precise (path, field, numbers) and LLM-friendly.

use lmac_protocol_runner::protocol::*;
use serde_json::json;

fn lbf() -> ProtocolEnv {
    ProtocolEnv::new(2, 27, 6, 300, 64)
}

fn examples_dir() -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../prompts/examples")
}

/// A minimal valid protocol as a JSON value, to be edited by each test.
fn base() -> serde_json::Value {
    json!({
        "name": "t",
        "message_design_instruction": "share food levels",
        "critical_state_dims": [3, {"start": 100, "end": 110}],
        "fields": [
            {"name": "food", "description": "food levels in view", "value": {"obs_slice": {"start": 9, "end": 18}}},
            {"name": "moves", "description": "free moves N S W E", "value": {"obs": [19, 25, 21, 23]}}
        ]
    })
}

fn errors(v: serde_json::Value, env: &ProtocolEnv) -> Vec<String> {
    let p = parse_value(&v).map_err(|e| format!("{e:?}")).expect("parses");
    match validate(&p, env) {
        Ok(_) => panic!("expected errors"),
        Err(es) => es.iter().map(|e| e.to_string()).collect(),
    }
}

fn one_error(v: serde_json::Value, env: &ProtocolEnv) -> String {
    let es = errors(v, env);
    assert_eq!(es.len(), 1, "{es:#?}");
    es.into_iter().next().unwrap()
}

#[test]
fn examples_validate_with_expected_widths() {
    let p0 = check_file(examples_dir().join("lbf_8x8_phase0.json"), &lbf()).unwrap();
    assert_eq!(p0.field_widths, vec![9, 4, 6]);
    assert_eq!(p0.width, 2 + 9 + 4 + 6);
    assert_eq!(p0.critical_dims.len(), 200);
    let p2 = validate_phase(
        &parse_str(&std::fs::read_to_string(examples_dir().join("lbf_8x8_phase2.json")).unwrap()).unwrap(),
        &lbf(),
        std::slice::from_ref(&p0),
    )
    .unwrap();
    assert_eq!(p2.field_widths, vec![9, 6, 1]);
    assert_eq!(p2.width, 2 + 16);
    // Compact: the sender's one-hot (2 columns) once for both phases; sender blocks: 21 + 18.
    assert_eq!(check_phases(&[p0.clone(), p2.clone()], &lbf()).unwrap(), 2 + 19 + 16);
    let p1 = check_file(examples_dir().join("lbf_8x8_phase1.json"), &lbf()).unwrap();
    assert_eq!((p1.field_widths.clone(), p1.width), (vec![4, 1], 7));
    assert_eq!(check_phases(&[p0.clone(), p1.clone(), p2.clone()], &lbf()).unwrap(), 2 + 19 + 5 + 16);
    let blocks: Vec<ValidatedProtocol> = [p0, p1, p2]
        .iter()
        .map(|v| {
            let mut p = v.protocol.clone();
            p.layout = MessageLayout::SenderBlocks;
            validate(&p, &lbf()).unwrap()
        })
        .collect();
    assert_eq!(check_phases(&blocks, &lbf()).unwrap(), 21 + 7 + 18);
    // Every example in the directory is valid for LBF 8x8.
    for e in std::fs::read_dir(examples_dir()).unwrap() {
        let path = e.unwrap().path();
        if path.file_name().unwrap().to_string_lossy().starts_with("lbf_8x8") {
            check_file(&path, &lbf()).unwrap_or_else(|e| panic!("{}: {}", path.display(), errors_to_text(&e)));
        }
    }
}

#[test]
fn obs_dim_out_of_range_names_path_field_and_range() {
    let mut v = base();
    v["fields"][1]["value"] = json!({"obs": [19, 25, 30]});
    assert_eq!(
        one_error(v, &lbf()),
        "fields[1].value.obs[2] (field \"moves\"): observation dim 30 is out of range: obs_dim is 27, valid dims are 0..=26"
    );
    let mut v = base();
    v["fields"][0]["value"] = json!({"mul": [{"const": 2}, {"obs_slice": {"start": 20, "end": 28}}]});
    assert_eq!(
        one_error(v, &lbf()),
        "fields[0].value.mul[1].obs_slice (field \"food\"): slice 20..28 is out of range: end is exclusive and at most obs_dim = 27 (valid dims are 0..=26)"
    );
    let mut v = base();
    v["fields"][0]["value"] = json!({"obs_slice": {"start": 5, "end": 5}});
    assert!(one_error(v, &lbf()).contains("empty slice: start 5 must be below end 5"));
}

#[test]
fn width_mismatch_reports_both_widths() {
    let mut v = base();
    v["fields"][0]["value"] = json!({"add": [{"obs_slice": {"start": 9, "end": 18}}, {"last_action": "one_hot"}]});
    assert_eq!(
        one_error(v, &lbf()),
        "fields[0].value.add (field \"food\"): width mismatch: add[0] has width 9 and add[1] has width 6; elementwise operators need equal widths or one side of width 1"
    );
    // Width 1 broadcasts.
    let mut v = base();
    v["fields"][0]["value"] =
        json!({"sub": [{"obs_slice": {"start": 9, "end": 18}}, {"reduce": {"op": "mean", "of": {"obs_slice": {"start": 9, "end": 18}}}}]});
    let p = validate(&parse_value(&v).unwrap(), &lbf()).unwrap();
    assert_eq!(p.field_widths[0], 9);
}

#[test]
fn budget_error_explains_the_arithmetic() {
    let env = ProtocolEnv::new(3, 27, 6, 300, 20);
    let mut blocks = base();
    blocks["layout"] = json!("sender_blocks");
    let e = one_error(blocks, &env);
    // 2 blocks x (3 + 9 + 4) = 32 > 20
    assert_eq!(
        e,
        "fields: the message is 32 columns per receiving agent but only 20 are available: width = (n_agents - 1 = 2) sender blocks x (3 sender one-hot + 13 field columns: food=9, moves=4) (layout sender_blocks). Remove or narrow fields (e.g. aggregate with reduce, or pick fewer obs dims) by at least 6 columns per block, or use the default compact layout"
    );
    // Compact: a full broadcast costs the same, and the text names the widest receiver.
    let e = one_error(base(), &env);
    assert_eq!(
        e,
        "fields: the message is 32 columns per receiving agent but only 20 are available: the widest receiver, agent 0, is reached by 2 sender(s), each costing 3 sender one-hot columns plus the fields it sends there (columns per sender 1: 16, 2: 16; field widths food=9, moves=4). Remove at least 12 columns there: send fewer fields to that agent (receivers/peer links), narrow fields (e.g. aggregate with reduce, or pick fewer obs dims), or have fewer agents send to it"
    );
    // Sending `food` only from 0 to 1: receiver 1 gets [3 | 9 | 4] from 0 and [3 | 4] from 2
    // (23), the others 2 x [3 | 4] (14); 23 of a budget of 23, where sender blocks need 32.
    let mut peer = base();
    peer["fields"][0]["senders"] = json!([0]);
    peer["fields"][0]["receivers"] = json!({"agents": [1]});
    let v = validate(&parse_value(&peer).unwrap(), &ProtocolEnv::new(3, 27, 6, 300, 23)).unwrap();
    assert_eq!(((0..3).map(|i| v.receiver_width(i)).collect::<Vec<_>>(), v.width), (vec![14, 23, 14], 23));
    assert_eq!(message_width(&v.protocol, &v.env, &v.field_widths), 32);
    // Earlier phases use part of the budget.
    let env = ProtocolEnv::new(2, 27, 6, 300, 20);
    let first = validate(&parse_value(&base()).unwrap(), &env).unwrap();
    assert_eq!(first.width, 15);
    let errs = validate_phase(&parse_value(&base()).unwrap(), &env, &[first]).unwrap_err();
    assert_eq!(errs[0].kind, ErrorKind::Budget);
    assert!(errs[0].message.contains("only 5 are available (the budget is 20 columns and earlier phases already use 15)"), "{}", errs[0]);
}

#[test]
fn receivers_never_only_the_sender() {
    let mut v = base();
    v["fields"][0]["senders"] = json!([0, 1]);
    v["fields"][0]["receivers"] = json!({"agents": [1]});
    assert_eq!(
        one_error(v, &lbf()),
        "fields[0].receivers.agents (field \"food\"): sender agent 1 would send only to itself: messages go to other agents; add other receivers or remove agent 1 from the senders"
    );
    let mut v = base();
    v["fields"][0]["receivers"] = json!({"peer": [{"from": 0, "to": [0]}, {"from": 1, "to": [0]}]});
    assert_eq!(
        one_error(v, &lbf()),
        "fields[0].receivers.peer[0].to[0] (field \"food\"): agent 0 cannot send to itself: messages go to other agents"
    );
    let mut v = base();
    v["fields"][0]["receivers"] = json!({"peer": [{"from": 0, "to": [1]}]});
    assert_eq!(
        one_error(v, &lbf()),
        "fields[0].receivers.peer (field \"food\"): agent 1 is a sender of this field but has no peer entry: add {\"from\": 1, \"to\": [...]} or restrict \"senders\""
    );
    let mut v = base();
    v["fields"][0]["senders"] = json!([0, 2]);
    assert_eq!(
        one_error(v, &lbf()),
        "fields[0].senders[1] (field \"food\"): sender agent 2 is out of range: n_agents is 2, so agents are 0..=1"
    );
    // The sender listed among the receivers is simply left out.
    let mut v = base();
    v["fields"][0]["receivers"] = json!({"agents": [0, 1]});
    let p = validate(&parse_value(&v).unwrap(), &lbf()).unwrap();
    assert_eq!(p.sends[0], vec![vec![false, true], vec![true, false]]);
}

#[test]
fn windows_are_checked() {
    let mut v = base();
    v["fields"][0]["value"] = json!({"window": {"op": "mean", "k": 0, "of": {"obs": [1]}}});
    assert_eq!(one_error(v, &lbf()), "fields[0].value.window.k (field \"food\"): window length k = 0 is out of range: k must be in 1..=64");
    let mut v = base();
    v["fields"][0]["value"] =
        json!({"window": {"op": "mean", "k": 3, "of": {"neg": {"window": {"op": "max", "k": 2, "of": {"obs": [1]}}}}}});
    assert_eq!(
        one_error(v, &lbf()),
        "fields[0].value.window.of.neg.window (field \"food\"): a window cannot contain another window: aggregate a per-step expression"
    );
}

#[test]
fn numbers_names_and_state_dims_are_checked() {
    let mut v = base();
    v["fields"][0]["value"] = json!({"clip": {"of": {"obs": [1]}, "min": 2, "max": 1}});
    assert_eq!(one_error(v, &lbf()), "fields[0].value.clip (field \"food\"): clip range is empty: min 2 is above max 1");
    let mut v = base();
    v["fields"][1]["name"] = json!("food");
    assert_eq!(one_error(v, &lbf()), "fields[1].name: field name \"food\" is used by an earlier field: field names must be unique");
    let mut v = base();
    v["critical_state_dims"] = json!([3, 300, 3]);
    let es = errors(v, &lbf());
    assert_eq!(
        es,
        vec![
            "critical_state_dims[1]: state dim 300 is out of range: state_dim is 300, valid dims are 0..=299",
            "critical_state_dims[2]: state dim 3 is listed twice"
        ]
    );
    let mut v = base();
    v["message_design_instruction"] = json!("  ");
    assert!(one_error(v, &lbf()).starts_with("message_design_instruction: the design description is empty"));
    let mut v = base();
    v["fields"] = json!([]);
    assert_eq!(one_error(v, &lbf()), "fields: the protocol has no fields: define at least one message field");
}

#[test]
fn several_errors_are_all_reported() {
    let mut v = base();
    v["fields"][0]["value"] = json!({"obs": [99]});
    v["fields"][1]["value"] = json!({"window": {"op": "sum", "k": 65, "of": {"obs": [28]}}});
    let es = errors(v, &lbf());
    assert_eq!(es.len(), 3, "{es:#?}");
    let p = parse_value(&base()).unwrap();
    let text = errors_to_text(&validate(&p, &ProtocolEnv::new(1, 27, 6, 300, 64)).unwrap_err());
    assert!(text.starts_with("The protocol has 1 error(s):\n- the environment has 1 agent(s)"), "{text}");
}

#[test]
fn parse_errors_carry_the_json_path() {
    let mut v = base();
    v["fields"][0]["valeu"] = v["fields"][0]["value"].take();
    v["fields"][0].as_object_mut().unwrap().remove("value");
    let e = parse_value(&v).unwrap_err();
    assert_eq!(e[0].kind, ErrorKind::Parse);
    assert_eq!(e[0].path, "fields[0].valeu");
    assert!(e[0].message.contains("unknown field `valeu`"), "{}", e[0]);

    let mut v = base();
    v["fields"][1]["value"] = json!({"obs_dims": [1]});
    let e = parse_value(&v).unwrap_err();
    assert_eq!(e[0].path, "fields[1].value");
    assert!(e[0].message.contains("unknown variant `obs_dims`, expected one of"), "{}", e[0]);
    assert!(e[0].message.contains("`obs_slice`"), "{}", e[0]);

    let mut v = base();
    v["fields"][1]["senders"] = json!("everyone");
    let e = parse_value(&v).unwrap_err();
    assert_eq!(e[0].path, "fields[1].senders");
    assert!(e[0].message.contains("\"all\" or a list of agent indices"), "{}", e[0]);

    let e = parse_str("{\"name\": ").unwrap_err();
    assert!(e[0].to_string().contains("invalid protocol JSON: EOF while parsing"), "{}", e[0]);
    let e = parse_str(&format!("{} trailing", base())).unwrap_err();
    assert!(e[0].message.contains("trailing"), "{}", e[0]);
}

#[test]
fn llm_answers_with_fences_parse() {
    let text = format!("Here is the protocol:\n```json\n{}\n```\nDone.", serde_json::to_string_pretty(&base()).unwrap());
    let p = parse_llm_text(&text).unwrap();
    assert_eq!(p.fields.len(), 2);
    let p2 = parse_llm_text(&format!("blah {} blah", base())).unwrap();
    assert_eq!(p, p2);
    assert!(parse_llm_text("no json here").is_err());
}

#[test]
fn a_string_broken_over_lines_is_read_as_its_escaped_text() {
    // What a small model wrote (SmolLM2 under a schema grammar): a raw newline inside a string.
    let mut v = base();
    v["message_design_instruction"] = serde_json::json!("first line\tsecond part\nthird line");
    let escaped = serde_json::to_string(&v).unwrap();
    let raw = escaped.replace("\\t", "\t").replace("\\n", "\n");
    assert!(parse_str(&raw).unwrap_err()[0].message.contains("control character"));
    assert_eq!(parse_llm_text(&raw).unwrap(), parse_str(&escaped).unwrap());
    // Escapes already there, quotes and backslashes inside strings, newlines between tokens: as
    // they were.
    let pretty = serde_json::to_string_pretty(&v).unwrap();
    assert_eq!(escape_controls_in_strings(&pretty), pretty);
    assert_eq!(escape_controls_in_strings("{\"a\": \"x\\\"\n\\\\\"}"), "{\"a\": \"x\\\"\\n\\\\\"}");
}

#[test]
fn protocols_round_trip_through_json() {
    for name in ["lbf_8x8_phase0.json", "lbf_8x8_phase2.json"] {
        let p = parse_str(&std::fs::read_to_string(examples_dir().join(name)).unwrap()).unwrap();
        let back = parse_str(&serde_json::to_string(&p).unwrap()).unwrap();
        assert_eq!(p, back);
    }
}

#[test]
fn check_summary_reports_widths_and_budget() {
    let v = check_file(examples_dir().join("lbf_8x8_phase0.json"), &lbf()).unwrap();
    assert_eq!(
        check_summary(&v),
        "OK: lbf_8x8_phase0 (3 field(s): food_in_view=9, free_moves=4, last_action=6): 21 message columns per receiving agent of a budget of 64 (2 agents, 200 critical state dims)"
    );
}

/// A protocol carries the environment it was designed for: used on another environment, or
/// after that environment's schema changed, it still validates when its indices fit, with a
/// warning naming both (before, an LBF protocol compiled silently against any env it fit).
#[test]
fn a_protocol_saved_for_another_environment_or_schema_is_flagged() {
    let mut env = lbf();
    env.env_name = "lbf:8x8-2p-2f-s1-coop".into();
    env.schema_fingerprint = "0123456789abcdef".into();
    let plain = parse_value(&base()).unwrap();
    assert!(validate_phase(&plain, &env, &[]).unwrap().warnings.is_empty(), "no recorded identity, nothing to compare");
    let same = Protocol { env: Some(env.env_name.clone()), schema_fingerprint: Some(env.schema_fingerprint.clone()), ..plain.clone() };
    assert!(validate_phase(&same, &env, &[]).unwrap().warnings.is_empty());
    let other = Protocol { env: Some("smaclite:bane_vs_hM".into()), ..same.clone() };
    let w = validate_phase(&other, &env, &[]).unwrap().warnings;
    assert!(w.len() == 1 && w[0].contains("smaclite:bane_vs_hM") && w[0].contains("lbf:8x8-2p-2f-s1-coop"), "{w:?}");
    let changed = Protocol { schema_fingerprint: Some("fedcba9876543210".into()), ..same };
    let w = validate_phase(&changed, &env, &[]).unwrap().warnings;
    assert!(w.len() == 1 && w[0].contains("fedcba9876543210") && w[0].contains("changed"), "{w:?}");
    // The identity is lmac's, not the LLM's: the JSON Schema an LLM gets does not offer it.
    let schema = serde_json::to_string(&schemars::schema_for!(Protocol)).unwrap();
    assert!(!schema.contains("schema_fingerprint") && !schema.contains("\"env\""));
}
