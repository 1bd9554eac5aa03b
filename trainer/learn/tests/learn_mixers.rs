//! Mixer shapes, VDN = sum, QMIX monotonicity (dQ_tot/dQ_i >= 0 everywhere), QPLEX shapes,
//! and the agent network's shapes.

use burn::tensor::{Device, Distribution, Tensor};
use lmac_learn::agent::RnnAgent;
use lmac_learn::mixer::{Mixer, QplexInputs};
use lmac_learn::{LearnConfig, LearnRng, MixerKind};

const N: usize = 64;
const AGENTS: usize = 5;
const STATE: usize = 12;
const ACTIONS: usize = 7;

fn dev() -> Device {
    let d = Device::default();
    d.seed(7);
    d
}

#[test]
fn qmix_shapes_and_monotonicity() {
    let device = dev();
    let ad = device.clone().autodiff();
    let cfg = LearnConfig::default();
    let mixer = Mixer::new(&mut LearnRng::seed_from(1), MixerKind::Qmix, AGENTS, STATE, ACTIONS, &cfg, &ad);
    assert_eq!(mixer.kind(), MixerKind::Qmix);
    for trial in 0..3 {
        let qs: Tensor<2> = Tensor::random([N, AGENTS], Distribution::Uniform(-10.0, 10.0), &ad).require_grad();
        let states: Tensor<2> = Tensor::random([N, STATE], Distribution::Normal(0.0, 2.0), &ad);
        let q_tot = mixer.forward(qs.clone(), states, None);
        assert_eq!(q_tot.dims(), [N]);
        let grads = q_tot.sum().backward();
        let g: Vec<f32> = qs.grad(&grads).unwrap().into_data().try_into_vec().unwrap();
        assert_eq!(g.len(), N * AGENTS);
        let min = g.iter().cloned().fold(f32::INFINITY, f32::min);
        assert!(min >= 0.0, "trial {trial}: QMIX must be monotonic, min dQtot/dQi = {min}");
        assert!(g.iter().any(|&x| x > 0.0));
    }
    // Finite differences on the plain device too: raising any Q_i never lowers Q_tot.
    let mixer = Mixer::new(&mut LearnRng::seed_from(1), MixerKind::Qmix, AGENTS, STATE, ACTIONS, &cfg, &device);
    let qs: Tensor<2> = Tensor::random([N, AGENTS], Distribution::Uniform(-5.0, 5.0), &device);
    let states: Tensor<2> = Tensor::random([N, STATE], Distribution::Normal(0.0, 1.0), &device);
    let base: Vec<f32> = mixer.forward(qs.clone(), states.clone(), None).into_data().try_into_vec().unwrap();
    for i in 0..AGENTS {
        let mut bump = vec![0.0f32; N * AGENTS];
        for r in 0..N {
            bump[r * AGENTS + i] = 0.5;
        }
        let bump: Tensor<2> = Tensor::from_data(burn::tensor::TensorData::new(bump, [N, AGENTS]), &device);
        let up: Vec<f32> = mixer.forward(qs.clone() + bump, states.clone(), None).into_data().try_into_vec().unwrap();
        for r in 0..N {
            assert!(up[r] >= base[r] - 1e-4, "agent {i} row {r}: {} < {}", up[r], base[r]);
        }
    }
}

#[test]
fn vdn_is_the_sum() {
    let device = dev();
    let mixer = Mixer::new(&mut LearnRng::seed_from(1), MixerKind::Vdn, AGENTS, STATE, ACTIONS, &LearnConfig::default(), &device);
    let qs: Tensor<2> = Tensor::random([N, AGENTS], Distribution::Uniform(-1.0, 1.0), &device);
    let states: Tensor<2> = Tensor::zeros([N, STATE], &device);
    let got: Vec<f32> = mixer.forward(qs.clone(), states, None).into_data().try_into_vec().unwrap();
    let q: Vec<f32> = qs.into_data().try_into_vec().unwrap();
    for r in 0..N {
        let s: f32 = q[r * AGENTS..(r + 1) * AGENTS].iter().sum();
        assert!((got[r] - s).abs() < 1e-5);
    }
}

#[test]
fn qplex_shapes_and_gradients() {
    let device = dev();
    let ad = device.clone().autodiff();
    for layers in 1..=3 {
        let cfg = LearnConfig { qplex_adv_hypernet_layers: layers, qplex_num_kernel: 4, ..LearnConfig::default() };
        let mixer = Mixer::new(&mut LearnRng::seed_from(1), MixerKind::Qplex, AGENTS, STATE, ACTIONS, &cfg, &ad);
        assert_eq!(mixer.kind(), MixerKind::Qplex);
        let qs: Tensor<2> = Tensor::random([N, AGENTS], Distribution::Uniform(-1.0, 1.0), &ad).require_grad();
        let max_q = qs.clone().detach() + 0.5;
        let acts: Tensor<2> = Tensor::random([N, AGENTS * ACTIONS], Distribution::Uniform(0.0, 1.0), &ad);
        let states: Tensor<2> = Tensor::random([N, STATE], Distribution::Normal(0.0, 1.0), &ad);
        let q_tot = mixer.forward(qs.clone(), states, Some(QplexInputs { actions_onehot: acts, max_q }));
        assert_eq!(q_tot.dims(), [N]);
        let grads = q_tot.sum().backward();
        let g: Vec<f32> = qs.grad(&grads).unwrap().into_data().try_into_vec().unwrap();
        // dQ_tot/dQ_i = w_i(s) > 0 (the advantage term is detached).
        assert!(g.iter().all(|&x| x > 0.0 && x.is_finite()));
    }
}

#[test]
fn agent_unroll_and_step_agree() {
    let device = dev();
    let agent = RnnAgent::new(&mut LearnRng::seed_from(2), 10, 16, ACTIONS, &device);
    let xs: Vec<Tensor<2>> = (0..4).map(|_| Tensor::random([6, 10], Distribution::Normal(0.0, 1.0), &device)).collect();
    let q_seq = agent.unroll(xs.clone());
    assert_eq!(q_seq.dims(), [4, 6, ACTIONS]);
    let mut h: Tensor<2> = Tensor::zeros([6, 16], &device);
    let seq: Vec<f32> = q_seq.into_data().try_into_vec().unwrap();
    for (t, x) in xs.into_iter().enumerate() {
        let (q, h2) = agent.step(x, h);
        h = h2;
        let q: Vec<f32> = q.into_data().try_into_vec().unwrap();
        for (i, v) in q.iter().enumerate() {
            assert!((v - seq[t * 6 * ACTIONS + i]).abs() < 1e-5);
        }
    }
}

/// Timing of one learner update at the DESIGN.md reference size (32 episodes x 50 steps x
/// 3 agents, GRU 64, mixer 32). Run with
/// `cargo test --release -p lmac-learn --test learn_mixers -- --ignored --nocapture`.
#[test]
#[ignore]
fn time_one_update() {
    use lmac_learn::episode::{Episode, EpisodeDims};
    use lmac_learn::{LearnRng, Learner};
    let dims = EpisodeDims { n_agents: 3, obs_width: 30, state_dim: 48, n_actions: 9 };
    for (mixer, parallel_target) in [(MixerKind::Qmix, false), (MixerKind::Qmix, true), (MixerKind::Vdn, false), (MixerKind::Qplex, false)]
    {
        let cfg = LearnConfig { mixer, parallel_target, ..LearnConfig::default() };
        let mut learner = Learner::new(dims, cfg, Device::default()).unwrap();
        let mut rng = LearnRng::seed_from(0);
        for _ in 0..32 {
            let len = 50;
            let mut ep = Episode::with_capacity(&dims, len);
            ep.len = len;
            ep.obs = (0..len * 3 * 30).map(|_| rng.uniform()).collect();
            ep.state = (0..len * 48).map(|_| rng.uniform()).collect();
            ep.avail = vec![1; len * 3 * 9];
            ep.actions = (0..len * 3).map(|_| rng.below(9) as i32).collect();
            ep.reward = (0..len).map(|_| rng.uniform()).collect();
            ep.terminated = true;
            learner.add_episode(ep).unwrap();
        }
        for _ in 0..3 {
            learner.train_step().unwrap();
        }
        let n = 10;
        let t0 = std::time::Instant::now();
        for _ in 0..n {
            learner.train_step().unwrap();
        }
        let ms = t0.elapsed().as_secs_f64() * 1000.0 / n as f64;
        eprintln!("{mixer:?} (parallel_target {parallel_target}): {ms:.1} ms per update (32 x 50 x 3 agents)");
    }
}

#[test]
fn acting_weights_can_cross_threads() {
    fn assert_send<T: Send>() {}
    assert_send::<RnnAgent>();
    assert_send::<lmac_learn::QNet>();
}
