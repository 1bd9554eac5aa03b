//! Speed work must not change results: every registered method, from a fixed seed on fixed
//! synthetic episodes, makes three updates whose losses and logged terms equal the values
//! recorded in `tests/data/golden_losses.json` (to float tolerance). The file was written by the
//! code before the learner's speed work (`LMAC_WRITE_GOLDEN=1 cargo test --release --test
//! golden_losses` writes it anew; do that only for a change that is meant to alter results, and
//! say so in the commit).
//!
//! LMAC runs with the settings of that code (`aux_layout = "compact"`,
//! `consistency_over_latent = "sum"`, raw rewards) so the comparison isolates the speed work
//! from the fidelity changes, which have their own tests.

use lmac_learn::episode::{Episode, EpisodeDims};
use lmac_learn::methods::{MethodContext, REGISTRY};
use lmac_learn::{Device, LearnConfig, LearnRng, Learner};
use std::collections::BTreeMap;

const DIMS: EpisodeDims = EpisodeDims { n_agents: 3, obs_width: 10, state_dim: 7, n_actions: 5 };
const MSG_COLS: usize = 4;
const UPDATES: usize = 3;

/// The settings each method runs with beyond its defaults (see the file's header).
fn settings(method: &str) -> toml::Table {
    let text = match method {
        "lmac" => "aux_layout = \"compact\"\nconsistency_over_latent = \"sum\"\nstandardise_rewards = false",
        _ => "",
    };
    toml::from_str(text).expect("settings parse")
}

/// name -> the loss and every logged term of each update.
fn measure() -> BTreeMap<String, Vec<Vec<(String, f64)>>> {
    let ctx = MethodContext { msg_cols: MSG_COLS, alpha: 0.1, critical_dims: vec![1, 3, 4], state_dim: DIMS.state_dim };
    let mut out = BTreeMap::new();
    for spec in REGISTRY {
        let agent = (spec.configure)(&settings(spec.name), &ctx).unwrap_or_else(|e| panic!("{}: {e}", spec.name));
        // The whole batch on one thread, as recorded: the default's two-thread split draws each
        // half's dropout separately (`data_parallel_updates_equal_whole_batch_updates` checks
        // the split against this update where no dropout is drawn).
        let mut learn = LearnConfig {
            batch_size: 4,
            buffer_size: 16,
            seed: 11,
            qplex_num_kernel: 2,
            data_parallel: false,
            parallel_target: false,
            ..LearnConfig::default()
        };
        if let Some(m) = spec.mixer {
            learn.mixer = m;
        }
        learn.agent_sees_state = spec.agent_sees_state;
        let mut learner = Learner::with_agent(DIMS, learn, agent, Device::default()).expect("learner");
        let mut rng = LearnRng::seed_from(23);
        // Episodes of unequal lengths, some terminated, so padding and masks are exercised.
        for i in 0..6 {
            let ep = Episode::synthetic(&DIMS, 4 + (i % 3) * 2, &mut rng, i % 2 == 0);
            learner.add_episode(ep).expect("episode");
        }
        let mut updates = Vec::new();
        for _ in 0..UPDATES {
            let s = learner.train_step().unwrap_or_else(|e| panic!("{}: {e}", spec.name));
            let mut terms = vec![("loss".to_string(), s.loss as f64), ("grad_norm".to_string(), s.grad_norm as f64)];
            terms.extend(s.method.iter().map(|(k, v)| (k.to_string(), *v as f64)));
            updates.push(terms);
        }
        out.insert(spec.name.to_string(), updates);
    }
    out
}

#[test]
fn every_method_makes_the_recorded_updates() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data/golden_losses.json");
    let got = measure();
    if std::env::var_os("LMAC_WRITE_GOLDEN").is_some() {
        std::fs::create_dir_all(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data")).unwrap();
        std::fs::write(path, serde_json::to_string_pretty(&got).unwrap()).unwrap();
        return;
    }
    let want: BTreeMap<String, Vec<Vec<(String, f64)>>> =
        serde_json::from_slice(&std::fs::read(path).expect("golden file")).expect("golden file parses");
    let mut problems = Vec::new();
    for spec in REGISTRY {
        let (Some(w), Some(g)) = (want.get(spec.name), got.get(spec.name)) else {
            problems.push(format!("{}: no recorded updates (a new method: record its values on purpose)", spec.name));
            continue;
        };
        for (u, (wu, gu)) in w.iter().zip(g).enumerate() {
            assert_eq!(wu.len(), gu.len(), "{} update {u}: terms {wu:?} vs {gu:?}", spec.name);
            for ((wk, wv), (gk, gv)) in wu.iter().zip(gu) {
                assert_eq!(wk, gk, "{} update {u}: term names", spec.name);
                // Relative tolerance: sums reordered by faster kernels differ in the last bits,
                // and three updates compound them a little.
                let tol = 1e-4 * wv.abs().max(1e-2);
                if (wv - gv).abs() > tol || !gv.is_finite() {
                    problems.push(format!("{} update {u} {wk}: recorded {wv}, now {gv}", spec.name));
                }
            }
        }
    }
    assert!(problems.is_empty(), "updates changed:\n{}", problems.join("\n"));
}
