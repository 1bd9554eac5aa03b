//! Checkpoint round trip (identical Q-values, counters, epsilon, and the same next update after
//! resuming), non-finite loss detection, and config errors that name the field.

use burn::tensor::Device;
use lmac_learn::episode::{Episode, EpisodeDims};
use lmac_learn::{Controller, LearnConfig, LearnError, LearnRng, Learner, MixerKind, OptimizerKind};

const DIMS: EpisodeDims = EpisodeDims { n_agents: 3, obs_width: 5, state_dim: 7, n_actions: 4 };

fn random_episode(rng: &mut LearnRng, len: usize, terminated: bool) -> Episode {
    let d = DIMS;
    let mut ep = Episode::with_capacity(&d, len);
    for _ in 0..len {
        for _ in 0..d.n_agents * d.obs_width {
            ep.obs.push(rng.uniform() * 2.0 - 1.0);
        }
        for _ in 0..d.state_dim {
            ep.state.push(rng.uniform());
        }
        for ag in 0..d.n_agents {
            let mut av = vec![0u8; d.n_actions];
            av[0] = 1;
            for a in 1..d.n_actions {
                av[a] = (rng.uniform() < 0.7) as u8;
            }
            let choices: Vec<usize> = (0..d.n_actions).filter(|&a| av[a] == 1).collect();
            ep.actions.push(choices[rng.below(choices.len())] as i32);
            ep.avail.extend_from_slice(&av);
            let _ = ag;
        }
        ep.reward.push(rng.uniform());
        ep.len += 1;
    }
    ep.terminated = terminated;
    ep.truncated = !terminated;
    ep
}

fn q_values(learner: &Learner, obs_seed: u64) -> Vec<f32> {
    let mut ctl = Controller::new(learner, 2);
    let mut rng = LearnRng::seed_from(obs_seed);
    let mut out = Vec::new();
    let mut last = vec![-1; 2 * DIMS.n_agents];
    for t in 0..3 {
        let obs: Vec<f32> = (0..2 * DIMS.n_agents * DIMS.obs_width).map(|_| rng.uniform()).collect();
        out.extend_from_slice(ctl.q_values(&obs, None, &last, &[t == 0, t == 0]));
        last = (0..2 * DIMS.n_agents).map(|i| (i % DIMS.n_actions) as i32).collect();
    }
    out
}

fn run_round_trip(mixer: MixerKind, optimizer: OptimizerKind) {
    let cfg = LearnConfig { mixer, optimizer, batch_size: 4, buffer_size: 16, seed: 3, qplex_num_kernel: 2, ..LearnConfig::default() };
    let mut learner = Learner::new(DIMS, cfg, Device::default()).unwrap();
    let mut rng = LearnRng::seed_from(11);
    for i in 0..20 {
        learner.add_episode(random_episode(&mut rng, 3 + i % 4, i % 3 != 0)).unwrap();
    }
    for _ in 0..3 {
        learner.train_step().unwrap();
    }
    let dir = std::env::temp_dir().join(format!("lmac-learn-ckpt-{}-{mixer:?}-{optimizer:?}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    learner.save_checkpoint(&dir, true).unwrap();
    // A second save over the first one must also succeed (atomic replace).
    learner.save_checkpoint(&dir, true).unwrap();
    let mut loaded = Learner::load_checkpoint(&dir, Device::default()).unwrap();

    assert_eq!(loaded.counters(), learner.counters());
    assert_eq!(loaded.epsilon(), learner.epsilon());
    assert_eq!(loaded.config(), learner.config());
    assert_eq!(loaded.buffer().len(), learner.buffer().len());
    assert_eq!(q_values(&loaded, 5), q_values(&learner, 5), "online Q-values differ after load");

    // Resuming continues the same curve: the next updates match.
    for step in 0..2 {
        let a = learner.train_step().unwrap();
        let b = loaded.train_step().unwrap();
        assert!((a.loss - b.loss).abs() <= 1e-5 * a.loss.abs().max(1.0), "{mixer:?} step {step}: loss {} vs {}", a.loss, b.loss);
    }
    assert_eq!(q_values(&loaded, 9), q_values(&learner, 9));
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn checkpoint_round_trip_qmix() {
    run_round_trip(MixerKind::Qmix, OptimizerKind::Adam);
}

#[test]
fn checkpoint_round_trip_qplex_adam_and_vdn_rmsprop() {
    run_round_trip(MixerKind::Qplex, OptimizerKind::Adam);
    run_round_trip(MixerKind::Vdn, OptimizerKind::Rmsprop);
}

#[test]
fn non_finite_loss_names_the_step() {
    let cfg = LearnConfig { batch_size: 2, buffer_size: 4, ..LearnConfig::default() };
    let mut learner = Learner::new(DIMS, cfg, Device::default()).unwrap();
    let mut rng = LearnRng::seed_from(1);
    for _ in 0..2 {
        let mut ep = random_episode(&mut rng, 3, true);
        ep.reward[1] = f32::NAN;
        learner.add_episode(ep).unwrap();
    }
    match learner.train_step() {
        Err(e @ LearnError::NonFinite { update: 1, .. }) => {
            let msg = e.to_string();
            assert!(msg.contains("loss") && msg.contains("update 1"), "{msg}");
        }
        other => panic!("expected a non-finite loss error, got {other:?}"),
    }
}

#[test]
fn config_errors_name_the_field() {
    let e = LearnConfig { batch_size: 0, ..LearnConfig::default() }.validate().unwrap_err();
    assert_eq!(e.field, "batch_size");
    assert!(e.to_string().contains("batch_size"));
    let e = LearnConfig { gamma: 1.5, ..LearnConfig::default() }.validate().unwrap_err();
    assert_eq!(e.field, "gamma");
    let e = LearnConfig { hypernet_layers: 3, ..LearnConfig::default() }.validate().unwrap_err();
    assert_eq!(e.field, "hypernet_layers");
    let e = LearnConfig::from_toml_str("lr = -0.1").unwrap_err();
    assert!(e.to_string().contains("`lr`"), "{e}");
    let e = LearnConfig::from_toml_str("mixing_embed = 32").unwrap_err();
    assert!(e.to_string().contains("mixing_embed"), "{e}");
    let e = LearnConfig::from_toml_str("mixer = \"qmx\"").unwrap_err();
    assert!(e.to_string().contains("mixer"), "{e}");
    let ok = LearnConfig::from_toml_str("mixer = \"qplex\"\nbatch_size = 16").unwrap();
    assert_eq!(ok.mixer, MixerKind::Qplex);
    assert_eq!(ok.batch_size, 16);
    // Learner::new validates too.
    let bad = LearnConfig { grad_norm_clip: 0.0, ..LearnConfig::default() };
    match Learner::new(DIMS, bad, Device::default()) {
        Err(LearnError::Config(e)) => assert_eq!(e.field, "grad_norm_clip"),
        other => panic!("expected a config error, got {:?}", other.err()),
    }
    // Table C.3 defaults.
    let d = LearnConfig::default();
    assert_eq!((d.buffer_size, d.batch_size, d.target_update_interval_episodes), (5000, 32, 200));
    assert_eq!((d.gamma, d.lr, d.mixing_embed_dim, d.grad_norm_clip), (0.99, 5e-4, 32, 10.0));
    assert_eq!((d.epsilon_start, d.epsilon_finish, d.epsilon_anneal_steps), (1.0, 0.05, 50_000));
    assert!((d.epsilon_at(25_000) - 0.525).abs() < 1e-6);
}

#[test]
fn batches_pad_and_mask() {
    use lmac_learn::{Batch, InputLayout};
    let cfg = LearnConfig::default();
    let layout = InputLayout::new(DIMS, &cfg);
    let mut rng = LearnRng::seed_from(4);
    let a = random_episode(&mut rng, 2, true);
    let b = random_episode(&mut rng, 4, false);
    let batch = Batch::from_episodes(&[&a, &b], &DIMS, &layout);
    assert_eq!((batch.b, batch.t), (2, 4));
    // time-major [t, b]
    assert_eq!(batch.mask, vec![1., 1., 1., 1., 0., 1., 0., 0.]);
    assert_eq!(batch.terminated, vec![0., 0., 1., 0., 0., 0., 0., 0.]);
    assert_eq!(batch.has_next, vec![1., 1., 0., 1., 0., 1., 0., 0.]);
    // padded steps of episode a (t = 2, 3): every action available, zero inputs.
    let (n, na, iw) = (DIMS.n_agents, DIMS.n_actions, layout.width());
    for t in 2..4 {
        let row = (t * 2) * n; // b = 0
        assert!(batch.avail[row * na..(row + n) * na].iter().all(|&x| x == 1));
        assert!(batch.inputs[row * iw..(row + n) * iw].iter().all(|&x| x == 0.0));
    }
    // last-action one-hot at t = 1 of episode b (b = 1) is its action at t = 0.
    let off = DIMS.obs_width; // agent_sees_state is off: obs | last action | id
    for ag in 0..n {
        let row = (2 + 1) * n + ag;
        let one_hot = &batch.inputs[row * iw + off..row * iw + off + na];
        let act = b.actions[ag] as usize;
        assert_eq!(one_hot.iter().position(|&x| x == 1.0), Some(act));
        assert_eq!(batch.inputs[row * iw + off + na + ag], 1.0, "agent id one-hot");
    }

    // A masked transition (the truncated last step) does not change the loss.
    let cfg = LearnConfig { batch_size: 2, buffer_size: 2, ..LearnConfig::default() };
    let learner = Learner::new(DIMS, cfg, Device::default()).unwrap();
    let (l1, _) = learner.td_loss(&batch).unwrap();
    let mut b2 = b.clone();
    *b2.reward.last_mut().unwrap() += 1e6;
    let batch2 = Batch::from_episodes(&[&a, &b2], &DIMS, &layout);
    let (l2, _) = learner.td_loss(&batch2).unwrap();
    let (l1, l2): (f32, f32) = (l1.into_scalar(), l2.into_scalar());
    assert_eq!(l1, l2);
    // ... while an unmasked one does.
    let mut a2 = a.clone();
    a2.reward[1] += 1.0;
    let batch3 = Batch::from_episodes(&[&a2, &b], &DIMS, &layout);
    let l3: f32 = learner.td_loss(&batch3).unwrap().0.into_scalar();
    assert_ne!(l1, l3);
}

#[test]
fn parallel_target_gives_the_same_updates() {
    let mut losses = Vec::new();
    for parallel_target in [false, true] {
        let cfg = LearnConfig { batch_size: 4, buffer_size: 8, parallel_target, ..LearnConfig::default() };
        let mut learner = Learner::new(DIMS, cfg, Device::default()).unwrap();
        let mut rng = LearnRng::seed_from(8);
        for i in 0..8 {
            learner.add_episode(random_episode(&mut rng, 2 + i % 3, i % 2 == 0)).unwrap();
        }
        losses.push((0..3).map(|_| learner.train_step().unwrap().loss).collect::<Vec<_>>());
    }
    assert_eq!(losses[0], losses[1]);
}

/// `learn.data_parallel` (the batch's two halves on two threads, gradients summed) trains the
/// same network as the whole-batch update up to float summation order, for the plain agent on
/// every mixer and for LMAC (dropout off, so both draw nothing; with standardised rewards), its
/// consistency term masked or, as released, averaged over the padded steps too.
#[test]
fn data_parallel_updates_equal_whole_batch_updates() {
    use lmac_learn::methods::lmac::{LmacConfig, LmacSettings};
    use lmac_learn::AgentConfig;
    let lmac = |mask_consistency: bool| {
        let settings = LmacSettings { dropout: 0.0, standardise_rewards: true, mask_consistency, ..LmacSettings::default() };
        AgentConfig::Lmac(LmacConfig { settings, msg_cols: 2, alpha: 0.05, critical_dims: vec![0, 3, 6] })
    };
    let cases = [
        ("qmix", MixerKind::Qmix, AgentConfig::Rnn),
        ("vdn", MixerKind::Vdn, AgentConfig::Rnn),
        ("qplex", MixerKind::Qplex, AgentConfig::Rnn),
        ("lmac", MixerKind::Qmix, lmac(true)),
        ("lmac, consistency averaged over padding too", MixerKind::Qmix, lmac(false)),
    ];
    for (name, mixer, agent) in cases {
        let mut runs = Vec::new();
        for data_parallel in [false, true] {
            let cfg = LearnConfig {
                mixer,
                batch_size: 6,
                buffer_size: 12,
                seed: 4,
                qplex_num_kernel: 2,
                data_parallel,
                ..LearnConfig::default()
            };
            let mut learner = Learner::with_agent(DIMS, cfg, agent.clone(), Device::default()).unwrap();
            let mut rng = LearnRng::seed_from(9);
            for i in 0..12 {
                learner.add_episode(random_episode(&mut rng, 2 + i % 4, i % 3 == 0)).unwrap();
            }
            let stats: Vec<_> = (0..4).map(|_| learner.train_step().unwrap()).collect();
            runs.push((stats, q_values(&learner, 21)));
        }
        let close = |a: f32, b: f32| (a - b).abs() <= 1e-4 * (1.0 + a.abs().max(b.abs()));
        let ((whole, q_whole), (halves, q_halves)) = (&runs[0], &runs[1]);
        for (u, (w, h)) in whole.iter().zip(halves).enumerate() {
            for (what, a, b) in [
                ("loss", w.loss, h.loss),
                ("grad norm", w.grad_norm, h.grad_norm),
                ("td error", w.td_error_abs, h.td_error_abs),
                ("q taken", w.q_taken_mean, h.q_taken_mean),
                ("target", w.target_mean, h.target_mean),
            ] {
                assert!(close(a, b), "{name}, update {u}: {what} {a} whole vs {b} in halves");
            }
            for ((term, a), (_, b)) in w.method.iter().zip(&h.method) {
                assert!(close(*a, *b), "{name}, update {u}: {term} {a} whole vs {b} in halves");
            }
        }
        for (a, b) in q_whole.iter().zip(q_halves) {
            assert!(close(*a, *b), "{name}: Q-values after 4 updates {a} whole vs {b} in halves");
        }
    }
}

/// A learner whose `t_env` grows with every `step` call (one 3-step episode each), so each save
/// is told apart by its counters.
fn small_learner() -> (Learner, LearnRng) {
    let cfg = LearnConfig { batch_size: 2, buffer_size: 8, seed: 5, ..LearnConfig::default() };
    (Learner::new(DIMS, cfg, Device::default()).unwrap(), LearnRng::seed_from(17))
}

fn step(learner: &mut Learner, rng: &mut LearnRng) -> u64 {
    learner.add_episode(random_episode(rng, 3, true)).unwrap();
    learner.counters().t_env
}

/// The save is stopped (as a crash would stop it: nothing after the step is
/// done, nothing cleaned up) at every step, then the run resumes from what it finds and its next
/// save is stopped at every step again: all combinations. After both crashes a complete
/// checkpoint loads, never older than the one the second segment resumed from, and a resume
/// from it saves and loads again.
#[test]
fn two_crashes_at_any_steps_of_the_save_never_lose_the_checkpoint() {
    use lmac_learn::checkpoint::{checkpoint_exists, fault, locate};
    let base = std::env::temp_dir().join(format!("lmac-ckpt-crash-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&base);
    let mut stopped = std::collections::BTreeSet::new();
    for (i, &first) in fault::STEPS.iter().enumerate() {
        for (j, &second) in fault::STEPS.iter().enumerate() {
            let case = format!("crash at {first:?}, resume, crash at {second:?}");
            let parent = base.join(format!("{i}-{j}"));
            std::fs::create_dir_all(&parent).unwrap();
            let dir = parent.join("checkpoint");
            let (mut learner, mut rng) = small_learner();
            let t0 = step(&mut learner, &mut rng);
            learner.save_checkpoint(&dir, true).unwrap();
            let t1 = step(&mut learner, &mut rng);
            // A step that is not on this save's path (e.g. removing an `.old` there is none of)
            // lets the save complete.
            fault::stop_at(Some(first));
            if learner.save_checkpoint(&dir, true).is_err() {
                stopped.insert(first);
            }
            fault::stop_at(None);

            // The first resume: a complete checkpoint, the old one or the new one.
            assert!(
                checkpoint_exists(&dir),
                "{case}: {:?}",
                std::fs::read_dir(&parent).unwrap().flatten().map(|e| e.file_name()).collect::<Vec<_>>()
            );
            let mut resumed = Learner::load_checkpoint(&dir, Device::default()).unwrap_or_else(|e| panic!("{case}: first resume: {e}"));
            let r1 = resumed.counters().t_env;
            assert!(r1 == t0 || r1 == t1, "{case}: resumed at {r1}, saved {t0} and {t1}");
            let t2 = step(&mut resumed, &mut rng);
            fault::stop_at(Some(second));
            if resumed.save_checkpoint(&dir, true).is_err() {
                stopped.insert(second);
            }
            fault::stop_at(None);

            // The second resume.
            let where_ = locate(&dir).unwrap_or_else(|| panic!("{case}: no checkpoint survived"));
            let mut again = Learner::load_checkpoint(&dir, Device::default())
                .unwrap_or_else(|e| panic!("{case}: second resume from {}: {e}", where_.display()));
            let r2 = again.counters().t_env;
            assert!(r2 == r1 || r2 == t2, "{case}: resumed at {r2}, expected {r1} (the first resume's) or {t2} (the save stopped)");
            // And the run goes on: a save that completes is what the next resume reads.
            let t3 = step(&mut again, &mut rng);
            again.save_checkpoint(&dir, true).unwrap_or_else(|e| panic!("{case}: a full save after two crashes: {e}"));
            assert_eq!(Learner::load_checkpoint(&dir, Device::default()).unwrap().counters().t_env, t3, "{case}");
            let left: Vec<_> =
                std::fs::read_dir(&parent).unwrap().flatten().map(|e| e.file_name().to_string_lossy().into_owned()).collect();
            assert_eq!(left, ["checkpoint"], "{case}: a completed save leaves only the checkpoint");
            std::fs::remove_dir_all(&parent).unwrap();
        }
    }
    let never: Vec<_> = fault::STEPS.iter().filter(|s| !stopped.contains(*s)).collect();
    assert!(never.is_empty(), "every step of the save was crashed at in some case; never: {never:?}");
    let _ = std::fs::remove_dir_all(&base);
}

/// A checkpoint moved to `<dir>.tmp` (the end state of two crashes in the old protocol) is used
/// when its manifest verifies; one with a corrupt file is not, and loading a corrupt checkpoint
/// names the file.
#[test]
fn a_complete_tmp_is_used_and_a_corrupt_file_is_named() {
    use lmac_learn::checkpoint::{checkpoint_exists, locate};
    let parent = std::env::temp_dir().join(format!("lmac-ckpt-tmp-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&parent);
    std::fs::create_dir_all(&parent).unwrap();
    let dir = parent.join("checkpoint");
    let tmp = parent.join("checkpoint.tmp");
    let (mut learner, mut rng) = small_learner();
    let t = step(&mut learner, &mut rng);
    learner.save_checkpoint(&dir, true).unwrap();
    std::fs::rename(&dir, &tmp).unwrap();
    assert_eq!(locate(&dir), Some(tmp.clone()));
    assert_eq!(Learner::load_checkpoint(&dir, Device::default()).unwrap().counters().t_env, t);

    // Flipped bytes in the network: the manifest no longer matches, so `.tmp` is not complete.
    let net = tmp.join("net.bpk");
    let mut bytes = std::fs::read(&net).unwrap();
    let mid = bytes.len() / 2;
    for b in &mut bytes[mid..mid + 16] {
        *b ^= 0xff;
    }
    std::fs::write(&net, &bytes).unwrap();
    assert!(!checkpoint_exists(&dir), "a .tmp that fails its manifest is not a checkpoint");
    // As `<dir>` it is loaded, and the load names the corrupt file.
    std::fs::rename(&tmp, &dir).unwrap();
    let e = Learner::load_checkpoint(&dir, Device::default()).err().expect("a corrupt file is refused").to_string();
    assert!(e.contains("net.bpk") && e.contains("CRC-32C"), "{e}");
    std::fs::remove_dir_all(&parent).unwrap();
}

/// A checkpoint's `state.json` is bytes from outside. A checkpoint without a manifest
/// (written before manifests, so nothing checks its sums) whose counters say t_env = 2^64-1
/// would mark the run finished, and a 60000-wide GRU in its config would abort the process
/// building it: both are refused, naming the file and the field.
#[test]
fn state_json_out_of_range_is_refused_naming_the_field() {
    let parent = std::env::temp_dir().join(format!("lmac-ckpt-range-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&parent);
    std::fs::create_dir_all(&parent).unwrap();
    let dir = parent.join("checkpoint");
    let (mut learner, mut rng) = small_learner();
    step(&mut learner, &mut rng);
    learner.save_checkpoint(&dir, false).unwrap();
    std::fs::remove_file(dir.join("manifest.json")).unwrap();
    let state = dir.join("state.json");
    let mut original: serde_json::Value = serde_json::from_slice(&std::fs::read(&state).unwrap()).unwrap();
    // As a checkpoint of a build before manifests records it (today's, saved with one, is
    // refused without it).
    original["manifested"] = serde_json::json!(false);
    for (section, field, value) in
        [("counters", "t_env", serde_json::json!(u64::MAX)), ("config", "rnn_hidden_dim", serde_json::json!(60000))]
    {
        let mut v = original.clone();
        v[section][field] = value;
        std::fs::write(&state, serde_json::to_vec(&v).unwrap()).unwrap();
        let e = Learner::load_checkpoint(&dir, Device::default()).err().expect("refused").to_string();
        assert!(e.contains("state.json") && e.contains(field), "{field}: {e}");
    }
    std::fs::write(&state, serde_json::to_vec(&original).unwrap()).unwrap();
    assert!(Learner::load_checkpoint(&dir, Device::default()).is_ok(), "the untouched state loads");
    std::fs::remove_dir_all(&parent).unwrap();
}

/// A run directory one did not make (copied, untarred, shared) may hold planted links. A save
/// that finds `checkpoint.old` (or `.tmp`) as a symlink to someone's directory removes the link,
/// never the files it points to; a checkpoint without a manifest whose `net.bpk` links to
/// `/dev/zero` is refused at once instead of read until memory runs out.
#[test]
fn planted_links_in_a_checkpoint_are_neither_followed_nor_read_forever() {
    let parent = std::env::temp_dir().join(format!("lmac-ckpt-links-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&parent);
    let victim = parent.join("victim");
    std::fs::create_dir_all(&victim).unwrap();
    for f in ["manifest.json", "state.json", "keep.txt"] {
        std::fs::write(victim.join(f), b"not lmac's").unwrap();
    }
    let dir = parent.join("checkpoint");
    let (mut learner, mut rng) = small_learner();
    step(&mut learner, &mut rng);
    learner.save_checkpoint(&dir, false).unwrap();
    for planted in ["checkpoint.old", "checkpoint.tmp"] {
        std::os::unix::fs::symlink(&victim, parent.join(planted)).unwrap();
        step(&mut learner, &mut rng);
        learner.save_checkpoint(&dir, false).unwrap();
        for f in ["manifest.json", "state.json", "keep.txt"] {
            assert_eq!(std::fs::read(victim.join(f)).unwrap(), b"not lmac's", "{planted}: {f} was touched");
        }
    }
    // No manifest (a checkpoint of a build before manifests), net.bpk a link to a device:
    // refused naming the file.
    std::fs::remove_file(dir.join("manifest.json")).unwrap();
    let state = std::fs::read_to_string(dir.join("state.json")).unwrap();
    assert!(state.contains("\"manifested\": true"), "{state}");
    std::fs::write(dir.join("state.json"), state.replace("\"manifested\": true", "\"manifested\": false")).unwrap();
    std::fs::remove_file(dir.join("net.bpk")).unwrap();
    std::os::unix::fs::symlink("/dev/zero", dir.join("net.bpk")).unwrap();
    let e = Learner::load_checkpoint(&dir, Device::default()).err().expect("a device is refused").to_string();
    assert!(e.contains("net.bpk") && e.contains("not a regular file"), "{e}");
    std::fs::remove_dir_all(&parent).unwrap();
}

/// A checkpoint corrupted beside an intact `checkpoint.old` gives way to it; one whose manifest
/// was deleted (so its sums cannot be checked) is refused, not loaded with whatever bytes it has.
#[test]
fn a_corrupt_checkpoint_falls_back_to_old_and_a_missing_manifest_is_refused() {
    use lmac_learn::checkpoint::locate;
    let parent = std::env::temp_dir().join(format!("lmac-ckpt-fallback-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&parent);
    std::fs::create_dir_all(&parent).unwrap();
    let dir = parent.join("checkpoint");
    let old = parent.join("checkpoint.old");
    let (mut learner, mut rng) = small_learner();
    let t_old = step(&mut learner, &mut rng);
    learner.save_checkpoint(&dir, false).unwrap();
    copy_dir(&dir, &parent.join("first"));
    step(&mut learner, &mut rng);
    learner.save_checkpoint(&dir, false).unwrap();
    copy_dir(&dir, &old.with_extension("keep"));
    // A save removes `.old` once the new checkpoint is in place: put the first one back there.
    std::fs::rename(parent.join("first"), &old).unwrap();
    let net = dir.join("net.bpk");
    let mut bytes = std::fs::read(&net).unwrap();
    let mid = bytes.len() / 2;
    bytes[mid] ^= 0xff;
    std::fs::write(&net, &bytes).unwrap();
    assert_eq!(locate(&dir), Some(old.clone()));
    assert_eq!(Learner::load_checkpoint(&dir, Device::default()).unwrap().counters().t_env, t_old);
    // The intact newer checkpoint without its manifest: refused, naming the missing file.
    std::fs::remove_dir_all(&dir).unwrap();
    std::fs::remove_dir_all(&old).unwrap();
    std::fs::rename(old.with_extension("keep"), &dir).unwrap();
    std::fs::remove_file(dir.join("manifest.json")).unwrap();
    let e = Learner::load_checkpoint(&dir, Device::default()).err().expect("refused").to_string();
    assert!(e.contains("manifest.json") && e.contains("missing"), "{e}");
    std::fs::remove_dir_all(&parent).unwrap();
}

fn copy_dir(from: &std::path::Path, to: &std::path::Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap().flatten() {
        std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
    }
}
