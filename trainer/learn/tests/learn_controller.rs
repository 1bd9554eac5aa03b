//! Acting switches to new weights between episodes: an env in the middle of an episode keeps
//! the weights it started with, an env that starts a new episode takes the newest.

use burn::tensor::Device;
use lmac_learn::episode::EpisodeDims;
use lmac_learn::{Controller, LearnConfig, Learner};

const DIMS: EpisodeDims = EpisodeDims { n_agents: 2, obs_width: 3, state_dim: 2, n_actions: 4 };

fn learner(seed: u64) -> Learner {
    Learner::new(DIMS, LearnConfig { seed, ..Default::default() }, Device::default()).unwrap()
}

fn obs(t: usize, envs: usize) -> Vec<f32> {
    (0..envs * DIMS.n_agents * DIMS.obs_width).map(|k| ((k + 7 * t) % 5) as f32 * 0.3).collect()
}

#[test]
fn new_weights_take_effect_when_an_env_starts_its_next_episode() {
    let (old, new) = (learner(1), learner(2));
    let last = vec![1; 2 * DIMS.n_agents];
    let mut ctl = Controller::new(&old, 2);
    ctl.q_values(&obs(0, 2), None, &last, &[true, true]);
    ctl.offer_agent(new.acting_net().agent);
    assert_eq!(ctl.versions_in_use(), 2);
    // Env 0 starts a new episode, env 1 goes on.
    let q = ctl.q_values(&obs(1, 2), None, &last, &[true, false]).to_vec();
    let per_env = DIMS.n_agents * DIMS.n_actions;

    // What the new weights give on a first step, and the old weights on a second step.
    let mut fresh_new = Controller::new(&new, 2);
    let q_new = fresh_new.q_values(&obs(1, 2), None, &last, &[true, true]).to_vec();
    let mut only_old = Controller::new(&old, 2);
    only_old.q_values(&obs(0, 2), None, &last, &[true, true]);
    let q_old = only_old.q_values(&obs(1, 2), None, &last, &[true, false]).to_vec();

    let close = |a: &[f32], b: &[f32]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-5);
    assert!(close(&q[..per_env], &q_new[..per_env]), "env 0 acts with the new weights");
    assert!(close(&q[per_env..], &q_old[per_env..]), "env 1 finishes its episode with the old weights");
    assert!(!close(&q_new[per_env..], &q_old[per_env..]), "the two versions differ (else the test shows nothing)");

    // Once env 1 starts over too, the old version is dropped.
    ctl.q_values(&obs(2, 2), None, &last, &[false, true]);
    assert_eq!(ctl.versions_in_use(), 1);
}

#[test]
fn weights_offered_while_no_episode_started_replace_each_other() {
    let mut ctl = Controller::new(&learner(1), 3);
    let last = vec![0; 3 * DIMS.n_agents];
    ctl.q_values(&obs(0, 3), None, &last, &[true; 3]);
    for seed in 2..6 {
        ctl.offer_agent(learner(seed).acting_net().agent);
    }
    // Only the version the envs act with and the newest are kept.
    assert_eq!(ctl.versions_in_use(), 2);
}
