//! Time limits: a truncated episode's last transition bootstraps from the step that followed it
//! (`Episode::next`), a terminated one's target is the reward alone. A reward paid only on the
//! last step of truncated episodes must reach the Q-values.

use burn::tensor::Device;
use lmac_learn::episode::{Episode, EpisodeDims, NextStep};
use lmac_learn::{Batch, Controller, LearnConfig, Learner, MixerKind};

const DIMS: EpisodeDims = EpisodeDims { n_agents: 2, obs_width: 4, state_dim: 4, n_actions: 2 };
const LEN: usize = 3;

fn one_hot(t: usize) -> Vec<f32> {
    (0..4).map(|k| if k == t { 1.0 } else { 0.0 }).collect()
}

/// Steps 0..LEN see observation one_hot(t); the reward 1 comes only with the last action; the
/// time limit cuts the episode there. `with_next`: the observation after it (one_hot(LEN)) is kept.
fn truncated_episode(with_next: bool) -> Episode {
    let mut ep = Episode::with_capacity(&DIMS, LEN);
    for t in 0..LEN {
        let o = one_hot(t);
        ep.obs.extend(o.iter().chain(o.iter()));
        ep.state.extend(&o);
        ep.avail.extend([1u8; 4]);
        ep.actions.extend([0, 0]);
        ep.reward.push(if t + 1 == LEN { 1.0 } else { 0.0 });
        ep.len += 1;
    }
    ep.truncated = true;
    if with_next {
        let o = one_hot(LEN);
        ep.next = Some(NextStep { obs: o.iter().chain(o.iter()).copied().collect(), state: o, avail: vec![1; 4] });
    }
    ep
}

fn trained(with_next: bool) -> Learner {
    let cfg = LearnConfig {
        mixer: MixerKind::Vdn,
        gamma: 0.5,
        batch_size: 8,
        buffer_size: 64,
        target_update_interval_episodes: 16,
        lr: 5e-3,
        seed: 3,
        ..Default::default()
    };
    let mut l = Learner::new(DIMS, cfg, Device::default()).unwrap();
    for _ in 0..16 {
        l.add_episode(truncated_episode(with_next)).unwrap();
    }
    for k in 0..1000 {
        l.train_step().unwrap();
        if k % 25 == 0 {
            l.add_episode(truncated_episode(with_next)).unwrap(); // advances the target schedule
        }
    }
    l
}

/// Q_tot (VDN: the sum over agents) of the taken action at each step of the episode.
fn q_tot_per_step(l: &Learner) -> Vec<f32> {
    let mut ctl = Controller::new(l, 1);
    let ep = truncated_episode(false);
    (0..LEN)
        .map(|t| {
            let obs = &ep.obs[t * 8..(t + 1) * 8];
            let last = if t == 0 { [-1, -1] } else { [0, 0] };
            let q = ctl.q_values(obs, None, &last, &[t == 0]).to_vec();
            q[0] + q[2] // agent 0 action 0 + agent 1 action 0
        })
        .collect()
}

#[test]
fn the_batch_bootstraps_a_truncated_episode_from_its_next_step() {
    let l = Learner::new(DIMS, LearnConfig { batch_size: 1, ..Default::default() }, Device::default()).unwrap();
    let ep = truncated_episode(true);
    let b = Batch::from_episodes(&[&ep], &DIMS, l.layout());
    assert_eq!(b.t, LEN + 1, "the next step is in the batch");
    assert_eq!(b.mask, vec![1.0, 1.0, 1.0, 0.0], "every transition is trained on, the next step only read");
    assert_eq!(b.has_next, vec![1.0, 1.0, 1.0, 0.0]);
    assert_eq!(b.terminated, vec![0.0; 4], "a time limit is not a termination");
    assert_eq!(&b.state[LEN * 4..], &one_hot(LEN)[..]);
    let cut = truncated_episode(false);
    let b = Batch::from_episodes(&[&cut], &DIMS, l.layout());
    assert_eq!(b.mask, vec![1.0, 1.0, 0.0], "without its next step the last transition has no target");
    let mut term = truncated_episode(false);
    (term.truncated, term.terminated) = (false, true);
    let b = Batch::from_episodes(&[&term], &DIMS, l.layout());
    assert_eq!((b.mask[2], b.terminated[2], b.has_next[2]), (1.0, 1.0, 0.0), "terminated: the reward alone");
}

#[test]
fn a_reward_on_the_last_step_of_truncated_episodes_reaches_q() {
    let q = q_tot_per_step(&trained(true));
    // The last transition's target is 1 + gamma * Q'(next): at least the reward.
    assert!(q[LEN - 1] > 0.8, "Q_tot at the last step {:.3} should have learned the reward 1 (all steps: {q:?})", q[LEN - 1]);
    // It propagates back: Q(t) ~ gamma^(LEN-1-t) * Q(LEN-1).
    assert!(q[0] > 0.1, "Q_tot at the first step {:.3} should carry the discounted reward (all steps: {q:?})", q[0]);
    // Without the next step (the old behaviour: the transition masked) nothing is learned.
    let cut = q_tot_per_step(&trained(false));
    assert!(cut[LEN - 1].abs() < 0.3, "with the last transition masked Q_tot should stay near 0, got {cut:?}");
}

#[test]
fn an_episode_with_a_badly_sized_next_step_is_refused() {
    let mut l = Learner::new(DIMS, LearnConfig::default(), Device::default()).unwrap();
    let mut ep = truncated_episode(true);
    ep.next.as_mut().unwrap().state.pop();
    let err = l.add_episode(ep).unwrap_err().to_string();
    assert!(err.contains("next state 3 (expected 4)"), "{err}");
}

/// `learn.time_limit = "terminal"` (SMAC as the LMAC authors run it): the same truncated
/// episodes train as terminated ones, the last target the reward alone, so the reward still
/// reaches Q but nothing is bootstrapped past the limit.
#[test]
fn a_terminal_time_limit_trains_truncated_episodes_as_terminated() {
    use lmac_learn::TimeLimit;
    let cfg = LearnConfig { batch_size: 1, time_limit: TimeLimit::Terminal, ..Default::default() };
    let mut l = Learner::new(DIMS, cfg, Device::default()).unwrap();
    l.add_episode(truncated_episode(true)).unwrap();
    let stored = l.buffer().get(0).clone();
    assert!(stored.terminated && !stored.truncated && stored.next.is_none(), "stored as a termination");
    let b = Batch::from_episodes(&[&stored], &DIMS, l.layout());
    assert_eq!(b.t, LEN, "no next step in the batch");
    assert_eq!((b.mask[LEN - 1], b.terminated[LEN - 1]), (1.0, 1.0), "the last transition trains on the reward alone");
}
