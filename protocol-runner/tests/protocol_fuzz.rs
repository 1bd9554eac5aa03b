//! Fuzz-style robustness: arbitrary and mutated JSON never panics the parser, the validator, the
//! explainer, the compiler or the compiled plan. Seeded, a few thousand cases, fast.

use lmac_protocol_runner::plan::{MessagePlan, StepView};
use lmac_protocol_runner::protocol::*;
use serde_json::{json, Map, Value};

struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        // splitmix64
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    fn below(&mut self, n: u64) -> u64 {
        self.next() % n.max(1)
    }
    fn chance(&mut self, p: f64) -> bool {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64 <= p
    }
    fn pick<'a, T>(&mut self, xs: &'a [T]) -> &'a T {
        &xs[self.below(xs.len() as u64) as usize]
    }
}

const WORDS: &[&str] = &[
    "name",
    "phase",
    "message_design_instruction",
    "critical_state_dims",
    "critical_state_reasoning",
    "sender_one_hot",
    "history_padding",
    "fields",
    "description",
    "senders",
    "receivers",
    "value",
    "all",
    "broadcast",
    "agents",
    "peer",
    "from",
    "to",
    "obs",
    "obs_slice",
    "start",
    "end",
    "last_action",
    "one_hot",
    "index",
    "const",
    "window",
    "op",
    "k",
    "of",
    "add",
    "sub",
    "mul",
    "div",
    "min",
    "max",
    "gt",
    "lt",
    "eq",
    "neg",
    "abs",
    "clip",
    "reduce",
    "concat",
    "mean",
    "sum",
    "last",
    "delta",
    "minus_one",
    "zero",
    "repeat",
    "",
    "x",
    "\u{1F600}",
];

fn number(r: &mut Rng) -> Value {
    match r.below(8) {
        0 => json!(-1),
        1 => json!(u64::MAX),
        2 => json!(1e300),
        3 => json!(-0.5),
        4 => json!(i64::MIN),
        _ => json!(r.below(40)),
    }
}

fn random_value(r: &mut Rng, depth: usize) -> Value {
    let leaf = depth == 0 || r.chance(0.3);
    match if leaf { r.below(4) } else { 4 + r.below(2) } {
        0 => Value::Null,
        1 => Value::Bool(r.chance(0.5)),
        2 => number(r),
        3 => Value::String(r.pick(WORDS).to_string()),
        4 => Value::Array((0..r.below(4)).map(|_| random_value(r, depth - 1)).collect()),
        _ => {
            let mut m = Map::new();
            for _ in 0..r.below(4) {
                m.insert(r.pick(WORDS).to_string(), random_value(r, depth - 1));
            }
            Value::Object(m)
        }
    }
}

fn dim(r: &mut Rng, od: usize) -> usize {
    if r.chance(0.05) {
        od + r.below(3) as usize
    } else {
        r.below(od as u64) as usize
    }
}

/// A grammatical expression (mostly valid, sometimes not).
fn random_expr(r: &mut Rng, env: &ProtocolEnv, depth: usize, in_window: bool) -> Value {
    let od = env.obs_dim;
    let leaf = depth == 0 || r.chance(0.35);
    if leaf {
        return match r.below(6) {
            0 => json!({"obs": (0..1 + r.below(4)).map(|_| dim(r, od)).collect::<Vec<_>>()}),
            1 => {
                let s = r.below(od as u64) as usize;
                let extra = if r.chance(0.05) { 2 } else { 0 };
                let e = s + 1 + r.below((od - s) as u64 + extra) as usize;
                json!({"obs_slice": {"start": s, "end": e}})
            }
            2 => {
                let enc = *r.pick(&["one_hot", "index"]);
                json!({"last_action": enc})
            }
            3 => json!("sender_one_hot"),
            4 => json!({"const": (r.below(200) as f64 - 100.0) / 8.0}),
            _ => json!({"obs": [dim(r, od)]}),
        };
    }
    let sub = |r: &mut Rng| random_expr(r, env, depth - 1, in_window);
    match r.below(9) {
        0 if !in_window || r.chance(0.05) => {
            let k = if r.chance(0.05) { 0 } else { 1 + r.below(12) };
            let op = *r.pick(&["mean", "sum", "min", "max", "last", "delta", "last_nonzero"]);
            json!({"window": {"op": op, "k": k, "of": random_expr(r, env, depth - 1, true)}})
        }
        1 | 2 => {
            let op = *r.pick(&["add", "sub", "mul", "div", "min", "max", "gt", "lt", "eq"]);
            json!({op: [sub(r), sub(r)]})
        }
        3 => {
            let op = *r.pick(&["neg", "abs"]);
            json!({op: sub(r)})
        }
        4 => {
            let lo = r.below(5) as f64 - 2.0;
            json!({"clip": {"of": sub(r), "min": lo, "max": lo + r.below(4) as f64 - 0.5}})
        }
        5 => {
            let op = *r.pick(&["sum", "mean", "min", "max"]);
            json!({"reduce": {"op": op, "of": sub(r)}})
        }
        _ => json!({"concat": (0..1 + r.below(3)).map(|_| sub(r)).collect::<Vec<_>>()}),
    }
}

fn random_protocol(r: &mut Rng, env: &ProtocolEnv) -> Value {
    let n = env.n_agents;
    let fields: Vec<Value> = (0..1 + r.below(4))
        .map(|k| {
            let senders = if r.chance(0.5) { json!("all") } else { json!((0..n).filter(|_| r.chance(0.6)).collect::<Vec<_>>()) };
            let receivers = match r.below(3) {
                0 => json!("broadcast"),
                1 => json!({"agents": (0..n + 1).filter(|_| r.chance(0.5)).collect::<Vec<_>>()}),
                _ => json!({"peer": (0..n).map(|j| json!({"from": j, "to": [(j + 1 + r.below(n as u64) as usize) % (n + 1)]})).collect::<Vec<_>>()}),
            };
            json!({"name": format!("f{k}"), "description": "d", "senders": senders, "receivers": receivers, "value": random_expr(r, env, 4, false)})
        })
        .collect();
    let (crit, onehot, pad) = (r.below(env.state_dim as u64 + 1), r.chance(0.7), *r.pick(&["minus_one", "zero", "repeat"]));
    let layout = *r.pick(&["compact", "sender_blocks"]);
    json!({
        "name": "fz", "message_design_instruction": "fuzz", "critical_state_dims": [crit],
        "sender_one_hot": onehot, "history_padding": pad, "layout": layout, "fields": fields
    })
}

/// Replace, delete or retype a random node.
fn mutate(r: &mut Rng, v: &mut Value) {
    match v {
        Value::Object(m) if !m.is_empty() && r.chance(0.75) => {
            let keys: Vec<String> = m.keys().cloned().collect();
            let key = r.pick(&keys).clone();
            match r.below(5) {
                0 => {
                    m.remove(&key);
                }
                1 => *m.get_mut(&key).unwrap() = random_value(r, 3),
                2 => {
                    let val = m.remove(&key).unwrap();
                    m.insert(r.pick(WORDS).to_string(), val);
                }
                _ => mutate(r, m.get_mut(&key).unwrap()),
            }
        }
        Value::Array(a) if !a.is_empty() && r.chance(0.75) => {
            let i = r.below(a.len() as u64) as usize;
            match r.below(4) {
                0 => {
                    a.remove(i);
                }
                1 => a.push(random_value(r, 2)),
                _ => mutate(r, &mut a[i]),
            }
        }
        Value::Number(_) => *v = number(r),
        _ => *v = random_value(r, 3),
    }
}

fn run_plan(r: &mut Rng, plan: &mut dyn MessagePlan, env: &ProtocolEnv) {
    let (n, od) = (env.n_agents, env.obs_dim);
    let md = plan.msg_dim() + r.below(3) as usize;
    let ne = 1 + r.below(3) as usize;
    let mut rows = vec![0.0f32; ne * n * (od + md)];
    for _ in 0..4 {
        for x in rows.iter_mut() {
            *x = match r.below(20) {
                0 => f32::NAN,
                1 => 1e30,
                _ => r.below(5) as f32 - 1.0,
            };
        }
        let first: Vec<bool> = (0..ne).map(|_| r.chance(0.3)).collect();
        let la: Vec<i32> = (0..ne * n).map(|_| r.below(env.n_actions as u64 + 2) as i32 - 1).collect();
        plan.apply(&mut StepView {
            num_envs: ne,
            n_agents: n,
            obs_dim: od,
            msg_dim: md,
            rows: &mut rows,
            first: &first,
            last_actions: &la,
        });
    }
}

fn exercise(r: &mut Rng, v: &Value, env: &ProtocolEnv) -> bool {
    let text = v.to_string();
    let from_text = parse_str(&text);
    let from_value = parse_value(v);
    assert_eq!(from_text.is_ok(), from_value.is_ok(), "text and value parsing disagree on {text}");
    let p = match from_value {
        Ok(p) => p,
        Err(es) => {
            assert!(es.iter().all(|e| !e.to_string().is_empty()));
            return false;
        }
    };
    let _ = explain(&p, Some(env));
    let _ = explain(&p, None);
    match validate(&p, env) {
        Ok(vp) => {
            let plan = compile_plan(std::slice::from_ref(&vp), env).expect("a validated protocol compiles");
            assert_eq!(plan.msg_dim(), vp.width);
            assert_eq!(plan.column_labels(0).len(), vp.width);
            // Every receiver has the plan's width; in the compact layout its columns before the
            // padding are exactly the linked ones, and the widest receiver has no padding.
            for i in 0..env.n_agents {
                let cols = plan.columns(i);
                assert_eq!(cols.len(), vp.width);
                let used = cols.iter().filter(|c| !c.padding).count();
                assert_eq!(used, vp.receiver_width(i));
                assert!(cols[used..].iter().all(|c| c.padding), "padding comes last");
                if p.layout == MessageLayout::Compact {
                    assert!(cols[..used].iter().all(|c| c.linked), "compact spends columns only on links");
                }
            }
            assert_eq!((0..env.n_agents).map(|i| vp.receiver_width(i)).max().unwrap_or(0), vp.width);
            let mut plan = plan;
            run_plan(r, &mut plan, env);
            true
        }
        Err(es) => {
            assert!(!es.is_empty());
            for e in &es {
                assert!(!e.message.is_empty());
            }
            false
        }
    }
}

fn envs() -> Vec<ProtocolEnv> {
    vec![
        ProtocolEnv::new(2, 27, 6, 300, 200),
        ProtocolEnv::new(3, 5, 4, 10, 120),
        ProtocolEnv::new(1, 4, 2, 3, 50),
        ProtocolEnv::new(4, 3, 0, 0, 400),
    ]
}

#[test]
fn arbitrary_json_never_panics() {
    let mut r = Rng(7);
    let envs = envs();
    for case in 0..3000 {
        let v = random_value(&mut r, 5);
        exercise(&mut r, &v, &envs[case % envs.len()]);
        // Raw text too, including truncated and garbage text.
        let text = v.to_string();
        let cut = r.below(text.len() as u64 + 1) as usize;
        let cut = (0..=cut).rev().find(|&c| text.is_char_boundary(c)).unwrap_or(0);
        let _ = parse_str(&text[..cut]);
        let _ = parse_llm_text(&text[..cut]);
    }
}

#[test]
fn grammatical_random_protocols_validate_compile_and_run() {
    let mut r = Rng(11);
    let envs = envs();
    let mut valid = 0;
    for case in 0..1500 {
        let env = &envs[case % 2];
        let v = random_protocol(&mut r, env);
        if exercise(&mut r, &v, env) {
            valid += 1;
        }
    }
    assert!(valid > 150, "only {valid} of 1500 generated protocols were valid: the generator is too hostile");
}

#[test]
fn mutated_protocols_never_panic() {
    let mut r = Rng(13);
    let envs = envs();
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../prompts/examples");
    let mut seeds: Vec<Value> = std::fs::read_dir(&dir)
        .unwrap()
        .filter_map(|e| {
            let p = e.ok()?.path();
            (p.extension()? == "json").then(|| serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap())
        })
        .collect();
    seeds.push(random_protocol(&mut r, &envs[0]));
    for case in 0..2500 {
        let mut v = r.pick(&seeds).clone();
        for _ in 0..1 + r.below(3) {
            mutate(&mut r, &mut v);
        }
        exercise(&mut r, &v, &envs[case % envs.len()]);
    }
}

#[test]
fn deep_nesting_is_an_error_not_a_crash() {
    let env = ProtocolEnv::new(2, 27, 6, 300, 200);
    let mut e = json!({"obs": [0]});
    for _ in 0..40 {
        e = json!({"neg": e});
    }
    let v =
        json!({"message_design_instruction": "x", "critical_state_dims": [0], "fields": [{"name": "a", "description": "d", "value": e}]});
    let errs = validate(&parse_value(&v).unwrap(), &env).unwrap_err();
    assert_eq!(errs[0].kind, ErrorKind::Size);
    // Far deeper than serde_json's recursion limit: a parse error.
    let deep = format!("{}{}", "[".repeat(100_000), "]".repeat(100_000));
    assert!(parse_str(&deep).is_err());
    let deep = format!("{{\"message_design_instruction\": \"x\", \"critical_state_dims\": [], \"fields\": [{{\"name\": \"a\", \"description\": \"d\", \"value\": {}{{\"obs\": [0]}}{}}}]}}", "{\"neg\": ".repeat(5000), "}".repeat(5000));
    assert!(parse_str(&deep).is_err());
}
