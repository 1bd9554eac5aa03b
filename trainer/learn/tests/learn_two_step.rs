//! The two-step cooperative matrix game of the QMIX paper (Rashid et al. 2018, Sec. 6.1):
//! in state 1 agent 1's action picks state 2A (every joint action pays 7) or 2B (payoff
//! [[0, 1], [1, 8]]). Trained from uniformly random play, QMIX learns the optimal joint policy
//! (return 8) while VDN's additive decomposition cannot represent 2B and settles for 7.

use burn::tensor::Device;
use lmac_learn::episode::{Episode, EpisodeDims};
use lmac_learn::{Controller, LearnConfig, LearnRng, Learner, MixerKind};

const DIMS: EpisodeDims = EpisodeDims { n_agents: 2, obs_width: 3, state_dim: 3, n_actions: 2 };

fn one_hot(s: usize) -> [f32; 3] {
    let mut v = [0.0; 3];
    v[s] = 1.0;
    v
}

/// Play one episode; `policy(step, state_id) -> [a0, a1]`.
fn play(mut policy: impl FnMut(usize, usize) -> [i32; 2]) -> Episode {
    let mut ep = Episode::with_capacity(&DIMS, 2);
    let a = policy(0, 0);
    push_step(&mut ep, 0, a, 0.0);
    let s2 = if a[0] == 0 { 1 } else { 2 };
    let b = policy(1, s2);
    let r = if s2 == 1 { 7.0 } else { [[0.0, 1.0], [1.0, 8.0]][b[0] as usize][b[1] as usize] };
    push_step(&mut ep, s2, b, r);
    ep.terminated = true;
    ep
}

fn push_step(ep: &mut Episode, s: usize, a: [i32; 2], r: f32) {
    let o = one_hot(s);
    ep.obs.extend_from_slice(&o);
    ep.obs.extend_from_slice(&o);
    ep.state.extend_from_slice(&o);
    ep.avail.extend_from_slice(&[1, 1, 1, 1]);
    ep.actions.extend_from_slice(&a);
    ep.reward.push(r);
    ep.len += 1;
}

fn greedy_return(learner: &Learner) -> f32 {
    let mut ctl = Controller::new(learner, 1);
    let mut rng = LearnRng::seed_from(0);
    let mut last = vec![-1, -1];
    let ep = play(|t, s| {
        let o = one_hot(s);
        let obs: Vec<f32> = o.iter().chain(o.iter()).copied().collect();
        let acts = ctl.select_actions(&obs, Some(&o), &last, &[1, 1, 1, 1], &[t == 0], 0.0, &mut rng);
        last = acts.clone();
        [acts[0], acts[1]]
    });
    ep.team_return()
}

fn train(mixer: MixerKind, seed: u64) -> Learner {
    let cfg = LearnConfig {
        mixer,
        seed,
        buffer_size: 500,
        batch_size: 32,
        lr: 1e-3,
        target_update_interval_episodes: 100,
        ..LearnConfig::default()
    };
    let mut learner = Learner::new(DIMS, cfg, Device::default()).unwrap();
    let mut rng = LearnRng::seed_from(seed + 17);
    for _ in 0..1200 {
        for _ in 0..4 {
            let ep = play(|_, _| [rng.below(2) as i32, rng.below(2) as i32]);
            learner.add_episode(ep).unwrap();
        }
        if learner.can_train() {
            learner.train_step().unwrap();
        }
    }
    learner
}

#[test]
fn qmix_learns_the_optimal_joint_policy_and_vdn_does_not() {
    let qmix = train(MixerKind::Qmix, 1);
    let vdn = train(MixerKind::Vdn, 1);
    let (rq, rv) = (greedy_return(&qmix), greedy_return(&vdn));
    eprintln!("greedy return: qmix {rq}, vdn {rv}");
    assert_eq!(rq, 8.0, "QMIX should find the return-8 joint policy");
    assert_eq!(rv, 7.0, "VDN should settle for state 2A (return 7)");
}

#[test]
fn qplex_solves_the_two_step_game() {
    // QPLEX's duplex dueling mixer is fully expressive for this game (IGM-complete).
    let qplex = train(MixerKind::Qplex, 2);
    assert_eq!(greedy_return(&qplex), 8.0);
}
