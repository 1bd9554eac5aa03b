//! A speaker/listener matrix game: a one-step episode in which the speaker (agent 0) observes a
//! bit c and the listener (agent 1) observes nothing; the team is paid 1 when the listener's
//! action equals c (the speaker's action does not matter). Without messages the listener's best
//! is a fixed guess (expected return 0.5); with a message it can always be right (1). Trained from
//! uniformly random play with fixed seeds: NDQ, MAIC, MASIA and T2MAC, which make their own
//! messages inside the network, solve it; QMIX, which sends nothing, cannot (COLA sends nothing
//! either: `cola_consensus.rs` tests what it does).

use burn::tensor::Device;
use lmac_learn::episode::{Episode, EpisodeDims};
use lmac_learn::methods::{method, AgentConfig, MethodContext};
use lmac_learn::{Controller, LearnConfig, LearnRng, Learner, OptimizerKind};

const DIMS: EpisodeDims = EpisodeDims { n_agents: 2, obs_width: 2, state_dim: 2, n_actions: 2 };

/// Observations of both agents for bit `c`: the speaker sees it one-hot, the listener zeros.
fn obs(c: usize) -> Vec<f32> {
    let mut o = vec![0.0; 4];
    o[c] = 1.0;
    o
}

fn episode(c: usize, a: [i32; 2]) -> Episode {
    let mut ep = Episode::with_capacity(&DIMS, 1);
    ep.obs = obs(c);
    ep.state = obs(c)[..2].to_vec();
    ep.avail = vec![1; 4];
    ep.actions = a.to_vec();
    ep.reward = vec![if a[1] as usize == c { 1.0 } else { 0.0 }];
    ep.len = 1;
    ep.terminated = true;
    ep
}

/// Greedy return averaged over both bits.
fn greedy_return(learner: &Learner) -> f32 {
    let mut total = 0.0;
    for c in 0..2 {
        let mut ctl = Controller::new(learner, 1);
        let o = obs(c);
        let acts = ctl.greedy_actions(&o, Some(&o[..2]), &[-1, -1], &[1, 1, 1, 1], &[true]);
        total += episode(c, [acts[0], acts[1]]).team_return();
    }
    total / 2.0
}

/// Trained from uniformly random play (4 episodes per round, one update per round once the
/// buffer holds a batch) with RMSprop, the optimizer of both released codes and of pymarl's QMIX.
fn train(algo: &str, settings: &str, seed: u64, rounds: usize) -> Learner {
    let spec = method(algo).unwrap();
    let agent: AgentConfig = (spec.configure)(&toml::from_str(settings).unwrap(), &MethodContext::default()).unwrap();
    let mut cfg = LearnConfig {
        seed,
        buffer_size: 400,
        batch_size: 32,
        lr: 1e-3,
        optimizer: OptimizerKind::Rmsprop,
        target_update_interval_episodes: 40,
        ..LearnConfig::default()
    };
    if let Some(m) = spec.mixer {
        cfg.mixer = m;
    }
    let mut learner = Learner::with_agent(DIMS, cfg, agent, Device::default()).unwrap();
    let mut rng = LearnRng::seed_from(seed + 17);
    for _ in 0..rounds {
        for _ in 0..4 {
            let ep = episode(rng.below(2), [rng.below(2) as i32, rng.below(2) as i32]);
            learner.add_episode(ep).unwrap();
        }
        if learner.can_train() {
            learner.train_step().unwrap();
        }
    }
    learner
}

fn check(algo: &str, settings: &str, seed: u64, rounds: usize) -> f32 {
    let t = std::time::Instant::now();
    let r = greedy_return(&train(algo, settings, seed, rounds));
    eprintln!("{algo} {settings:?} seed {seed}, {rounds} rounds: greedy return {r} ({:.1} s)", t.elapsed().as_secs_f32());
    r
}

#[test]
fn qmix_cannot_beat_a_fixed_guess() {
    assert_eq!(check("qmix", "", 1, 600), 0.5, "without messages the listener cannot know the bit");
}

#[test]
fn ndq_learns_to_tell_the_listener_the_bit() {
    // The released code's SMAC weights (c_beta 0.1, comm_beta 1e-4, entropy_beta 0). With the
    // default ones (1, 1e-3, 1e-6) the KL term wins over the weak early TD signal on this tiny
    // game: the message means shrink to |mu| ~ 0.04 within 600 updates and only 1 of seeds 1-4
    // learns in 2000 rounds (the SMAC weights: 4 of 4).
    assert_eq!(check("ndq", "c_beta = 0.1\ncomm_beta = 1e-4\nentropy_beta = 0.0", 1, 2000), 1.0);
}

#[test]
fn maic_learns_to_tell_the_listener_the_bit() {
    assert_eq!(check("maic", "", 1, 300), 1.0);
}

#[test]
fn maic_with_the_released_codes_choices_learns_it_too() {
    // The receiver's hidden state in the message net, batch norm always on the forward pass's
    // rows (here the acting environment's two agents), the greedy action in the MI loss.
    assert_eq!(check("maic", "message_input = \"receiver\"\nbatch_norm = \"batch\"\nmi_action = \"greedy\"", 1, 300), 1.0);
}

#[test]
fn masia_learns_to_tell_the_listener_the_bit() {
    // The encoder aggregates both agents' inputs, so the listener's z holds the bit; its gate and
    // Q network learn to read it from the TD signal. Seeds 1-4 (`measure_over_seeds`): 4 of 4
    // within 500 rounds (seed 4 is the slowest, at 400-500), with RMSprop and with MASIA's Adam.
    assert_eq!(check("masia", "", 1, 300), 1.0);
}

#[test]
fn t2mac_learns_to_tell_the_listener_the_bit() {
    assert_eq!(check("t2mac", "", 1, 300), 1.0);
}

/// Not in CI: every method and variant over seeds 1-4 (`cargo test --test comm_game -- --ignored
/// --nocapture`; `COMM_GAME_ALGO=<algo>` for one method), the numbers the comments above and the
/// methods' doc comments quote.
#[test]
#[ignore]
fn measure_over_seeds() {
    let runs: &[(&str, &str, usize)] = &[
        ("qmix", "", 600),
        ("ndq", "", 2000),
        ("ndq", "c_beta = 0.1\ncomm_beta = 1e-4\nentropy_beta = 0.0", 2000),
        ("maic", "", 300),
        ("maic", "message_input = \"receiver\"", 300),
        ("maic", "batch_norm = \"batch\"", 300),
        ("maic", "mi_action = \"greedy\"", 300),
        ("maic", "message_input = \"receiver\"\nbatch_norm = \"batch\"\nmi_action = \"greedy\"", 300),
        ("masia", "", 600),
        ("masia", "momentum_interval = 1\nmomentum_tau = 0.01", 600),
        ("t2mac", "", 600),
        ("t2mac", "evidence = \"relu\"", 600),
        ("t2mac", "selector = \"frozen\"", 600),
        ("t2mac", "evidence = \"relu\"\nselector = \"frozen\"\nown_weight = 2.0", 600),
    ];
    // COMM_GAME_ALGO=t2mac measures one method only.
    let only = std::env::var("COMM_GAME_ALGO").ok();
    for &(algo, settings, rounds) in runs.iter().filter(|r| only.as_deref().is_none_or(|o| o == r.0)) {
        let r: Vec<f32> = (1..=4).map(|seed| check(algo, settings, seed, rounds)).collect();
        eprintln!("== {algo} {settings:?}: {r:?}");
    }
}
