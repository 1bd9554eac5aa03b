//! COLA's mechanism on a game made for it: at every step a hidden value c (one of 8) is drawn and
//! each of three agents sees it through its own permutation (agent i observes the one-hot of
//! (c (2i + 1) + i) mod 8), so the agents' observations of a step differ but say the same thing.
//! The consensus loss must make the agents of a step pick the same class (K = 4: chance 1/4)
//! without collapsing into one class; without it (`consensus_weight = 0`) they do not. The agents
//! see no last action (`obs_last_action = false`): the all-zero last action of an episode's first
//! step is a feature every agent shares, on which the classes could split instead of on c.

use burn::tensor::{Device, Tensor, TensorData};
use lmac_learn::episode::{Episode, EpisodeDims};
use lmac_learn::methods::{method, AgentConfig, AgentNet, MethodContext};
use lmac_learn::{LearnConfig, LearnRng, Learner, OptimizerKind, RowParts};

const DIMS: EpisodeDims = EpisodeDims { n_agents: 3, obs_width: 8, state_dim: 8, n_actions: 2 };
const LEN: usize = 4;
/// Updates of 8 episodes (RMSprop, lr 5e-4, the released optimizer): seeds 1-4 all reach
/// agreement 1.0 with 1.9-2 bits of class entropy by 800; without the consensus loss the
/// untrained student puts (nearly) every row in one class (0-0.65 bits).
const UPDATES: usize = 800;

fn view(agent: usize, c: usize) -> usize {
    (c * (2 * agent + 1) + agent) % 8
}

fn episode(rng: &mut LearnRng) -> Episode {
    let mut ep = Episode::with_capacity(&DIMS, LEN);
    for _ in 0..LEN {
        let c = rng.below(8);
        for i in 0..DIMS.n_agents {
            let mut o = vec![0.0; 8];
            o[view(i, c)] = 1.0;
            ep.obs.extend(o);
        }
        let mut s = vec![0.0; 8];
        s[c] = 1.0;
        ep.state.extend(s);
        ep.avail.extend(vec![1; DIMS.n_agents * DIMS.n_actions]);
        ep.actions.extend((0..DIMS.n_agents).map(|_| rng.below(2) as i32));
        ep.reward.push(rng.uniform());
    }
    ep.len = LEN;
    ep.terminated = true;
    ep
}

fn train(settings: &str, seed: u64, updates: usize) -> Learner {
    let spec = method("cola").unwrap();
    let agent: AgentConfig = (spec.configure)(&toml::from_str(settings).unwrap(), &MethodContext::default()).unwrap();
    let cfg = LearnConfig {
        seed,
        buffer_size: 200,
        batch_size: 16,
        optimizer: OptimizerKind::Rmsprop,
        obs_last_action: false,
        ..LearnConfig::default()
    };
    let mut learner = Learner::with_agent(DIMS, cfg, agent, Device::default()).unwrap();
    let mut rng = LearnRng::seed_from(seed + 17);
    while !learner.can_train() {
        learner.add_episode(episode(&mut rng)).unwrap();
    }
    for _ in 0..updates {
        learner.add_episode(episode(&mut rng)).unwrap();
        learner.train_step().unwrap();
    }
    learner
}

/// The acting network's classes [agent][c] at an episode's first step, the share of ordered
/// agent pairs that agree over the 8 values, and the entropy (bits) of the classes used.
fn consensus(learner: &Learner) -> (Vec<Vec<usize>>, f32, f32) {
    let net = learner.acting_net();
    let AgentNet::Cola(a) = &net.agent else { panic!("not a COLA network") };
    let layout = learner.layout();
    let iw = layout.width();
    let mut cls = vec![Vec::new(); DIMS.n_agents];
    for c in 0..8 {
        let mut x = vec![0.0; DIMS.n_agents * iw];
        for (i, row) in x.chunks_mut(iw).enumerate() {
            let mut o = vec![0.0; 8];
            o[view(i, c)] = 1.0;
            layout.write(row, RowParts::step(&o, None, -1, i));
        }
        let x: Tensor<2> = Tensor::from_data(TensorData::new(x, [DIMS.n_agents, iw]), learner.device());
        let h = Tensor::zeros([DIMS.n_agents, a.state_width()], learner.device());
        for (i, k) in a.consensus_classes(x, h).into_iter().enumerate() {
            cls[i].push(k);
        }
    }
    let (mut same, mut pairs) = (0, 0);
    let mut usage = [0usize; 4];
    for c in 0..8 {
        for i in 0..DIMS.n_agents {
            usage[cls[i][c]] += 1;
            for j in (0..DIMS.n_agents).filter(|&j| j != i) {
                pairs += 1;
                same += (cls[i][c] == cls[j][c]) as usize;
            }
        }
    }
    let total = usage.iter().sum::<usize>() as f32;
    let entropy = usage.iter().filter(|&&u| u > 0).map(|&u| -(u as f32 / total) * (u as f32 / total).log2()).sum();
    (cls, same as f32 / pairs as f32, entropy)
}

fn check(settings: &str, seed: u64, updates: usize) -> (f32, f32) {
    let t = std::time::Instant::now();
    let learner = train(settings, seed, updates);
    let (cls, agreement, entropy) = consensus(&learner);
    eprintln!(
        "cola {settings:?} seed {seed}, {updates} updates: agreement {agreement:.2}, class entropy {entropy:.2} bits, classes {cls:?} ({:.1} s)",
        t.elapsed().as_secs_f32()
    );
    (agreement, entropy)
}

#[test]
fn agents_of_a_step_agree_on_the_consensus_class() {
    let (agreement, entropy) = check("", 1, UPDATES);
    assert!(agreement >= 0.9, "agreement {agreement} (chance 0.25)");
    assert!(entropy >= 1.0, "the classes collapsed: entropy {entropy} bits");
}

#[test]
fn without_the_consensus_loss_they_do_not() {
    let (agreement, entropy) = check("consensus_weight = 0.0", 1, UPDATES);
    assert!(agreement < 0.9 || entropy < 1.0, "agreement {agreement}, entropy {entropy}");
}

/// Not in CI: seeds 1-4 with and without the loss (`cargo test --release --test cola_consensus
/// -- --ignored --nocapture`).
#[test]
#[ignore]
fn measure_over_seeds() {
    for settings in ["", "consensus_weight = 0.0"] {
        let r: Vec<(f32, f32)> = (1..=4).map(|seed| check(settings, seed, UPDATES)).collect();
        eprintln!("== {settings:?}: {r:?}");
    }
}

fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().try_into_vec::<f32>().unwrap()
}

#[test]
fn the_teacher_and_the_center_are_saved_and_copied_to_the_target_but_never_trained() {
    let mut l = train("", 3, 5);
    l.update_target();
    let cola = |net: &lmac_learn::QNet| match &net.agent {
        AgentNet::Cola(a) => (values(a.center.value()), values(a.teacher.proj2.weight.val()), values(a.student.proj2.weight.val())),
        _ => panic!("not a COLA network"),
    };
    let online = cola(l.online_net());
    assert!(online.0.iter().any(|v| *v != 0.0), "five updates moved the center: {:?}", online.0);
    assert_eq!(cola(l.target_net()), online, "the target copy");
    let dir = std::env::temp_dir().join(format!("lmac-cola-{}", std::process::id()));
    l.save_checkpoint(&dir, false).unwrap();
    let r = Learner::load_checkpoint(&dir, Device::default()).unwrap();
    assert_eq!(cola(r.online_net()), online, "the checkpoint");
    assert_eq!(cola(r.target_net()), online);
    let AgentNet::Cola(a) = &r.online_net().agent else { panic!("not a COLA network") };
    assert!(!a.teacher.view1.weight.val().is_require_grad(), "a loaded teacher stays out of the optimizer");
    assert!(a.student.view1.weight.val().is_require_grad());
    let _ = std::fs::remove_dir_all(&dir);
}
