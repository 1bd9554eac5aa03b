//! End-to-end tests of the data plane with real processes, real shared memory and the real
//! Level-Based Foraging environment. They run the release `lmac` binary built by
//! `scripts/setup.sh` (or `$LMAC_BIN`).

use lmac_e2e::harness::{lmac, root, wait_for};
use std::collections::HashSet;
use std::os::unix::fs::PermissionsExt;

use std::process::{Child, Command, Stdio};
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// The tests watch /dev/shm; one at a time.
static SERIAL: Mutex<()> = Mutex::new(());

fn lmac_shm_files() -> HashSet<String> {
    std::fs::read_dir("/dev/shm")
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().to_string())
        .filter(|n| n.starts_with("lmac-"))
        .collect()
}

/// Every file in /dev/shm except iceoryx2's machine-wide node-id counter (`*global_mgmt`),
/// which iceoryx2 keeps across runs by design.
fn all_shm_files() -> HashSet<String> {
    std::fs::read_dir("/dev/shm")
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().to_string())
        .filter(|n| !n.ends_with("global_mgmt"))
        .collect()
}

fn wait_exit(child: &mut Child, timeout: Duration) -> Option<std::process::ExitStatus> {
    wait_for(timeout, || child.try_wait().unwrap())
}

/// The env server's pid, read from its slab header (owner_pid at byte 60).
fn slab_owner_pid(file: &str) -> u32 {
    let bytes = std::fs::read(format!("/dev/shm/{file}")).unwrap();
    assert_eq!(&bytes[..8], b"LMACSLAB");
    u32::from_le_bytes(bytes[60..64].try_into().unwrap())
}

#[test]
fn lbf_episodes_flow_end_to_end_with_fullcomm_messages() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = std::env::temp_dir().join(format!("lmac-e2e-{}.jsonl", std::process::id()));
    let out = lmac()
        .args(["run", "--env", "lbf:8x8-2p-2f-s1-coop", "--envs", "8", "--servers", "2", "--protocol", "fullcomm"])
        .args(["--steps", "4000", "--verify", "--json", "--episodes-out"])
        .arg(&tmp)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "lmac run failed: {stderr}");
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).expect("JSON report");
    assert_eq!(report["violation_count"], 0, "invariant violations: {}", report["violations"]);
    assert!(report["env_steps"].as_u64().unwrap() >= 4000);
    let episodes: Vec<serde_json::Value> =
        std::fs::read_to_string(&tmp).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    std::fs::remove_file(&tmp).ok();
    assert!(episodes.len() >= 100, "only {} episodes finished", episodes.len());
    let mut members = HashSet::new();
    for e in &episodes {
        members.insert(e["member"].as_u64().unwrap());
        let len = e["len"].as_u64().unwrap();
        let ret = e["team_return"].as_f64().unwrap();
        let (term, trunc) = (e["terminated"].as_bool().unwrap(), e["truncated"].as_bool().unwrap());
        assert!(term ^ trunc, "an episode ends exactly one way: {e}");
        assert!((1..=25).contains(&len), "episode length {len} outside 1..=25: {e}");
        if trunc {
            assert_eq!(len, 25, "truncation happens at the episode limit: {e}");
        }
        // LBF's normalised rewards add up to 1 exactly when all food is eaten (termination).
        assert!((-1e-5..=1.0 + 1e-5).contains(&ret), "team return {ret} outside [0, 1]: {e}");
        assert_eq!(term, (ret - 1.0).abs() < 1e-4, "terminated iff all food eaten (return 1): {e}");
    }
    // 2 env servers x 2 sub-batches (the default double buffering): 4 ring members.
    assert_eq!(members.len(), 4, "every sub-batch of both env servers delivered episodes");
    // Episode ids are unique.
    let ids: HashSet<u64> = episodes.iter().map(|e| e["episode_id"].as_u64().unwrap()).collect();
    assert_eq!(ids.len(), episodes.len());
}

#[test]
fn clean_shutdown_leaves_no_shared_memory_and_files_are_owner_only() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let before = all_shm_files();
    let mut child = lmac()
        // One sub-batch: the plain (not double-buffered) server loop.
        .args(["run", "--env", "lbf:8x8-2p-2f-s1-coop", "--envs", "4", "--sub-batches", "1", "--steps", "3000000"])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let ours = wait_for(Duration::from_secs(30), || {
        let f: Vec<String> = lmac_shm_files().difference(&before).cloned().collect();
        (!f.is_empty()).then_some(f)
    })
    .expect("the run's slab appears in /dev/shm");
    for f in &ours {
        let mode = std::fs::metadata(format!("/dev/shm/{f}")).unwrap().permissions().mode() & 0o777;
        assert_eq!(mode, 0o600, "/dev/shm/{f} has mode {mode:o}");
    }
    std::thread::sleep(Duration::from_millis(500));
    // Ctrl-C: stop everything and clean up.
    unsafe { libc::kill(child.id() as i32, libc::SIGINT) };
    let st = wait_exit(&mut child, Duration::from_secs(10)).expect("lmac exits after Ctrl-C");
    assert!(!st.success(), "an interrupted run reports it was interrupted");
    let left: Vec<String> = all_shm_files().difference(&before).cloned().collect();
    assert!(left.is_empty(), "shared-memory files left after shutdown: {left:?}");
}

#[test]
fn a_killed_env_server_is_reported_by_name_and_nothing_hangs() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let before = all_shm_files();
    let mut child = lmac()
        .args(["run", "--env", "lbf:8x8-2p-2f-s1-coop", "--envs", "4", "--servers", "2", "--steps", "3000000"])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // 2 servers x 4 envs = 2 sub-batches each: env server 1 owns the slabs of ring members 2 and 3.
    let slab = wait_for(Duration::from_secs(30), || lmac_shm_files().difference(&before).find(|f| f.ends_with("-s3")).cloned())
        .expect("env server 1's second slab appears");
    std::thread::sleep(Duration::from_millis(1500)); // let the ring run
    let pid = slab_owner_pid(&slab);
    unsafe { libc::kill(pid as i32, libc::SIGKILL) };
    let killed_at = Instant::now();
    let st = wait_exit(&mut child, Duration::from_secs(10)).expect("lmac exits after an env server dies");
    let took = killed_at.elapsed();
    let mut stderr = String::new();
    std::io::Read::read_to_string(child.stderr.as_mut().unwrap(), &mut stderr).unwrap();
    assert!(!st.success());
    assert!(stderr.contains("env server 1") && stderr.contains("died"), "stderr names the dead server: {stderr}");
    assert!(took < Duration::from_secs(6), "took {took:?} to notice and shut down");
    let left: Vec<String> = lmac_shm_files().difference(&before).cloned().collect();
    assert!(left.is_empty(), "slabs left after the failure: {left:?}");
    // Nothing of the run survives: no process still holds the killed server's peers.
    let run = slab.trim_start_matches("lmac-").trim_end_matches("-s3");
    let pids_alive = std::process::Command::new("pgrep").args(["-f", &format!("--run {run}")]).output().unwrap();
    assert!(String::from_utf8_lossy(&pids_alive.stdout).trim().is_empty());
}

#[test]
fn all_smaclite_maps_run_through_the_pipeline() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    for map in ["bane_vs_hM", "1o_10b_vs_1r", "2o_20b_vs_2r", "5z_vs_1ul"] {
        let env = format!("smaclite:{map}");
        let out = lmac()
            .args(["run", "--env", &env, "--envs", "4", "--protocol", "fullcomm", "--steps", "1200", "--verify", "--json"])
            .output()
            .unwrap();
        assert!(out.status.success(), "{env}: {}", String::from_utf8_lossy(&out.stderr));
        let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        assert_eq!(report["violation_count"], 0, "{env}: {}", report["violations"]);
        assert!(report["episodes"].as_u64().unwrap() > 0, "{env}: no episode finished");
    }
}

#[test]
fn a_three_phase_protocol_runs_in_the_runner_and_matches_an_independent_recomputation() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let ex = root().join("prompts/examples");
    let protocol =
        ["lbf_8x8_phase0.json", "lbf_8x8_phase1.json", "lbf_8x8_phase2.json"].map(|f| ex.join(f).display().to_string()).join("+");
    let out = lmac()
        .args(["run", "--env", "lbf:8x8-2p-2f-s1-coop", "--envs", "8", "--servers", "2", "--protocol", &protocol])
        .args(["--steps", "4000", "--verify", "--json"])
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(report["violation_count"], 0, "{}", report["violations"]);
}

#[test]
fn a_protocol_over_the_message_budget_is_refused_before_anything_starts() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    // A copy of the LBF schema whose message budget is smaller than FullComm's 31 columns.
    let dir = std::env::temp_dir().join(format!("lmac-budget-{}", std::process::id()));
    std::fs::create_dir_all(dir.join("lbf")).unwrap();
    let text = std::fs::read_to_string(root().join("env-server/schemas/lbf/8x8-2p-2f-s1-coop.toml")).unwrap();
    std::fs::write(dir.join("lbf/8x8-2p-2f-s1-coop.toml"), text.replace("message_columns = 64", "message_columns = 10")).unwrap();
    let before = lmac_shm_files();
    let out = lmac()
        .args(["run", "--env", "lbf:8x8-2p-2f-s1-coop", "--protocol", "fullcomm", "--steps", "100"])
        .env("LMAC_SCHEMA_DIR", &dir)
        .output()
        .unwrap();
    std::fs::remove_dir_all(&dir).ok();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("writes 31 message columns") && err.contains("allows 10"), "{err}");
    assert_eq!(lmac_shm_files(), before, "nothing was started");
    let out = lmac().args(["run", "--envs", "4", "--sub-batches", "3", "--steps", "100"]).output().unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("--sub-batches 3 must be at least 1 and divide --envs 4"), "{err}");
    assert_eq!(lmac_shm_files(), before, "nothing was started");
    let out = lmac().args(["run", "--protocol", "nonsense", "--steps", "100"]).output().unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("unknown protocol \"nonsense\""), "{err}");
}

/// Real Google Research Football episodes through the whole pipeline (both scenarios). Skipped,
/// saying so, where gfootball is not installed (`LMAC_WITH_GRF=0`).
#[test]
fn grf_episodes_run_through_the_pipeline() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let python = root().join(".venv/bin/python");
    let have = Command::new(&python).args(["-c", "import gfootball, gfootball_engine"]).output().map(|o| o.status.success());
    if have.ok() != Some(true) {
        eprintln!("skipped: gfootball is not installed in .venv (LMAC_WITH_GRF=1 bash scripts/setup.sh installs it)");
        return;
    }
    for (sc, n) in [("academy_3_vs_1_with_keeper", 3u64), ("academy_run_pass_and_shoot_with_keeper", 2)] {
        let env = format!("grf:{sc}");
        let tmp = std::env::temp_dir().join(format!("lmac-grf-{}-{n}.jsonl", std::process::id()));
        let out = lmac()
            .args(["run", "--env", &env, "--envs", "4", "--protocol", "fullcomm", "--steps", "1200", "--verify", "--json"])
            .arg("--episodes-out")
            .arg(&tmp)
            .output()
            .unwrap();
        assert!(out.status.success(), "{env}: {}", String::from_utf8_lossy(&out.stderr));
        let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        assert_eq!(report["violation_count"], 0, "{env}: {}", report["violations"]);
        let episodes: Vec<serde_json::Value> =
            std::fs::read_to_string(&tmp).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect();
        std::fs::remove_file(&tmp).ok();
        assert!(!episodes.is_empty(), "{env}: no episode finished in 1200 steps");
        for e in &episodes {
            let (len, ret) = (e["len"].as_u64().unwrap(), e["team_return"].as_f64().unwrap());
            assert!((1..=150).contains(&len), "{env}: episode length {len} outside 1..=150: {e}");
            // Scoring reward only: +1 for our goal, -1 for theirs, at most one goal per episode.
            assert!([-1.0, 0.0, 1.0].contains(&ret), "{env}: team return {ret} is not a scoring reward: {e}");
            if e["truncated"].as_bool().unwrap() {
                assert_eq!(len, 150, "{env}: truncation happens at the episode limit: {e}");
            }
        }
    }
}

#[test]
fn the_pipeline_bench_interleaves_raw_and_pipeline_blocks_and_cleans_up() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let before = all_shm_files();
    let out = lmac()
        .args(["bench", "pipeline", "--env", "lbf:8x8-2p-2f-s1-coop", "--envs", "8", "--steps", "2400", "--repeat", "3", "--json"])
        .output()
        .unwrap();
    assert!(out.status.success(), "bench failed: {}", String::from_utf8_lossy(&out.stderr));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).expect("JSON report");
    assert_eq!(v["method"], "interleaved block pairs");
    assert_eq!(v["sub_batches"], 2);
    // One raw and one pipeline rate per block pair, each a real measurement.
    for key in ["raw_runs", "pipeline_runs", "ratio_runs"] {
        let runs = v[key].as_array().unwrap_or_else(|| panic!("{key} missing"));
        assert_eq!(runs.len(), 3, "{key}: {runs:?}");
        assert!(runs.iter().all(|r| r.as_f64().is_some_and(|x| x.is_finite() && x > 0.0)), "{key}: {runs:?}");
    }
    // 2400 env steps over 3 blocks of 8 envs: 100 batched steps, 800 env steps per block.
    let t = &v["pipeline_time"];
    assert_eq!(t["block_env_steps"], 800.0);
    let share = t["handover_share"].as_f64().unwrap();
    assert!((0.0..1.0).contains(&share), "hand-over share {share}");
    assert!(t["stepping_vs_raw"].as_f64().unwrap() > 0.0);
    let left: Vec<String> = all_shm_files().difference(&before).cloned().collect();
    assert!(left.is_empty(), "shared-memory files left after the bench: {left:?}");
}

/// The arguments of a live process, from /proc.
fn cmdline(pid: i32) -> Vec<String> {
    let raw = std::fs::read(format!("/proc/{pid}/cmdline")).unwrap_or_default();
    raw.split(|&b| b == 0).filter(|a| !a.is_empty()).map(|a| String::from_utf8_lossy(a).into_owned()).collect()
}

/// The trainer's report is never written through a symlink another local user
/// planted. The attacker reads the run id and the report's path from the trainer's argv (which
/// every user can) and links every name the report may use to a file of the victim's: the names
/// it had in the shared temp directory (`lmac-<run>-report.json` and `.tmp`) and its own path
/// and temporary name. The run must succeed and the victim's file stay as it was.
#[test]
fn the_trainers_report_is_never_written_through_a_planted_symlink() {
    use lmac_benches::faults::{pipeline_children, Role};
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    // The shared temp directory of this test (TMPDIR), where the report used to go.
    let shared = std::env::temp_dir().join(format!("lmac-symlink-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&shared);
    std::fs::create_dir_all(&shared).unwrap();
    let victim = shared.join("victim.conf");
    std::fs::write(&victim, "precious\n").unwrap();
    let child = lmac()
        .env("TMPDIR", &shared)
        .args(["run", "--env", "lbf:8x8-2p-2f-s1-coop", "--envs", "8", "--servers", "1", "--protocol", "none"])
        .args(["--steps", "20000", "--json"])
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // The trainer is started at once; its report is written only after 20000 env steps.
    let trainer = wait_for(Duration::from_secs(30), || {
        pipeline_children(child.id() as i32).into_iter().find(|p| p.role == Role::Trainer).map(|p| p.pid)
    })
    .expect("the trainer child appears");
    let args = cmdline(trainer);
    let after = |flag: &str| args.iter().position(|a| a == flag).and_then(|i| args.get(i + 1)).cloned().expect(flag);
    // The report's path is in the trainer's job file (in the run's private directory).
    let (run, job) = (after("--run"), after("--job"));
    let report = lmac_run::supervisor::TrainerJobFile::load(std::path::Path::new(&job)).unwrap().report;
    let mut report_tmp = report.clone().into_os_string();
    report_tmp.push(".tmp");
    let planted = [
        shared.join(format!("lmac-{run}-report.json")),
        shared.join(format!("lmac-{run}-report.tmp")),
        report.clone(),
        report.with_extension("tmp"),
        report_tmp.into(),
    ];
    for p in &planted {
        // Where the directory is private to the run, only its owner could plant (this test can:
        // it is the same user); the write must still not follow the link.
        let _ = std::os::unix::fs::symlink(&victim, p);
    }
    let out = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "lmac run failed: {stderr}");
    let _: serde_json::Value = serde_json::from_slice(&out.stdout).expect("the report reached the parent");
    assert_eq!(std::fs::read_to_string(&victim).unwrap(), "precious\n", "the report was written through a planted symlink");
    assert!(
        report.parent() != Some(shared.as_path()),
        "the report lives in a directory of its own, not in the shared one: {}",
        report.display()
    );
    let dirs_left: Vec<_> =
        std::fs::read_dir(&shared).unwrap().flatten().filter(|e| e.file_type().is_ok_and(|t| t.is_dir())).map(|e| e.path()).collect();
    assert!(dirs_left.is_empty(), "the run's private directory is removed when it ends: {dirs_left:?}");
    let _ = std::fs::remove_dir_all(&shared);
}
