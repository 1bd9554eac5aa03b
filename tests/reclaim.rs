//! Shared memory left by runs killed whole is reclaimed (`lmac clean` and every
//! start), never a live run's or another user's; a parent killed during start-up takes its
//! children with it even while they wait for slabs that will never come. Real `lmac` processes,
//! real /dev/shm and iceoryx2.

use iceoryx2::prelude::*;
use lmac_benches::faults::{alive, pipeline_children, Role};
use lmac_e2e::harness::{lmac, lmac_shm_files, wait_for};
use lmac_shm_schema::leftovers::{survey, Kind};
use std::os::unix::process::CommandExt;
use std::process::{Child, Stdio};
use std::sync::Mutex;
use std::time::Duration;

/// The tests kill runs and clean shared memory; one at a time.
static SERIAL: Mutex<()> = Mutex::new(());

/// A long random-policy run in a process group of its own (as a scheduler starts a job).
fn start_run() -> Child {
    lmac()
        .args(["run", "--env", "lbf:8x8-2p-2f-s1-coop", "--envs", "4", "--servers", "1", "--steps", "300000000"])
        .process_group(0)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap()
}

/// The run id of a running `lmac run`, once its four iceoryx2 nodes (2 sub-batches, runner,
/// trainer) are alive: the ring is up, everything it will leave exists.
fn run_id_when_up(parent: &Child) -> String {
    let trainer = wait_for(Duration::from_secs(30), || {
        pipeline_children(parent.id() as i32).into_iter().find(|p| p.role == Role::Trainer).map(|p| p.pid)
    })
    .expect("the trainer child appears");
    let cmd = std::fs::read(format!("/proc/{trainer}/cmdline")).unwrap();
    let args: Vec<String> = cmd.split(|&b| b == 0).map(|a| String::from_utf8_lossy(a).into_owned()).collect();
    let run = args[args.iter().position(|a| a == "--run").unwrap() + 1].clone();
    wait_for(Duration::from_secs(30), || {
        (survey().kept.iter().filter(|f| f.run == run && f.kind == Kind::Node && f.why.starts_with("alive")).count() == 4).then_some(())
    })
    .expect("the run's four nodes come alive");
    run
}

/// `kill -9` of the whole process group, as `timeout -s KILL` or the OOM killer does, and wait
/// until every process of it is gone (none can clean up after itself).
fn kill_group(child: &mut Child) {
    let pids: Vec<i32> = pipeline_children(child.id() as i32).into_iter().map(|p| p.pid).collect();
    unsafe { libc::kill(-(child.id() as i32), libc::SIGKILL) };
    child.wait().unwrap();
    wait_for(Duration::from_secs(30), || pids.iter().all(|&p| !alive(p)).then_some(())).expect("the killed processes are gone");
}

/// The iceoryx2 services of run `run` (`lmac/<run>/...`), dead or alive.
fn services_of(run: &str) -> Vec<String> {
    let mut v = Vec::new();
    let _ = ipc::Service::list(&lmac_shm_schema::ring::ring_config(), |s| {
        let name = s.static_details.name().to_string();
        if name.starts_with(&format!("lmac/{run}/")) {
            v.push(name);
        }
        CallbackProgression::Continue
    });
    v
}

/// Everything of run `run` that is in shared memory: slabs, nodes (dead or alive), services.
fn traces_of(run: &str) -> (Vec<String>, Vec<String>, Vec<String>) {
    let slabs = lmac_shm_files().into_iter().filter(|f| f.starts_with(&format!("lmac-{run}-"))).collect();
    let s = survey();
    let nodes = s.dead.iter().chain(&s.kept).filter(|f| f.run == run && f.kind == Kind::Node).map(|f| f.name.clone()).collect();
    (slabs, nodes, services_of(run))
}

fn is_root() -> bool {
    unsafe { libc::geteuid() == 0 }
}

#[test]
fn lmac_clean_removes_a_run_killed_whole_and_never_a_live_run_or_another_users() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let mut live = start_run();
    let live_run = run_id_when_up(&live);
    let mut killed = start_run();
    let dead_run = run_id_when_up(&killed);
    kill_group(&mut killed);
    let (slabs, nodes, services) = traces_of(&dead_run);
    assert_eq!(slabs.len(), 2, "the killed run left its slabs: {slabs:?}");
    assert_eq!(nodes.len(), 4, "the killed run left its nodes: {nodes:?}");
    assert!(!services.is_empty(), "the killed run left its services");
    // Another user's leftover of the same shape is not ours to remove (root can hand a slab over).
    let foreign = format!("lmac-{dead_run}-s1");
    if is_root() {
        std::os::unix::fs::chown(format!("/dev/shm/{foreign}"), Some(4242), None).unwrap();
    }
    let out = lmac().args(["clean"]).output().unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "lmac clean failed: {stdout}{}", String::from_utf8_lossy(&out.stderr));
    let (slabs, nodes, services) = traces_of(&dead_run);
    let expect_slabs = if is_root() { vec![foreign.clone()] } else { vec![] };
    assert_eq!(slabs, expect_slabs, "only another user's slab of the killed run is left:\n{stdout}");
    assert!(nodes.is_empty() && services.is_empty(), "nodes {nodes:?} and services {services:?} of the killed run are left:\n{stdout}");
    if is_root() {
        assert!(stdout.contains(&format!("kept     slab {foreign}")) && stdout.contains("another user's (uid 4242)"), "{stdout}");
        lmac_shm_schema::slab::unlink(&foreign);
    }
    // The live run lost nothing and still runs.
    let (slabs, nodes, _) = traces_of(&live_run);
    assert_eq!((slabs.len(), nodes.len()), (2, 4), "the live run's slabs {slabs:?} and nodes {nodes:?}:\n{stdout}");
    assert!(live.try_wait().unwrap().is_none(), "the live run survived lmac clean");
    unsafe { libc::kill(live.id() as i32, libc::SIGINT) };
    let st = wait_for(Duration::from_secs(30), || live.try_wait().unwrap()).expect("the live run stops on Ctrl-C");
    assert_eq!(st.code(), Some(2), "it stops as interrupted, not because its shared memory went away");
    assert_eq!(traces_of(&live_run).0, Vec::<String>::new(), "and cleans up after itself");
}

#[test]
fn the_next_start_removes_a_run_killed_whole() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let mut killed = start_run();
    let dead_run = run_id_when_up(&killed);
    kill_group(&mut killed);
    assert_eq!(traces_of(&dead_run).0.len(), 2, "the killed run left its slabs");
    let out = lmac().args(["run", "--env", "lbf:8x8-2p-2f-s1-coop", "--envs", "4", "--steps", "500"]).output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "the next run failed: {stderr}");
    assert!(stderr.contains("leftovers of dead runs") && stderr.contains(&dead_run), "the start says what it removed: {stderr}");
    let (slabs, nodes, services) = traces_of(&dead_run);
    assert!(slabs.is_empty() && nodes.is_empty() && services.is_empty(), "left: {slabs:?} {nodes:?} {services:?}");
}

/// Whether `pid` has a handler for SIGTERM installed (`SigCgt` in /proc/<pid>/status).
fn catches_sigterm(pid: i32) -> bool {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    let mask = status.lines().find_map(|l| l.strip_prefix("SigCgt:")).and_then(|m| u64::from_str_radix(m.trim(), 16).ok());
    mask.is_some_and(|m| m & (1 << (libc::SIGTERM - 1)) != 0)
}

#[test]
fn a_parent_killed_during_start_up_takes_its_children_waiting_for_slabs_with_it() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    // Env servers that never make their slabs: the runner and the trainer wait for them, as they
    // do in the first moments of every run while Python starts.
    let dir = std::env::temp_dir().join(format!("lmac-reclaim-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let python = dir.join("python");
    std::fs::write(&python, "#!/bin/sh\nexec sleep 600\n").unwrap();
    std::fs::set_permissions(&python, std::os::unix::fs::PermissionsExt::from_mode(0o755)).unwrap();
    let mut parent = lmac()
        .env("LMAC_PYTHON", &python)
        .args(["run", "--env", "lbf:8x8-2p-2f-s1-coop", "--envs", "4", "--steps", "1000", "--startup-timeout", "600"])
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    // Both lmac children are waiting for slabs (their SIGTERM handler is in place).
    let children = wait_for(Duration::from_secs(30), || {
        let c = pipeline_children(parent.id() as i32);
        let waiting = c.iter().filter(|p| matches!(p.role, Role::ProtocolRunner | Role::Trainer) && catches_sigterm(p.pid)).count();
        (waiting == 2).then_some(c)
    })
    .expect("the runner and the trainer start");
    unsafe { libc::kill(parent.id() as i32, libc::SIGKILL) };
    parent.wait().unwrap();
    // The kernel sends each child SIGTERM (PR_SET_PDEATHSIG); waiting for a slab must end on it,
    // long before the 600 s start-up timeout.
    let gone = wait_for(Duration::from_secs(30), || children.iter().all(|p| !alive(p.pid)).then_some(()));
    let left: Vec<String> = children.iter().filter(|p| alive(p.pid)).map(|p| format!("{} (pid {})", p.role.name(), p.pid)).collect();
    for p in &children {
        unsafe { libc::kill(p.pid, libc::SIGKILL) };
    }
    let _ = std::fs::remove_dir_all(&dir);
    assert!(gone.is_some(), "children still running after their parent died: {left:?}");
}
