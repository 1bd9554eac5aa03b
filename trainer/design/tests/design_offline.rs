//! The offline designer on synthetic datasets built here: its phases, its budget, the rules it
//! chooses by (what the return depends on, which agent sends, whole entities, a blind
//! discriminator) and the design loop's verdicts on each phase.

mod common;

use common::*;
use lmac_design::discriminator::DiscriminatorConfig;
use lmac_design::meta::{self, MetaConfig};
use lmac_design::offline::{CriticalBy, FieldsBy, OfflineConfig, OfflineDesigner};
use lmac_design::{DesignContext, Designer, PhaseProtocol};
use lmac_protocol_runner::protocol::{self, ValidatedProtocol};
use lmac_run::dataset::{Dataset, Trajectory};
use lmac_run::learn::LearnRng;

#[test]
fn offline_designer_three_phases() {
    let data = synthetic(400, 8);
    let schema = synthetic_schema(30);
    let env = lmac_protocol_runner::protocol_env(&schema);
    let c = ctx(&schema, &env, &data);
    let ocfg = OfflineConfig { discriminator: quick_disc(), ..OfflineConfig::least_squares_rules() };
    let mcfg = MetaConfig { discriminator: quick_disc(), max_target_dims: 8, ..Default::default() };
    let mut designer = OfflineDesigner::new(ocfg);
    assert!(designer.needs_data_for_initial());
    let mut phases: Vec<PhaseProtocol> = Vec::new();
    let p0 = designer.initial(&c).unwrap();
    eprintln!("phase 0:\n{}\n{}", serde_json::to_string_pretty(&p0.protocol).unwrap(), p0.reasoning);
    assert!(p0.protocol.message_design_instruction.starts_with("offline designer:"));
    // The dims one agent alone sees are critical; the shared bit and the constant are not.
    assert_eq!(p0.validated.critical_dims, vec![0, 3, 4]);
    // Agent 0's o[0] goes to agent 1 and agent 1's o[2] to agent 0: the only useful links.
    let json = serde_json::to_string(&p0.protocol).unwrap();
    assert!(json.contains("\"obs\":[0"), "{json}");
    phases.push(p0);
    let mut means = Vec::new();
    for k in 0..3 {
        let validated: Vec<ValidatedProtocol> = phases.iter().map(|p| p.validated.clone()).collect();
        // Every phase validates against the ones before it.
        for (i, p) in phases.iter().enumerate() {
            protocol::validate_phase(&p.protocol, &env, &validated[..i]).unwrap();
        }
        let m = meta::evaluate(&c, &validated, &mcfg).unwrap();
        eprintln!("phase {k}: {}", m.summary_line());
        means.push((m.summary.with_communication.mean_recovery, m.summary.without_communication.mean_recovery));
        if k == 2 {
            break;
        }
        let fb = designer.feedback(&c, k + 1, &phases, &m).unwrap();
        assert!(fb.evaluation.starts_with("offline designer:") && fb.evaluation.contains("with the messages"), "{}", fb.evaluation);
        assert!(!fb.missing_information_hypothesis.is_empty() && !fb.improvement_suggestions.is_empty());
        let next = designer.refine(&c, k + 1, &phases, &fb, &m).unwrap();
        eprintln!("phase {}:\n{}\n{}", k + 1, serde_json::to_string_pretty(&next.protocol).unwrap(), next.reasoning);
        assert!(next.protocol.message_design_instruction.starts_with("offline designer:"));
        phases.push(next);
    }
    // Messages raise recovery well above the no-message baseline, and the later phases (memory
    // of the episode constant seen every 4th step) raise it further.
    assert!(means[0].0 > means[0].1 + 0.2, "{means:?}");
    assert!(means[2].0 > means[0].0 + 0.02, "{means:?}");
    let total: usize = phases.iter().map(|p| p.validated.width).sum();
    assert!(total <= 30);
    let t = designer.transcript();
    let kinds: Vec<&str> = t.iter().map(|e| e.kind.as_str()).collect();
    assert_eq!(kinds, vec!["relevance", "critical_dims", "protocol", "feedback", "protocol", "feedback", "protocol"]);
    // No reward on this dataset: the relevance ranking cannot be used, and phase 0 says so.
    assert!(t[1].reply.contains("falls back to the hardest dims to recover"), "{}", t[1].reply);
    // Deterministic: the same inputs give the same phase 0.
    let mut again = OfflineDesigner::new(OfflineConfig { discriminator: quick_disc(), ..OfflineConfig::least_squares_rules() });
    assert_eq!(again.initial(&c).unwrap().protocol, phases[0].protocol);
    // Told that the newest phase added nothing, the designer asks more of the next one.
    let validated: Vec<ValidatedProtocol> = phases[..2].iter().map(|p| p.validated.clone()).collect();
    let mut m = meta::evaluate(&c, &validated, &mcfg).unwrap();
    m.newest_phase_added = Some(false);
    let fb = designer.feedback(&c, 2, &phases[..2], &m).unwrap();
    let stricter = designer.refine(&c, 2, &phases[..2], &fb, &m).unwrap();
    assert!(stricter.reasoning.contains("Phase 1 added nothing") && stricter.reasoning.contains("2x min_gain"), "{}", stricter.reasoning);
}

#[test]
fn offline_designer_reports_an_exhausted_budget() {
    let data = synthetic(60, 9);
    // 2 agents: one sender block of 2 one-hot columns + 1 value needs 3 columns.
    let schema = synthetic_schema(2);
    let env = lmac_protocol_runner::protocol_env(&schema);
    let c = ctx(&schema, &env, &data);
    let mut designer = OfflineDesigner::new(OfflineConfig {
        discriminator: DiscriminatorConfig { updates: 50, ..Default::default() },
        ..OfflineConfig::least_squares_rules()
    });
    let e = format!("{:#}", designer.initial(&c).unwrap_err());
    assert!(e.contains("no message budget for phase 0"), "{e}");
}

// ------------------------------------------------------------------------------------------
// Design-sized run (ignored by default: about a minute). A random-policy walk on an LBF 8x8
// grid built here with the real schema's layout (3x3x3 views and own position, 3 x 10 x 10 padded state), 5000
// episodes of 25 steps as in the paper, the default configurations, three phases. Prints the
// time of each stage: `cargo test --release -p lmac-design --test design_data -- --ignored --nocapture`.

fn lbf_walk(episodes: usize, seed: u64) -> Dataset {
    let (n, od, sd, na, limit, size) = (2usize, 29usize, 300usize, 6usize, 25usize, 8i32);
    let mut rng = LearnRng::seed_from(seed);
    let mut eps = Vec::new();
    for _ in 0..episodes {
        // Cells in field coordinates 0..8; padded = field + 1.
        let mut taken: Vec<(i32, i32)> = Vec::new();
        let mut place = |rng: &mut LearnRng| loop {
            let c = (rng.below(size as usize) as i32, rng.below(size as usize) as i32);
            if !taken.contains(&c) {
                taken.push(c);
                return c;
            }
        };
        let mut agents: Vec<(i32, i32)> = (0..n).map(|_| place(&mut rng)).collect();
        let mut food: Vec<(i32, i32)> = (0..2).map(|_| place(&mut rng)).collect();
        let mut tr = Trajectory::default();
        for t in 0..limit {
            let level = |r: i32, c: i32, agents: &[(i32, i32)], food: &[(i32, i32)]| -> [f32; 3] {
                let inside = (0..size).contains(&r) && (0..size).contains(&c);
                let a = agents.contains(&(r, c)) as u8 as f32;
                let f = 2.0 * food.contains(&(r, c)) as u8 as f32;
                [a, f, (inside && a == 0.0 && f == 0.0) as u8 as f32]
            };
            for &(ar, ac) in &agents {
                let mut o = [0f32; 29];
                for dr in -1..=1 {
                    for dc in -1..=1 {
                        let v = level(ar + dr, ac + dc, &agents, &food);
                        let k = ((dr + 1) * 3 + dc + 1) as usize;
                        for l in 0..3 {
                            o[l * 9 + k] = v[l];
                        }
                    }
                }
                // Own row and column, scaled to [0, 1] as the LBF env server writes them.
                o[27] = ar as f32 / (size - 1) as f32;
                o[28] = ac as f32 / (size - 1) as f32;
                tr.obs.extend_from_slice(&o);
            }
            let mut s = [0f32; 300];
            for pr in 0..10 {
                for pc in 0..10 {
                    let v = level(pr - 1, pc - 1, &agents, &food);
                    for l in 0..3 {
                        s[l * 100 + (pr * 10 + pc) as usize] = v[l];
                    }
                }
            }
            tr.state.extend_from_slice(&s);
            let acts: Vec<i32> = (0..n).map(|_| rng.below(na) as i32).collect();
            tr.actions.extend_from_slice(&acts);
            let mut reward = 0.0;
            // Loading: both agents load next to the same food.
            if acts.iter().all(|&a| a == 5) {
                if let Some(k) = food.iter().position(|&(fr, fc)| agents.iter().all(|&(r, c)| (r - fr).abs() + (c - fc).abs() == 1)) {
                    food.remove(k);
                    reward = 0.5;
                }
            }
            for (i, &a) in acts.iter().enumerate() {
                let (r, c) = agents[i];
                let to = match a {
                    1 => (r - 1, c),
                    2 => (r + 1, c),
                    3 => (r, c - 1),
                    4 => (r, c + 1),
                    _ => (r, c),
                };
                if to != (r, c) && (0..size).contains(&to.0) && (0..size).contains(&to.1) && !agents.contains(&to) && !food.contains(&to) {
                    agents[i] = to;
                }
            }
            tr.reward.push(reward);
            tr.len += 1;
            if food.is_empty() {
                tr.terminated = true;
                break;
            }
            tr.truncated = t + 1 == limit;
        }
        eps.push(tr);
    }
    Dataset { header: header("lbf:8x8-2p-2f-s1-coop", n, od, sd, na, limit), episodes: eps }
}

#[test]
#[ignore]
fn design_sized_run() {
    let t0 = std::time::Instant::now();
    let data = lbf_walk(5000, 12);
    eprintln!("dataset: {} episodes, {} steps, built in {:.1} s", data.episodes.len(), data.steps(), t0.elapsed().as_secs_f64());
    let schema = lmac_shm_schema::schema::load_env("lbf:8x8-2p-2f-s1-coop").unwrap();
    let env = lmac_protocol_runner::protocol_env(&schema);
    let c = DesignContext { env_name: "lbf:8x8-2p-2f-s1-coop", schema: &schema, env: &env, dataset: Some(&data), seed: 1 };
    let mut designer = OfflineDesigner::default();
    let mcfg = MetaConfig::default();
    let t = std::time::Instant::now();
    let mut phases = vec![designer.initial(&c).unwrap()];
    eprintln!("phase 0 designed in {:.1} s: {}", t.elapsed().as_secs_f64(), phases[0].protocol.message_design_instruction);
    for k in 0..3 {
        let validated: Vec<ValidatedProtocol> = phases.iter().map(|p| p.validated.clone()).collect();
        let t = std::time::Instant::now();
        let m = meta::evaluate(&c, &validated, &mcfg).unwrap();
        eprintln!("phase {k} evaluated in {:.1} s: {}", t.elapsed().as_secs_f64(), m.summary_line());
        eprintln!("  discriminator: {}", serde_json::to_string(&m.discriminators.with_communication).unwrap());
        if k == 2 {
            break;
        }
        let t = std::time::Instant::now();
        let fb = designer.feedback(&c, k + 1, &phases, &m).unwrap();
        let next = designer.refine(&c, k + 1, &phases, &fb, &m).unwrap();
        eprintln!("feedback: {}\n{}\n{}", fb.evaluation, fb.missing_information_hypothesis, fb.improvement_suggestions);
        eprintln!("phase {} designed in {:.1} s: {}", k + 1, t.elapsed().as_secs_f64(), next.protocol.message_design_instruction);
        phases.push(next);
    }
    eprintln!("design total {:.1} s", t0.elapsed().as_secs_f64());
}

// ------------------------------------------------------------------------------------------
// Dead fields

#[test]
fn dead_fields_are_constant_or_copied_links() {
    let data = synthetic(40, 3);
    let schema = synthetic_schema(24);
    let env = lmac_protocol_runner::protocol_env(&schema);
    // Agent 0 -> agent 1: o[2] (always 0 for agent 0), o[1] (the shared bit agent 1 sees
    // itself), o[0] (hidden value A: information), and [o[0], o[2]] (one live column).
    let p0 = phase_from(
        r#"{"message_design_instruction": "x", "critical_state_dims": [0], "fields": [
            {"name": "zero", "description": "z", "senders": [0], "receivers": {"peer": [{"from": 0, "to": [1]}]}, "value": {"obs": [2]}},
            {"name": "bit", "description": "b", "senders": [0], "receivers": {"peer": [{"from": 0, "to": [1]}]}, "value": {"obs": [1]}},
            {"name": "value", "description": "v", "senders": [0], "receivers": {"peer": [{"from": 0, "to": [1]}]}, "value": {"obs": [0]}},
            {"name": "mixed", "description": "m", "senders": [0], "receivers": {"peer": [{"from": 0, "to": [1]}]}, "value": {"obs": [0, 2]}}]}"#,
        &env,
        &[],
    );
    let dead = lmac_design::dead_fields::find(&data, &[p0.clone()], &env).unwrap();
    let names: Vec<(&str, usize, usize)> = dead.iter().map(|d| (d.field.as_str(), d.sender, d.receiver)).collect();
    assert_eq!(names, vec![("zero", 0, 1), ("bit", 0, 1)], "{dead:?}");
    use lmac_design::dead_fields::DeadColumn;
    assert_eq!(dead[0].columns, vec![DeadColumn::Constant(0.0)]);
    assert_eq!(dead[1].columns, vec![DeadColumn::CopyOfObs(1)]);
    assert!(dead[1].describe().contains("equals the receiver's own o[1]"), "{}", dead[1].describe());
    // In the design loop the designer reads them with the meta-information.
    let cfg = MetaConfig { discriminator: quick_disc(), max_target_dims: 2, ..Default::default() };
    let m = meta::evaluate(&ctx(&schema, &env, &data), &[p0], &cfg).unwrap();
    assert_eq!(m.dead_fields.len(), 2, "{:?}", m.dead_fields);
    assert!(m.json()["dead_fields"][0].as_str().unwrap().contains("field `zero` from agent 0 to agent 1"));
}

// ------------------------------------------------------------------------------------------
// The fixed-dim trend

#[test]
fn phase_evaluation_reads_the_trend_on_fixed_dims_with_both_definitions() {
    use lmac_design::run::{evaluate_phase, fixed_dims};
    let data = synthetic(300, 6);
    let schema = synthetic_schema(24);
    let env = lmac_protocol_runner::protocol_env(&schema);
    // Phase 0 sends hidden value A (s[0], seen by agent 0 only) to agent 1 and names s[0] and
    // s[3] as critical; phase 1 adds a field about s[3] but names other critical dims, which
    // must not move the fixed set.
    let p0 = phase_from(
        r#"{"message_design_instruction": "x", "critical_state_dims": [3, 0], "fields": [
            {"name": "a", "description": "v", "senders": [0], "receivers": {"peer": [{"from": 0, "to": [1]}]}, "value": {"obs": [0]}}]}"#,
        &env,
        &[],
    );
    let p1 = phase_from(
        r#"{"message_design_instruction": "y", "critical_state_dims": [4], "fields": [
            {"name": "b", "description": "v", "senders": [1], "receivers": {"peer": [{"from": 1, "to": [0]}]}, "value": {"obs": [2]}}]}"#,
        &env,
        &[p0.clone()],
    );
    let (fixed, source) = fixed_dims(&p0);
    assert_eq!((fixed.clone(), source), (vec![0, 3], "phase 0's critical state dims"));
    let cfg = MetaConfig { discriminator: quick_disc(), max_target_dims: 8, ..Default::default() };
    let dir = tmp_dir("trend");
    let c = ctx(&schema, &env, &data);
    let (_, e0) = evaluate_phase(&c, &[p0.clone()], 0, &fixed, &cfg, &dir.join("phase0")).unwrap();
    let (_, e1) = evaluate_phase(&c, &[p0, p1], 1, &fixed, &cfg, &dir.join("phase1")).unwrap();
    assert_eq!((e0.fixed_dims.dims, e1.fixed_dims.dims), (2, 2));
    assert_eq!(e1.all_dims.dims, 5);
    // Phase 1 brings s[3] to agent 0: the fixed-dim recovery of agent 0 rises with messages, not
    // without (a retrained discriminator never sees them).
    let (a0, a1) = (e0.fixed_dims.with_messages.per_agent[0], e1.fixed_dims.with_messages.per_agent[0]);
    assert!(a1 > a0 + 0.2, "agent 0 on the fixed dims: {a0} after phase 0, {a1} after phase 1");
    let w = &e1.fixed_dims;
    assert!(w.with_messages.skill > w.without_retrained.skill + 0.2, "{w:?}");
    // The paper's definition: the with-messages discriminator given zeroed messages loses what
    // the messages carried.
    assert!(w.without_zeroed.mean_recovery < w.with_messages.mean_recovery, "{w:?}");
    // Every dim is written, with its constant guess and per-agent rates for all three.
    let rec: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(dir.join("phase1/recovery.json")).unwrap()).unwrap();
    let dims = rec["dims"].as_array().unwrap();
    assert_eq!(dims.len(), 5);
    for d in dims {
        for side in ["with_messages", "without_retrained", "without_zeroed"] {
            assert_eq!(d[side].as_array().unwrap().len(), 2, "{d}");
        }
        assert!(d["constant_guess_rate"].is_number());
    }
    assert!(dir.join("phase1/meta.json").exists());
}

/// With a return that depends on hidden value B (state dim 3, seen by agent 1 only),
/// relevance picks that dim alone; hidden value A and the episode constant are as hard to
/// recover but the return does not depend on them. `critical_by = recovery` keeps the old rule.
#[test]
fn offline_designer_chooses_what_the_return_depends_on() {
    let data = hidden_b_rewarded();
    let schema = synthetic_schema(30);
    let env = lmac_protocol_runner::protocol_env(&schema);
    let c = ctx(&schema, &env, &data);
    let mut designer = OfflineDesigner::new(OfflineConfig { discriminator: quick_disc(), ..OfflineConfig::least_squares_rules() });
    let p0 = designer.initial(&c).unwrap();
    let rel = designer.relevance().expect("phase 0 measured relevance");
    assert_eq!(rel.ranking()[0], 3, "{rel:?}");
    assert!(rel.held_out_r2 > 0.05, "the return-to-go is mostly future noise, but h3 explains part of it: {rel:?}");
    assert_eq!(p0.validated.critical_dims, vec![3], "{}", p0.reasoning);
    let t = designer.transcript();
    assert!(t[0].kind == "relevance" && t[0].reply.contains("s[3] - hidden value B: relevance"), "{}", t[0].reply);
    assert!(t[0].reply.contains("CHOSEN"), "{}", t[0].reply);
    // Agent 1's o[2] (hidden value B) goes to agent 0.
    let json = serde_json::to_string(&p0.protocol).unwrap();
    assert!(json.contains("\"obs\":[2"), "{json}");
    let mut old = OfflineDesigner::new(OfflineConfig {
        discriminator: quick_disc(),
        critical_by: CriticalBy::Recovery,
        ..OfflineConfig::least_squares_rules()
    });
    assert_eq!(old.initial(&c).unwrap().validated.critical_dims, vec![0, 3, 4]);
    // `--critical-by action`: this B's actions are random, so no model of them explains
    // anything; phase 0 says so in the actions' terms and ranks the dims by the return instead.
    let mut by_action = OfflineDesigner::new(OfflineConfig {
        discriminator: quick_disc(),
        critical_by: CriticalBy::Action,
        ..OfflineConfig::least_squares_rules()
    });
    assert_eq!(by_action.initial(&c).unwrap().validated.critical_dims, vec![3]);
    let t = by_action.transcript();
    assert!(t[0].kind == "relevance" && t[0].reply.starts_with("A linear model of each agent's action"), "{}", t[0].reply);
    assert!(t[1].kind == "relevance" && t[1].reply.starts_with("A value model of the state"), "{}", t[1].reply);
    let critical = t.iter().find(|e| e.kind == "critical_dims").unwrap();
    assert!(
        critical.reply.contains("of the held-out actions' variance") && critical.reply.contains("ranked by the return instead"),
        "{}",
        critical.reply
    );
    let measured = by_action.measurements().unwrap();
    assert!(measured["relevance"]["what"].as_str().unwrap().starts_with("permutation importance"), "{measured}");
}

/// Agent 0 acts on hidden value B (action 2 when it is 1 or more, else 0), which only agent 1 sees; agent 1 acts at
/// random. By the actions, s[3] is critical, and the design log and `measurements()` say that
/// agent 0 needs it (its actions depend on it and it cannot recover it) and agent 1 supplies it
/// best; agent 1 needs it hardly at all.
#[test]
fn each_agents_need_and_its_supplier_are_measured_and_said() {
    let mut data = hidden_b_rewarded();
    for ep in &mut data.episodes {
        for t in 0..ep.len {
            ep.actions[t * SYN_N] = if ep.state[t * SYN_SD + 3] >= 1.0 { 2 } else { 0 };
        }
    }
    let schema = synthetic_schema(30);
    let env = lmac_protocol_runner::protocol_env(&schema);
    let c = ctx(&schema, &env, &data);
    let mut designer = OfflineDesigner::new(OfflineConfig {
        discriminator: quick_disc(),
        critical_by: CriticalBy::Action,
        ..OfflineConfig::least_squares_rules()
    });
    let p0 = designer.initial(&c).unwrap();
    assert!(p0.validated.critical_dims.contains(&3), "{}", p0.reasoning);
    let measured = designer.measurements().unwrap();
    let needs = measured["needs"].as_array().unwrap();
    assert_eq!(needs.len(), SYN_N, "{measured}");
    let of = |agent: usize| needs[agent]["dims"].as_array().unwrap().iter().find(|d| d["dim"] == 3).unwrap().clone();
    let (a0, a1) = (of(0), of(1));
    assert_eq!(needs[0]["dims"][0]["dim"], 3, "agent 0 needs hidden value B most: {measured}");
    assert_eq!(a0["supplier"], 1, "agent 1 sees it: {a0}");
    assert!(a0["failure"].as_f64().unwrap() > 0.5 && a0["action_dependence"].as_f64().unwrap() > 0.05, "{a0}");
    assert!(a1["need"].as_f64().unwrap() < a0["need"].as_f64().unwrap() / 5.0, "agent 1 acts at random and sees B: {a1} vs {a0}");
    let t = designer.transcript();
    let log = t.iter().find(|e| e.kind == "needs").expect("the needs in the design log");
    assert!(log.reply.contains("agent 0: s[3] - hidden value B") && log.reply.contains("best recovered by agent 1"), "{}", log.reply);
    // The ranking is printed by the quantity the choice is made by.
    let ranking = t.iter().find(|e| e.kind == "relevance").unwrap();
    assert!(ranking.reply.contains("Dims by relevance x (1 - skill), the order the choice is made in:\n1. s[3]"), "{}", ranking.reply);
}

/// The observer-and-actors game (agent 0 sees the goal and cannot act; agents 1 and 2 act on
/// it and cannot see it; agent 3 is a bystander): by default (routed by need) the observer sends
/// the goal to the two actors only, never to the bystander; `--receivers-by everyone` sends it to
/// all three.
#[test]
fn by_default_the_observer_sends_the_goal_to_the_actors_only() {
    let data = observer_and_actors(400, 11);
    let schema = observer_and_actors_schema();
    let env = lmac_protocol_runner::protocol_env(&schema);
    let c = DesignContext { env_name: "synthetic:observer-and-actors", schema: &schema, env: &env, dataset: Some(&data), seed: 5 };
    let mut designer = OfflineDesigner::new(OfflineConfig { discriminator: quick_disc(), ..OfflineConfig::default() });
    let p0 = designer.initial(&c).unwrap();
    assert!(p0.validated.critical_dims.contains(&0), "the goal is critical: {}", p0.reasoning);
    let measured = designer.measurements().unwrap();
    let needs = measured["needs"].as_array().unwrap();
    let need_of = |i: usize| needs[i]["dims"].as_array().unwrap().iter().map(|x| x["need"].as_f64().unwrap()).sum::<f64>();
    let least = need_of(1).min(need_of(2));
    assert!(least > 0.05 && need_of(0) < 0.1 * least && need_of(3) < 0.1 * least, "{measured}");
    let goal_of = |i: usize| needs[i]["dims"].as_array().unwrap().iter().find(|x| x["dim"] == 0).unwrap().clone();
    assert_eq!(goal_of(1)["supplier"], 0, "{measured}");
    let protocol = serde_json::to_value(&p0.protocol).unwrap();
    assert!(!p0.protocol.fields.is_empty(), "{protocol}");
    for f in protocol["fields"].as_array().unwrap() {
        assert_eq!(f["senders"], serde_json::json!([0]), "only the observer sends: {protocol}");
        let to: Vec<u64> = f["receivers"]["peer"][0]["to"].as_array().unwrap().iter().map(|v| v.as_u64().unwrap()).collect();
        assert_eq!(to, vec![1, 2], "to the two actors: {protocol}");
    }
    assert!(sent_obs(&protocol).contains(&0), "the goal value is sent: {protocol}");
    // Named as the observer sees it (its own meanings in the schema), not as the bystander does.
    let description = protocol["fields"][0]["description"].as_str().unwrap();
    assert!(description.contains("o[0] (the goal)"), "{description}");
    let everyone = OfflineConfig {
        discriminator: quick_disc(),
        receivers_by: lmac_design::offline::ReceiversBy::Everyone,
        ..OfflineConfig::default()
    };
    let p0 = OfflineDesigner::new(everyone).initial(&c).unwrap();
    let protocol = serde_json::to_value(&p0.protocol).unwrap();
    let to: Vec<u64> =
        protocol["fields"][0]["receivers"]["peer"][0]["to"].as_array().unwrap().iter().map(|v| v.as_u64().unwrap()).collect();
    assert_eq!(to, vec![1, 2, 3], "every other agent, the bystander too: {protocol}");
}

/// A sender's entities are its own groups': where the shared groups make the whole view one
/// entity (as the bystander reads it), the observer's own groups make the goal one entity, and
/// the designer ranks and sends that.
#[test]
fn the_designer_ranks_each_senders_own_entities() {
    let data = observer_and_actors(400, 11);
    let mut schema = observer_and_actors_schema();
    schema.obs_dims = vec![group(3, "the bystander's view (unused, unused, the shared bit)")];
    let env = lmac_protocol_runner::protocol_env(&schema);
    let c = DesignContext { env_name: "synthetic:observer-and-actors", schema: &schema, env: &env, dataset: Some(&data), seed: 5 };
    let mut designer = OfflineDesigner::new(OfflineConfig { discriminator: quick_disc(), ..OfflineConfig::default() });
    let p0 = designer.initial(&c).unwrap();
    let ranking = designer.transcript().iter().find(|e| e.kind == "observation_relevance").expect("the ranking is logged").reply.clone();
    let goal = ranking.lines().find(|l| l.contains("agent 0's the goal (o[0..1])")).unwrap_or_else(|| panic!("{ranking}"));
    assert!(goal.contains("CHOSEN"), "{goal}");
    assert!(!ranking.contains("agent 0's the bystander's view"), "{ranking}");
    let protocol = serde_json::to_value(&p0.protocol).unwrap();
    assert!(sent_obs(&protocol).contains(&0), "the goal is sent: {protocol}");
}

/// The return depends on hidden value B, which
/// only agent 1 sees (its o[2]). Sending all of agent 1's observation raises agent 0's recovery
/// of s[3]; agent 0's observation tells agent 1 nothing it lacks. So agent 1 is the one
/// sender, and o[2] is among what it sends, to agent 0.
#[test]
fn observation_relevance_chooses_the_agent_that_sees_what_matters() {
    let data = hidden_b_rewarded();
    let schema = synthetic_schema(30);
    let env = lmac_protocol_runner::protocol_env(&schema);
    let c = ctx(&schema, &env, &data);
    let cfg =
        OfflineConfig { discriminator: quick_disc(), fields_by: FieldsBy::ObservationRelevance, ..OfflineConfig::least_squares_rules() };
    let mut designer = OfflineDesigner::new(cfg);
    let p0 = designer.initial(&c).unwrap();
    assert_eq!(p0.validated.critical_dims, vec![3], "{}", p0.reasoning);
    let t = designer.transcript();
    let obs_rel = t.iter().find(|e| e.kind == "observation_relevance").expect("the ranking is in the transcript");
    assert!(obs_rel.reply.contains("agent 1: all it sees") && obs_rel.reply.contains("a SENDER"), "{}", obs_rel.reply);
    let sender_line = obs_rel.reply.lines().find(|l| l.contains("a SENDER")).unwrap();
    assert!(sender_line.starts_with("agent 1:"), "{}", obs_rel.reply);
    assert!(
        p0.protocol.message_design_instruction.contains("by the relevance of what each agent sees"),
        "{}",
        p0.protocol.message_design_instruction
    );
    let json = serde_json::to_value(&p0.protocol).unwrap();
    for f in json["fields"].as_array().unwrap() {
        assert_eq!(f["senders"], serde_json::json!([1]), "{f}");
    }
    let sent = sent_obs(&json);
    assert!(sent.contains(&2), "agent 1's view of hidden value B is sent: {json}");
}

/// The observation values a protocol's fields send (`{"obs": [...]}` fields), in field order.
fn sent_obs(protocol: &serde_json::Value) -> Vec<u64> {
    protocol["fields"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|f| f["value"]["obs"].as_array().cloned().unwrap_or_default())
        .map(|v| v.as_u64().unwrap())
        .collect()
}

/// The split-view task rewarded when hidden value B (agent 1's o[2]) is 1 or more.
fn hidden_b_rewarded() -> Dataset {
    synthetic_rewarded(400, 8, |s| if s[3] >= 1.0 { 1.0 } else { 0.0 })
}

/// Phase 0 by observation relevance with the senders ranked by the return.
fn senders_by_return(values_by: lmac_design::offline::ValuesBy) -> OfflineConfig {
    OfflineConfig {
        discriminator: quick_disc(),
        fields_by: FieldsBy::ObservationRelevance,
        senders_by: lmac_design::offline::SendersBy::Return,
        values_by,
        ..OfflineConfig::least_squares_rules()
    }
}

/// The same task with `--senders-by return`: the agent whose view the others need to predict
/// the return is the sender (a value model on a receiver's observation with and without it),
/// and it sends the value of its view that model uses.
#[test]
fn senders_by_return_chooses_the_agent_whose_view_the_return_needs() {
    let data = hidden_b_rewarded();
    let schema = synthetic_schema(30);
    let env = lmac_protocol_runner::protocol_env(&schema);
    let c = ctx(&schema, &env, &data);
    let mut designer = OfflineDesigner::new(senders_by_return(lmac_design::offline::ValuesBy::Value));
    let p0 = designer.initial(&c).unwrap();
    let t = designer.transcript();
    let obs_rel = t.iter().find(|e| e.kind == "observation_relevance").expect("the ranking is in the transcript");
    assert!(obs_rel.reply.contains("most helps the others predict the team's return"), "{}", obs_rel.reply);
    let sender_line = obs_rel.reply.lines().find(|l| l.contains("a SENDER")).unwrap();
    assert!(sender_line.starts_with("agent 1: all it sees, beside another agent's own observation"), "{}", obs_rel.reply);
    let json = serde_json::to_value(&p0.protocol).unwrap();
    let mut sent = Vec::new();
    for f in json["fields"].as_array().unwrap() {
        assert_eq!(f["senders"], serde_json::json!([1]), "{f}");
        sent.extend(f["value"]["obs"].as_array().cloned().unwrap_or_default().into_iter().map(|v| v.as_u64().unwrap()));
    }
    assert!(sent.contains(&2), "agent 1's view of hidden value B is sent: {json}");
}

/// `--values-by entity`: the sender sends the whole entity of its view the receivers' value
/// model needs first (here o[2..4], "what agent 1 sees of B", as the schema groups it), except a
/// value that never varies for it (its o[3]: the flash only agent 0 sees), and the ranking names
/// the entity. Entities need `--senders-by return`, which is said before anything is measured.
#[test]
fn values_by_entity_sends_the_whole_entity_the_return_needs() {
    let data = hidden_b_rewarded();
    let mut schema = synthetic_schema(30);
    schema.obs_dims.truncate(2);
    schema.obs_dims.push(group(2, "what this agent sees of hidden value B and the flash: value {k}"));
    let env = lmac_protocol_runner::protocol_env(&schema);
    let c = ctx(&schema, &env, &data);
    let cfg = senders_by_return(lmac_design::offline::ValuesBy::Entity);
    let mut designer = OfflineDesigner::new(cfg.clone());
    let p0 = designer.initial(&c).unwrap();
    let t = designer.transcript();
    let obs_rel = t.iter().find(|e| e.kind == "observation_relevance").expect("the ranking is in the transcript");
    let line = obs_rel.reply.lines().find(|l| l.contains("CHOSEN")).unwrap_or_else(|| panic!("{}", obs_rel.reply));
    assert!(
        line.starts_with("agent 1's what this agent sees of hidden value B and the flash (o[2..4]): relevance")
            && line.ends_with("CHOSEN: o[2] sent by this agent to every other agent"),
        "{}",
        obs_rel.reply
    );
    assert!(p0.protocol.message_design_instruction.contains("Phase 0 sends whole entities"), "{}", p0.protocol.message_design_instruction);
    let json = serde_json::to_value(&p0.protocol).unwrap();
    let mut sent = Vec::new();
    for f in json["fields"].as_array().unwrap() {
        assert_eq!(f["senders"], serde_json::json!([1]), "{f}");
        sent.extend(f["value"]["obs"].as_array().cloned().unwrap_or_default().into_iter().map(|v| v.as_u64().unwrap()));
    }
    assert!(sent.contains(&2) && !sent.contains(&3), "o[2] is sent, o[3] (constant for agent 1) is not: {json}");

    // `--phase1-by frame`: agent 0 never sees B itself, so no step tells what would place it in
    // agent 1's view; phase 1 says so and turns to least squares.
    let frame = OfflineConfig { phase1_by: lmac_design::offline::Phase1By::Frame, ..cfg.clone() };
    let mut designer = OfflineDesigner::new(frame.clone());
    let p0 = designer.initial(&c).unwrap();
    let mcfg = MetaConfig { discriminator: quick_disc(), max_target_dims: 8, ..Default::default() };
    let m = meta::evaluate(&c, std::slice::from_ref(&p0.validated), &mcfg).unwrap();
    let fb = designer.feedback(&c, 1, std::slice::from_ref(&p0), &m).unwrap();
    // Phase 0 already sends all of B, the one critical dim, so least squares finds nothing
    // either, and says so.
    let e = designer.refine(&c, 1, std::slice::from_ref(&p0), &fb, &m).unwrap_err();
    assert!(format!("{e:#}").contains("phase 1 has nothing to send"), "{e:#}");
    let t = designer.transcript();
    let fit = t.iter().find(|e| e.kind == "frame").expect("the fits are in the transcript");
    assert!(fit.reply.contains("agent 0: sees it together with agent 1 on 0 steps of B, too few to fit"), "{}", fit.reply);
    let fallback = t.iter().find(|e| e.kind == "fields_by").expect("the fallback is in the transcript");
    assert!(fallback.reply.starts_with("By least squares instead: no value of agent 1's view adds"), "{}", fallback.reply);
    let by_value = OfflineConfig { values_by: lmac_design::offline::ValuesBy::Value, ..frame };
    let e = OfflineDesigner::new(by_value).initial(&c).unwrap_err();
    assert!(format!("{e:#}").contains("(--phase1-by frame) places the receivers"), "{e:#}");
    let given_alone = OfflineConfig { frame_given_own_view: true, ..cfg.clone() };
    let e = OfflineDesigner::new(given_alone).initial(&c).unwrap_err();
    assert!(format!("{e:#}").contains("--frame-given-own-view changes how"), "{e:#}");

    let recovery = OfflineConfig { senders_by: lmac_design::offline::SendersBy::Recovery, ..cfg };
    let e = OfflineDesigner::new(recovery).initial(&c).unwrap_err();
    assert!(format!("{e:#}").contains("--values-by entity) needs --senders-by return"), "{e:#}");
}

/// `--values-by recovery` on LBF-shaped random walks: a grid cell of the state is recoverable
/// from the teammate's row and column, not from a value model of the return (the walk's
/// actions are random), and the teammate's view rows say nothing about absolute cells without
/// them. Each entity of the sender's view is probed alone with a discriminator, and the
/// sender's row and column (o[27], o[28], one value each) add the most per value, so phase 0
/// sends them first; the ranking says what every probe added.
#[test]
fn values_by_recovery_sends_where_the_sender_is() {
    let data = lbf_walk(300, 5);
    let schema = lmac_shm_schema::schema::load_env("lbf:8x8-2p-2f-s1-coop").unwrap();
    let env = lmac_protocol_runner::protocol_env(&schema);
    let c = ctx(&schema, &env, &data);
    let cfg = OfflineConfig {
        discriminator: quick_disc(),
        fields_by: FieldsBy::ObservationRelevance,
        values_by: lmac_design::offline::ValuesBy::Recovery,
        critical_by: CriticalBy::Recovery,
        ..OfflineConfig::least_squares_rules()
    };
    let mut designer = OfflineDesigner::new(cfg.clone());
    let p0 = designer.initial(&c).unwrap();
    let t = designer.transcript();
    let obs_rel = t.iter().find(|e| e.kind == "observation_relevance").expect("the ranking is in the transcript");
    let probes: Vec<&str> = obs_rel.reply.lines().filter(|l| l.contains("sent alone to the others, it raises their recovery")).collect();
    assert!(probes.len() >= 8, "every entity of the sender's view is probed: {}", obs_rel.reply);
    for first in &probes[..2] {
        assert!(first.contains("own field row") || first.contains("own field column"), "{}", obs_rel.reply);
        assert!(first.contains("CHOSEN"), "{}", obs_rel.reply);
    }
    assert!(p0.protocol.message_design_instruction.contains("most raises their recovery of the critical dims per value sent first"));
    let json = serde_json::to_value(&p0.protocol).unwrap();
    let sent = sent_obs(&json);
    assert!(sent.contains(&27) && sent.contains(&28), "the sender's row and column are sent: {json}");
    assert!(sent.len() <= cfg.max_relevant_values, "{json}");
}

/// Where a discriminator cannot read even the best sender's whole view (the state is noise, so
/// with it the receivers recover the critical dims no better than a constant guess of each),
/// the default rules do not rank entities by gains that are noise: every agent sends all of
/// its view that varies on B to every other agent, and the design says why.
/// `--rank-when-blind` (`whole_view_when_blind: false`) ranks them anyway.
#[test]
fn a_blind_discriminator_sends_every_agents_whole_view() {
    let data = lbf_like(160, 21);
    let schema = lmac_shm_schema::schema::load_env("lbf:8x8-2p-2f-s1-coop").unwrap();
    let env = lmac_protocol_runner::protocol_env(&schema);
    let c = ctx(&schema, &env, &data);
    let cfg = OfflineConfig { discriminator: quick_disc(), ..Default::default() };
    assert!(cfg.whole_view_when_blind);
    let p0 = OfflineDesigner::new(cfg.clone()).initial(&c).unwrap();
    let json = serde_json::to_value(&p0.protocol).unwrap();
    // lbf_like's observations are uniform in {0, 1, 2}: every value varies for both agents.
    let mut by_sender = [Vec::new(), Vec::new()];
    for f in json["fields"].as_array().unwrap() {
        let senders = f["senders"].as_array().unwrap_or_else(|| panic!("{f}"));
        assert_eq!(senders.len(), 1, "{f}");
        let j = senders[0].as_u64().unwrap() as usize;
        by_sender[j].extend(f["value"]["obs"].as_array().unwrap().iter().map(|v| v.as_u64().unwrap()));
    }
    for (j, sent) in by_sender.iter_mut().enumerate() {
        sent.sort_unstable();
        assert_eq!(*sent, (0..29).collect::<Vec<u64>>(), "agent {j} sends its whole view: {json}");
    }
    let instruction = &p0.protocol.message_design_instruction;
    assert!(instruction.contains("Phase 0 sends every agent's whole view (58 values"), "{instruction}");
    assert!(instruction.contains("against") && instruction.contains("for a constant guess of each dim"), "{instruction}");
    // Ranked anyway (or, with no sender found, by least squares): not the whole views.
    let ranked = OfflineConfig { whole_view_when_blind: false, ..cfg };
    let p0 = OfflineDesigner::new(ranked).initial(&c).unwrap();
    assert!(!p0.protocol.message_design_instruction.contains("whole view"), "{}", p0.protocol.message_design_instruction);
    assert!(sent_obs(&serde_json::to_value(&p0.protocol).unwrap()).len() < 58);
}

/// Dropping the phases that add nothing (the default) on a dataset whose state is noise (no message can help recover
/// it): every phase, phase 0 included, is judged against what was kept before it (no messages
/// for phase 0); a phase in the final protocol either adds or says why it is there anyway; the
/// training side reads exactly the phases kept; and something is always kept.
#[test]
fn a_design_keeps_only_phases_that_add_or_says_why() {
    let dir = tmp_dir("drop-phases");
    let data = lbf_like(160, 21);
    data.save(&dir.join("dataset")).unwrap();
    let opts = lmac_design::run::DesignOptions {
        env: "lbf:8x8-2p-2f-s1-coop".into(),
        out: dir.join("designs"),
        seed: 3,
        pretrain_steps: 0,
        collect_algo: "qmix".into(),
        dataset_episodes: 0,
        dataset_epsilon: None,
        envs: 1,
        servers: 1,
        dataset: Some(dir.join("dataset")),
        phases: 3,
        without: meta::NoMessages::Retrained,
        drop_unhelpful_phases: true,
    };
    let disc = DiscriminatorConfig { updates: 300, batch_size: 64, lr: 2e-3, ..Default::default() };
    let mut designer = OfflineDesigner::new(OfflineConfig { discriminator: disc.clone(), ..Default::default() });
    let mcfg = MetaConfig { discriminator: disc, ..Default::default() };
    let design = lmac_design::run::run_design(&opts, &mut designer, &mcfg, Default::default()).unwrap();
    let summary: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(design.join("summary.json")).unwrap()).unwrap();
    // The design says how it was made: the offline designer's knobs, as they parse back.
    let settings: OfflineConfig = serde_json::from_value(summary["designer_settings"].clone()).unwrap();
    assert_eq!(settings, designer.config().clone());
    let evals = summary["evaluations"].as_array().unwrap();
    assert_eq!(evals.len(), 3);
    let mut kept = Vec::new();
    for (k, e) in evals.iter().enumerate() {
        let adds = &e["adds"];
        let text = adds["text"].as_str().unwrap_or_else(|| panic!("phase {k} has no verdict on what it adds: {e}"));
        let helps = adds["messages_help"].as_bool().unwrap();
        let dropped = e["dropped"].as_bool().unwrap();
        assert!(text.contains("adds to") || text.contains("does NOT add to"), "{text}");
        if dropped {
            assert!(!helps, "phase {k} helps but was dropped: {text}");
        } else {
            kept.push(k);
            assert!(
                helps
                    || e["kept_because"]
                        .as_str()
                        .is_some_and(|w| w.contains("a design must send something") || w.contains("cannot be measured on this data")),
                "phase {k}: {e}"
            );
        }
    }
    assert!(!kept.is_empty(), "{summary}");
    // Phase 0 is judged against no messages.
    assert!(evals[0]["adds"]["text"].as_str().unwrap().contains("no messages"), "{}", evals[0]);
    // Training reads the kept phases, in order.
    let files = lmac_run::train::protocol_files(design.to_str().unwrap(), None).unwrap();
    let expected: Vec<String> = kept.iter().map(|k| design.join(format!("phase{k}")).join("protocol.json").display().to_string()).collect();
    assert_eq!(files, expected);
    eprintln!(
        "kept phases {kept:?}: {}",
        evals.iter().map(|e| e["adds"]["text"].as_str().unwrap().to_string()).collect::<Vec<_>>().join("\n")
    );
}
