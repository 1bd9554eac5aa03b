//! The data side of protocol design: the dataset B on disk, messages recomputed by the runner's
//! plan, the discriminator, the meta-information JSON and the offline designer, on synthetic
//! datasets built here (small enough to run in seconds in release).

use burn::tensor::Device;
use lmac_design::discriminator::{split_episodes, DiscInput, Discriminator, DiscriminatorConfig};
use lmac_design::meta::{self, MetaConfig, Recovery};
use lmac_design::offline::{CriticalBy, FieldsBy, OfflineConfig, OfflineDesigner};
use lmac_design::{DesignContext, Designer, PhaseProtocol};
use lmac_protocol_runner::builtin::FullComm;
use lmac_protocol_runner::plan::{MessagePlan, StepView};
use lmac_protocol_runner::protocol::{self, ProtocolEnv, ValidatedProtocol};
use lmac_run::dataset::{Dataset, DatasetHeader, Trajectory};
use lmac_run::episode::Episode;
use lmac_run::learn::LearnRng;
use lmac_shm_schema::schema::{DimGroup, EnvSchema};
use std::path::PathBuf;

fn tmp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("lmac-design-data-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn header(env: &str, n: usize, od: usize, sd: usize, na: usize, limit: usize) -> DatasetHeader {
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
fn lbf_like(episodes: usize, seed: u64) -> Dataset {
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

const SYN_N: usize = 2;
const SYN_OD: usize = 4;
const SYN_SD: usize = 5;
const SYN_NA: usize = 3;
const SYN_LEN: usize = 12;

fn synthetic(episodes: usize, seed: u64) -> Dataset {
    synthetic_rewarded(episodes, seed, |_| 0.0)
}

/// [`synthetic`] with each step's reward a function of its state.
fn synthetic_rewarded(episodes: usize, seed: u64, reward: impl Fn(&[f32]) -> f32) -> Dataset {
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

fn group(count: usize, meaning: &str) -> DimGroup {
    DimGroup { count, shape: None, meaning: meaning.into(), labels: None, repeat: None }
}

fn synthetic_schema(message_columns: usize) -> EnvSchema {
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
    }
}

fn quick_disc() -> DiscriminatorConfig {
    DiscriminatorConfig { updates: 2500, batch_size: 64, lr: 2e-3, ..Default::default() }
}

// ------------------------------------------------------------------------------------------
// Dataset

#[test]
fn dataset_round_trip_and_errors() {
    let dir = tmp_dir("roundtrip");
    let data = lbf_like(7, 1);
    let path = dir.join("dataset");
    data.save(&path).unwrap();
    assert_eq!(Dataset::load(&path).unwrap(), data);
    // Saving again replaces it atomically and leaves no temporary directory behind.
    data.save(&path).unwrap();
    let names: Vec<String> = std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into()).collect();
    assert_eq!(names, vec!["dataset".to_string()]);

    let bin = path.join("episodes.bin");
    let good = std::fs::read(&bin).unwrap();
    // The payload parser's own errors, as for a dataset written before payload checksums (with
    // them, each damage below is refused first by its size or CRC: tests/hostile_files.rs).
    let hp = path.join("header.json");
    let mut h: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&hp).unwrap()).unwrap();
    h.as_object_mut().unwrap().remove("episodes_bytes");
    h.as_object_mut().unwrap().remove("episodes_crc32c");
    std::fs::write(&hp, serde_json::to_string_pretty(&h).unwrap()).unwrap();
    // Truncated in the middle of an episode.
    std::fs::write(&bin, &good[..good.len() - 10]).unwrap();
    let e = format!("{:#}", Dataset::load(&path).unwrap_err());
    assert!(e.contains("episodes.bin") && e.contains("truncated in episode 6"), "{e}");
    // Bytes after the announced episodes.
    let mut long = good.clone();
    long.extend_from_slice(&[0, 0, 0, 0]);
    std::fs::write(&bin, &long).unwrap();
    let e = format!("{:#}", Dataset::load(&path).unwrap_err());
    assert!(e.contains("4 bytes after the 7 episodes"), "{e}");
    // Wrong magic.
    let mut bad = good.clone();
    bad[0] = b'X';
    std::fs::write(&bin, &bad).unwrap();
    let e = format!("{:#}", Dataset::load(&path).unwrap_err());
    assert!(e.contains("episodes.bin") && e.contains("magic"), "{e}");
    std::fs::write(&bin, &good).unwrap();
    // Header problems: version, not JSON, missing.
    let hp = path.join("header.json");
    let text = std::fs::read_to_string(&hp).unwrap();
    std::fs::write(&hp, text.replace("\"version\": 1", "\"version\": 9")).unwrap();
    let e = format!("{:#}", Dataset::load(&path).unwrap_err());
    assert!(e.contains("header.json") && e.contains("version 9"), "{e}");
    std::fs::write(&hp, "{not json").unwrap();
    let e = format!("{:#}", Dataset::load(&path).unwrap_err());
    assert!(e.contains("header.json") && e.contains("not JSON"), "{e}");
    std::fs::remove_file(&hp).unwrap();
    let e = format!("{:#}", Dataset::load(&path).unwrap_err());
    assert!(e.contains("header.json") && e.contains("cannot read"), "{e}");
    // Inconsistent shapes are refused before anything is written.
    let mut wrong = data.clone();
    wrong.episodes[2].state.pop();
    let e = format!("{:#}", wrong.save(&dir.join("other")).unwrap_err());
    assert!(e.contains("episode 2") && e.contains("state"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn trajectory_from_episode_drops_message_columns() {
    let (n, od, md) = (2, 3, 2);
    let mut ep = Episode { len: 2, ..Default::default() };
    for t in 0..2 {
        for a in 0..n {
            let base = (t * 10 + a * 5) as f32;
            ep.obs.extend_from_slice(&[base, base + 1.0, base + 2.0]);
            ep.obs.extend_from_slice(&[-1.0; 2][..md]);
        }
    }
    ep.state = vec![0.5; 2 * 4];
    ep.actions = vec![0, 1, 2, 3];
    ep.reward = vec![1.0, 0.0];
    ep.terminated = true;
    let tr = Trajectory::from_episode(&ep, n, od);
    assert_eq!(tr.obs, vec![0.0, 1.0, 2.0, 5.0, 6.0, 7.0, 10.0, 11.0, 12.0, 15.0, 16.0, 17.0]);
    assert_eq!((tr.len, tr.terminated, tr.truncated), (2, true, false));
    assert_eq!(tr.actions, ep.actions);
}

/// What the runner does: several envs stepping side by side, each starting its next episode
/// when one ends (first flag, last actions -1), one plan for all of them.
fn runner_reference(data: &Dataset, plan: &mut dyn MessagePlan, envs: usize) -> Vec<Vec<f32>> {
    let (n, od, md) = (data.header.n_agents, data.header.obs_dim, plan.msg_dim());
    let row = od + md;
    let mut out: Vec<Vec<f32>> = vec![Vec::new(); data.episodes.len()];
    // Env e plays episodes e, e + envs, e + 2 envs, ...
    let mut cur: Vec<(usize, usize)> = (0..envs).map(|e| (e, 0)).collect();
    let mut rows = vec![0f32; envs * n * row];
    let mut first = vec![false; envs];
    let mut last = vec![-1i32; envs * n];
    loop {
        let live: Vec<bool> = cur.iter().map(|&(k, _)| k < data.episodes.len()).collect();
        if !live.iter().any(|&x| x) {
            break;
        }
        for e in 0..envs {
            let (k, t) = cur[e];
            // Finished envs keep stepping on junk (their output is ignored), as a batch would.
            let ep = &data.episodes[k.min(data.episodes.len() - 1)];
            let t = t.min(ep.len - 1);
            first[e] = t == 0;
            for a in 0..n {
                let r = (e * n + a) * row;
                rows[r..r + od].copy_from_slice(&ep.obs[(t * n + a) * od..(t * n + a + 1) * od]);
                rows[r + od..r + row].fill(7.0); // stale garbage the plan must overwrite
                last[e * n + a] = if t == 0 { -1 } else { ep.actions[(t - 1) * n + a] };
            }
        }
        let mut view =
            StepView { num_envs: envs, n_agents: n, obs_dim: od, msg_dim: md, rows: &mut rows, first: &first, last_actions: &last };
        plan.apply(&mut view);
        for e in 0..envs {
            let (k, t) = cur[e];
            if !live[e] {
                continue;
            }
            for a in 0..n {
                let r = (e * n + a) * row;
                out[k].extend_from_slice(&rows[r + od..r + row]);
            }
            cur[e] = if t + 1 == data.episodes[k].len { (k + envs, 0) } else { (k, t + 1) };
        }
    }
    out
}

fn lbf_env() -> ProtocolEnv {
    let schema = lmac_shm_schema::schema::load_env("lbf:8x8-2p-2f-s1-coop").unwrap();
    lmac_protocol_runner::protocol_env(&schema)
}

fn example(name: &str) -> String {
    format!("{}/../../prompts/examples/{name}", env!("CARGO_MANIFEST_DIR"))
}

#[test]
fn messages_equal_the_runner_plan() {
    let data = lbf_like(9, 2);
    let env = lbf_env();
    // Built-in FullComm.
    let mut a = FullComm { n_agents: 2, obs_dim: 29 };
    let mut b = FullComm { n_agents: 2, obs_dim: 29 };
    let got = data.messages(&mut a);
    assert_eq!(got, runner_reference(&data, &mut b, 3));
    // Other agent's observation, then the one-hot of the sender (agent 1 for receiver 0).
    assert_eq!(&got[0][..29], &data.episodes[0].obs[29..58]);
    assert_eq!(&got[0][29..31], &[0.0, 1.0]);
    // The fullcomm-like example phase 0 and the phase 2 with 10-step windows, compiled.
    let phases: Vec<ValidatedProtocol> = ["lbf_8x8_phase0.json", "lbf_8x8_phase1.json", "lbf_8x8_phase2.json"]
        .iter()
        .scan(Vec::new(), |prev: &mut Vec<ValidatedProtocol>, f| {
            let p = protocol::parse_str(&std::fs::read_to_string(example(f)).unwrap()).unwrap();
            let v = protocol::validate_phase(&p, &env, prev).unwrap();
            prev.push(v.clone());
            Some(v)
        })
        .collect();
    for set in [&phases[..1], &phases[2..3], &phases[..]] {
        let mut p1 = protocol::compile(set, &env).unwrap();
        let mut p2 = protocol::compile(set, &env).unwrap();
        let got = data.messages(p1.as_mut());
        let want = runner_reference(&data, p2.as_mut(), 4);
        assert_eq!(got.len(), data.episodes.len());
        for (k, (g, w)) in got.iter().zip(&want).enumerate() {
            assert_eq!(g.len(), data.episodes[k].len * 2 * p1.msg_dim());
            assert_eq!(g, w, "episode {k} differs for a {}-phase protocol", set.len());
        }
    }
}

// ------------------------------------------------------------------------------------------
// Discriminator

#[test]
fn split_is_seeded_and_disjoint() {
    let (tr, te) = split_episodes(10, 0.2, 5).unwrap();
    assert_eq!((tr.len(), te.len()), (8, 2));
    assert!(te.iter().all(|e| !tr.contains(e)));
    assert_eq!(split_episodes(10, 0.2, 5).unwrap(), (tr, te));
    assert!(split_episodes(1, 0.2, 5).unwrap_err().to_string().contains("at least 2"));
    let e = DiscriminatorConfig { dropout: 1.5, updates: 0, ..Default::default() }.validate().unwrap_err().to_string();
    assert!(e.contains("dropout") && e.contains("updates"), "{e}");
}

/// Agent 0 alone sees s[0]; agent 1 alone sees s[3]. With a broadcast of the whole observation
/// each recovers both; without messages each recovers only its own.
#[test]
fn discriminator_recovers_what_the_messages_carry() {
    let data = synthetic(400, 3);
    let mut plan = FullComm { n_agents: SYN_N, obs_dim: SYN_OD };
    let msgs = data.messages(&mut plan);
    let md = plan.msg_dim();
    let cfg = quick_disc();
    let (train, test) = split_episodes(data.episodes.len(), cfg.holdout_fraction, 11).unwrap();
    let dev = Device::default();
    let with_in = DiscInput::with_messages(&data, &msgs, md);
    let without_in = DiscInput::without_messages(&data, md);
    let (d1, rep1) = Discriminator::train(&with_in, &train, &cfg, 1, &dev).unwrap();
    let (d0, _) = Discriminator::train(&without_in, &train, &cfg, 2, &dev).unwrap();
    assert_eq!(d1.input_width(), d0.input_width(), "same architecture with and without messages");
    assert!(rep1.final_loss.is_finite() && rep1.train_rows == train.len() * SYN_LEN * SYN_N);
    let dims: Vec<usize> = (0..SYN_SD).collect();
    let w = Recovery::measure(&d1, &with_in, &test, &dims, 0.1).unwrap();
    let wo = Recovery::measure(&d0, &without_in, &test, &dims, 0.1).unwrap();
    eprintln!("s[0] with {:?} without {:?}; s[3] with {:?} without {:?}", w.rates(0), wo.rates(0), w.rates(3), wo.rates(3));
    // The agent that sees a dim recovers it either way; the other one only with messages.
    assert!(w.rate(0, 0) > 0.95 && wo.rate(0, 0) > 0.95);
    assert!(w.rate(0, 1) > 0.9, "agent 1 recovers s[0] from agent 0's message: {}", w.rate(0, 1));
    assert!(wo.rate(0, 1) < 0.6, "agent 1 cannot recover s[0] without messages: {}", wo.rate(0, 1));
    assert!(w.rate(3, 0) > 0.9 && wo.rate(3, 0) < 0.6);
    // Shared and constant dims are recovered by everyone either way.
    for i in 0..2 {
        assert!(wo.rate(1, i) > 0.95 && wo.rate(2, i) > 0.99);
    }
    // Deterministic for a seed.
    let (d1b, _) = Discriminator::train(&with_in, &train, &cfg, 1, &dev).unwrap();
    assert_eq!(d1.predict(&with_in, &test[..3]).unwrap(), d1b.predict(&with_in, &test[..3]).unwrap());
    // A mismatched input is refused with the widths named.
    let e = d1.predict(&DiscInput::without_messages(&data, md + 1), &test).unwrap_err().to_string();
    assert!(e.contains("message columns"), "{e}");
}

/// The cost of one update at LBF 8x8 widths (obs 29, state 300, 64 message columns), the
/// default configuration (batch 32). Printed for the docs; run with --nocapture to see it.
#[test]
fn discriminator_cost() {
    let data = lbf_like(200, 4);
    let msgs: Vec<Vec<f32>> = data.episodes.iter().map(|e| vec![0.5; e.len * 2 * 64]).collect();
    let input = DiscInput::with_messages(&data, &msgs, 64);
    let (train, _) = split_episodes(data.episodes.len(), 0.2, 1).unwrap();
    for batch in [32usize, 128] {
        let cfg = DiscriminatorConfig { updates: 400, batch_size: batch, ..Default::default() };
        let (_, rep) = Discriminator::train(&input, &train, &cfg, 1, &Device::default()).unwrap();
        eprintln!(
            "discriminator cost, LBF 8x8 widths, batch {batch}: {:.3} ms per update ({} updates in {:.2} s)",
            rep.ms_per_update, rep.updates, rep.seconds
        );
        assert!(rep.ms_per_update.is_finite() && rep.ms_per_update > 0.0);
    }
}

// ------------------------------------------------------------------------------------------
// Meta-information

fn ctx<'a>(schema: &'a EnvSchema, env: &'a ProtocolEnv, data: &'a Dataset) -> DesignContext<'a> {
    DesignContext { env_name: "synthetic:split-view", schema, env, dataset: Some(data), seed: 5 }
}

fn phase_from(text: &str, env: &ProtocolEnv, prev: &[ValidatedProtocol]) -> ValidatedProtocol {
    protocol::validate_phase(&protocol::parse_str(text).unwrap(), env, prev).unwrap()
}

#[test]
fn meta_json_shape() {
    let data = synthetic(300, 6);
    let schema = synthetic_schema(24);
    let env = lmac_protocol_runner::protocol_env(&schema);
    let p0 = phase_from(
        r#"{"message_design_instruction": "agent 0 tells agent 1 its private value", "critical_state_dims": [0, {"start": 3, "end": 5}],
            "fields": [{"name": "a", "description": "private value", "senders": [0], "receivers": {"peer": [{"from": 0, "to": [1]}]}, "value": {"obs": [0]}}]}"#,
        &env,
        &[],
    );
    let cfg = MetaConfig { discriminator: quick_disc(), max_target_dims: 2, ..Default::default() };
    let m = meta::evaluate(&ctx(&schema, &env, &data), &[p0], &cfg).unwrap();
    let dims = &m.dimensions;
    // Critical dims 0, 3, 4 capped to the 2 worst recovered with messages: s[3] (agent 0
    // never learns it) and s[4] (seen every 4th step by agent 0 only); s[0] now reaches agent 1.
    assert_eq!(m.summary.target_dims, vec![3, 4], "{:#}", m.json());
    assert!(m.target_dims_selection.contains("cut to the 2 worst"));
    assert_eq!((dims[0].dim, dims[0].dimension.as_str()), (3, "s[3] - hidden value B"));
    for d in dims {
        for s in [&d.with_communication, &d.without_communication] {
            assert_eq!(s.agent_success_rates.len(), 2);
            for th in 0..3 {
                let (rates, var) = s.third(th);
                assert_eq!(rates.len(), 2);
                assert!(var >= 0.0);
            }
            assert!(s.variance_across_agents >= 0.0);
        }
    }
    for side in [&m.summary.with_communication, &m.summary.without_communication] {
        assert!((0.0..=1.0).contains(&side.mean_recovery));
        assert!(side.mean_variance_across_agents >= 0.0);
    }
    assert_eq!(m.message_columns, 2 + 1); // one sender block: one-hot (2) + one value
    assert!(m.evaluation.note.contains("neither discriminator trained on"));
    assert!(m.discriminators.with_communication.ms_per_update > 0.0);
    // The JSON written to meta.json and shown to the LLM keeps its keys, with the dim as a number.
    let j = m.json();
    assert_eq!(j["summary"]["target_dims"], serde_json::json!([3, 4]));
    assert_eq!(
        (&j["dimensions"][0]["dim"], &j["dimensions"][0]["dimension"]),
        (&serde_json::json!(3), &serde_json::json!("s[3] - hidden value B"))
    );
    assert!(j["dimensions"][0]["with_communication"]["variance_in_mid"].is_number());
    let line = m.summary_line();
    assert!(line.contains("with messages") && line.contains("2 target dims"), "{line}");
    // With the cap lifted, all three critical dims are listed and s[0]'s recovery by agent 1
    // rises with the message.
    let cfg = MetaConfig { max_target_dims: 10, ..cfg };
    let p0 = phase_from(
        r#"{"message_design_instruction": "x", "critical_state_dims": [0], "fields": [{"name": "a", "description": "v", "value": {"obs": [0]}}]}"#,
        &env,
        &[],
    );
    let m = meta::evaluate(&ctx(&schema, &env, &data), &[p0], &cfg).unwrap();
    let d0 = &m.dimensions[0];
    let with1 = d0.with_communication.agent_success_rates[1];
    let without1 = d0.without_communication.agent_success_rates[1];
    assert!(with1 > without1 + 0.3, "agent 1 on s[0]: {with1} with, {without1} without");
    // Without a dataset the evaluation explains what is missing.
    let no_data = DesignContext { dataset: None, ..ctx(&schema, &env, &data) };
    assert!(meta::evaluate(&no_data, &[], &cfg).unwrap_err().to_string().contains("dataset"));
}

// ------------------------------------------------------------------------------------------
// Offline designer

#[test]
fn offline_designer_three_phases() {
    let data = synthetic(400, 8);
    let schema = synthetic_schema(30);
    let env = lmac_protocol_runner::protocol_env(&schema);
    let c = ctx(&schema, &env, &data);
    let ocfg = OfflineConfig { discriminator: quick_disc(), ..OfflineConfig::least_squares_rules() };
    let mcfg = MetaConfig { discriminator: quick_disc(), max_target_dims: 8, ..Default::default() };
    let mut designer = OfflineDesigner::new(ocfg);
    assert!(designer.needs_data_for_initial());
    let mut phases: Vec<PhaseProtocol> = Vec::new();
    let p0 = designer.initial(&c).unwrap();
    eprintln!("phase 0:\n{}\n{}", serde_json::to_string_pretty(&p0.protocol).unwrap(), p0.reasoning);
    assert!(p0.protocol.message_design_instruction.starts_with("offline designer:"));
    // The dims one agent alone sees are critical; the shared bit and the constant are not.
    assert_eq!(p0.validated.critical_dims, vec![0, 3, 4]);
    // Agent 0's o[0] goes to agent 1 and agent 1's o[2] to agent 0: the only useful links.
    let json = serde_json::to_string(&p0.protocol).unwrap();
    assert!(json.contains("\"obs\":[0"), "{json}");
    phases.push(p0);
    let mut means = Vec::new();
    for k in 0..3 {
        let validated: Vec<ValidatedProtocol> = phases.iter().map(|p| p.validated.clone()).collect();
        // Every phase validates against the ones before it.
        for (i, p) in phases.iter().enumerate() {
            protocol::validate_phase(&p.protocol, &env, &validated[..i]).unwrap();
        }
        let m = meta::evaluate(&c, &validated, &mcfg).unwrap();
        eprintln!("phase {k}: {}", m.summary_line());
        means.push((m.summary.with_communication.mean_recovery, m.summary.without_communication.mean_recovery));
        if k == 2 {
            break;
        }
        let fb = designer.feedback(&c, k + 1, &phases, &m).unwrap();
        assert!(fb.evaluation.starts_with("offline designer:") && fb.evaluation.contains("with the messages"), "{}", fb.evaluation);
        assert!(!fb.missing_information_hypothesis.is_empty() && !fb.improvement_suggestions.is_empty());
        let next = designer.refine(&c, k + 1, &phases, &fb, &m).unwrap();
        eprintln!("phase {}:\n{}\n{}", k + 1, serde_json::to_string_pretty(&next.protocol).unwrap(), next.reasoning);
        assert!(next.protocol.message_design_instruction.starts_with("offline designer:"));
        phases.push(next);
    }
    // Messages raise recovery well above the no-message baseline, and the later phases (memory
    // of the episode constant seen every 4th step) raise it further.
    assert!(means[0].0 > means[0].1 + 0.2, "{means:?}");
    assert!(means[2].0 > means[0].0 + 0.02, "{means:?}");
    let total: usize = phases.iter().map(|p| p.validated.width).sum();
    assert!(total <= 30);
    let t = designer.transcript();
    let kinds: Vec<&str> = t.iter().map(|e| e.kind.as_str()).collect();
    assert_eq!(kinds, vec!["relevance", "critical_dims", "protocol", "feedback", "protocol", "feedback", "protocol"]);
    // No reward on this dataset: the relevance ranking cannot be used, and phase 0 says so.
    assert!(t[1].reply.contains("falls back to the hardest dims to recover"), "{}", t[1].reply);
    // Deterministic: the same inputs give the same phase 0.
    let mut again = OfflineDesigner::new(OfflineConfig { discriminator: quick_disc(), ..OfflineConfig::least_squares_rules() });
    assert_eq!(again.initial(&c).unwrap().protocol, phases[0].protocol);
    // Told that the newest phase added nothing, the designer asks more of the next one.
    let validated: Vec<ValidatedProtocol> = phases[..2].iter().map(|p| p.validated.clone()).collect();
    let mut m = meta::evaluate(&c, &validated, &mcfg).unwrap();
    m.newest_phase_added = Some(false);
    let fb = designer.feedback(&c, 2, &phases[..2], &m).unwrap();
    let stricter = designer.refine(&c, 2, &phases[..2], &fb, &m).unwrap();
    assert!(stricter.reasoning.contains("Phase 1 added nothing") && stricter.reasoning.contains("2x min_gain"), "{}", stricter.reasoning);
}

#[test]
fn offline_designer_reports_an_exhausted_budget() {
    let data = synthetic(60, 9);
    // 2 agents: one sender block of 2 one-hot columns + 1 value needs 3 columns.
    let schema = synthetic_schema(2);
    let env = lmac_protocol_runner::protocol_env(&schema);
    let c = ctx(&schema, &env, &data);
    let mut designer = OfflineDesigner::new(OfflineConfig {
        discriminator: DiscriminatorConfig { updates: 50, ..Default::default() },
        ..OfflineConfig::least_squares_rules()
    });
    let e = format!("{:#}", designer.initial(&c).unwrap_err());
    assert!(e.contains("no message budget for phase 0"), "{e}");
}

// ------------------------------------------------------------------------------------------
// Design-sized run (ignored by default: about a minute). A random-policy walk on an LBF 8x8
// grid built here with the real schema's layout (3x3x3 views and own position, 3 x 10 x 10 padded state), 5000
// episodes of 25 steps as in the paper, the default configurations, three phases. Prints the
// time of each stage: `cargo test --release -p lmac-design --test design_data -- --ignored --nocapture`.

fn lbf_walk(episodes: usize, seed: u64) -> Dataset {
    let (n, od, sd, na, limit, size) = (2usize, 29usize, 300usize, 6usize, 25usize, 8i32);
    let mut rng = LearnRng::seed_from(seed);
    let mut eps = Vec::new();
    for _ in 0..episodes {
        // Cells in field coordinates 0..8; padded = field + 1.
        let mut taken: Vec<(i32, i32)> = Vec::new();
        let mut place = |rng: &mut LearnRng| loop {
            let c = (rng.below(size as usize) as i32, rng.below(size as usize) as i32);
            if !taken.contains(&c) {
                taken.push(c);
                return c;
            }
        };
        let mut agents: Vec<(i32, i32)> = (0..n).map(|_| place(&mut rng)).collect();
        let mut food: Vec<(i32, i32)> = (0..2).map(|_| place(&mut rng)).collect();
        let mut tr = Trajectory::default();
        for t in 0..limit {
            let level = |r: i32, c: i32, agents: &[(i32, i32)], food: &[(i32, i32)]| -> [f32; 3] {
                let inside = (0..size).contains(&r) && (0..size).contains(&c);
                let a = agents.contains(&(r, c)) as u8 as f32;
                let f = 2.0 * food.contains(&(r, c)) as u8 as f32;
                [a, f, (inside && a == 0.0 && f == 0.0) as u8 as f32]
            };
            for &(ar, ac) in &agents {
                let mut o = [0f32; 29];
                for dr in -1..=1 {
                    for dc in -1..=1 {
                        let v = level(ar + dr, ac + dc, &agents, &food);
                        let k = ((dr + 1) * 3 + dc + 1) as usize;
                        for l in 0..3 {
                            o[l * 9 + k] = v[l];
                        }
                    }
                }
                // Own row and column, scaled to [0, 1] as the LBF env server writes them.
                o[27] = ar as f32 / (size - 1) as f32;
                o[28] = ac as f32 / (size - 1) as f32;
                tr.obs.extend_from_slice(&o);
            }
            let mut s = [0f32; 300];
            for pr in 0..10 {
                for pc in 0..10 {
                    let v = level(pr - 1, pc - 1, &agents, &food);
                    for l in 0..3 {
                        s[l * 100 + (pr * 10 + pc) as usize] = v[l];
                    }
                }
            }
            tr.state.extend_from_slice(&s);
            let acts: Vec<i32> = (0..n).map(|_| rng.below(na) as i32).collect();
            tr.actions.extend_from_slice(&acts);
            let mut reward = 0.0;
            // Loading: both agents load next to the same food.
            if acts.iter().all(|&a| a == 5) {
                if let Some(k) = food.iter().position(|&(fr, fc)| agents.iter().all(|&(r, c)| (r - fr).abs() + (c - fc).abs() == 1)) {
                    food.remove(k);
                    reward = 0.5;
                }
            }
            for (i, &a) in acts.iter().enumerate() {
                let (r, c) = agents[i];
                let to = match a {
                    1 => (r - 1, c),
                    2 => (r + 1, c),
                    3 => (r, c - 1),
                    4 => (r, c + 1),
                    _ => (r, c),
                };
                if to != (r, c) && (0..size).contains(&to.0) && (0..size).contains(&to.1) && !agents.contains(&to) && !food.contains(&to) {
                    agents[i] = to;
                }
            }
            tr.reward.push(reward);
            tr.len += 1;
            if food.is_empty() {
                tr.terminated = true;
                break;
            }
            tr.truncated = t + 1 == limit;
        }
        eps.push(tr);
    }
    Dataset { header: header("lbf:8x8-2p-2f-s1-coop", n, od, sd, na, limit), episodes: eps }
}

#[test]
#[ignore]
fn design_sized_run() {
    let t0 = std::time::Instant::now();
    let data = lbf_walk(5000, 12);
    eprintln!("dataset: {} episodes, {} steps, built in {:.1} s", data.episodes.len(), data.steps(), t0.elapsed().as_secs_f64());
    let schema = lmac_shm_schema::schema::load_env("lbf:8x8-2p-2f-s1-coop").unwrap();
    let env = lmac_protocol_runner::protocol_env(&schema);
    let c = DesignContext { env_name: "lbf:8x8-2p-2f-s1-coop", schema: &schema, env: &env, dataset: Some(&data), seed: 1 };
    let mut designer = OfflineDesigner::default();
    let mcfg = MetaConfig::default();
    let t = std::time::Instant::now();
    let mut phases = vec![designer.initial(&c).unwrap()];
    eprintln!("phase 0 designed in {:.1} s: {}", t.elapsed().as_secs_f64(), phases[0].protocol.message_design_instruction);
    for k in 0..3 {
        let validated: Vec<ValidatedProtocol> = phases.iter().map(|p| p.validated.clone()).collect();
        let t = std::time::Instant::now();
        let m = meta::evaluate(&c, &validated, &mcfg).unwrap();
        eprintln!("phase {k} evaluated in {:.1} s: {}", t.elapsed().as_secs_f64(), m.summary_line());
        eprintln!("  discriminator: {}", serde_json::to_string(&m.discriminators.with_communication).unwrap());
        if k == 2 {
            break;
        }
        let t = std::time::Instant::now();
        let fb = designer.feedback(&c, k + 1, &phases, &m).unwrap();
        let next = designer.refine(&c, k + 1, &phases, &fb, &m).unwrap();
        eprintln!("feedback: {}\n{}\n{}", fb.evaluation, fb.missing_information_hypothesis, fb.improvement_suggestions);
        eprintln!("phase {} designed in {:.1} s: {}", k + 1, t.elapsed().as_secs_f64(), next.protocol.message_design_instruction);
        phases.push(next);
    }
    eprintln!("design total {:.1} s", t0.elapsed().as_secs_f64());
}

// ------------------------------------------------------------------------------------------
// Dead fields

#[test]
fn dead_fields_are_constant_or_copied_links() {
    let data = synthetic(40, 3);
    let schema = synthetic_schema(24);
    let env = lmac_protocol_runner::protocol_env(&schema);
    // Agent 0 -> agent 1: o[2] (always 0 for agent 0), o[1] (the shared bit agent 1 sees
    // itself), o[0] (hidden value A: information), and [o[0], o[2]] (one live column).
    let p0 = phase_from(
        r#"{"message_design_instruction": "x", "critical_state_dims": [0], "fields": [
            {"name": "zero", "description": "z", "senders": [0], "receivers": {"peer": [{"from": 0, "to": [1]}]}, "value": {"obs": [2]}},
            {"name": "bit", "description": "b", "senders": [0], "receivers": {"peer": [{"from": 0, "to": [1]}]}, "value": {"obs": [1]}},
            {"name": "value", "description": "v", "senders": [0], "receivers": {"peer": [{"from": 0, "to": [1]}]}, "value": {"obs": [0]}},
            {"name": "mixed", "description": "m", "senders": [0], "receivers": {"peer": [{"from": 0, "to": [1]}]}, "value": {"obs": [0, 2]}}]}"#,
        &env,
        &[],
    );
    let dead = lmac_design::dead_fields::find(&data, &[p0.clone()], &env).unwrap();
    let names: Vec<(&str, usize, usize)> = dead.iter().map(|d| (d.field.as_str(), d.sender, d.receiver)).collect();
    assert_eq!(names, vec![("zero", 0, 1), ("bit", 0, 1)], "{dead:?}");
    use lmac_design::dead_fields::DeadColumn;
    assert_eq!(dead[0].columns, vec![DeadColumn::Constant(0.0)]);
    assert_eq!(dead[1].columns, vec![DeadColumn::CopyOfObs(1)]);
    assert!(dead[1].describe().contains("equals the receiver's own o[1]"), "{}", dead[1].describe());
    // In the design loop the designer reads them with the meta-information.
    let cfg = MetaConfig { discriminator: quick_disc(), max_target_dims: 2, ..Default::default() };
    let m = meta::evaluate(&ctx(&schema, &env, &data), &[p0], &cfg).unwrap();
    assert_eq!(m.dead_fields.len(), 2, "{:?}", m.dead_fields);
    assert!(m.json()["dead_fields"][0].as_str().unwrap().contains("field `zero` from agent 0 to agent 1"));
}

// ------------------------------------------------------------------------------------------
// The fixed-dim trend

#[test]
fn phase_evaluation_reads_the_trend_on_fixed_dims_with_both_definitions() {
    use lmac_design::run::{evaluate_phase, fixed_dims};
    let data = synthetic(300, 6);
    let schema = synthetic_schema(24);
    let env = lmac_protocol_runner::protocol_env(&schema);
    // Phase 0 sends hidden value A (s[0], seen by agent 0 only) to agent 1 and names s[0] and
    // s[3] as critical; phase 1 adds a field about s[3] but names other critical dims, which
    // must not move the fixed set.
    let p0 = phase_from(
        r#"{"message_design_instruction": "x", "critical_state_dims": [3, 0], "fields": [
            {"name": "a", "description": "v", "senders": [0], "receivers": {"peer": [{"from": 0, "to": [1]}]}, "value": {"obs": [0]}}]}"#,
        &env,
        &[],
    );
    let p1 = phase_from(
        r#"{"message_design_instruction": "y", "critical_state_dims": [4], "fields": [
            {"name": "b", "description": "v", "senders": [1], "receivers": {"peer": [{"from": 1, "to": [0]}]}, "value": {"obs": [2]}}]}"#,
        &env,
        &[p0.clone()],
    );
    let (fixed, source) = fixed_dims(&p0);
    assert_eq!((fixed.clone(), source), (vec![0, 3], "phase 0's critical state dims"));
    let cfg = MetaConfig { discriminator: quick_disc(), max_target_dims: 8, ..Default::default() };
    let dir = tmp_dir("trend");
    let c = ctx(&schema, &env, &data);
    let (_, e0) = evaluate_phase(&c, &[p0.clone()], 0, &fixed, &cfg, &dir.join("phase0")).unwrap();
    let (_, e1) = evaluate_phase(&c, &[p0, p1], 1, &fixed, &cfg, &dir.join("phase1")).unwrap();
    assert_eq!((e0.fixed_dims.dims, e1.fixed_dims.dims), (2, 2));
    assert_eq!(e1.all_dims.dims, 5);
    // Phase 1 brings s[3] to agent 0: the fixed-dim recovery of agent 0 rises with messages, not
    // without (a retrained discriminator never sees them).
    let (a0, a1) = (e0.fixed_dims.with_messages.per_agent[0], e1.fixed_dims.with_messages.per_agent[0]);
    assert!(a1 > a0 + 0.2, "agent 0 on the fixed dims: {a0} after phase 0, {a1} after phase 1");
    let w = &e1.fixed_dims;
    assert!(w.with_messages.skill > w.without_retrained.skill + 0.2, "{w:?}");
    // The paper's definition: the with-messages discriminator given zeroed messages loses what
    // the messages carried.
    assert!(w.without_zeroed.mean_recovery < w.with_messages.mean_recovery, "{w:?}");
    // Every dim is written, with its constant guess and per-agent rates for all three.
    let rec: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(dir.join("phase1/recovery.json")).unwrap()).unwrap();
    let dims = rec["dims"].as_array().unwrap();
    assert_eq!(dims.len(), 5);
    for d in dims {
        for side in ["with_messages", "without_retrained", "without_zeroed"] {
            assert_eq!(d[side].as_array().unwrap().len(), 2, "{d}");
        }
        assert!(d["constant_guess_rate"].is_number());
    }
    assert!(dir.join("phase1/meta.json").exists());
}

/// With a return that depends on hidden value B (state dim 3, seen by agent 1 only),
/// relevance picks that dim alone; hidden value A and the episode constant are as hard to
/// recover but the return does not depend on them. `critical_by = recovery` keeps the old rule.
#[test]
fn offline_designer_chooses_what_the_return_depends_on() {
    let data = hidden_b_rewarded();
    let schema = synthetic_schema(30);
    let env = lmac_protocol_runner::protocol_env(&schema);
    let c = ctx(&schema, &env, &data);
    let mut designer = OfflineDesigner::new(OfflineConfig { discriminator: quick_disc(), ..OfflineConfig::least_squares_rules() });
    let p0 = designer.initial(&c).unwrap();
    let rel = designer.relevance().expect("phase 0 measured relevance");
    assert_eq!(rel.ranking()[0], 3, "{rel:?}");
    assert!(rel.held_out_r2 > 0.05, "the return-to-go is mostly future noise, but h3 explains part of it: {rel:?}");
    assert_eq!(p0.validated.critical_dims, vec![3], "{}", p0.reasoning);
    let t = designer.transcript();
    assert!(t[0].kind == "relevance" && t[0].reply.contains("s[3] - hidden value B: relevance"), "{}", t[0].reply);
    assert!(t[0].reply.contains("CHOSEN"), "{}", t[0].reply);
    // Agent 1's o[2] (hidden value B) goes to agent 0.
    let json = serde_json::to_string(&p0.protocol).unwrap();
    assert!(json.contains("\"obs\":[2"), "{json}");
    let mut old = OfflineDesigner::new(OfflineConfig {
        discriminator: quick_disc(),
        critical_by: CriticalBy::Recovery,
        ..OfflineConfig::least_squares_rules()
    });
    assert_eq!(old.initial(&c).unwrap().validated.critical_dims, vec![0, 3, 4]);
    // `--critical-by action`: this B's actions are random, so no model of them explains
    // anything; phase 0 says so in the actions' terms and ranks the dims by the return instead.
    let mut by_action = OfflineDesigner::new(OfflineConfig {
        discriminator: quick_disc(),
        critical_by: CriticalBy::Action,
        ..OfflineConfig::least_squares_rules()
    });
    assert_eq!(by_action.initial(&c).unwrap().validated.critical_dims, vec![3]);
    let t = by_action.transcript();
    assert!(t[0].kind == "relevance" && t[0].reply.starts_with("A linear model of each agent's action"), "{}", t[0].reply);
    assert!(t[1].kind == "relevance" && t[1].reply.starts_with("A value model of the state"), "{}", t[1].reply);
    let critical = t.iter().find(|e| e.kind == "critical_dims").unwrap();
    assert!(
        critical.reply.contains("of the held-out actions' variance") && critical.reply.contains("ranked by the return instead"),
        "{}",
        critical.reply
    );
    let measured = by_action.measurements().unwrap();
    assert!(measured["relevance"]["what"].as_str().unwrap().starts_with("permutation importance"), "{measured}");
}

/// The return depends on hidden value B, which
/// only agent 1 sees (its o[2]). Sending all of agent 1's observation raises agent 0's recovery
/// of s[3]; agent 0's observation tells agent 1 nothing it lacks. So agent 1 is the one
/// sender, and o[2] is among what it sends, to agent 0.
#[test]
fn observation_relevance_chooses_the_agent_that_sees_what_matters() {
    let data = hidden_b_rewarded();
    let schema = synthetic_schema(30);
    let env = lmac_protocol_runner::protocol_env(&schema);
    let c = ctx(&schema, &env, &data);
    let cfg =
        OfflineConfig { discriminator: quick_disc(), fields_by: FieldsBy::ObservationRelevance, ..OfflineConfig::least_squares_rules() };
    let mut designer = OfflineDesigner::new(cfg);
    let p0 = designer.initial(&c).unwrap();
    assert_eq!(p0.validated.critical_dims, vec![3], "{}", p0.reasoning);
    let t = designer.transcript();
    let obs_rel = t.iter().find(|e| e.kind == "observation_relevance").expect("the ranking is in the transcript");
    assert!(obs_rel.reply.contains("agent 1: all it sees") && obs_rel.reply.contains("a SENDER"), "{}", obs_rel.reply);
    let sender_line = obs_rel.reply.lines().find(|l| l.contains("a SENDER")).unwrap();
    assert!(sender_line.starts_with("agent 1:"), "{}", obs_rel.reply);
    assert!(
        p0.protocol.message_design_instruction.contains("by the relevance of what each agent sees"),
        "{}",
        p0.protocol.message_design_instruction
    );
    let json = serde_json::to_value(&p0.protocol).unwrap();
    for f in json["fields"].as_array().unwrap() {
        assert_eq!(f["senders"], serde_json::json!([1]), "{f}");
    }
    let sent = sent_obs(&json);
    assert!(sent.contains(&2), "agent 1's view of hidden value B is sent: {json}");
}

/// The observation values a protocol's fields send (`{"obs": [...]}` fields), in field order.
fn sent_obs(protocol: &serde_json::Value) -> Vec<u64> {
    protocol["fields"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|f| f["value"]["obs"].as_array().cloned().unwrap_or_default())
        .map(|v| v.as_u64().unwrap())
        .collect()
}

/// The split-view task rewarded when hidden value B (agent 1's o[2]) is 1 or more.
fn hidden_b_rewarded() -> Dataset {
    synthetic_rewarded(400, 8, |s| if s[3] >= 1.0 { 1.0 } else { 0.0 })
}

/// Phase 0 by observation relevance with the senders ranked by the return.
fn senders_by_return(values_by: lmac_design::offline::ValuesBy) -> OfflineConfig {
    OfflineConfig {
        discriminator: quick_disc(),
        fields_by: FieldsBy::ObservationRelevance,
        senders_by: lmac_design::offline::SendersBy::Return,
        values_by,
        ..OfflineConfig::least_squares_rules()
    }
}

/// The same task with `--senders-by return`: the agent whose view the others need to predict
/// the return is the sender (a value model on a receiver's observation with and without it),
/// and it sends the value of its view that model uses.
#[test]
fn senders_by_return_chooses_the_agent_whose_view_the_return_needs() {
    let data = hidden_b_rewarded();
    let schema = synthetic_schema(30);
    let env = lmac_protocol_runner::protocol_env(&schema);
    let c = ctx(&schema, &env, &data);
    let mut designer = OfflineDesigner::new(senders_by_return(lmac_design::offline::ValuesBy::Value));
    let p0 = designer.initial(&c).unwrap();
    let t = designer.transcript();
    let obs_rel = t.iter().find(|e| e.kind == "observation_relevance").expect("the ranking is in the transcript");
    assert!(obs_rel.reply.contains("most helps the others predict the team's return"), "{}", obs_rel.reply);
    let sender_line = obs_rel.reply.lines().find(|l| l.contains("a SENDER")).unwrap();
    assert!(sender_line.starts_with("agent 1: all it sees, beside another agent's own observation"), "{}", obs_rel.reply);
    let json = serde_json::to_value(&p0.protocol).unwrap();
    let mut sent = Vec::new();
    for f in json["fields"].as_array().unwrap() {
        assert_eq!(f["senders"], serde_json::json!([1]), "{f}");
        sent.extend(f["value"]["obs"].as_array().cloned().unwrap_or_default().into_iter().map(|v| v.as_u64().unwrap()));
    }
    assert!(sent.contains(&2), "agent 1's view of hidden value B is sent: {json}");
}

/// `--values-by entity`: the sender sends the whole entity of its view the receivers' value
/// model needs first (here o[2..4], "what agent 1 sees of B", as the schema groups it), except a
/// value that never varies for it (its o[3]: the flash only agent 0 sees), and the ranking names
/// the entity. Entities need `--senders-by return`, which is said before anything is measured.
#[test]
fn values_by_entity_sends_the_whole_entity_the_return_needs() {
    let data = hidden_b_rewarded();
    let mut schema = synthetic_schema(30);
    schema.obs_dims.truncate(2);
    schema.obs_dims.push(group(2, "what this agent sees of hidden value B and the flash: value {k}"));
    let env = lmac_protocol_runner::protocol_env(&schema);
    let c = ctx(&schema, &env, &data);
    let cfg = senders_by_return(lmac_design::offline::ValuesBy::Entity);
    let mut designer = OfflineDesigner::new(cfg.clone());
    let p0 = designer.initial(&c).unwrap();
    let t = designer.transcript();
    let obs_rel = t.iter().find(|e| e.kind == "observation_relevance").expect("the ranking is in the transcript");
    let line = obs_rel.reply.lines().find(|l| l.contains("CHOSEN")).unwrap_or_else(|| panic!("{}", obs_rel.reply));
    assert!(
        line.starts_with("agent 1's what this agent sees of hidden value B and the flash (o[2..4]): relevance")
            && line.ends_with("CHOSEN: o[2] sent by this agent to every other agent"),
        "{}",
        obs_rel.reply
    );
    assert!(p0.protocol.message_design_instruction.contains("Phase 0 sends whole entities"), "{}", p0.protocol.message_design_instruction);
    let json = serde_json::to_value(&p0.protocol).unwrap();
    let mut sent = Vec::new();
    for f in json["fields"].as_array().unwrap() {
        assert_eq!(f["senders"], serde_json::json!([1]), "{f}");
        sent.extend(f["value"]["obs"].as_array().cloned().unwrap_or_default().into_iter().map(|v| v.as_u64().unwrap()));
    }
    assert!(sent.contains(&2) && !sent.contains(&3), "o[2] is sent, o[3] (constant for agent 1) is not: {json}");

    // `--phase1-by frame`: agent 0 never sees B itself, so no step tells what would place it in
    // agent 1's view; phase 1 says so and turns to least squares.
    let frame = OfflineConfig { phase1_by: lmac_design::offline::Phase1By::Frame, ..cfg.clone() };
    let mut designer = OfflineDesigner::new(frame.clone());
    let p0 = designer.initial(&c).unwrap();
    let mcfg = MetaConfig { discriminator: quick_disc(), max_target_dims: 8, ..Default::default() };
    let m = meta::evaluate(&c, std::slice::from_ref(&p0.validated), &mcfg).unwrap();
    let fb = designer.feedback(&c, 1, std::slice::from_ref(&p0), &m).unwrap();
    // Phase 0 already sends all of B, the one critical dim, so least squares finds nothing
    // either, and says so.
    let e = designer.refine(&c, 1, std::slice::from_ref(&p0), &fb, &m).unwrap_err();
    assert!(format!("{e:#}").contains("phase 1 has nothing to send"), "{e:#}");
    let t = designer.transcript();
    let fit = t.iter().find(|e| e.kind == "frame").expect("the fits are in the transcript");
    assert!(fit.reply.contains("agent 0: sees it together with agent 1 on 0 steps of B, too few to fit"), "{}", fit.reply);
    let fallback = t.iter().find(|e| e.kind == "fields_by").expect("the fallback is in the transcript");
    assert!(fallback.reply.starts_with("By least squares instead: no value of agent 1's view adds"), "{}", fallback.reply);
    let by_value = OfflineConfig { values_by: lmac_design::offline::ValuesBy::Value, ..frame };
    let e = OfflineDesigner::new(by_value).initial(&c).unwrap_err();
    assert!(format!("{e:#}").contains("(--phase1-by frame) places the receivers"), "{e:#}");
    let given_alone = OfflineConfig { frame_given_own_view: true, ..cfg.clone() };
    let e = OfflineDesigner::new(given_alone).initial(&c).unwrap_err();
    assert!(format!("{e:#}").contains("--frame-given-own-view changes how"), "{e:#}");

    let recovery = OfflineConfig { senders_by: lmac_design::offline::SendersBy::Recovery, ..cfg };
    let e = OfflineDesigner::new(recovery).initial(&c).unwrap_err();
    assert!(format!("{e:#}").contains("--values-by entity) needs --senders-by return"), "{e:#}");
}

/// `--values-by recovery` on LBF-shaped random walks: a grid cell of the state is recoverable
/// from the teammate's row and column, not from a value model of the return (the walk's
/// actions are random), and the teammate's view rows say nothing about absolute cells without
/// them. Each entity of the sender's view is probed alone with a discriminator, and the
/// sender's row and column (o[27], o[28], one value each) add the most per value, so phase 0
/// sends them first; the ranking says what every probe added.
#[test]
fn values_by_recovery_sends_where_the_sender_is() {
    let data = lbf_walk(300, 5);
    let schema = lmac_shm_schema::schema::load_env("lbf:8x8-2p-2f-s1-coop").unwrap();
    let env = lmac_protocol_runner::protocol_env(&schema);
    let c = ctx(&schema, &env, &data);
    let cfg = OfflineConfig {
        discriminator: quick_disc(),
        fields_by: FieldsBy::ObservationRelevance,
        values_by: lmac_design::offline::ValuesBy::Recovery,
        critical_by: CriticalBy::Recovery,
        ..OfflineConfig::least_squares_rules()
    };
    let mut designer = OfflineDesigner::new(cfg.clone());
    let p0 = designer.initial(&c).unwrap();
    let t = designer.transcript();
    let obs_rel = t.iter().find(|e| e.kind == "observation_relevance").expect("the ranking is in the transcript");
    let probes: Vec<&str> = obs_rel.reply.lines().filter(|l| l.contains("sent alone to the others, it raises their recovery")).collect();
    assert!(probes.len() >= 8, "every entity of the sender's view is probed: {}", obs_rel.reply);
    for first in &probes[..2] {
        assert!(first.contains("own field row") || first.contains("own field column"), "{}", obs_rel.reply);
        assert!(first.contains("CHOSEN"), "{}", obs_rel.reply);
    }
    assert!(p0.protocol.message_design_instruction.contains("most raises their recovery of the critical dims per value sent first"));
    let json = serde_json::to_value(&p0.protocol).unwrap();
    let sent = sent_obs(&json);
    assert!(sent.contains(&27) && sent.contains(&28), "the sender's row and column are sent: {json}");
    assert!(sent.len() <= cfg.max_relevant_values, "{json}");
}

/// Where a discriminator cannot read even the best sender's whole view (the state is noise, so
/// with it the receivers recover the critical dims no better than a constant guess of each),
/// the default rules do not rank entities by gains that are noise: every agent sends all of
/// its view that varies on B to every other agent, and the design says why.
/// `--rank-when-blind` (`whole_view_when_blind: false`) ranks them anyway.
#[test]
fn a_blind_discriminator_sends_every_agents_whole_view() {
    let data = lbf_like(160, 21);
    let schema = lmac_shm_schema::schema::load_env("lbf:8x8-2p-2f-s1-coop").unwrap();
    let env = lmac_protocol_runner::protocol_env(&schema);
    let c = ctx(&schema, &env, &data);
    let cfg = OfflineConfig { discriminator: quick_disc(), ..Default::default() };
    assert!(cfg.whole_view_when_blind);
    let p0 = OfflineDesigner::new(cfg.clone()).initial(&c).unwrap();
    let json = serde_json::to_value(&p0.protocol).unwrap();
    // lbf_like's observations are uniform in {0, 1, 2}: every value varies for both agents.
    let mut by_sender = [Vec::new(), Vec::new()];
    for f in json["fields"].as_array().unwrap() {
        let senders = f["senders"].as_array().unwrap_or_else(|| panic!("{f}"));
        assert_eq!(senders.len(), 1, "{f}");
        let j = senders[0].as_u64().unwrap() as usize;
        by_sender[j].extend(f["value"]["obs"].as_array().unwrap().iter().map(|v| v.as_u64().unwrap()));
    }
    for (j, sent) in by_sender.iter_mut().enumerate() {
        sent.sort_unstable();
        assert_eq!(*sent, (0..29).collect::<Vec<u64>>(), "agent {j} sends its whole view: {json}");
    }
    let instruction = &p0.protocol.message_design_instruction;
    assert!(instruction.contains("Phase 0 sends every agent's whole view (58 values"), "{instruction}");
    assert!(instruction.contains("against") && instruction.contains("for a constant guess of each dim"), "{instruction}");
    // Ranked anyway (or, with no sender found, by least squares): not the whole views.
    let ranked = OfflineConfig { whole_view_when_blind: false, ..cfg };
    let p0 = OfflineDesigner::new(ranked).initial(&c).unwrap();
    assert!(!p0.protocol.message_design_instruction.contains("whole view"), "{}", p0.protocol.message_design_instruction);
    assert!(sent_obs(&serde_json::to_value(&p0.protocol).unwrap()).len() < 58);
}

/// Dropping the phases that add nothing (the default) on a dataset whose state is noise (no message can help recover
/// it): every phase, phase 0 included, is judged against what was kept before it (no messages
/// for phase 0); a phase in the final protocol either adds or says why it is there anyway; the
/// training side reads exactly the phases kept; and something is always kept.
#[test]
fn a_design_keeps_only_phases_that_add_or_says_why() {
    let dir = tmp_dir("drop-phases");
    let data = lbf_like(160, 21);
    data.save(&dir.join("dataset")).unwrap();
    let opts = lmac_design::run::DesignOptions {
        env: "lbf:8x8-2p-2f-s1-coop".into(),
        out: dir.join("designs"),
        seed: 3,
        pretrain_steps: 0,
        collect_algo: "qmix".into(),
        dataset_episodes: 0,
        dataset_epsilon: None,
        envs: 1,
        servers: 1,
        dataset: Some(dir.join("dataset")),
        phases: 3,
        without: meta::NoMessages::Retrained,
        drop_unhelpful_phases: true,
    };
    let disc = DiscriminatorConfig { updates: 300, batch_size: 64, lr: 2e-3, ..Default::default() };
    let mut designer = OfflineDesigner::new(OfflineConfig { discriminator: disc.clone(), ..Default::default() });
    let mcfg = MetaConfig { discriminator: disc, ..Default::default() };
    let design = lmac_design::run::run_design(&opts, &mut designer, &mcfg, Default::default()).unwrap();
    let summary: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(design.join("summary.json")).unwrap()).unwrap();
    // The design says how it was made: the offline designer's knobs, as they parse back.
    let settings: OfflineConfig = serde_json::from_value(summary["designer_settings"].clone()).unwrap();
    assert_eq!(settings, designer.config().clone());
    let evals = summary["evaluations"].as_array().unwrap();
    assert_eq!(evals.len(), 3);
    let mut kept = Vec::new();
    for (k, e) in evals.iter().enumerate() {
        let adds = &e["adds"];
        let text = adds["text"].as_str().unwrap_or_else(|| panic!("phase {k} has no verdict on what it adds: {e}"));
        let helps = adds["messages_help"].as_bool().unwrap();
        let dropped = e["dropped"].as_bool().unwrap();
        assert!(text.contains("adds to") || text.contains("does NOT add to"), "{text}");
        if dropped {
            assert!(!helps, "phase {k} helps but was dropped: {text}");
        } else {
            kept.push(k);
            assert!(
                helps
                    || e["kept_because"]
                        .as_str()
                        .is_some_and(|w| w.contains("a design must send something") || w.contains("cannot be measured on this data")),
                "phase {k}: {e}"
            );
        }
    }
    assert!(!kept.is_empty(), "{summary}");
    // Phase 0 is judged against no messages.
    assert!(evals[0]["adds"]["text"].as_str().unwrap().contains("no messages"), "{}", evals[0]);
    // Training reads the kept phases, in order.
    let files = lmac_run::train::protocol_files(design.to_str().unwrap(), None).unwrap();
    let expected: Vec<String> = kept.iter().map(|k| design.join(format!("phase{k}")).join("protocol.json").display().to_string()).collect();
    assert_eq!(files, expected);
    eprintln!(
        "kept phases {kept:?}: {}",
        evals.iter().map(|e| e["adds"]["text"].as_str().unwrap().to_string()).collect::<Vec<_>>().join("\n")
    );
}
