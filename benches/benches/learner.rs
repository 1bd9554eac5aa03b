//! One learner update (QMIX / VDN / QPLEX, and LMAC with each encoder on QMIX) at the DESIGN.md
//! reference size: 32 episodes x 50 steps x 3 agents, GRU 64, mixing embed 32 (LMAC: 10 of the
//! 30 observation columns are messages, all 48 state dims reconstructed); plus one batched
//! acting step for 8 envs.
//! Needs in benches/Cargo.toml: `lmac-run.workspace = true` under [dependencies] and
//! `[[bench]] name = "learner" harness = false`.

use criterion::{criterion_group, criterion_main, Criterion};
use lmac_run::episode::{Episode, EpisodeDims};
use lmac_run::learn::methods::lmac::{EncoderKind, LmacConfig, LmacSettings};
use lmac_run::learn::Device;
use lmac_run::learn::{AgentConfig, Controller, LearnConfig, LearnRng, Learner, MixerKind};

const DIMS: EpisodeDims = EpisodeDims { n_agents: 3, obs_width: 30, state_dim: 48, n_actions: 9 };

fn filled_learner(mixer: MixerKind) -> Learner {
    filled(mixer, AgentConfig::Rnn)
}

fn filled(mixer: MixerKind, agent: AgentConfig) -> Learner {
    // The update on one thread, as these figures always measured it (the default since runs it
    // on both cores; `lmac bench learner --two-cores` times that).
    let cfg = LearnConfig { mixer, data_parallel: false, parallel_target: false, ..LearnConfig::default() };
    let mut learner = Learner::with_agent(DIMS, cfg, agent, Device::default()).unwrap();
    let mut rng = LearnRng::seed_from(0);
    let d = DIMS;
    for _ in 0..64 {
        learner.add_episode(Episode::synthetic(&d, 50, &mut rng, true)).unwrap();
    }
    learner
}

fn bench_update(c: &mut Criterion) {
    lmac_run::tune_allocator();
    let mut g = c.benchmark_group("learner_update_32x50x3");
    g.sample_size(10);
    for mixer in [MixerKind::Qmix, MixerKind::Vdn, MixerKind::Qplex] {
        let mut learner = filled_learner(mixer);
        g.bench_function(format!("{mixer:?}").to_lowercase(), |b| b.iter(|| learner.train_step().unwrap()));
    }
    for (name, encoder) in [("lmac_gru_gate", EncoderKind::GruGate), ("lmac_window", EncoderKind::Window)] {
        let settings = LmacSettings { encoder, ..LmacSettings::default() };
        let agent = AgentConfig::Lmac(LmacConfig { settings, msg_cols: 10, alpha: 0.1, critical_dims: (0..DIMS.state_dim).collect() });
        let mut learner = filled(MixerKind::Qmix, agent);
        g.bench_function(name, |b| b.iter(|| learner.train_step().unwrap()));
    }
    g.finish();
}

fn bench_act(c: &mut Criterion) {
    let mut learner = filled_learner(MixerKind::Qmix);
    let envs = 8;
    let mut ctl = Controller::new(&learner, envs);
    let d = DIMS;
    let obs = vec![0.5f32; envs * d.n_agents * d.obs_width];
    let last = vec![0i32; envs * d.n_agents];
    let avail = vec![1u8; envs * d.n_agents * d.n_actions];
    let first = vec![false; envs];
    c.bench_function("act_step_8_envs", |b| b.iter(|| ctl.select_actions(&obs, None, &last, &avail, &first, 0.1, learner.rng_mut())));
}

/// The fused GRU recurrence alone (forward with saved activations, and backward through time)
/// at the agent-row counts of the two reference shapes: LBF 8x8 (32 x 2 agents, 25 steps) and
/// 1o_10b_vs_1r (32 x 11 agents, 50 steps), hidden 64.
fn bench_gru_sequence(c: &mut Criterion) {
    lmac_run::tune_allocator();
    use lmac_run::learn::gru_sequence::Saved;
    let mut g = c.benchmark_group("gru_sequence");
    g.sample_size(10);
    for (name, t, n) in [("lbf8x8", 25, 64), ("1o10b", 50, 352)] {
        let h = 64;
        let mut rng = LearnRng::seed_from(1);
        let gi: Vec<f32> = (0..t * n * 3 * h).map(|_| rng.uniform() * 2.0 - 1.0).collect();
        let w: Vec<f32> = (0..h * 3 * h).map(|_| (rng.uniform() * 2.0 - 1.0) * 0.125).collect();
        let b: Vec<f32> = (0..3 * h).map(|_| rng.uniform() * 0.1).collect();
        let d_hs: Vec<f32> = (0..t * n * h).map(|_| rng.uniform() - 0.5).collect();
        g.bench_function(format!("{name}_forward"), |bch| bch.iter(|| Saved::forward(&gi, w.clone(), &b, t, n, h, true)));
        let saved = Saved::forward(&gi, w.clone(), &b, t, n, h, true);
        g.bench_function(format!("{name}_backward"), |bch| bch.iter(|| saved.backward(&d_hs)));
    }
    g.finish();
}

/// The LMAC window encoder's attention alone (forward keeping the weights, and backward) at
/// 1o_10b_vs_1r's agent rows (32 x 11 agents, 50 steps) with the default width 64 in 4 heads
/// and a window of 10.
fn bench_window_attention(c: &mut Criterion) {
    lmac_run::tune_allocator();
    use lmac_run::learn::window_attention::Saved;
    let mut g = c.benchmark_group("window_attention");
    g.sample_size(10);
    let (t, n, heads, d, w) = (50, 352, 4, 16, 10);
    let mut rng = LearnRng::seed_from(2);
    let mut random = |len: usize| -> Vec<f32> { (0..len).map(|_| rng.uniform() * 2.0 - 1.0).collect() };
    let len = t * n * heads * d;
    let (q, k, v, d_out) = (random(len), random(len), random(len), random(len));
    g.bench_function("1o10b_forward", |b| b.iter(|| Saved::forward(q.clone(), k.clone(), v.clone(), t, n, heads, d, w, true)));
    let saved = Saved::forward(q.clone(), k.clone(), v.clone(), t, n, heads, d, w, true);
    g.bench_function("1o10b_backward", |b| b.iter(|| saved.backward(&d_out)));
    g.finish();
}

criterion_group!(benches, bench_update, bench_act, bench_gru_sequence, bench_window_attention);
criterion_main!(benches);
