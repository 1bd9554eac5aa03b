//! `lmac evaluate` end to end: NDQ trained for a few thousand steps through the pipeline (the run
//! ends with a final evaluation of its best checkpoint, in marl-eval's shape), then its
//! checkpoint evaluated greedily at two message cuts; a change that would need other weights is
//! refused (naming what differs) and the checkpoint is left as it was; a finished run whose
//! final evaluation cannot run is reported without failing the command.

use lmac_e2e::harness::lmac;

#[test]
fn a_trained_run_is_evaluated_at_each_message_cut_and_a_shape_change_is_refused() {
    let out = std::env::temp_dir().join(format!("lmac-evaluate-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let train = lmac()
        .args(["train", "--env", "lbf:8x8-2p-2f-s1-coop", "--algo", "ndq", "--steps", "3000", "--seeds", "0"])
        .args(["--set", "run.envs=8", "--set", "run.servers=1", "--set", "run.test_interval=1000", "--set", "run.test_episodes=4"])
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(train.status.success(), "{}", String::from_utf8_lossy(&train.stderr));
    let group = std::fs::read_dir(out.join("lbf_8x8-2p-2f-s1-coop/ndq")).unwrap().flatten().next().unwrap().path();
    // The run ended with a final evaluation of its best test phase's checkpoint (10 x 4 episodes),
    // written with its test phases in marl-eval's shape.
    let seed = group.join("seed0");
    assert!(seed.join("checkpoint_best/state.json").exists() && seed.join("best_test.json").exists());
    let me: serde_json::Value = serde_json::from_slice(&std::fs::read(seed.join("marl_eval.json")).unwrap()).unwrap();
    let runs = &me["lbf"]["8x8-2p-2f-s1-coop"]["ndq"]["seed_0"];
    assert_eq!(runs["absolute_metrics"]["return"].as_array().unwrap().len(), 40, "{me}");
    assert_eq!(runs["absolute_metrics_source"]["checkpoint"], "best");
    assert_eq!(runs["step_0"]["step_count"], 0);
    assert!(runs["step_3"]["step_count"].as_u64().unwrap() >= 3000, "test phases at 0, 1000, 2000 and the end: {me}");
    let json = out.join("eval.json");
    let eval =
        lmac().arg("evaluate").arg(&group).args(["--episodes", "6", "--set", "method.cut=0,100", "--json"]).arg(&json).output().unwrap();
    let stdout = String::from_utf8_lossy(&eval.stdout);
    assert!(eval.status.success(), "{}", String::from_utf8_lossy(&eval.stderr));
    assert!(stdout.contains("cut = 0:") && stdout.contains("cut = 100:"), "{stdout}");
    let results: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    let rows = results.as_array().unwrap();
    assert_eq!(rows.len(), 2);
    for (row, cut) in rows.iter().zip([0, 100]) {
        assert_eq!(row["method"]["cut"], cut);
        assert_eq!(row["episodes"], 6);
        assert_eq!(row["returns"].as_array().unwrap().len(), 6);
        assert!(row["t_env"].as_u64().unwrap() >= 3000 && row["algo"] == "ndq");
    }
    // Each evaluation is kept with the run.
    let kept = std::fs::read_dir(group.join("seed0/evaluations")).unwrap().count();
    assert_eq!(kept, 6, "the final evaluation's and two more specs and results");

    // The message width is part of the weights: refused, checkpoint untouched.
    let ck = group.join("seed0/checkpoint/state.json");
    let before = std::fs::read(&ck).unwrap();
    let bad = lmac().arg("evaluate").arg(&group).args(["--episodes", "2", "--set", "method.msg_dim=2"]).output().unwrap();
    assert!(!bad.status.success());
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(err.contains("only test-time settings can change") && err.contains("method.cut"), "{err}");
    assert!(err.contains("msg_dim: 3 -> 2"), "the error names what differs: {err}");
    assert_eq!(std::fs::read(&ck).unwrap(), before);

    // A finished run whose config now describes another network (a protocol or setting changed
    // since it trained): rerunning it is refused before anything starts, naming the change, and
    // touches nothing (marl_eval.json stays unwritten for a rerun with the run's own settings).
    let seed_dir = group.join("seed0");
    let config = seed_dir.join("config.toml");
    // The saved config states every method setting (msg_dim = 3 among them): edit it in place.
    let mut doc: toml::Table = toml::from_str(&std::fs::read_to_string(&config).unwrap()).unwrap();
    let method = doc.get_mut("method").and_then(toml::Value::as_table_mut).expect("config.toml states the method's settings");
    assert_eq!(method.get("msg_dim").and_then(toml::Value::as_integer), Some(3), "the default is written out");
    method.insert("msg_dim".into(), toml::Value::Integer(2));
    std::fs::write(&config, toml::to_string_pretty(&doc).unwrap()).unwrap();
    std::fs::remove_file(seed_dir.join("marl_eval.json")).unwrap();
    let metrics_before = std::fs::read(seed_dir.join("metrics.csv")).unwrap();
    let rerun = lmac().args(["train", "--resume"]).arg(&seed_dir).output().unwrap();
    let err = String::from_utf8_lossy(&rerun.stderr);
    assert!(!rerun.status.success(), "{err}");
    assert!(err.contains("differs from the configuration its checkpoint") && err.contains("method.msg_dim: 3 -> 2"), "{err}");
    assert!(!seed_dir.join("marl_eval.json").exists());
    assert_eq!(std::fs::read(&ck).unwrap(), before);
    assert_eq!(std::fs::read(seed_dir.join("metrics.csv")).unwrap(), metrics_before);
    let _ = std::fs::remove_dir_all(&out);
}
