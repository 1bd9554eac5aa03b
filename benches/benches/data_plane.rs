//! Data-plane micro-benchmarks.
//! - `slot_handover_round_trip`: one slot message around the whole ring (env -> runner ->
//!   trainer -> env) over iceoryx2, with the event notifications, in one process.
//! - `fullcomm`: writing the FullComm messages in place into a slot of the shared slab, against
//!   republishing the batch: copying the slot into a new iceoryx2 sample, sending and receiving it.

use criterion::{criterion_group, criterion_main, BatchSize, Criterion};
use iceoryx2::prelude::*;
use lmac_protocol_runner::builtin::FullComm;
use lmac_protocol_runner::runner::apply_to_slot;
use lmac_shm_schema::ring::{Port, RingSpec};
use lmac_shm_schema::schema::load_env;
use lmac_shm_schema::{LayoutParams, Slab, Stage};
use std::time::Duration;

fn run_id(tag: &str) -> String {
    format!("bench{tag}{}", std::process::id())
}

fn handover(c: &mut Criterion) {
    let run = run_id("h");
    let spec = |role| RingSpec { run: run.clone(), n_members: 1, n_slots: 4, role, member: 0 };
    let mut trainer = Port::new(spec(Stage::Trainer)).unwrap();
    let mut runner = Port::new(spec(Stage::Runner)).unwrap();
    let mut env = Port::new(spec(Stage::Env)).unwrap();
    // The handshake needs the runner and trainer to forward tokens: drive them by hand.
    let mut done = false;
    for _ in 0..200 {
        env.send_slot(0, 0, 0).unwrap();
        if let Some(m) = runner.recv(Duration::from_millis(5)).unwrap() {
            runner.send_slot(0, m.slot as usize, m.seq).unwrap();
        }
        if let Some(m) = trainer.recv(Duration::from_millis(5)).unwrap() {
            trainer.send_slot(0, m.slot as usize, m.seq).unwrap();
        }
        if env.recv(Duration::from_millis(5)).unwrap().is_some() {
            done = true;
            break;
        }
    }
    assert!(done, "ring did not connect");
    // Drain leftovers.
    for p in [&mut env, &mut runner, &mut trainer] {
        while p.recv(Duration::from_millis(20)).unwrap().is_some() {}
    }
    let mut seq = 0u64;
    c.bench_function("slot_handover_round_trip (3 hops, in-process)", |b| {
        b.iter(|| {
            seq += 1;
            env.send_slot(0, 1, seq).unwrap();
            let m = runner.recv(Duration::from_secs(1)).unwrap().unwrap();
            runner.send_slot(0, m.slot as usize, m.seq).unwrap();
            let m = trainer.recv(Duration::from_secs(1)).unwrap().unwrap();
            trainer.send_slot(0, m.slot as usize, m.seq).unwrap();
            let m = env.recv(Duration::from_secs(1)).unwrap().unwrap();
            assert_eq!(m.seq, seq);
        })
    });
}

fn fullcomm(c: &mut Criterion) {
    let schema = load_env("lbf:11x11-6p-4f-s1-coop").expect("schema");
    let num_envs = 32;
    let msg = FullComm::columns(schema.n_agents, schema.obs_dim);
    let name = run_id("f");
    let slab = Slab::create(&name, &schema, LayoutParams { num_envs, msg_dim: msg, n_slots: 2 }).unwrap();
    slab.set_stage(0, Stage::Runner);
    {
        let mut s = slab.slot(0, Stage::Runner).unwrap();
        for (i, v) in s.obs_mut().iter_mut().enumerate() {
            *v = (i % 7) as f32;
        }
    }
    let mut plan = FullComm { n_agents: schema.n_agents, obs_dim: schema.obs_dim };
    let mut g = c.benchmark_group(format!("fullcomm {} x {} agents, {} message columns", num_envs, schema.n_agents, msg));
    g.bench_function("in place in the shared slab", |b| b.iter(|| apply_to_slot(&mut plan, &slab, 0).unwrap()));

    // Republishing: copy the slot into a fresh iceoryx2 sample, add the messages, send, receive.
    let stride = slab.layout().slot_stride;
    let node = NodeBuilder::new().create::<ipc::Service>().unwrap();
    let svc = node
        .service_builder(&ServiceName::new(&format!("lmac/{name}/republish")).unwrap())
        .publish_subscribe::<[u8]>()
        .subscriber_max_buffer_size(2)
        .open_or_create()
        .unwrap();
    let publisher = svc.publisher_builder().initial_max_slice_len(stride).create().unwrap();
    let subscriber = svc.subscriber_builder().create().unwrap();
    let src = slab.slot_ptr(0);
    let layout = slab.layout().clone();
    g.bench_function("republished with a copy (iceoryx2 sample)", |b| {
        b.iter_batched(
            || (),
            |_| {
                let sample = publisher.loan_slice_uninit(stride).unwrap();
                let bytes = unsafe { std::slice::from_raw_parts(src, stride) };
                let mut sample = sample.write_from_slice(bytes);
                // Apply the same messages to the copy.
                let data = sample.payload_mut();
                let rows: &mut [f32] =
                    unsafe { std::slice::from_raw_parts_mut(data.as_mut_ptr().add(layout.obs.offset) as *mut f32, layout.obs.bytes / 4) };
                let first = vec![false; layout.num_envs];
                let la = vec![0i32; layout.num_envs * layout.n_agents];
                let mut view = lmac_protocol_runner::plan::StepView {
                    num_envs: layout.num_envs,
                    n_agents: layout.n_agents,
                    obs_dim: layout.obs_dim,
                    msg_dim: layout.msg_dim,
                    rows,
                    first: &first,
                    last_actions: &la,
                };
                lmac_protocol_runner::plan::MessagePlan::apply(&mut plan, &mut view);
                sample.send().unwrap();
                let got = subscriber.receive().unwrap().unwrap();
                std::hint::black_box(got.payload().len());
            },
            BatchSize::SmallInput,
        )
    });
    g.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(50).measurement_time(Duration::from_secs(3)).warm_up_time(Duration::from_secs(1));
    targets = handover, fullcomm
}
criterion_main!(benches);
