//! Protocol execution per batched step: a compiled protocol (30 message columns per sender
//! block, windows over the last 10 steps) against the FullComm append, on the same batch.
//!
//! Needs in benches/Cargo.toml: `[[bench]] name = "protocol" harness = false`.

use criterion::{black_box, criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use lmac_protocol_runner::builtin::FullComm;
use lmac_protocol_runner::plan::{MessagePlan, StepView};
use lmac_protocol_runner::protocol::{check_str, compile, ProtocolEnv};

/// 30 columns per sender block (+ the sender one-hot): 8 raw obs dims, 10 thresholded dims,
/// a 10-step mean of the last-action one-hot (n_actions columns) and a 10-step delta.
fn protocol_json(n_actions: usize, od: usize) -> String {
    let rest = 30 - 8 - 10 - n_actions;
    format!(
        r#"{{
  "name": "bench30",
  "message_design_instruction": "benchmark protocol: own features, thresholded neighbourhood, 10-step action histogram and trends",
  "critical_state_dims": [0],
  "fields": [
    {{"name": "own", "description": "own features", "value": {{"obs_slice": {{"start": 0, "end": 8}}}}}},
    {{"name": "seen", "description": "which of 10 cells are occupied", "value": {{"gt": [{{"obs_slice": {{"start": 8, "end": 18}}}}, {{"const": 0}}]}}}},
    {{"name": "moves", "description": "10-step action histogram", "value": {{"window": {{"op": "mean", "k": 10, "of": {{"last_action": "one_hot"}}}}}}}},
    {{"name": "trend", "description": "10-step change of the last dims", "value": {{"window": {{"op": "delta", "k": 10, "of": {{"obs_slice": {{"start": {s}, "end": {od}}}}}}}}}}}
  ]
}}"#,
        s = od - rest,
    )
}

struct Batch {
    rows: Vec<f32>,
    first: Vec<bool>,
    last_actions: Vec<i32>,
}

fn batch(num_envs: usize, n: usize, od: usize, md: usize, n_actions: usize) -> Batch {
    let rw = od + md;
    let mut rows = vec![0.0f32; num_envs * n * rw];
    for (k, r) in rows.chunks_exact_mut(rw).enumerate() {
        for (d, x) in r[..od].iter_mut().enumerate() {
            *x = ((k * 31 + d * 7) % 13) as f32 / 13.0;
        }
    }
    let last_actions = (0..num_envs * n).map(|k| (k % n_actions) as i32).collect();
    Batch { rows, first: vec![false; num_envs], last_actions }
}

fn run(plan: &mut dyn MessagePlan, b: &mut Batch, num_envs: usize, n: usize, od: usize, md: usize, step: &mut usize) {
    // A new episode every 50 steps in env 0, so history restarts are exercised too.
    b.first[0] = *step % 50 == 0;
    *step += 1;
    let mut view =
        StepView { num_envs, n_agents: n, obs_dim: od, msg_dim: md, rows: &mut b.rows, first: &b.first, last_actions: &b.last_actions };
    plan.apply(&mut view);
    black_box(&b.rows);
}

fn bench(c: &mut Criterion) {
    let mut g = c.benchmark_group("protocol_apply");
    // (label, num_envs, n_agents, obs_dim, n_actions): SMAC-like 5 agents, LBF-like 2 agents.
    for (label, num_envs, n, od, na) in [("5ag_obs80_x32", 32usize, 5usize, 80usize, 11usize), ("2ag_obs27_x64", 64, 2, 27, 6)] {
        let fc_md = FullComm::columns(n, od);
        let env = ProtocolEnv::new(n, od, na, 1, 10_000);
        let p = check_str(&protocol_json(na, od), &env).unwrap_or_else(|e| panic!("{e:?}"));
        let mut plan = compile(&[p], &env).unwrap();
        let md = fc_md.max(plan.msg_dim());
        g.throughput(Throughput::Elements((num_envs * n) as u64));

        let mut b = batch(num_envs, n, od, md, na);
        let mut step = 0;
        g.bench_function(BenchmarkId::new("protocol30_w10", label), |bch| {
            bch.iter(|| run(plan.as_mut(), &mut b, num_envs, n, od, md, &mut step))
        });

        let mut fc = FullComm { n_agents: n, obs_dim: od };
        let mut b = batch(num_envs, n, od, md, na);
        let mut step = 0;
        g.bench_function(BenchmarkId::new("fullcomm", label), |bch| bch.iter(|| run(&mut fc, &mut b, num_envs, n, od, md, &mut step)));
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
