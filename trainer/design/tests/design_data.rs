//! The data side of protocol design: the dataset B on disk, messages recomputed by the runner's
//! plan, the discriminator and the meta-information JSON, on synthetic datasets built here (small
//! enough to run in seconds in release).

mod common;

use burn::tensor::Device;
use common::*;
use lmac_design::discriminator::{split_episodes, DiscInput, Discriminator, DiscriminatorConfig};
use lmac_design::meta::{self, MetaConfig, Recovery};
use lmac_design::DesignContext;
use lmac_protocol_runner::builtin::FullComm;
use lmac_protocol_runner::plan::{MessagePlan, StepView};
use lmac_protocol_runner::protocol::{self, ValidatedProtocol};
use lmac_run::dataset::{Dataset, Trajectory};
use lmac_run::episode::Episode;

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
