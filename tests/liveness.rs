//! Liveness through iceoryx2 alone (no supervisor): a peer process that is killed is reported
//! by name within 2 seconds by the waiting side, and its stale resources are cleaned up.
use iceoryx2::node::NodeView;
use iceoryx2::prelude::*;
use lmac_shm_schema::ring::{node_name, ring_config, Port, RingError, RingSpec};
use lmac_shm_schema::Stage;
use std::process::Command;
use std::time::{Duration, Instant};

const CHILD: &str = "LMAC_LIVENESS_CHILD_RUN";

fn spec(run: &str, role: Stage) -> RingSpec {
    RingSpec { run: run.into(), n_members: 1, n_slots: 2, role, member: 0 }
}

#[test]
fn killed_peer_is_reported_by_name_within_two_seconds() {
    if let Ok(run) = std::env::var(CHILD) {
        // Child: be env server 0 of `run` and wait to be killed.
        let _port = Port::new(spec(&run, Stage::Env)).unwrap();
        std::thread::sleep(Duration::from_secs(60));
        return;
    }
    let run = format!("live{}", std::process::id());
    let mut trainer = Port::new(spec(&run, Stage::Trainer)).unwrap();
    trainer.set_startup_timeout(Duration::from_secs(600)); // the runner never comes here
    let mut child = Command::new(std::env::current_exe().unwrap())
        .args(["--exact", "killed_peer_is_reported_by_name_within_two_seconds", "--nocapture"])
        .env(CHILD, &run)
        .spawn()
        .unwrap();
    // Wait until the child's node is seen alive.
    let t0 = Instant::now();
    loop {
        trainer.check_peers().unwrap();
        let alive = child_node_alive(&run);
        if alive && t0.elapsed() > Duration::from_millis(800) {
            break;
        }
        assert!(t0.elapsed() < Duration::from_secs(20), "child never started");
        std::thread::sleep(Duration::from_millis(50));
    }
    unsafe { libc::kill(child.id() as i32, libc::SIGKILL) };
    let _ = child.wait();
    let killed = Instant::now();
    let err = loop {
        match trainer.recv(Duration::from_millis(100)) {
            Err(e) => break e,
            Ok(_) => assert!(killed.elapsed() < Duration::from_secs(5), "death not noticed"),
        }
    };
    let took = killed.elapsed();
    match &err {
        RingError::PeerDied { name, pid } => {
            assert_eq!(name, &format!("lmac-{run}-env0"));
            assert_eq!(*pid, child.id());
        }
        other => panic!("expected PeerDied, got {other}"),
    }
    assert!(took < Duration::from_secs(2), "took {took:?}");
    assert!(err.to_string().contains("env0") && err.to_string().contains("died"));
}

/// Whether env server 0 of `run` has a live node, looked up in lmac's own iceoryx2 namespace
/// (where `Port::new` creates it), not in iceoryx2's default directory.
fn child_node_alive(run: &str) -> bool {
    let want = node_name(run, Stage::Env, 0);
    let mut alive = false;
    let _ = Node::<ipc::Service>::list(&ring_config(), |state| {
        if let NodeState::Alive(v) = state {
            alive |= v.details().as_ref().is_some_and(|d| d.name().to_string() == want);
        }
        CallbackProgression::Continue
    });
    alive
}
