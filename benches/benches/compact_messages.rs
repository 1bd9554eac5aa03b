//! Message columns and runner cost of a designed protocol in the compact layout against the
//! earlier sender-blocks layout: per receiving agent the columns it uses, the plan's
//! width (the widest receiver's), how many of them are sender one-hots, and the plan's cost per
//! batched step of 32 environments. Prints one JSON object (docs/figures/compact_messages.json).
//!
//! `cargo bench -p lmac-benches --bench compact_messages [-- ENV=DESIGN_DIR ...]`; by default
//! `smaclite:1o_10b_vs_1r=docs/figures/design_1o_10b_vs_1r` and
//! `smaclite:2o_20b_vs_2r=docs/figures/design_2o_20b_vs_2r` (skipped when missing).

use lmac_protocol_runner::plan::{MessagePlan, StepView};
use lmac_protocol_runner::protocol::{self, compile_plan, MessageLayout, ProtocolEnv, ProtocolPlan, ValidatedProtocol};
use lmac_run::stats::median;
use std::path::{Path, PathBuf};
use std::time::Instant;

const ENVS: usize = 32;

fn load(dir: &Path, env: &ProtocolEnv, layout: MessageLayout) -> Result<Vec<ValidatedProtocol>, String> {
    let mut phases: Vec<ValidatedProtocol> = Vec::new();
    for k in 0.. {
        let f = dir.join(format!("phase{k}")).join("protocol.json");
        if !f.is_file() {
            break;
        }
        let text = std::fs::read_to_string(&f).map_err(|e| format!("{}: {e}", f.display()))?;
        let mut p = protocol::parse_str(&text).map_err(|e| format!("{}: {}", f.display(), protocol::errors_to_text(&e)))?;
        p.layout = layout;
        // The recorded designs were validated against a budget for the sender-blocks layout;
        // lift the budget so both layouts of the same fields compile.
        let mut big = env.clone();
        big.message_budget = usize::MAX / 4;
        phases.push(protocol::validate_phase(&p, &big, &phases).map_err(|e| format!("{}: {}", f.display(), protocol::errors_to_text(&e)))?);
    }
    if phases.is_empty() {
        return Err(format!("{}: no phase*/protocol.json", dir.display()));
    }
    Ok(phases)
}

struct Batch {
    rows: Vec<f32>,
    first: Vec<bool>,
    last_actions: Vec<i32>,
}

fn batch(n: usize, od: usize, md: usize, na: usize) -> Batch {
    let rw = od + md;
    let mut rows = vec![0.0f32; ENVS * n * rw];
    for (k, r) in rows.chunks_exact_mut(rw).enumerate() {
        for (d, x) in r[..od].iter_mut().enumerate() {
            *x = ((k * 31 + d * 7) % 13) as f32 / 13.0 - 0.3;
        }
    }
    Batch { rows, first: vec![false; ENVS], last_actions: (0..ENVS * n).map(|k| (k % na) as i32).collect() }
}

/// ns per batched step of each of `reps` timed runs of `steps` steps (the JSON reports the
/// median over all runs and the fastest run: on a shared machine the minimum is the steadier).
fn time(plan: &mut ProtocolPlan, n: usize, od: usize, na: usize, steps: usize, reps: usize) -> Vec<f64> {
    let md = plan.msg_dim();
    let mut b = batch(n, od, md, na);
    let mut step = 0usize;
    let mut go = |b: &mut Batch, k: usize| {
        for _ in 0..k {
            b.first[0] = step % 50 == 0;
            step += 1;
            let mut view = StepView {
                num_envs: ENVS,
                n_agents: n,
                obs_dim: od,
                msg_dim: md,
                rows: &mut b.rows,
                first: &b.first,
                last_actions: &b.last_actions,
            };
            plan.apply(&mut view);
            std::hint::black_box(&b.rows);
        }
    };
    go(&mut b, steps / 4);
    (0..reps)
        .map(|_| {
            let t = Instant::now();
            go(&mut b, steps);
            t.elapsed().as_nanos() as f64 / steps as f64
        })
        .collect()
}

fn main() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let args: Vec<String> = std::env::args().skip(1).filter(|a| a.contains('=') && !a.starts_with('-')).collect();
    let pairs: Vec<(String, PathBuf)> = if args.is_empty() {
        vec![
            ("smaclite:1o_10b_vs_1r".into(), root.join("docs/figures/design_1o_10b_vs_1r")),
            ("smaclite:2o_20b_vs_2r".into(), root.join("docs/figures/design_2o_20b_vs_2r")),
        ]
    } else {
        args.iter().map(|a| a.split_once('=').map(|(e, d)| (e.to_string(), PathBuf::from(d))).unwrap()).collect()
    };
    let mut out = Vec::new();
    for (env_name, dir) in pairs {
        if !dir.is_dir() {
            eprintln!("{env_name}: {} missing, skipped", dir.display());
            continue;
        }
        let schema = lmac_shm_schema::schema::load_env(&env_name).unwrap_or_else(|e| panic!("{e}"));
        let env = lmac_protocol_runner::protocol_env(&schema);
        let (n, od, na) = (env.n_agents, env.obs_dim, env.n_actions);
        let mut layouts = Vec::new();
        let mut plans = Vec::new();
        for layout in [MessageLayout::SenderBlocks, MessageLayout::Compact] {
            let phases = load(&dir, &env, layout).unwrap_or_else(|e| panic!("{e}"));
            let plan = compile_plan(&phases, &{
                let mut big = env.clone();
                big.message_budget = usize::MAX / 4;
                big
            })
            .unwrap_or_else(|e| panic!("{}", protocol::errors_to_text(&e)));
            let per: Vec<usize> = (0..n).map(|i| plan.columns(i).iter().filter(|c| !c.padding).count()).collect();
            let onehot: Vec<usize> = (0..n).map(|i| plan.columns(i).iter().filter(|c| !c.padding && c.field.is_none()).count()).collect();
            let values: Vec<usize> = (0..n).map(|i| plan.columns(i).iter().filter(|c| c.linked && c.field.is_some()).count()).collect();
            layouts.push(serde_json::json!({
                "layout": if layout == MessageLayout::Compact { "compact" } else { "sender_blocks" },
                "msg_dim": plan.msg_dim(),
                "within_budget": plan.msg_dim() <= schema.message_columns,
                "columns_per_receiver": per,
                "sender_one_hot_columns_per_receiver": onehot,
                "value_columns_per_receiver": values,
            }));
            plans.push(plan);
        }
        // Interleaved timed runs, so drift on this shared machine hits both layouts alike.
        let steps = (200_000 / (ENVS * n)).max(200);
        let mut ns = vec![Vec::new(), Vec::new()];
        for _ in 0..9 {
            for (k, p) in plans.iter_mut().enumerate() {
                ns[k].extend(time(p, n, od, na, steps, 3));
            }
        }
        for (k, l) in layouts.iter_mut().enumerate() {
            let m = median(&ns[k]);
            l["ns_per_batched_step"] = serde_json::json!(m.round());
            l["ns_min_per_batched_step"] = serde_json::json!(ns[k].iter().cloned().fold(f64::INFINITY, f64::min).round());
            l["ns_per_env_step"] = serde_json::json!((m / ENVS as f64 * 10.0).round() / 10.0);
            l["ns_samples"] = serde_json::json!(ns[k].iter().map(|x| x.round()).collect::<Vec<_>>());
        }
        let ratio = median(&ns[1]) / median(&ns[0]);
        out.push(serde_json::json!({
            "env": env_name, "design": dir.strip_prefix(&root).unwrap_or(&dir).display().to_string(),
            "n_agents": n, "obs_dim": od, "message_budget": schema.message_columns, "envs_per_batch": ENVS,
            "steps_per_timed_run": steps, "layouts": layouts, "compact_over_blocks_time": (ratio * 1000.0).round() / 1000.0,
        }));
        eprintln!("{env_name}: {}", serde_json::to_string(&out.last().unwrap()["layouts"]).unwrap());
    }
    println!("{}", serde_json::to_string_pretty(&serde_json::json!({ "runs": out })).unwrap());
}
