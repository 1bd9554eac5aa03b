//! Hostile input on the ring is refused, never trusted: a real publisher process sends crafted
//! slot messages (member, slot or kind out of range) to a real `Port`, which must return an
//! error naming the sending node and the field, and keep working for the next good message.
//! Clean-up of dead iceoryx2 nodes removes this run's dead nodes only, never those of another
//! run or application on the same machine (real processes killed with SIGKILL).
use iceoryx2::node::NodeView;
use iceoryx2::prelude::*;
use lmac_shm_schema::ring::{
    cleanup_dead_nodes, config_without_machine_wide_cleanup, is_run_node, node_name, pubsub, ring_config, Port, RingError, RingSpec,
    SlotMsg, KIND_SLOT,
};
use lmac_shm_schema::Stage;
use std::io::{BufRead, BufReader, Read, Write};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

const SENDER: &str = "LMAC_TEST_RING_SENDER";
const SLEEPER: &str = "LMAC_TEST_RING_SLEEPER";
const LEGACY: &str = "LMAC_TEST_RING_LEGACY";

fn unique_run(tag: &str) -> String {
    let t = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().subsec_nanos();
    format!("{tag}{}x{t:08x}", std::process::id())
}

/// Re-run this test binary as a child that executes `test` with `vars` set.
fn child(test: &str, vars: &[(&str, String)]) -> Child {
    let mut c = Command::new(std::env::current_exe().unwrap());
    c.args(["--exact", test, "--nocapture", "--test-threads=1"]).stdin(Stdio::piped()).stdout(Stdio::piped()).stderr(Stdio::inherit());
    for (k, v) in vars {
        c.env(k, v);
    }
    c.spawn().unwrap()
}

/// Wait for the child to print `word` on a line of its own (it is ready).
fn wait_for_line(c: &mut Child, word: &str) {
    let out = c.stdout.as_mut().unwrap();
    let mut r = BufReader::new(out);
    let mut line = String::new();
    loop {
        line.clear();
        assert!(r.read_line(&mut line).unwrap() > 0, "child exited before printing {word}");
        // The test harness may print "test NAME ... " before it on the same line.
        if line.trim_end().ends_with(word) {
            return;
        }
    }
}

/// Child of `bad_messages_are_refused_naming_the_sender`: pose as env server `member` of the
/// run and publish the crafted messages given as `kind,member,slot` triples separated by ';',
/// then stay alive (so the receiver can look the sender up) until stdin closes.
fn sender_child(spec: &str) {
    set_log_level(LogLevel::Error);
    let mut it = spec.split(' ');
    let (run, member, n_slots, msgs) = (it.next().unwrap(), it.next().unwrap(), it.next().unwrap(), it.next().unwrap());
    let n_slots: usize = n_slots.parse().unwrap();
    // lmac's own namespace and settings (no clean-up of every dead node on creation or drop: the
    // clean-up test running beside this one keeps dead nodes that must stay listed).
    let node = NodeBuilder::new()
        .config(&ring_config())
        .name(&NodeName::new(&format!("lmac-{run}-env{member}")).unwrap())
        .signal_handling_mode(SignalHandlingMode::Disabled)
        .create::<ipc::Service>()
        .unwrap();
    // The ring's own service settings, as any peer must use.
    let service = pubsub(&node, &format!("lmac/{run}/s{member}/to_runner"), n_slots).unwrap();
    let publisher = service.publisher_builder().create().unwrap();
    for m in msgs.split(';') {
        let v: Vec<u32> = m.split(',').map(|x| x.parse().unwrap()).collect();
        publisher.send_copy(SlotMsg { kind: v[0], member: v[1], slot: v[2], _pad: 0, seq: 42 }).unwrap();
    }
    println!("SENT");
    std::io::stdout().flush().unwrap();
    let mut rest = Vec::new();
    let _ = std::io::stdin().read_to_end(&mut rest);
}

#[test]
fn bad_messages_are_refused_naming_the_sender() {
    if let Ok(spec) = std::env::var(SENDER) {
        return sender_child(&spec);
    }
    // (crafted message sent by "env server 1", the field the error must name)
    let cases: [((u32, u32, u32), &str); 4] = [
        ((KIND_SLOT, 7, 0), "member = 7 is out of range"),
        ((KIND_SLOT, 0, 1), "member = 0 does not match"),
        ((KIND_SLOT, 1, 9), "slot = 9 is out of range"),
        ((77, 1, 0), "kind = 77 is not a message kind"),
    ];
    for ((kind, member, slot), expect) in cases {
        let run = unique_run("hr");
        let n_slots = 2;
        let mut port = Port::new(RingSpec { run: run.clone(), n_members: 2, n_slots, role: Stage::Runner, member: 0 }).unwrap();
        port.set_startup_timeout(Duration::from_secs(600)); // the other peers never come
                                                            // The bad message, then a good one: the port must refuse the first and deliver the second.
        let msgs = format!("{kind},{member},{slot};{KIND_SLOT},1,1");
        let mut c = child("bad_messages_are_refused_naming_the_sender", &[(SENDER, format!("{run} 1 {n_slots} {msgs}"))]);
        wait_for_line(&mut c, "SENT");
        let err = port.recv(Duration::from_secs(5)).expect_err("a bad message must be refused");
        let text = err.to_string();
        match &err {
            RingError::BadMessage { peer, service, .. } => {
                assert!(peer.contains(&format!("lmac-{run}-env1")) && peer.contains(&c.id().to_string()), "{text}");
                assert_eq!(service, &format!("lmac/{run}/s1/to_runner"));
            }
            other => panic!("expected BadMessage, got {other}"),
        }
        assert!(text.contains(expect), "{text}");
        let good = port.recv(Duration::from_secs(5)).unwrap().expect("the good message after the bad one");
        assert_eq!((good.kind, good.member, good.slot, good.seq), (KIND_SLOT, 1, 1, 42));
        drop(c.stdin.take());
        assert!(c.wait().unwrap().success());
    }
}

#[test]
fn out_of_range_sends_and_specs_are_errors() {
    let run = unique_run("hs");
    for (spec, expect) in [
        (RingSpec { run: run.clone(), n_members: 0, n_slots: 2, role: Stage::Runner, member: 0 }, "n_members = 0"),
        (RingSpec { run: run.clone(), n_members: 1, n_slots: 0, role: Stage::Runner, member: 0 }, "n_slots = 0"),
        (RingSpec { run: run.clone(), n_members: 2, n_slots: 2, role: Stage::Env, member: 2 }, "ring member 2 does not exist"),
    ] {
        let err = Port::new(spec).err().expect("refused");
        assert!(matches!(err, RingError::Usage(_)) && err.to_string().contains(expect), "{err}");
    }
    let mut port = Port::new(RingSpec { run: run.clone(), n_members: 2, n_slots: 2, role: Stage::Trainer, member: 0 }).unwrap();
    assert!(port.send_slot(2, 0, 0).unwrap_err().to_string().contains("ring member 2"));
    assert!(port.send_slot(1, 2, 0).unwrap_err().to_string().contains("slot 2"));
    assert!(port.send_bye(5).is_err());
    assert!(matches!(port.handshake(Duration::from_millis(10)), Err(RingError::Usage(_))));
}

#[test]
fn run_nodes_are_recognised_exactly() {
    for role in [Stage::Env, Stage::Runner, Stage::Trainer] {
        assert!(is_run_node("ab", &node_name("ab", role, 3)));
        assert!(!is_run_node("a", &node_name("ab", role, 3)));
        assert!(!is_run_node("ab", &node_name("ab-2", role, 3)));
    }
    for name in ["lmac-ab-env", "lmac-ab-env03", "lmac-ab-envx", "lmac-ab-runner2", "lmac-ab", "ab-runner", "other-app"] {
        assert!(!is_run_node("ab", name), "{name}");
    }
}

/// Child of `cleanup_leaves_other_applications_dead_nodes_alone`: create a node named as given
/// (lmac's namespace for an lmac name, iceoryx2's default config as another application would
/// otherwise), say so, and sleep until killed.
fn sleeper_child(name: &str) {
    set_log_level(LogLevel::Error);
    // LMAC_TEST_RING_LEGACY: an lmac node where lmac versions before its namespace put them.
    let legacy = std::env::var_os(LEGACY).is_some();
    let config = match (name.starts_with("lmac-"), legacy) {
        (true, false) => ring_config(),
        // As an lmac before the namespace made its nodes.
        (true, true) => config_without_machine_wide_cleanup(),
        (false, _) => Config::global_config().clone(),
    };
    let _node = NodeBuilder::new()
        .config(&config)
        .name(&NodeName::new(name).unwrap())
        .signal_handling_mode(SignalHandlingMode::Disabled)
        .create::<ipc::Service>()
        .unwrap();
    println!("READY");
    std::io::stdout().flush().unwrap();
    std::thread::sleep(Duration::from_secs(60));
}

/// State of every node named in `names` (in lmac's namespace and iceoryx2's default one):
/// Some(true) alive, Some(false) dead, None not listed.
fn states(names: &[String]) -> Vec<Option<bool>> {
    let mut out = vec![None; names.len()];
    for config in [ring_config(), Config::global_config().clone()] {
        list_states(&config, names, &mut out);
    }
    out
}

fn list_states(config: &Config, names: &[String], out: &mut [Option<bool>]) {
    let _ = Node::<ipc::Service>::list(config, |state| {
        let (alive, details) = match &state {
            NodeState::Alive(v) => (true, v.details().clone()),
            NodeState::Dead(v) => (false, v.details().clone()),
            _ => return CallbackProgression::Continue,
        };
        if let Some(d) = details {
            if let Some(k) = names.iter().position(|n| *n == d.name().to_string()) {
                out[k] = Some(alive);
            }
        }
        CallbackProgression::Continue
    });
}

#[test]
fn cleanup_leaves_other_applications_dead_nodes_alone() {
    if let Ok(name) = std::env::var(SLEEPER) {
        return sleeper_child(&name);
    }
    set_log_level(LogLevel::Error);
    let run = unique_run("hc");
    let names = vec![
        format!("otherapp-{run}"),         // another application
        format!("lmac-{run}0-env0"),       // another lmac run whose id starts with ours
        node_name(&run, Stage::Env, 0),    // ours
        node_name(&run, Stage::Runner, 0), // ours
    ];
    let mut kids: Vec<Child> =
        names.iter().map(|n| child("cleanup_leaves_other_applications_dead_nodes_alone", &[(SLEEPER, n.clone())])).collect();
    for k in kids.iter_mut() {
        wait_for_line(k, "READY");
    }
    for k in kids.iter_mut() {
        unsafe { libc::kill(k.id() as i32, libc::SIGKILL) };
        let _ = k.wait();
    }
    let t0 = Instant::now();
    while states(&names) != vec![Some(false); 4] {
        assert!(t0.elapsed() < Duration::from_secs(5), "killed nodes not seen dead: {:?}", states(&names));
        std::thread::sleep(Duration::from_millis(20));
    }
    // Everything our processes do about dead nodes: create a port (iceoryx2 would clean every
    // dead node on node creation by default), look at peers, clean up, drop the port.
    let mut port = Port::new(RingSpec { run: run.clone(), n_members: 1, n_slots: 2, role: Stage::Trainer, member: 0 }).unwrap();
    port.set_startup_timeout(Duration::from_secs(600));
    let seen = port.check_peers();
    assert!(matches!(seen, Err(RingError::PeerDied { .. })), "our dead env server is reported: {seen:?}");
    let cleaned = cleanup_dead_nodes(&run);
    drop(port);
    let after = states(&names);
    // Remove the foreign dead nodes we made before asserting, so a failure leaves nothing behind.
    for config in [ring_config(), Config::global_config().clone()] {
        let _ = Node::<ipc::Service>::list(&config, |state| {
            if let NodeState::Dead(v) = state {
                if v.details().as_ref().is_some_and(|d| names[..2].contains(&d.name().to_string())) {
                    let _ = v.try_remove_stale_resources();
                }
            }
            CallbackProgression::Continue
        });
    }
    assert_eq!(after[..2], [Some(false), Some(false)], "another application's / run's dead nodes must be left alone");
    assert_eq!(after[2..], [None, None], "this run's dead nodes are cleaned up");
    assert!(cleaned <= 2, "cleaned {cleaned} nodes, only ours may be");
}

/// lmac's iceoryx2 files live in a namespace of this user's own: a root directory that
/// is 0700, and iceoryx2's node-id counter in /dev/shm (which iceoryx2 creates 0666) made 0600.
#[test]
fn the_ring_lives_in_a_namespace_of_this_users_own() {
    use std::os::unix::fs::MetadataExt;
    set_log_level(LogLevel::Error);
    let run = unique_run("ns");
    let port = Port::new(RingSpec { run, n_members: 1, n_slots: 2, role: Stage::Trainer, member: 0 }).unwrap();
    let uid = unsafe { libc::getuid() };
    let root = std::fs::symlink_metadata(format!("/tmp/lmac-iox2-{uid}")).unwrap();
    assert!(root.is_dir() && root.uid() == uid && root.mode() & 0o777 == 0o700, "root mode {:o}", root.mode());
    let counters: Vec<_> = std::fs::read_dir("/dev/shm")
        .unwrap()
        .flatten()
        .filter(|e| {
            let n = e.file_name().to_string_lossy().into_owned();
            n.starts_with(&format!("iox2_lmac{uid}_")) && n.ends_with(".global_mgmt")
        })
        .map(|e| (e.file_name(), e.metadata().unwrap()))
        .collect();
    assert!(!counters.is_empty(), "the node-id counter is in the namespace");
    for (name, md) in counters {
        assert_eq!((md.uid(), md.mode() & 0o777), (uid, 0o600), "{name:?}");
    }
    drop(port);
}

/// A machine upgraded from an lmac that kept its nodes in iceoryx2's default namespace: such a
/// run, killed whole, leaves its dead nodes there, and `lmac clean`'s survey finds and removes
/// them (only them: the survey still touches nothing alive and nothing not named as lmac's).
#[test]
fn dead_nodes_an_older_lmac_left_in_iceoryx2s_default_namespace_are_removed() {
    if let Ok(name) = std::env::var(SLEEPER) {
        return sleeper_child(&name);
    }
    set_log_level(LogLevel::Error);
    let run = unique_run("hl");
    let name = node_name(&run, Stage::Env, 0);
    let mut k =
        child("dead_nodes_an_older_lmac_left_in_iceoryx2s_default_namespace_are_removed", &[(SLEEPER, name.clone()), (LEGACY, "1".into())]);
    wait_for_line(&mut k, "READY");
    unsafe { libc::kill(k.id() as i32, libc::SIGKILL) };
    let _ = k.wait();
    let names = vec![name.clone()];
    let t0 = Instant::now();
    while states(&names) != vec![Some(false)] {
        assert!(t0.elapsed() < Duration::from_secs(5), "the killed node is not seen dead: {:?}", states(&names));
        std::thread::sleep(Duration::from_millis(20));
    }
    let survey = lmac_shm_schema::leftovers::survey();
    assert!(survey.dead.iter().any(|f| f.name == name), "the old namespace's dead node is found");
    let removed = survey.remove();
    assert!(removed.removed.iter().any(|f| f.name == name), "and removed");
    assert_eq!(states(&names), vec![None], "it is gone from iceoryx2's node list");
}
