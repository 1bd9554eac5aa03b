//! The compiled plan writes exactly the hand-computed message values.

use lmac_protocol_runner::plan::{MessagePlan, StepView};
use lmac_protocol_runner::protocol::*;
use serde_json::json;

fn plan_for(v: serde_json::Value, env: &ProtocolEnv) -> ProtocolPlan {
    let p = validate(&parse_value(&v).unwrap(), env).unwrap_or_else(|e| panic!("{}", errors_to_text(&e)));
    compile_plan(&[p], env).unwrap()
}

/// Run one step: returns the rows after the plan wrote the message columns.
fn step(plan: &mut dyn MessagePlan, n: usize, od: usize, md: usize, obs: &[Vec<Vec<f32>>], first: &[bool], la: &[i32]) -> Vec<f32> {
    let ne = obs.len();
    let rw = od + md;
    let mut rows = vec![-7.0f32; ne * n * rw];
    for e in 0..ne {
        for a in 0..n {
            rows[(e * n + a) * rw..(e * n + a) * rw + od].copy_from_slice(&obs[e][a]);
        }
    }
    let mut view = StepView { num_envs: ne, n_agents: n, obs_dim: od, msg_dim: md, rows: &mut rows, first, last_actions: la };
    plan.apply(&mut view);
    // Observations are never touched.
    for e in 0..ne {
        for a in 0..n {
            assert_eq!(&rows[(e * n + a) * rw..(e * n + a) * rw + od], &obs[e][a][..]);
        }
    }
    rows
}

fn msg(rows: &[f32], n: usize, od: usize, md: usize, env: usize, agent: usize) -> Vec<f32> {
    let rw = od + md;
    rows[(env * n + agent) * rw + od..(env * n + agent + 1) * rw].to_vec()
}

fn close(a: &[f32], b: &[f32]) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-5)
}

macro_rules! assert_close {
    ($a:expr, $b:expr) => {{
        let (a, b): (Vec<f32>, Vec<f32>) = ($a, $b);
        assert!(close(&a, &b), "got {a:?}, expected {b:?}");
    }};
}

/// Three agents: `a` broadcast by all, `b` from 0 to 2 only, `c` from 1 and 2 to 0 only.
fn three_field_protocol(layout: Option<&str>) -> serde_json::Value {
    let mut v = json!({
        "message_design_instruction": "test",
        "critical_state_dims": [0],
        "fields": [
            {"name": "a", "description": "dims 1 and 3", "value": {"obs": [1, 3]}},
            {"name": "b", "description": "0.5 + dims 0,1", "senders": [0], "receivers": {"agents": [2]},
             "value": {"add": [{"obs_slice": {"start": 0, "end": 2}}, {"const": 0.5}]}},
            {"name": "c", "description": "last action", "senders": [1, 2],
             "receivers": {"peer": [{"from": 1, "to": [0]}, {"from": 2, "to": [0]}]},
             "value": {"last_action": "one_hot"}}
        ]
    });
    if let Some(l) = layout {
        v["layout"] = json!(l);
    }
    v
}

#[test]
fn sender_blocks_layout_is_kept() {
    let env = ProtocolEnv::new(3, 4, 3, 5, 100);
    let mut plan = plan_for(three_field_protocol(Some("sender_blocks")), &env);
    assert_eq!(plan.msg_dim(), 20);
    assert_eq!(plan.column_labels(0).len(), 20);
    assert_eq!(plan.column_labels(0)[3], "phase0/from1/a[0]");
    assert!(plan.columns(1).iter().all(|c| !c.padding));
    let (n, od, md) = (3, 4, 23); // 3 reserved columns more than the plan writes
    let obs: Vec<Vec<Vec<f32>>> = vec![(0..n).map(|a| (0..od).map(|d| (10 * a + d) as f32).collect()).collect()];
    let rows = step(&mut plan, n, od, md, &obs, &[true], &[2, -1, 0]);
    let z3 = [0.0; 3];
    let cat = |parts: &[&[f32]]| parts.concat();
    assert_close!(
        msg(&rows, n, od, md, 0, 0),
        cat(&[&[0., 1., 0.], &[11., 13.], &[0., 0.], &[0., 0., 0.], &[0., 0., 1.], &[21., 23.], &[0., 0.], &[1., 0., 0.], &z3])
    );
    assert_close!(
        msg(&rows, n, od, md, 0, 1),
        cat(&[&[1., 0., 0.], &[1., 3.], &[0., 0.], &[0., 0., 0.], &[0., 0., 1.], &[21., 23.], &[0., 0.], &[0., 0., 0.], &z3])
    );
    assert_close!(
        msg(&rows, n, od, md, 0, 2),
        cat(&[&[1., 0., 0.], &[1., 3.], &[0.5, 1.5], &[0., 0., 0.], &[0., 1., 0.], &[11., 13.], &[0., 0.], &[0., 0., 0.], &z3])
    );
}

#[test]
fn compact_layout_senders_receivers_and_one_hots() {
    let env = ProtocolEnv::new(3, 4, 3, 5, 100);
    let p = validate(&parse_value(&three_field_protocol(None)).unwrap(), &env).unwrap();
    // Receiver 0: from 1 [one-hot 3 | a 2 | c 3], from 2 the same: 16. Receiver 1: from 0
    // [3 | a 2], from 2 [3 | a 2]: 10. Receiver 2: from 0 [3 | a 2 | b 2], from 1 [3 | a 2]: 12.
    assert_eq!((0..3).map(|i| p.receiver_width(i)).collect::<Vec<_>>(), vec![16, 10, 12]);
    assert_eq!(p.width, 16);
    let mut plan = compile_plan(std::slice::from_ref(&p), &env).unwrap();
    assert_eq!(plan.msg_dim(), 16);
    for i in 0..3 {
        assert_eq!(plan.columns(i).len(), 16, "every receiver has the plan's width");
        assert_eq!(plan.columns(i).iter().filter(|c| c.padding).count(), 16 - p.receiver_width(i));
        // Every non-padding column is linked: the compact layout spends nothing on unsent parts.
        assert!(plan.columns(i).iter().all(|c| c.padding != c.linked), "receiver {i}");
    }
    assert_eq!(plan.column_labels(0)[3], "phase0/from1/a[0]");
    assert_eq!(plan.column_labels(0)[5], "phase0/from1/c[0]");
    assert_eq!(plan.column_labels(1)[5], "phase0/from2/sender_one_hot[0]");
    assert_eq!(plan.column_labels(1)[10], "phase0/padding[0]");
    let c = &plan.columns(2)[5];
    assert_eq!((c.sender, c.field, c.name.as_str(), c.q, c.linked, c.padding), (0, Some(1), "b", 0, true, false));
    let (n, od, md) = (3, 4, 19); // 3 reserved columns more than the plan writes
    let obs: Vec<Vec<Vec<f32>>> = vec![(0..n).map(|a| (0..od).map(|d| (10 * a + d) as f32).collect()).collect()];
    let rows = step(&mut plan, n, od, md, &obs, &[true], &[2, -1, 0]);
    let z3 = [0.0; 3];
    let cat = |parts: &[&[f32]]| parts.concat();
    assert_close!(
        msg(&rows, n, od, md, 0, 0),
        cat(&[&[0., 1., 0.], &[11., 13.], &[0., 0., 0.], &[0., 0., 1.], &[21., 23.], &[1., 0., 0.], &z3])
    );
    assert_close!(msg(&rows, n, od, md, 0, 1), cat(&[&[1., 0., 0.], &[1., 3.], &[0., 0., 1.], &[21., 23.], &[0.; 6], &z3]));
    assert_close!(msg(&rows, n, od, md, 0, 2), cat(&[&[1., 0., 0.], &[1., 3.], &[0.5, 1.5], &[0., 1., 0.], &[11., 13.], &[0.; 4], &z3]));
}

/// The compact layout carries exactly the sender-blocks layout's linked columns (same values),
/// over several phases with windows, and nothing else.
#[test]
fn compact_layout_holds_the_linked_columns_of_sender_blocks() {
    let env = ProtocolEnv::new(4, 5, 3, 5, 1000);
    let phase0 = three_field_protocol_4();
    let mut phase1 = json!({
        "message_design_instruction": "test", "critical_state_dims": [1],
        "fields": [
            {"name": "w", "description": "max", "senders": [3], "value": {"window": {"op": "max", "k": 3, "of": {"obs": [0, 4]}}}},
            {"name": "z", "description": "d", "receivers": {"peer": [{"from": 0, "to": [3]}]}, "senders": [0], "value": {"obs": [2]}}
        ]
    });
    let compile_with = |layout: &str, p1: &serde_json::Value| {
        let mut a = phase0.clone();
        a["layout"] = json!(layout);
        let mut b = p1.clone();
        b["layout"] = json!(layout);
        let va = validate(&parse_value(&a).unwrap(), &env).unwrap();
        let vb = validate_phase(&parse_value(&b).unwrap(), &env, std::slice::from_ref(&va)).unwrap();
        compile_plan(&[va, vb], &env).unwrap()
    };
    phase1["name"] = json!("second");
    let mut blocks = compile_with("sender_blocks", &phase1);
    let mut compact = compile_with("compact", &phase1);
    assert!(compact.msg_dim() < blocks.msg_dim(), "{} vs {}", compact.msg_dim(), blocks.msg_dim());
    let n = 4;
    let od = 5;
    let (mb, mc) = (blocks.msg_dim(), compact.msg_dim());
    for t in 0..6 {
        let obs: Vec<Vec<Vec<f32>>> =
            (0..2).map(|e| (0..n).map(|a| (0..od).map(|d| ((t * 7 + e * 3 + a * 5 + d) % 11) as f32 - 4.0).collect()).collect()).collect();
        let first = [t == 0, t == 3];
        let la = [1, 0, 2, -1, 2, 2, 0, 1];
        let rb = step(&mut blocks, n, od, mb, &obs, &first, &la);
        let rc = step(&mut compact, n, od, mc, &obs, &first, &la);
        for e in 0..2 {
            for i in 0..n {
                let (m_b, m_c) = (msg(&rb, n, od, mb, e, i), msg(&rc, n, od, mc, e, i));
                let linked: std::collections::BTreeMap<String, f32> = blocks
                    .columns(i)
                    .iter()
                    .zip(&m_b)
                    .filter(|(c, _)| c.linked && c.field.is_some())
                    .map(|(c, &v)| (c.label(), v))
                    .collect();
                let got: std::collections::BTreeMap<String, f32> =
                    compact.columns(i).iter().zip(&m_c).filter(|(c, _)| c.field.is_some()).map(|(c, &v)| (c.label(), v)).collect();
                assert_eq!(got, linked, "step {t} env {e} receiver {i}");
                let onehots = compact.columns(i).iter().filter(|c| !c.padding && c.field.is_none()).count();
                let reach = (0..n).filter(|&j| j != i && compact_senders_reach(j, i)).count();
                assert_eq!(onehots, n * reach, "one one-hot per reaching sender");
                assert!(compact.columns(i).iter().zip(&m_c).filter(|(c, _)| c.padding).all(|(_, &v)| v == 0.0));
            }
        }
    }
}

/// Does sender j reach receiver i in [`three_field_protocol_4`] or its second phase?
fn compact_senders_reach(j: usize, i: usize) -> bool {
    // phase 0: a from 0, 1 to all; b from 2 to 0, 1; c from 3 to 0. phase 1: w from 3 to all; z from 0 to 3.
    matches!((j, i), (0, _) | (1, _) | (2, 0) | (2, 1) | (3, _))
}

fn three_field_protocol_4() -> serde_json::Value {
    json!({
        "message_design_instruction": "test", "critical_state_dims": [0],
        "fields": [
            {"name": "a", "description": "d", "senders": [0, 1], "value": {"obs": [1, 3]}},
            {"name": "b", "description": "d", "senders": [2], "receivers": {"agents": [0, 1]}, "value": {"window": {"op": "mean", "k": 2, "of": {"obs": [0]}}}},
            {"name": "c", "description": "d", "receivers": {"peer": [{"from": 3, "to": [0]}]}, "senders": [3], "value": {"last_action": "one_hot"}}
        ]
    })
}

#[test]
fn one_hot_is_zero_when_nothing_is_sent_and_can_be_turned_off() {
    let env = ProtocolEnv::new(3, 2, 2, 1, 100);
    let v = json!({
        "message_design_instruction": "test", "critical_state_dims": [0], "layout": "sender_blocks",
        "fields": [{"name": "x", "description": "d", "senders": [0], "receivers": {"agents": [1]}, "value": {"obs": [1]}}]
    });
    let mut plan = plan_for(v.clone(), &env);
    let (n, od, md) = (3, 2, 8);
    let obs = vec![vec![vec![1.0, 2.0], vec![3.0, 4.0], vec![5.0, 6.0]]];
    let rows = step(&mut plan, n, od, md, &obs, &[true], &[0, 0, 0]);
    assert_close!(msg(&rows, n, od, md, 0, 1), vec![1., 0., 0., 2., 0., 0., 0., 0.]);
    assert_close!(msg(&rows, n, od, md, 0, 2), vec![0.; 8]); // receives nothing at all
    let mut v2 = v.clone();
    v2["sender_one_hot"] = json!(false);
    let mut plan = plan_for(v2, &env);
    assert_eq!(plan.msg_dim(), 2);
    let rows = step(&mut plan, n, od, 2, &obs, &[true], &[0, 0, 0]);
    assert_close!(msg(&rows, n, od, 2, 0, 1), vec![2., 0.]);
    assert_close!(msg(&rows, n, od, 2, 0, 0), vec![0., 0.]);
    // Compact: one block, [one-hot of 0 | x], for agent 1 only; the others are all padding.
    let mut v3 = v.clone();
    v3.as_object_mut().unwrap().remove("layout");
    let mut plan = plan_for(v3.clone(), &env);
    assert_eq!(plan.msg_dim(), 4);
    let rows = step(&mut plan, n, od, md, &obs, &[true], &[0, 0, 0]);
    assert_close!(msg(&rows, n, od, md, 0, 1), vec![1., 0., 0., 2., 0., 0., 0., 0.]);
    assert_close!(msg(&rows, n, od, md, 0, 2), vec![0.; 8]);
    assert!(plan.columns(2).iter().all(|c| c.padding && !c.linked));
    v3["sender_one_hot"] = json!(false);
    let mut plan = plan_for(v3, &env);
    assert_eq!(plan.msg_dim(), 1);
    let rows = step(&mut plan, n, od, 1, &obs, &[true], &[0, 0, 0]);
    assert_close!(msg(&rows, n, od, 1, 0, 1), vec![2.]);
    assert_close!(msg(&rows, n, od, 1, 0, 0), vec![0.]);
}

#[test]
fn arithmetic_and_reductions() {
    let env = ProtocolEnv::new(2, 3, 2, 1, 100);
    let mut plan = plan_for(
        json!({
            "message_design_instruction": "test", "critical_state_dims": [0], "sender_one_hot": false,
            "fields": [{"name": "x", "description": "d", "value": {"concat": [
                {"sub": [{"obs_slice": {"start": 0, "end": 3}}, {"const": 1}]},
                {"mul": [{"obs": [0, 1]}, {"obs": [2, 2]}]},
                {"div": [{"obs": [1]}, {"obs": [0]}]},
                {"min": [{"obs": [0]}, {"obs": [2]}]},
                {"max": [{"obs": [0]}, {"obs": [2]}]},
                {"gt": [{"obs": [0, 1, 2]}, {"const": 2}]},
                {"lt": [{"obs": [0]}, {"const": 2}]},
                {"eq": [{"obs": [1]}, {"const": 2}]},
                {"neg": {"obs": [2]}},
                {"abs": {"neg": {"obs": [2]}}},
                {"clip": {"of": {"obs_slice": {"start": 0, "end": 3}}, "min": 1.5, "max": 2.5}},
                {"reduce": {"op": "sum", "of": {"obs_slice": {"start": 0, "end": 3}}}},
                {"reduce": {"op": "mean", "of": {"obs_slice": {"start": 0, "end": 3}}}},
                {"reduce": {"op": "min", "of": {"obs_slice": {"start": 0, "end": 3}}}},
                {"reduce": {"op": "max", "of": {"obs_slice": {"start": 0, "end": 3}}}},
                {"last_action": "index"},
                "sender_one_hot"
            ]}}]
        }),
        &env,
    );
    assert_eq!(plan.msg_dim(), 3 + 2 + 1 + 1 + 1 + 3 + 1 + 1 + 1 + 1 + 3 + 4 + 1 + 2);
    let (n, od) = (2, 3);
    let md = plan.msg_dim();
    // agent 0 observes [1, 2, 3] and sends to agent 1; agent 1 observes [0, 0, 0] (div by 0 -> 0)
    let obs = vec![vec![vec![1.0, 2.0, 3.0], vec![0.0, 5.0, -1.0]]];
    let rows = step(&mut plan, n, od, md, &obs, &[false], &[1, -1]);
    assert_close!(
        msg(&rows, n, od, md, 0, 1),
        vec![0., 1., 2., 3., 6., 2., 1., 3., 0., 0., 1., 1., 1., -3., 3., 1.5, 2., 2.5, 6., 2., 1., 3., 1., 1., 0.]
    );
    assert_close!(
        msg(&rows, n, od, md, 0, 0),
        vec![-1., 4., -2., 0., -5., 0., -1., 0., 0., 1., 0., 1., 0., 1., 1., 1.5, 2.5, 1.5, 4., 4. / 3., -1., 5., -1., 0., 1.]
    );
}

/// Window aggregates over obs[0] of agent 0 (received by agent 1), env 0 restarting its
/// episode at step 3, env 1 not.
fn window_run(padding: &str) -> Vec<[Vec<f32>; 2]> {
    let env = ProtocolEnv::new(2, 1, 2, 1, 100);
    let w = |op: &str, k: usize| json!({"window": {"op": op, "k": k, "of": {"obs": [0]}}});
    let mut plan = plan_for(
        json!({
            "message_design_instruction": "test", "critical_state_dims": [0], "sender_one_hot": false,
            "history_padding": padding,
            "fields": [
                {"name": "w", "description": "d", "value": {"concat": [w("mean", 3), w("last", 3), w("delta", 3), w("min", 3), w("max", 2), w("sum", 2)]}},
                {"name": "acts", "description": "d", "value": {"window": {"op": "sum", "k": 2, "of": {"last_action": "one_hot"}}}}
            ]
        }),
        &env,
    );
    assert_eq!(plan.history_shape(), (2, 3)); // two channels (obs[0] shared by all six windows), depth 3
    let env0 = [1.0, 2.0, 4.0, 8.0, 16.0];
    let env1 = [3.0, 5.0, 7.0, 9.0, 11.0];
    let firsts = [[true, true], [false, false], [false, false], [true, false], [false, false]];
    let acts = [[-1, -1, -1, -1], [1, 0, 0, 0], [0, 0, 1, 0], [-1, 0, 1, 0], [1, 0, 1, 0]];
    let md = 8;
    let mut out = Vec::new();
    for t in 0..5 {
        let obs = vec![vec![vec![env0[t]], vec![100.0]], vec![vec![env1[t]], vec![100.0]]];
        let rows = step(&mut plan, 2, 1, md, &obs, &firsts[t], &acts[t]);
        out.push([msg(&rows, 2, 1, md, 0, 1), msg(&rows, 2, 1, md, 1, 1)]);
    }
    out
}

#[test]
fn window_aggregates_minus_one_padding_across_episode_boundary() {
    let o = window_run("minus_one");
    // [mean3, last3, delta3, min3, max2, sum2, acts sum2 (2 cols)]
    assert_close!(o[0][0].clone(), vec![-1. / 3., -1., 2., -1., 1., 0., -1., -1.]);
    assert_close!(o[1][0].clone(), vec![2. / 3., -1., 3., -1., 2., 3., 0., 1.]);
    assert_close!(o[2][0].clone(), vec![7. / 3., 1., 3., 1., 4., 6., 1., 1.]);
    assert_close!(o[3][0].clone(), vec![2., -1., 9., -1., 8., 7., -1., -1.]); // new episode
    assert_close!(o[4][0].clone(), vec![23. / 3., -1., 17., -1., 16., 24., 0., 1.]);
    // env 1 never restarts
    assert_close!(o[2][1].clone(), vec![5., 3., 4., 3., 7., 12., 1., 1.]);
    assert_close!(o[4][1].clone(), vec![9., 7., 4., 7., 11., 20., 0., 2.]);
}

#[test]
fn window_aggregates_repeat_and_zero_padding() {
    let o = window_run("repeat");
    assert_close!(o[0][0].clone(), vec![1., 1., 0., 1., 1., 2., 0., 0.]);
    assert_close!(o[3][0].clone(), vec![8., 8., 0., 8., 8., 16., 0., 0.]);
    assert_close!(o[4][0].clone(), vec![32. / 3., 8., 8., 8., 16., 24., 0., 1.]);
    let o = window_run("zero");
    assert_close!(o[0][0].clone(), vec![1. / 3., 0., 1., 0., 1., 1., 0., 0.]);
    assert_close!(o[3][0].clone(), vec![8. / 3., 0., 8., 0., 8., 8., 0., 0.]);
}

/// The same phases in the other layout (validated again).
fn with_layout(phases: &[ValidatedProtocol], env: &ProtocolEnv, layout: MessageLayout) -> Vec<ValidatedProtocol> {
    let mut out: Vec<ValidatedProtocol> = Vec::new();
    for p in phases {
        let mut q = p.protocol.clone();
        q.layout = layout;
        out.push(validate_phase(&q, env, &out).unwrap());
    }
    out
}

/// The plan compiled from all phases writes, per receiver, what each phase's own plan writes
/// (random data, random episode restarts): in the sender-blocks layout exactly their
/// concatenation; in the compact layout every linked field column of every phase (found by its
/// phase, sender, field and position), each reaching sender's one-hot once, then zeros.
fn assert_concat_equals_parts(phases: &[ValidatedProtocol], env: &ProtocolEnv) {
    let (n, od) = (env.n_agents, env.obs_dim);
    let blocks = phases[0].protocol.layout == MessageLayout::SenderBlocks;
    let mut both = compile_plan(phases, env).unwrap();
    let mut parts: Vec<ProtocolPlan> = phases.iter().map(|p| compile_plan(std::slice::from_ref(p), env).unwrap()).collect();
    let dims: Vec<usize> = parts.iter().map(|p| p.msg_dim()).collect();
    if blocks {
        assert_eq!(both.msg_dim(), dims.iter().sum::<usize>());
    } else {
        assert!(both.msg_dim() <= dims.iter().sum::<usize>());
        assert_eq!(both.msg_dim(), combined_width(phases));
    }
    let md = both.msg_dim();
    let mut seed = 12345u64;
    let mut rnd = || {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        (seed % 4) as f32
    };
    let mut checked = 0usize;
    for t in 0..30 {
        let obs: Vec<Vec<Vec<f32>>> = (0..3).map(|_| (0..n).map(|_| (0..od).map(|_| rnd()).collect()).collect()).collect();
        let first = [t % 7 == 0, t == 0, t % 11 == 0];
        let la: Vec<i32> = (0..3 * n).map(|k| if first[k / n] { -1 } else { rnd() as i32 }).collect();
        let rb = step(&mut both, n, od, md, &obs, &first, &la);
        let rps: Vec<Vec<f32>> = parts.iter_mut().zip(&dims).map(|(p, &d)| step(p, n, od, d, &obs, &first, &la)).collect();
        for e in 0..3 {
            for i in 0..n {
                let m = msg(&rb, n, od, md, e, i);
                if blocks {
                    let mut off = 0;
                    for (rp, &d) in rps.iter().zip(&dims) {
                        assert_eq!(&m[off..off + d], &msg(rp, n, od, d, e, i)[..], "t={t} env={e} receiver={i}");
                        off += d;
                    }
                    continue;
                }
                let key = |c: &Column| (c.sender, c.field, c.q);
                let mut fields = 0;
                let mut onehots = std::collections::BTreeSet::new();
                for (c, &v) in both.columns(i).iter().zip(&m) {
                    if c.padding {
                        assert_eq!(v, 0.0);
                    } else if c.field.is_none() {
                        assert_eq!(v, (c.q == c.sender) as u8 as f32, "one-hot of {}", c.sender);
                        onehots.insert(c.sender);
                    } else {
                        let k = c.phase;
                        let part = msg(&rps[k], n, od, dims[k], e, i);
                        let at =
                            parts[k].columns(i).iter().position(|pc| !pc.padding && key(pc) == key(c)).expect("in the phase's own plan");
                        assert_eq!(v, part[at], "t={t} env={e} receiver={i} {}", c.label());
                        fields += 1;
                    }
                }
                let own: usize =
                    (0..phases.len()).map(|k| parts[k].columns(i).iter().filter(|c| !c.padding && c.field.is_some()).count()).sum();
                assert_eq!(fields, own, "receiver {i} gets every field column of every phase");
                let reach: std::collections::BTreeSet<usize> =
                    (0..n).filter(|&j| j != i && phases.iter().any(|p| p.links(j, i) && p.protocol.sender_one_hot)).collect();
                assert_eq!(onehots, reach, "one one-hot per reaching sender");
                checked += 1;
            }
        }
    }
    assert!(blocks || checked > 0);
}

#[test]
fn phases_concatenate() {
    let env = ProtocolEnv::new(2, 27, 6, 300, 64);
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../prompts/examples");
    let p0 = check_file(dir.join("lbf_8x8_phase0.json"), &env).unwrap();
    let p2 = check_file(dir.join("lbf_8x8_phase2.json"), &env).unwrap();
    assert_eq!(compile(&[p0.clone(), p2.clone()], &env).unwrap().name(), "lbf_8x8_phase0+lbf_8x8_phase2");
    // Compact: the one sender's one-hot (2) once, then 19 + 16 value columns.
    assert_eq!(compile(&[p0.clone(), p2.clone()], &env).unwrap().msg_dim(), 2 + 19 + 16);
    assert_concat_equals_parts(&[p0.clone(), p2.clone()], &env);
    let old = with_layout(&[p0, p2], &env, MessageLayout::SenderBlocks);
    assert_eq!(compile(&old, &env).unwrap().msg_dim(), 21 + 18);
    assert_concat_equals_parts(&old, &env);
}

#[test]
fn phases_with_different_paddings_concatenate() {
    let env = ProtocolEnv::new(3, 2, 3, 1, 200);
    let phase = |pad: &str, k: usize| {
        let v = json!({
            "message_design_instruction": "test", "critical_state_dims": [0], "history_padding": pad,
            "fields": [
                {"name": "m", "description": "d", "value": {"window": {"op": "mean", "k": k, "of": {"obs": [0]}}}},
                {"name": "a", "description": "d", "senders": [1], "value": {"window": {"op": "sum", "k": 3, "of": {"last_action": "one_hot"}}}},
                {"name": "l", "description": "d", "value": {"window": {"op": "last", "k": 2, "of": {"obs": [0]}}}}
            ]
        });
        validate(&parse_value(&v).unwrap(), &env).unwrap()
    };
    let phases = [phase("repeat", 3), phase("minus_one", 5), phase("zero", 4), phase("minus_one", 2)];
    assert_concat_equals_parts(&phases, &env);
    assert_concat_equals_parts(&with_layout(&phases, &env, MessageLayout::SenderBlocks), &env);
}

/// Peer links and senders that reach a receiver only in a later phase, without one-hots in one
/// phase: the one-hot appears once per sender that reaches the receiver in a phase that has it on.
#[test]
fn compact_phases_with_sparse_links() {
    let env = ProtocolEnv::new(4, 3, 3, 1, 500);
    let p0 = validate(
        &parse_value(&json!({
            "message_design_instruction": "t", "critical_state_dims": [0],
            "fields": [{"name": "x", "description": "d", "senders": [0], "receivers": {"agents": [1]}, "value": {"obs": [0, 2]}}]
        }))
        .unwrap(),
        &env,
    )
    .unwrap();
    let p1 = validate_phase(
        &parse_value(&json!({
            "message_design_instruction": "t", "critical_state_dims": [0], "sender_one_hot": false,
            "fields": [
                {"name": "y", "description": "d", "receivers": {"peer": [{"from": 2, "to": [3]}, {"from": 0, "to": [1, 3]}]}, "senders": [0, 2],
                 "value": {"window": {"op": "max", "k": 3, "of": {"obs": [1]}}}},
                {"name": "z", "description": "d", "value": {"last_action": "one_hot"}}
            ]
        }))
        .unwrap(),
        &env,
        std::slice::from_ref(&p0),
    )
    .unwrap();
    let phases = [p0, p1];
    // Receiver 1: from 0 [one-hot 4 | x 2 | y 1 | z 3], from 2 [z 3], from 3 [z 3]: 16.
    // Receiver 3: from 0 [y 1 | z 3] (no one-hot: phase 1 has it off), from 1 [z], from 2 [y | z]: 11.
    assert_eq!(combined_receiver_widths(&phases), vec![9, 16, 9, 11]);
    assert_eq!(combined_width(&phases), 16);
    assert_concat_equals_parts(&phases, &env);
    assert_concat_equals_parts(&with_layout(&phases, &env, MessageLayout::SenderBlocks), &env);
}

#[test]
fn phases_over_budget_do_not_compile() {
    let env = ProtocolEnv::new(2, 27, 6, 300, 36);
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../prompts/examples");
    let p0 = check_file(dir.join("lbf_8x8_phase0.json"), &ProtocolEnv::new(2, 27, 6, 300, 64)).unwrap();
    let p2 = check_file(dir.join("lbf_8x8_phase2.json"), &ProtocolEnv::new(2, 27, 6, 300, 64)).unwrap();
    let e = compile(&[p0.clone(), p2.clone()], &env).err().unwrap();
    assert_eq!(
        e[0].to_string(),
        "the phases together need 37 message columns per receiving agent (on their own: phase 0: 21, phase 2: 18) but the budget is 36"
    );
    // Layouts cannot be mixed.
    let big = ProtocolEnv::new(2, 27, 6, 300, 64);
    let old = with_layout(std::slice::from_ref(&p2), &big, MessageLayout::SenderBlocks);
    let e = compile(&[p0, old[0].clone()], &big).err().unwrap();
    assert!(e[0].to_string().contains("all phases of one protocol use the same layout"), "{}", e[0]);
}

#[test]
fn compile_rechecks_phases_against_its_environment() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../prompts/examples");
    let env = ProtocolEnv::new(2, 27, 6, 300, 64);
    let mut p0 = check_file(dir.join("lbf_8x8_phase0.json"), &env).unwrap();
    // Validated elsewhere, compiled for a smaller observation: precise errors, no panic.
    let small = ProtocolEnv::new(2, 12, 6, 300, 64);
    let e = compile(std::slice::from_ref(&p0), &small).err().unwrap();
    assert_eq!(e[0].path, "phases[0].fields[0].value.obs_slice");
    // Tampered derived facts are ignored.
    p0.field_widths = vec![1, 1, 1];
    p0.width = 3;
    assert_eq!(compile(&[p0], &env).unwrap().msg_dim(), 21);
}

#[test]
fn last_nonzero_remembers_within_the_window() {
    let env = ProtocolEnv::new(2, 2, 2, 1, 100);
    let mut plan = plan_for(
        json!({
            "message_design_instruction": "test", "critical_state_dims": [0], "sender_one_hot": false, "history_padding": "zero",
            "fields": [{"name": "m", "description": "d", "value": {"window": {"op": "last_nonzero", "k": 3, "of": {"obs": [0, 1]}}}}]
        }),
        &env,
    );
    // agent 0's obs[0..2] over steps; receiver 1 reads it.
    let seq = [[0.0, 5.0], [2.0, 0.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0]];
    let want = [[0.0, 5.0], [2.0, 5.0], [2.0, 5.0], [2.0, 0.0], [0.0, 0.0]];
    for t in 0..5 {
        let obs = vec![vec![seq[t].to_vec(), vec![0.0, 0.0]]];
        let rows = step(&mut plan, 2, 2, 2, &obs, &[t == 0], &[0, 0]);
        assert_close!(msg(&rows, 2, 2, 2, 0, 1), want[t].to_vec());
    }
}

/// A fresh copy of a plan that has run starts with no history: it writes what a newly compiled
/// plan writes, step for step, whatever the original saw before.
#[test]
fn a_fresh_plan_forgets_the_history_of_the_one_it_was_copied_from() {
    let env = ProtocolEnv::new(2, 2, 2, 1, 100);
    let v = json!({
        "message_design_instruction": "test", "critical_state_dims": [0],
        "fields": [{"name": "m", "description": "mean of obs 0 over 3 steps", "senders": [0], "receivers": {"agents": [1]},
                    "value": {"window": {"op": "mean", "k": 3, "of": {"obs": [0]}}}}]
    });
    let (n, od) = (2, 2);
    let mut used = plan_for(v.clone(), &env);
    let md = used.msg_dim();
    let at = |x: f32| vec![vec![vec![x, 0.0], vec![0.0, 0.0]]];
    // The original sees an episode of 10s, mid-episode.
    for (t, x) in [10.0, 10.0, 10.0].into_iter().enumerate() {
        step(&mut used, n, od, md, &at(x), &[t == 0], &[0, 0]);
    }
    let mut copy = used.fresh();
    let mut new = plan_for(v.clone(), &env);
    // Both see the same steps, the first one not an episode start: a plan that kept the 10s
    // would average them in.
    for x in [1.0, 2.0, 3.0, 4.0] {
        let a = step(copy.as_mut(), n, od, md, &at(x), &[false], &[0, 0]);
        let b = step(&mut new, n, od, md, &at(x), &[false], &[0, 0]);
        assert_close!(msg(&a, n, od, md, 0, 1), msg(&b, n, od, md, 0, 1));
    }
    // And the original, which kept its history, differs on the same steps.
    let a = step(&mut used, n, od, md, &at(1.0), &[false], &[0, 0]);
    let b = step(&mut plan_for(v, &env), n, od, md, &at(1.0), &[false], &[0, 0]);
    assert!(!close(&msg(&a, n, od, md, 0, 1), &msg(&b, n, od, md, 0, 1)), "the original still averages its 10s");
}
