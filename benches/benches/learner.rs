//! One learner update (QMIX / VDN / QPLEX, and LMAC with each encoder on QMIX) at the DESIGN.md
//! reference size: 32 episodes x 50 steps x 3 agents, GRU 64, mixing embed 32 (LMAC: 10 of the
//! 30 observation columns are messages, all 48 state dims reconstructed); plus one batched
//! acting step for 8 envs.
//! Needs in benches/Cargo.toml: `lmac-trainer.workspace = true` under [dependencies] and
//! `[[bench]] name = "learner" harness = false`.

use criterion::{criterion_group, criterion_main, Criterion};
use lmac_trainer::episode::{Episode, EpisodeDims};
use lmac_trainer::learn::methods::lmac::{EncoderKind, LmacConfig, LmacSettings};
use lmac_trainer::learn::Device;
use lmac_trainer::learn::{AgentConfig, Controller, LearnConfig, LearnRng, Learner, MixerKind};

const DIMS: EpisodeDims = EpisodeDims { n_agents: 3, obs_width: 30, state_dim: 48, n_actions: 9 };

fn filled_learner(mixer: MixerKind) -> Learner {
    filled(mixer, AgentConfig::Rnn)
}

fn filled(mixer: MixerKind, agent: AgentConfig) -> Learner {
    let cfg = LearnConfig { mixer, ..LearnConfig::default() };
    let mut learner = Learner::with_agent(DIMS, cfg, agent, Device::default()).unwrap();
    let mut rng = LearnRng::seed_from(0);
    let d = DIMS;
    for _ in 0..64 {
        learner.add_episode(Episode::synthetic(&d, 50, &mut rng, true)).unwrap();
    }
    learner
}

fn bench_update(c: &mut Criterion) {
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

criterion_group!(benches, bench_update, bench_act);
criterion_main!(benches);
