//! Long runs you can trust: a real `lmac train` through the pipeline, stopped with SIGINT or by
//! a SIGKILL of its trainer child, resumed with `lmac train --resume`, reaching its step target
//! with metrics that continue without a step backwards and with no shared memory left behind.
//! Runs the release `lmac` binary built by `scripts/setup.sh` (or `$LMAC_BIN`).

use lmac_benches::faults::{metrics_t_env, pipeline_children, Role};
use lmac_e2e::harness::{lmac, lmac_shm_files, wait_for};
use std::path::{Path, PathBuf};
use std::process::{Child, Stdio};
use std::sync::Mutex;
use std::time::Duration;

/// The tests watch /dev/shm and share the two cores; one at a time.
static SERIAL: Mutex<()> = Mutex::new(());

const STEPS: u64 = 40_000;

/// The lmac slabs in /dev/shm that were not there at `before` (other runs on the machine,
/// started before the test, keep theirs).
fn new_shm_files(before: &[String]) -> Vec<String> {
    lmac_shm_files().into_iter().filter(|f| !before.contains(f)).collect()
}

/// Start a small QMIX run on LBF 8x8 (one env server of 8 envs, checkpoints every 5k steps).
fn start_training(out: &Path, save_buffer: bool) -> Child {
    lmac()
        .args(["train", "--env", "lbf:8x8-2p-2f-s1-coop", "--algo", "qmix", "--steps", &STEPS.to_string()])
        .args(["--set", "run.envs=8", "--set", "run.servers=1", "--set", "run.checkpoint_interval=5000"])
        .args(["--set", "run.log_interval=1000", "--set", "run.test_interval=10000", "--set", "run.test_episodes=8"])
        .args(["--set", &format!("run.save_buffer={save_buffer}")])
        .arg("--out")
        .arg(out)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap()
}

fn seed_dir(out: &Path) -> PathBuf {
    let group = wait_for(Duration::from_secs(30), || {
        let env = std::fs::read_dir(out.join("lbf_8x8-2p-2f-s1-coop/qmix")).ok()?;
        env.flatten().map(|e| e.path()).next()
    })
    .expect("the run directory appears");
    group.join("seed0")
}

/// (t_env, checkpoint path) of every checkpoint row in metrics.jsonl.
fn checkpoint_rows(dir: &Path) -> Vec<(u64, String)> {
    std::fs::read_to_string(dir.join("metrics.jsonl"))
        .unwrap_or_default()
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .filter_map(|v| Some((v["t_env"].as_u64()?, v["checkpoint"].as_str()?.to_string())))
        .collect()
}

/// Wait until the run has written a checkpoint and logged some rows past it.
fn wait_past_first_checkpoint(dir: &Path) {
    wait_for(Duration::from_secs(120), || {
        let ck = checkpoint_rows(dir);
        let rows = metrics_t_env(dir);
        (!ck.is_empty() && rows.last().is_some_and(|&t| t > ck[0].0 + 2000)).then_some(())
    })
    .expect("a checkpoint and rows after it within 120 s");
}

fn finish(child: Child) -> (bool, String) {
    let out = child.wait_with_output().unwrap();
    (out.status.success(), String::from_utf8_lossy(&out.stderr).replace('\r', "\n"))
}

/// Resume the group and check it reaches the target with continuous metrics.
fn resume_and_check(dir: &Path, stop_kind: &str, save_buffer: bool, shm_before: &[String]) {
    let before = checkpoint_rows(dir);
    let resumed_from = before.last().expect("a checkpoint before the stop").0;
    let out = lmac().arg("train").arg("--resume").arg(dir.parent().unwrap()).output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr).replace('\r', "\n");
    assert!(out.status.success(), "resume after {stop_kind} failed: {stderr}");
    assert!(stderr.contains(&format!("resuming from {}", dir.join("checkpoint").display())), "{stderr}");
    if save_buffer {
        assert!(stderr.contains("with its replay buffer ("), "the run says it has its buffer: {stderr}");
    } else {
        assert!(stderr.contains("refills it with 32 episodes"), "the run says the buffer is refilled: {stderr}");
    }
    // Off a terminal (stderr is a pipe here) each test phase prints a progress line.
    assert!(
        stderr.contains("lmac: seed 0: t_env ") && stderr.contains(&format!("/{STEPS} (100%)")) && stderr.contains("test return"),
        "a progress line at the final test phase: {stderr}"
    );
    let t = metrics_t_env(dir);
    assert!(t.windows(2).all(|w| w[0] <= w[1]), "metrics.csv t_env steps backwards after {stop_kind}: {t:?}");
    assert!(*t.last().unwrap() >= STEPS, "the resumed run reaches {STEPS} env steps: {t:?}");
    assert!(t.iter().any(|&x| x > resumed_from), "rows after the resume point");
    let json_t: Vec<u64> = std::fs::read_to_string(dir.join("metrics.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).expect("every metrics.jsonl line is JSON")["t_env"].as_u64().unwrap())
        .collect();
    assert!(json_t.windows(2).all(|w| w[0] <= w[1]), "metrics.jsonl t_env steps backwards after {stop_kind}: {json_t:?}");
    let after = checkpoint_rows(dir);
    assert!(after.last().unwrap().0 >= STEPS, "a final checkpoint at the target: {after:?}");
    assert!(new_shm_files(shm_before).is_empty(), "shared memory left behind: {:?}", new_shm_files(shm_before));
    // A finished run is not trained again.
    let again = lmac().arg("train").arg("--resume").arg(dir).output().unwrap();
    assert!(again.status.success());
    assert!(String::from_utf8_lossy(&again.stderr).contains("already finished"), "{}", String::from_utf8_lossy(&again.stderr));
}

#[test]
fn a_run_interrupted_with_sigint_resumes_to_its_target() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let shm_before = lmac_shm_files();
    let out = std::env::temp_dir().join(format!("lmac-resume-int-{}", std::process::id()));
    let child = start_training(&out, false);
    let dir = seed_dir(&out);
    wait_past_first_checkpoint(&dir);
    // A second lmac on the same run is refused while the first runs.
    let second = lmac().arg("train").arg("--resume").arg(&dir).output().unwrap();
    let text = String::from_utf8_lossy(&second.stderr);
    assert!(!second.status.success() && text.contains("being trained by another lmac"), "{text}");
    unsafe { libc::kill(child.id() as i32, libc::SIGINT) };
    let (ok, stderr) = finish(child);
    assert!(!ok, "an interrupted run exits non-zero");
    assert!(stderr.contains("interrupted"), "{stderr}");
    // Asked to stop, the trainer writes a last checkpoint at the step it reached.
    let ck = checkpoint_rows(&dir);
    let last_row = *metrics_t_env(&dir).last().unwrap();
    assert!(ck.last().unwrap().0 >= last_row, "a last checkpoint on SIGINT: {ck:?}, last row at {last_row}");
    resume_and_check(&dir, "SIGINT", false, &shm_before);
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn a_run_whose_trainer_is_killed_resumes_from_its_last_checkpoint() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let shm_before = lmac_shm_files();
    let out = std::env::temp_dir().join(format!("lmac-resume-kill-{}", std::process::id()));
    // With the replay buffer in its checkpoints: the resume samples from the same data.
    let child = start_training(&out, true);
    let dir = seed_dir(&out);
    wait_past_first_checkpoint(&dir);
    let trainer = pipeline_children(child.id() as i32).into_iter().find(|p| p.role == Role::Trainer).expect("the trainer child");
    unsafe { libc::kill(trainer.pid, libc::SIGKILL) };
    let (ok, stderr) = finish(child);
    assert!(!ok);
    assert!(stderr.contains("trainer") && stderr.contains("SIGKILL"), "the parent names the dead child: {stderr}");
    assert!(new_shm_files(&shm_before).is_empty(), "shared memory left behind after SIGKILL: {:?}", new_shm_files(&shm_before));
    let ck = checkpoint_rows(&dir).last().unwrap().0;
    assert!(metrics_t_env(&dir).last().unwrap() > &ck, "rows were logged after the last checkpoint (they must be dropped)");
    resume_and_check(&dir, "SIGKILL of the trainer", true, &shm_before);
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn chaos_kills_every_kind_of_process_and_every_resume_continues() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let shm_before = lmac_shm_files();
    let report = std::env::temp_dir().join(format!("lmac-chaos-{}.json", std::process::id()));
    let out = lmac()
        .args(["chaos", "--kills", "4", "--kill-after", "3,6", "--checkpoint-interval", "3000", "--seed", "7", "--report"])
        .arg(&report)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let r: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&report).expect("the chaos report")).unwrap();
    let _ = std::fs::remove_file(&report);
    assert!(out.status.success(), "lmac chaos found a fault: {stdout}\n{}", String::from_utf8_lossy(&out.stderr));
    assert_eq!(r["kills"], 4);
    assert_eq!(r["undetected"], 0, "every death is noticed: {r}");
    assert_eq!(r["resumes_continued"], 4, "{r}");
    assert_eq!(r["checkpoint_load_failures"], 0, "{r}");
    assert_eq!(r["shm_files_left"], 0, "{r}");
    assert_eq!(r["metrics_monotone"], true);
    for k in r["runs"].as_array().unwrap() {
        let lost = k["steps_lost"].as_u64().expect("every kill's loss is measured");
        assert!(lost <= 2 * 3000, "a crash costs at most about one checkpoint interval: {k}");
    }
    assert!(new_shm_files(&shm_before).is_empty(), "{:?}", new_shm_files(&shm_before));
}

/// Kills inside the checkpoint save (the trainer aborts at a step of the save
/// protocol) and in the start-up window of a resume, besides kills of a running pipeline.
#[test]
fn chaos_kills_inside_the_save_and_at_start_up_and_every_resume_continues() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let shm_before = lmac_shm_files();
    let report = std::env::temp_dir().join(format!("lmac-chaos-modes-{}.json", std::process::id()));
    let out = lmac()
        .args(["chaos", "--mode", "all", "--kills", "6", "--kill-after", "3,5", "--checkpoint-interval", "3000", "--seed", "3"])
        .arg("--report")
        .arg(&report)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let Ok(text) = std::fs::read_to_string(&report) else {
        panic!("no chaos report: {stdout}\n{}", String::from_utf8_lossy(&out.stderr));
    };
    let r: serde_json::Value = serde_json::from_str(&text).unwrap();
    let _ = std::fs::remove_file(&report);
    assert!(out.status.success(), "lmac chaos found a fault: {stdout}\n{}", String::from_utf8_lossy(&out.stderr));
    let modes: Vec<&str> = r["runs"].as_array().unwrap().iter().map(|k| k["mode"].as_str().unwrap()).collect();
    assert_eq!(modes, ["running", "save", "startup", "running", "save", "startup"]);
    for k in r["runs"].as_array().unwrap() {
        if k["mode"] == "save" {
            assert!(k["save_step"].is_string() && k["victim"] == "trainer", "the trainer aborted inside its save: {k}");
        }
        assert_eq!(k["resume_continued"], true, "{k}");
        assert!(k["steps_lost"].as_u64().expect("measured") <= 2 * 3000, "{k}");
    }
    assert_eq!(r["undetected"], 0, "{r}");
    assert_eq!(r["checkpoint_load_failures"], 0, "{r}");
    assert_eq!(r["shm_files_left"], 0, "{r}");
    assert_eq!(r["metrics_monotone"], true);
    assert!(new_shm_files(&shm_before).is_empty(), "{:?}", new_shm_files(&shm_before));
}

#[test]
fn a_checkpoint_that_cannot_be_written_ends_the_run_naming_the_file() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let shm_before = lmac_shm_files();
    let out = std::env::temp_dir().join(format!("lmac-ck-fail-{}", std::process::id()));
    let child = start_training(&out, false);
    let dir = seed_dir(&out);
    // A file where the checkpoint writer stages its directory: the write must fail.
    std::fs::write(dir.join("checkpoint.tmp"), b"in the way").unwrap();
    let (ok, stderr) = finish(child);
    assert!(!ok, "the run must not go on without checkpoints");
    assert!(stderr.contains("writing the checkpoint failed") && stderr.contains("checkpoint.tmp"), "{stderr}");
    assert!(new_shm_files(&shm_before).is_empty(), "{:?}", new_shm_files(&shm_before));
    let _ = std::fs::remove_dir_all(&out);
}

/// A short QMIX run on LBF 8x8 to `steps`, checkpoints every 2000 steps, no test phases (so only
/// the run's own checkpoint is saved), with `env` set for the lmac process and its children.
fn short_training(out: &Path, steps: u64, set: &[&str], env: &[(&str, &str)]) -> std::process::Command {
    let mut c = lmac();
    c.args(["train", "--env", "lbf:8x8-2p-2f-s1-coop", "--algo", "qmix", "--steps", &steps.to_string()])
        .args(["--set", "run.envs=8", "--set", "run.servers=1", "--set", "run.checkpoint_interval=2000"])
        .args(["--set", "run.log_interval=500", "--set", "run.test_episodes=0", "--set", "run.final_eval_episodes=0"]);
    for s in set {
        c.args(["--set", s]);
    }
    c.arg("--out").arg(out).stdin(Stdio::null());
    for (k, v) in env {
        c.env(k, v);
    }
    c
}

/// The trainer aborts inside the save of its
/// second checkpoint just after `checkpoint` became `checkpoint.old` (the window of the issue),
/// the resume aborts in its first save at the same step, and the next resume still continues
/// from the complete checkpoint (t_env 2000), not from 0, and reaches the target.
#[test]
fn two_crashes_inside_checkpoint_saves_resume_from_the_surviving_checkpoint() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let out = std::env::temp_dir().join(format!("lmac-ck-double-crash-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let first = short_training(&out, 6000, &[], &[("LMAC_FAULT_CHECKPOINT", "moved-dir-to-old@2")]).output().unwrap();
    let stderr = String::from_utf8_lossy(&first.stderr);
    assert!(!first.status.success() && stderr.contains("aborting inside the checkpoint save"), "{stderr}");
    let dir = seed_dir(&out);
    assert!(dir.join("checkpoint.old").is_dir() && dir.join("checkpoint.tmp").is_dir() && !dir.join("checkpoint").exists());
    let second = lmac().arg("train").arg("--resume").arg(&dir).env("LMAC_FAULT_CHECKPOINT", "moved-dir-to-old").output().unwrap();
    let stderr = String::from_utf8_lossy(&second.stderr).replace('\r', "\n");
    assert!(!second.status.success() && stderr.contains("aborting inside the checkpoint save"), "{stderr}");
    assert!(stderr.contains("at t_env 2000"), "the first resume continues from the first checkpoint: {stderr}");
    let third = lmac().arg("train").arg("--resume").arg(&dir).output().unwrap();
    let stderr = String::from_utf8_lossy(&third.stderr).replace('\r', "\n");
    assert!(third.status.success(), "{stderr}");
    assert!(
        stderr.contains("at t_env 2000") && !stderr.contains("at t_env 0 "),
        "the second resume continues from the checkpoint: {stderr}"
    );
    let t = metrics_t_env(&dir);
    assert!(t.first().is_some_and(|&f| f <= 2000) && t.windows(2).all(|w| w[0] <= w[1]) && *t.last().unwrap() >= 6000, "{t:?}");
    assert!(dir.join("checkpoint").is_dir() && !dir.join("checkpoint.old").exists() && !dir.join("checkpoint.tmp").exists());
    let _ = std::fs::remove_dir_all(&out);
}

/// A finished run whose checkpoint is only `checkpoint.tmp`
/// (complete: its manifest verifies) is still finished, not trained again from t_env 0; with no
/// usable checkpoint at all, a resume refuses instead of dropping the metrics.
#[test]
fn a_checkpoint_left_as_tmp_is_not_a_restart_and_no_checkpoint_refuses() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let out = std::env::temp_dir().join(format!("lmac-ck-tmp-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let run = short_training(&out, 2000, &[], &[]).output().unwrap();
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let dir = seed_dir(&out);
    let rows = std::fs::read_to_string(dir.join("metrics.csv")).unwrap();
    std::fs::rename(dir.join("checkpoint"), dir.join("checkpoint.tmp")).unwrap();
    let again = lmac().arg("train").arg("--resume").arg(&dir).output().unwrap();
    let stderr = String::from_utf8_lossy(&again.stderr).replace('\r', "\n");
    assert!(again.status.success() && stderr.contains("already finished (t_env "), "{stderr}");
    assert_eq!(std::fs::read_to_string(dir.join("metrics.csv")).unwrap(), rows, "the metrics are kept");

    // No usable checkpoint: a clear refusal naming the run, and the metrics stay.
    std::fs::remove_dir_all(dir.join("checkpoint.tmp")).unwrap();
    let refused = lmac().arg("train").arg("--resume").arg(&dir).output().unwrap();
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(!refused.status.success(), "{stderr}");
    assert!(
        stderr.contains("no usable checkpoint") && stderr.contains("refusing") && stderr.contains(&dir.display().to_string()),
        "{stderr}"
    );
    assert_eq!(std::fs::read_to_string(dir.join("metrics.csv")).unwrap(), rows, "the metrics are kept");
    let _ = std::fs::remove_dir_all(&out);
}

/// The group directory a `lmac train` said it trains in.
fn group_of(stderr: &str) -> PathBuf {
    let line = stderr.lines().find_map(|l| l.strip_prefix("lmac: training ")).expect("the group line");
    PathBuf::from(line.split_once(" run(s) in ").expect("the group").1.trim())
}

/// Two `lmac train --out R` started together with the same stamp (forced with
/// LMAC_STAMP; the clock to the second gave the same one) get two group directories, and each
/// is trained with its own config (its own learning rate and step target).
#[test]
fn two_launches_in_the_same_second_train_their_own_configs() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let out = std::env::temp_dir().join(format!("lmac-same-second-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let stamp = [("LMAC_STAMP", "20260101-000000")];
    let launches = [(1000u64, "learn.lr=0.001"), (2000u64, "learn.lr=0.002")];
    let children: Vec<_> = launches
        .iter()
        .map(|&(steps, lr)| short_training(&out, steps, &[lr], &stamp).stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().unwrap())
        .collect();
    let mut groups = Vec::new();
    for (child, &(steps, lr)) in children.into_iter().zip(&launches) {
        let (ok, stderr) = finish(child);
        assert!(ok, "{lr}: {stderr}");
        let group = group_of(&stderr);
        let cfg: toml::Value = toml::from_str(&std::fs::read_to_string(group.join("seed0/config.toml")).unwrap()).unwrap();
        assert_eq!(cfg["run"]["steps"].as_integer(), Some(steps as i64), "{lr}: {}", group.display());
        assert_eq!(cfg["learn"]["lr"].as_float(), lr.split('=').nth(1).unwrap().parse().ok(), "{}", group.display());
        let t = metrics_t_env(&group.join("seed0"));
        assert!(*t.last().unwrap() >= steps && *t.last().unwrap() < steps + 1000, "{lr}: trained to its own target: {t:?}");
        groups.push(group);
    }
    assert_ne!(groups[0], groups[1], "two launches, two directories");
    let _ = std::fs::remove_dir_all(&out);
}

/// Rebuilding lmac while a run is under way does not break it: with the binary's file removed
/// after the run started (what `cargo build` does when it replaces it), the next seed's
/// pipeline still starts, on the same build. Before, children were started by the file's path,
/// which then no longer existed ("starting the protocol runner: No such file or directory").
#[test]
fn a_run_survives_its_binary_being_replaced() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = std::env::temp_dir().join(format!("lmac-rebuilt-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
    std::fs::create_dir_all(&tmp).unwrap();
    let built = std::env::var("LMAC_BIN").map(PathBuf::from).unwrap_or_else(|_| lmac_e2e::harness::root().join("target/release/lmac"));
    let copy = tmp.join("lmac");
    std::fs::copy(&built, &copy).unwrap();
    let out = tmp.join("runs");
    let child = std::process::Command::new(&copy)
        .current_dir(lmac_e2e::harness::root())
        .env("LMAC_ROOT", lmac_e2e::harness::root())
        .args(["train", "--env", "lbf:8x8-2p-2f-s1-coop", "--algo", "qmix", "--steps", "3000", "--seeds", "0,1"])
        .args(["--set", "run.envs=8", "--set", "run.servers=1", "--set", "run.test_interval=1000", "--set", "run.test_episodes=4"])
        .args(["--set", "run.final_eval_episodes=0"])
        .arg("--out")
        .arg(&out)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // Seed 0's pipeline is up: remove the binary's file, as a rebuild replacing it does.
    wait_for(Duration::from_secs(60), || pipeline_children(child.id() as i32).into_iter().find(|p| p.role == Role::Trainer))
        .expect("seed 0's trainer starts");
    std::fs::remove_file(&copy).unwrap();
    let (ok, stderr) = finish(child);
    assert!(ok, "the run failed after its binary was removed:\n{stderr}");
    let seeds: Vec<PathBuf> = std::fs::read_dir(out.join("lbf_8x8-2p-2f-s1-coop/qmix"))
        .unwrap()
        .flatten()
        .flat_map(|g| std::fs::read_dir(g.path()).unwrap().flatten().map(|s| s.path()))
        .filter(|p| p.join("metrics.csv").exists())
        .collect();
    assert_eq!(seeds.len(), 2, "both seeds trained: {seeds:?}\n{stderr}");
    for s in &seeds {
        assert!(metrics_t_env(s).last().copied().unwrap_or(0) >= 3000, "{} reached its steps", s.display());
    }
    let _ = std::fs::remove_dir_all(&tmp);
}

/// A resume compares the run's `config.toml` with the configuration its checkpoint was trained
/// with, before any process starts: an edited learning rate or algorithm is refused with the list
/// of changes (the labels would otherwise follow the file while the network follows the
/// checkpoint); a longer step target is not a change; `--allow-changed` continues under the new
/// settings, saying each.
#[test]
fn a_resume_refuses_an_edited_run_unless_allowed() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let out = std::env::temp_dir().join(format!("lmac-resume-edited-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let run = short_training(&out, 2000, &[], &[]).output().unwrap();
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let dir = seed_dir(&out);
    let cfg_path = dir.join("config.toml");
    let original = std::fs::read_to_string(&cfg_path).unwrap();
    let edited =
        original.replace("algo = \"qmix\"", "algo = \"vdn\"").replace("lr = 0.0005", "lr = 0.002").replace("steps = 2000", "steps = 4000");
    assert_ne!(edited, original);
    std::fs::write(&cfg_path, &edited).unwrap();
    let refused = lmac().arg("train").arg("--resume").arg(&dir).output().unwrap();
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(!refused.status.success(), "{stderr}");
    assert!(stderr.contains("differs from the configuration its checkpoint") && stderr.contains("--allow-changed"), "{stderr}");
    assert!(stderr.contains("run.algo: \"qmix\" -> \"vdn\"") && stderr.contains("learn.lr: 0.0005 -> 0.002"), "{stderr}");
    assert!(!stderr.contains("run.steps"), "the step target is free to change: {stderr}");
    assert!(!stderr.contains("env server"), "refused before the pipeline started: {stderr}");
    // Only the step target changed: resumes.
    std::fs::write(&cfg_path, original.replace("steps = 2000", "steps = 4000")).unwrap();
    let longer = lmac().arg("train").arg("--resume").arg(&dir).output().unwrap();
    assert!(longer.status.success(), "{}", String::from_utf8_lossy(&longer.stderr));
    // Allowed: trains on under the new learning rate, saying so.
    std::fs::write(&cfg_path, original.replace("steps = 2000", "steps = 6000").replace("lr = 0.0005", "lr = 0.002")).unwrap();
    let allowed = lmac().arg("train").arg("--resume").arg(&dir).arg("--allow-changed").output().unwrap();
    let stderr = String::from_utf8_lossy(&allowed.stderr);
    assert!(allowed.status.success(), "{stderr}");
    assert!(stderr.contains("resuming with a changed setting (--allow-changed): learn.lr: 0.0005 -> 0.002"), "{stderr}");
    let _ = std::fs::remove_dir_all(&out);
}
