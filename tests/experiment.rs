//! `lmac experiment` end to end with tiny budgets: a real offline design, LMAC and QMIX trained
//! through the pipeline, interrupted with SIGINT during LMAC's run, rerun with the same command:
//! the design is reused, the interrupted run resumes from its checkpoint, and the comparison
//! table, CSV, JSON and curves are written.

use lmac_e2e::harness::{lmac, wait_for};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::Duration;

fn experiment(out: &Path) -> Command {
    let mut c = lmac();
    c.args(["experiment", "--env", "lbf:8x8-2p-2f-s1-coop", "--seeds", "0", "--steps", "12000", "--algos", "lmac,qmix"])
        .args(["--design-steps", "3000", "--dataset-episodes", "60", "--disc-updates", "50"])
        .args(["--set", "run.envs=8", "--set", "run.servers=1", "--set", "run.test_interval=2000", "--set", "run.test_episodes=4"])
        .args(["--set", "run.checkpoint_interval=2000", "--set", "run.log_interval=1000"])
        .arg("--out")
        .arg(out)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    c
}

#[test]
fn an_experiment_designs_trains_resumes_after_an_interruption_and_writes_its_table() {
    let out = std::env::temp_dir().join(format!("lmac-experiment-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let child = experiment(&out).spawn().unwrap();
    // Interrupt once LMAC's run has written a checkpoint.
    let lmac_run = out.join("runs/lmac/seed0");
    let ck = wait_for(Duration::from_secs(240), || lmac_run.join("checkpoint/state.json").exists().then_some(()));
    assert!(ck.is_some(), "LMAC's run wrote a checkpoint");
    unsafe { libc::kill(child.id() as i32, libc::SIGINT) };
    let first = child.wait_with_output().unwrap();
    assert!(!first.status.success(), "the interrupted experiment reports failure");
    assert!(!out.join("comparison.md").exists(), "no table from an interrupted experiment");

    let second = experiment(&out).output().unwrap();
    let err = String::from_utf8_lossy(&second.stderr);
    assert!(second.status.success(), "the rerun finishes: {err}");
    assert!(err.contains("reusing the design"), "{err}");
    assert!(err.contains("resuming from"), "the interrupted run resumed: {err}");
    let table = std::fs::read_to_string(out.join("comparison.md")).unwrap();
    assert!(table.contains("| lmac | 1 |") && table.contains("| qmix | 1 |"), "{table}");
    // Each row's return carries its seeds' own values beside the mean and the sample SD.
    let row = table.lines().find(|l| l.starts_with("| qmix | 1 |")).unwrap();
    let cell = row.split(" | ").nth(2).unwrap();
    assert!(cell.contains(" +- 0.000 (") && cell.ends_with(')'), "one seed: SD 0 and its value: {row}");
    // Every row says the schedule it was trained with (here lmac train's default).
    assert_eq!(table.matches("| 1 update per episode, batch 32, target copy every 200 episodes |").count(), 2, "{table}");
    let json: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("comparison.json")).unwrap()).unwrap();
    assert_eq!(json["rows"].as_array().unwrap().len(), 2);
    assert!(out.join("comparison.csv").exists() && out.join("curves.png").exists());
    // LMAC's metrics carry its module's terms, and its curve never steps backwards.
    let csv = std::fs::read_to_string(lmac_run.join("metrics.csv")).unwrap();
    assert!(csv.lines().next().unwrap().ends_with("lmac_recon_mse,lmac_meta_bce,lmac_cons,lmac_recovered,lmac_reliability,lmac_z_sq"));
    let t: Vec<u64> = csv.lines().skip(1).map(|l| l.split(',').next().unwrap().parse().unwrap()).collect();
    assert!(t.windows(2).all(|w| w[0] <= w[1]) && *t.last().unwrap() >= 12_000, "{t:?}");
    // A third run finds everything done and writes the same table.
    let third = experiment(&out).output().unwrap();
    assert!(third.status.success() && String::from_utf8_lossy(&third.stderr).contains("already finished"));
    let _ = std::fs::remove_dir_all(&out);
}

/// `--algos ''` trains only the extra rows (here one --variant), and an experiment with no row
/// at all is refused before anything is created.
#[test]
fn an_empty_algo_list_trains_only_the_variant_rows() {
    let out = std::env::temp_dir().join(format!("lmac-experiment-variant-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let run = |extra: &[&str]| {
        let mut c = lmac();
        c.args(["experiment", "--env", "lbf:8x8-2p-2f-s1-coop", "--seeds", "0", "--steps", "2000", "--algos", ""])
            .args(extra)
            .args(["--set", "run.envs=8", "--set", "run.servers=1", "--set", "run.test_interval=1000", "--set", "run.test_episodes=2"])
            .arg("--out")
            .arg(&out)
            .stdin(Stdio::null());
        c.output().unwrap()
    };
    let none = run(&[]);
    assert!(!none.status.success());
    assert!(String::from_utf8_lossy(&none.stderr).contains("nothing to train"), "{}", String::from_utf8_lossy(&none.stderr));
    assert!(!out.exists(), "a refused experiment created {}", out.display());
    let only = run(&["--variant", "qmix-lr=qmix,learn.lr=0.001"]);
    assert!(only.status.success(), "{}", String::from_utf8_lossy(&only.stderr));
    let rows: Vec<String> =
        std::fs::read_dir(out.join("runs")).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    assert_eq!(rows, vec!["qmix-lr".to_string()]);
    let cfg = std::fs::read_to_string(out.join("runs/qmix-lr/seed0/config.toml")).unwrap();
    assert!(cfg.contains("lr = 0.001"), "{cfg}");
    let _ = std::fs::remove_dir_all(&out);
}

/// `lmac design --collect-with qmix` collects the dataset B with QMIX's policy (the paper's;
/// the default is QMIX+State's), the dataset and the design's options say so, and a method name
/// it does not know is refused before anything is trained.
#[test]
fn a_design_collects_its_dataset_with_the_method_asked_for() {
    let out = std::env::temp_dir().join(format!("lmac-design-collect-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let design = |algo: &str| {
        let mut c = lmac();
        c.args(["design", "--env", "lbf:8x8-2p-2f-s1-coop", "--collect-with", algo, "--pretrain-steps", "2000"])
            .args(["--dataset-episodes", "40", "--disc-updates", "50", "--phases", "1", "--envs", "8", "--servers", "1"])
            .arg("--out")
            .arg(&out)
            .stdin(Stdio::null());
        c.output().unwrap()
    };
    let bad = design("qmix-sate");
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(!bad.status.success() && err.contains("qmix-sate"), "{err}");
    assert!(!err.contains("collecting the dataset: qmix-sate for"), "nothing is trained for an unknown method: {err}");

    let ok = design("qmix");
    assert!(ok.status.success(), "{}", String::from_utf8_lossy(&ok.stderr));
    let dir = std::fs::read_dir(out.join("lbf_8x8-2p-2f-s1-coop"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.join("phase0/protocol.json").exists())
        .expect("a finished design");
    let options: serde_json::Value = serde_json::from_slice(&std::fs::read(dir.join("options.json")).unwrap()).unwrap();
    assert_eq!(options["collect_algo"], "qmix");
    let header: serde_json::Value = serde_json::from_slice(&std::fs::read(dir.join("collect/dataset/header.json")).unwrap()).unwrap();
    assert!(header["policy"].as_str().unwrap().starts_with("qmix (qmix mixer) after "), "{header}");
    let _ = std::fs::remove_dir_all(&out);
}
