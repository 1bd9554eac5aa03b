//! Synthetic datasets, schemas and contexts the design crate's tests share.
#![allow(dead_code)]

use lmac_design::discriminator::DiscriminatorConfig;
use lmac_design::DesignContext;
use lmac_protocol_runner::protocol::{self, ProtocolEnv, ValidatedProtocol};
use lmac_run::dataset::{Dataset, DatasetHeader, Trajectory};
use lmac_run::learn::LearnRng;
use lmac_shm_schema::schema::{AgentObs, DimGroup, EnvSchema};
use std::path::PathBuf;

pub fn tmp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("lmac-design-data-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

pub fn header(env: &str, n: usize, od: usize, sd: usize, na: usize, limit: usize) -> DatasetHeader {
    DatasetHeader {
        env: env.into(),
        n_agents: n,
        obs_dim: od,
        state_dim: sd,
        n_actions: na,
        episode_limit: limit,
        protocol: "none".into(),
        policy: "synthetic".into(),
        seed: 7,
    }
}

/// Random LBF-8x8-shaped episodes (values 0..3, random lengths and actions).
pub fn lbf_like(episodes: usize, seed: u64) -> Dataset {
    let (n, od, sd, na, limit) = (2, 29, 300, 6, 25);
    let mut rng = LearnRng::seed_from(seed);
    let eps = (0..episodes)
        .map(|_| {
            let len = 1 + rng.below(limit);
            Trajectory {
                len,
                obs: (0..len * n * od).map(|_| rng.below(3) as f32).collect(),
                state: (0..len * sd).map(|_| rng.below(3) as f32).collect(),
                actions: (0..len * n).map(|_| rng.below(na) as i32).collect(),
                reward: (0..len).map(|_| rng.uniform()).collect(),
                terminated: len < limit,
                truncated: len == limit,
            }
        })
        .collect();
    Dataset { header: header("lbf:8x8-2p-2f-s1-coop", n, od, sd, na, limit), episodes: eps }
}

// ------------------------------------------------------------------------------------------
// A synthetic task where each agent alone sees part of the state.
//
// 2 agents, obs 4, state 5, 3 actions, episodes of 12 steps:
// - s[0] in {0,1,2}: seen by agent 0 only (o0[0]); agent 1's o[0] is noise;
// - s[1] in {0,1}: seen by both (o[1]);
// - s[2] = 1: a constant (a wall);
// - s[3] in {0,1,2}: seen by agent 1 only (o1[2]); agent 0's o[2] is 0;
// - s[4] in {1,2}: fixed per episode, shown to agent 0 (o0[3]) only every 4th step, else 0;
//   agent 1's o[3] is 0. Recovering it at every step needs memory (a window aggregate).

pub const SYN_N: usize = 2;
pub const SYN_OD: usize = 4;
pub const SYN_SD: usize = 5;
pub const SYN_NA: usize = 3;
pub const SYN_LEN: usize = 12;

pub fn synthetic(episodes: usize, seed: u64) -> Dataset {
    synthetic_rewarded(episodes, seed, |_| 0.0)
}

/// [`synthetic`] with each step's reward a function of its state.
pub fn synthetic_rewarded(episodes: usize, seed: u64, reward: impl Fn(&[f32]) -> f32) -> Dataset {
    let mut rng = LearnRng::seed_from(seed);
    let mut eps = Vec::new();
    for _ in 0..episodes {
        let mut tr = Trajectory { len: SYN_LEN, terminated: false, truncated: true, ..Default::default() };
        let (mut h0, mut h3) = (rng.below(3) as f32, rng.below(3) as f32);
        let g = 1.0 + rng.below(2) as f32;
        for t in 0..SYN_LEN {
            if rng.uniform() < 0.3 {
                h0 = rng.below(3) as f32;
            }
            if rng.uniform() < 0.3 {
                h3 = rng.below(3) as f32;
            }
            let b = rng.below(2) as f32;
            let shown = if t % 4 == 0 { g } else { 0.0 };
            tr.obs.extend_from_slice(&[h0, b, 0.0, shown]);
            tr.obs.extend_from_slice(&[rng.below(3) as f32, b, h3, 0.0]);
            tr.state.extend_from_slice(&[h0, b, 1.0, h3, g]);
            tr.actions.extend((0..SYN_N).map(|_| rng.below(SYN_NA) as i32));
            tr.reward.push(reward(&[h0, b, 1.0, h3, g]));
        }
        eps.push(tr);
    }
    Dataset { header: header("synthetic:split-view", SYN_N, SYN_OD, SYN_SD, SYN_NA, SYN_LEN), episodes: eps }
}

pub fn group(count: usize, meaning: &str) -> DimGroup {
    DimGroup { count, shape: None, meaning: meaning.into(), labels: None, repeat: None }
}

pub fn synthetic_schema(message_columns: usize) -> EnvSchema {
    EnvSchema {
        name: "synthetic:split-view".into(),
        task: "A synthetic task where each agent sees part of the state.".into(),
        n_agents: SYN_N,
        obs_dim: SYN_OD,
        state_dim: SYN_SD,
        n_actions: SYN_NA,
        episode_limit: SYN_LEN,
        message_columns,
        double_buffer: true,
        alpha: 0.1,
        reward: "none".into(),
        actions: vec!["a".into(), "b".into(), "c".into()],
        obs_dims: vec![
            group(1, "private value (agent 0: hidden value A; agent 1: noise)"),
            group(1, "shared bit"),
            group(1, "private value B (agent 1 only)"),
            group(1, "flash of the episode constant (agent 0, every 4th step)"),
        ],
        state_dims: vec![
            group(1, "hidden value A"),
            group(1, "shared bit"),
            group(1, "constant"),
            group(1, "hidden value B"),
            group(1, "episode constant"),
        ],
        agent_obs: Vec::new(),
    }
}

pub fn quick_disc() -> DiscriminatorConfig {
    DiscriminatorConfig { updates: 2500, batch_size: 64, lr: 2e-3, ..Default::default() }
}

// ------------------------------------------------------------------------------------------
// Dataset

pub fn lbf_env() -> ProtocolEnv {
    let schema = lmac_shm_schema::schema::load_env("lbf:8x8-2p-2f-s1-coop").unwrap();
    lmac_protocol_runner::protocol_env(&schema)
}

pub fn example(name: &str) -> String {
    format!("{}/../../prompts/examples/{name}", env!("CARGO_MANIFEST_DIR"))
}

pub fn ctx<'a>(schema: &'a EnvSchema, env: &'a ProtocolEnv, data: &'a Dataset) -> DesignContext<'a> {
    DesignContext { env_name: "synthetic:split-view", schema, env, dataset: Some(data), seed: 5 }
}

pub fn phase_from(text: &str, env: &ProtocolEnv, prev: &[ValidatedProtocol]) -> ValidatedProtocol {
    protocol::validate_phase(&protocol::parse_str(text).unwrap(), env, prev).unwrap()
}

// ------------------------------------------------------------------------------------------
// A communication game with a known answer and agents that differ.
//
// 4 agents, obs 3, state 4, 3 actions, episodes of 12 steps. Agent 0 is an observer that
// cannot act (its action is always 0): it sees the goal (o0[0] = s[0] in {0,1,2}, changing
// now and then). Agents 1 and 2 are actors that cannot see the goal: each sees its own
// position (o[1] = s[1] or s[2]) and a bit all agents share (o[2] = s[3]). Agent 3 is a
// bystander: it sees the bit only and does nothing. B's policy (one that saw the state) moves
// each actor towards the goal: action 2 when the goal is 1 or more, else 0, and the team is
// rewarded when both do. The right protocol: agent 0 sends o[0] to agents 1 and 2; neither the
// observer nor the bystander needs anything.

pub const GAME_N: usize = 4;
pub const GAME_OD: usize = 3;
pub const GAME_SD: usize = 4;

pub fn observer_and_actors(episodes: usize, seed: u64) -> Dataset {
    let mut rng = LearnRng::seed_from(seed);
    let len = 12;
    let mut eps = Vec::new();
    for _ in 0..episodes {
        let mut tr = Trajectory { len, terminated: false, truncated: true, ..Default::default() };
        let mut goal = rng.below(3) as f32;
        for _ in 0..len {
            if rng.uniform() < 0.3 {
                goal = rng.below(3) as f32;
            }
            let (p1, p2, bit) = (rng.below(3) as f32, rng.below(3) as f32, rng.below(2) as f32);
            tr.obs.extend_from_slice(&[goal, 0.0, bit]);
            tr.obs.extend_from_slice(&[0.0, p1, bit]);
            tr.obs.extend_from_slice(&[0.0, p2, bit]);
            tr.obs.extend_from_slice(&[0.0, 0.0, bit]);
            tr.state.extend_from_slice(&[goal, p1, p2, bit]);
            let toward = if goal >= 1.0 { 2 } else { 0 };
            // The actors follow the goal nine times in ten (B's policy explores).
            let mut act = || if rng.uniform() < 0.9 { toward } else { rng.below(3) as i32 };
            let (a1, a2) = (act(), act());
            tr.actions.extend_from_slice(&[0, a1, a2, 0]);
            tr.reward.push(if a1 == toward && a2 == toward { 1.0 } else { 0.0 });
        }
        eps.push(tr);
    }
    Dataset { header: header("synthetic:observer-and-actors", GAME_N, GAME_OD, GAME_SD, 3, len), episodes: eps }
}

pub fn observer_and_actors_schema() -> EnvSchema {
    EnvSchema {
        name: "synthetic:observer-and-actors".into(),
        task: "An observer that sees the goal but cannot act, two actors that act on it but cannot see it, and a bystander.".into(),
        n_agents: GAME_N,
        obs_dim: GAME_OD,
        state_dim: GAME_SD,
        n_actions: 3,
        episode_limit: 12,
        message_columns: 60,
        double_buffer: true,
        alpha: 0.1,
        reward: "1 when both actors move towards the goal".into(),
        actions: vec!["stay".into(), "left".into(), "right".into()],
        obs_dims: vec![group(1, "unused: always 0"), group(1, "unused: always 0"), group(1, "shared bit")],
        state_dims: vec![group(1, "the goal"), group(1, "actor 1's position"), group(1, "actor 2's position"), group(1, "shared bit")],
        // The bystander (agent 3) reads `obs_dims`; the observer and the actors their own.
        agent_obs: vec![
            AgentObs {
                name: "observer".into(),
                agents: vec![0],
                obs_dims: vec![group(1, "the goal"), group(1, "unused: always 0"), group(1, "shared bit")],
            },
            AgentObs {
                name: "actor".into(),
                agents: vec![1, 2],
                obs_dims: vec![group(1, "unused: always 0"), group(1, "own position"), group(1, "shared bit")],
            },
        ],
    }
}
