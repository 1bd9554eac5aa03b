//! The slot ring's control plane over iceoryx2: small fixed-size slot messages over
//! publish-subscribe, one event listener per process for wake-ups (no busy spinning), a start-up
//! handshake so no slot message is lost, shutdown messages, and liveness (a dead peer is found
//! through iceoryx2's node list and reported by name).
//!
//! Ownership of a slot travels env server -> protocol runner -> trainer -> env server. Per ring
//! member `s` (one sub-batch of an env server process: each has its own slab) there are three publish-subscribe services `lmac/<run>/s<s>/to_<stage>`; each
//! process has one event service `lmac/<run>/wake/<process>` it sleeps on.
//!
//! Hostile input is refused, never trusted: every slot message read from the ring is checked
//! against the ring's sizes (kind, member, slot) before anyone indexes with it, and an
//! out-of-range message is a [`RingError::BadMessage`] naming the sending node. Clean-up of dead
//! iceoryx2 nodes touches only this run's nodes (see [`is_run_node`]), never another
//! application's on the same machine.

use crate::slab::Stage;
use iceoryx2::identifiers::{UniqueNodeId, UniquePublisherId};
use iceoryx2::node::{NodeDetails, NodeView};
use iceoryx2::port::listener::{Listener, ListenerWaitError};
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use std::collections::{HashMap, HashSet};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

/// What travels on the ring: which slot of which member, and what kind of message it is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ZeroCopySend)]
#[repr(C)]
pub struct SlotMsg {
    pub kind: u32,
    pub member: u32,
    pub slot: u32,
    pub _pad: u32,
    pub seq: u64,
}

pub const KIND_SLOT: u32 = 0;
/// Start-up token: sent by an env server until it comes back around the ring.
pub const KIND_HELLO: u32 = 1;
/// Shutdown: the trainer tells the env servers, which tell the runner.
pub const KIND_BYE: u32 = 2;

/// Event id iceoryx2 sends when a notifier of the service died (see `event`).
const NOTIFIER_DEAD: usize = 200;

/// How long a wait sleeps before looking at peers' liveness.
const LIVENESS_PERIOD: Duration = Duration::from_millis(250);
/// How long an expected peer may take to appear at start-up.
pub const DEFAULT_STARTUP: Duration = Duration::from_secs(60);

static STOP: AtomicBool = AtomicBool::new(false);

/// Ask every wait of this process to return [`RingError::Stopped`] (from a signal handler).
pub fn request_stop() {
    STOP.store(true, Ordering::SeqCst);
}
/// Whether this process's waits should stop: asked by a signal handler, or the `lmac` parent
/// that started this pipeline process is gone. The second does not rely on its death signal
/// reaching a handler: a Python env server runs its SIGTERM handler only between bytecodes, so
/// one inside a long wait of this crate would otherwise wait out its start-up timeout.
pub fn stop_requested() -> bool {
    STOP.load(Ordering::SeqCst) || parent_gone()
}

/// The variable through which the supervisor tells each pipeline process its parent's pid.
pub const PARENT_PID_VAR: &str = "LMAC_PARENT_PID";

/// Whether the process named by `LMAC_PARENT_PID` is no longer this process's parent (it died;
/// the kernel re-parented this one). False when the variable is absent (not started by lmac).
fn parent_gone() -> bool {
    static PARENT: std::sync::OnceLock<Option<libc::pid_t>> = std::sync::OnceLock::new();
    // SAFETY: getppid has no preconditions and cannot fail.
    PARENT.get_or_init(|| std::env::var(PARENT_PID_VAR).ok().and_then(|v| v.parse().ok())).is_some_and(|p| unsafe { libc::getppid() } != p)
}

#[derive(Debug, thiserror::Error)]
pub enum RingError {
    #[error("peer {name} (pid {pid}) died")]
    PeerDied { name: String, pid: u32 },
    #[error("peer {name} exited without saying goodbye")]
    PeerGone { name: String },
    #[error("peer {name} did not start within {waited:?}")]
    PeerMissing { name: String, waited: Duration },
    #[error("stopped by request")]
    Stopped,
    #[error("iceoryx2: {0}")]
    Ipc(String),
    #[error("the start-up handshake of ring member {member} did not complete within {waited:?}")]
    Handshake { member: usize, waited: Duration },
    /// A slot message whose fields do not fit the ring: the peer is broken or hostile.
    #[error("bad ring message from {peer} on {service}: {field} = {value} {problem}")]
    BadMessage { peer: String, service: String, field: &'static str, value: u64, problem: String },
    /// This process asked for something the ring cannot do (a bad spec, an out-of-range send).
    #[error("ring: {0}")]
    Usage(String),
}

fn ipc<E: std::fmt::Debug>(what: &str) -> impl FnOnce(E) -> RingError + '_ {
    move |e| RingError::Ipc(format!("{what}: {e:?}"))
}

/// Name of a process's iceoryx2 node (also what errors report).
pub fn node_name(run: &str, role: Stage, member: usize) -> String {
    match role {
        Stage::Env => format!("lmac-{run}-env{member}"),
        Stage::Runner => format!("lmac-{run}-runner"),
        Stage::Trainer => format!("lmac-{run}-trainer"),
    }
}

/// Whether `name` is the node name of a process of run `run`, exactly as [`node_name`] spells it.
/// A prefix test is not enough: run ids need not be prefix-free (run `ab` must not claim the nodes
/// of run `ab-2`), and other applications may name their nodes anything.
pub fn is_run_node(run: &str, name: &str) -> bool {
    let Some(role) = name.strip_prefix("lmac-").and_then(|r| r.strip_prefix(run)).and_then(|r| r.strip_prefix('-')) else {
        return false;
    };
    match role {
        "runner" | "trainer" => true,
        _ => role.strip_prefix("env").and_then(|d| d.parse::<usize>().ok().map(|s| s.to_string() == d)).unwrap_or(false),
    }
}

/// The run of an lmac node name (as [`node_name`] spells it), or None for any other name.
pub fn run_of_node(name: &str) -> Option<&str> {
    let rest = name.strip_prefix("lmac-")?;
    // The role is the last dash-separated part; run ids may hold dashes themselves.
    let (run, _) = rest.rsplit_once('-')?;
    is_run_node(run, name).then_some(run)
}

/// The iceoryx2 configuration of lmac's nodes: the global one in a namespace of this user's own
/// (see [`private_namespace`]), and creating or dropping a node does not clean up every dead node
/// it can see (iceoryx2's default). This run's dead nodes are cleaned by [`Port::check_peers`] and
/// [`cleanup_dead_nodes`]; opening a service still cleans the dead nodes attached to that
/// service, which are all participants of this run's services.
pub fn ring_config() -> Config {
    let mut config = config_without_machine_wide_cleanup();
    let uid = current_uid();
    // Both are short ASCII, far below iceoryx2's name limits.
    config.global.set_root_path(&Path::new(private_root(uid).as_bytes()).expect("a valid root path"));
    config.global.prefix = FileName::new(namespace_prefix(uid).as_bytes()).expect("a valid file-name prefix");
    config
}

/// iceoryx2's global configuration without its clean-up of every dead node on the machine when a
/// node is created or dropped (which would remove other applications' stale resources too); in
/// iceoryx2's default namespace, where lmac versions before [`private_namespace`] kept their nodes.
pub fn config_without_machine_wide_cleanup() -> Config {
    let mut config = Config::global_config().clone();
    config.global.node.cleanup_dead_nodes_on_creation = false;
    config.global.node.cleanup_dead_nodes_on_destruction = false;
    config
}

fn current_uid() -> u32 {
    // SAFETY: getuid has no preconditions and cannot fail.
    unsafe { libc::getuid() }
}

/// The directory of this user's lmac iceoryx2 files (node and service descriptions, event
/// sockets): iceoryx2's default, `/tmp/iceoryx2/`, is one directory for every user and
/// application on the machine, so the first to create it decides who may use it.
fn private_root(uid: u32) -> String {
    format!("/tmp/lmac-iox2-{uid}/")
}

/// The prefix of this user's lmac files in /dev/shm.
fn namespace_prefix(uid: u32) -> String {
    format!("iox2_lmac{uid}_")
}

/// Make sure lmac's iceoryx2 namespace belongs to this user alone, before a node is created in
/// it: the root directory is created 0700, or if it exists it must be a real directory (not a
/// symlink) owned by this user that nobody else can write; and iceoryx2's node-id counter in
/// /dev/shm, which it creates world-writable (0666) whatever the config says, is made 0600 once it
/// exists (another user's file there is refused).
/// Called by [`Port::new`] before and after its node is created; an error names the path and what
/// is wrong with it.
pub fn private_namespace() -> Result<(), RingError> {
    use std::os::unix::fs::{MetadataExt, PermissionsExt};
    let uid = current_uid();
    let refuse = |path: &std::path::Path, problem: String| {
        RingError::Usage(format!(
            "{}: {problem}; lmac keeps its iceoryx2 files there and uses it only when it is this user's alone (uid {uid})",
            path.display()
        ))
    };
    let root = std::path::PathBuf::from(private_root(uid));
    ensure_private_dir(&root, uid).map_err(|problem| refuse(&root, problem))?;
    let prefix = namespace_prefix(uid);
    let Ok(entries) = std::fs::read_dir("/dev/shm") else { return Ok(()) };
    for e in entries.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        if !(name.starts_with(&prefix) && name.ends_with(".global_mgmt")) {
            continue;
        }
        let path = e.path();
        let Ok(md) = std::fs::symlink_metadata(&path) else { continue };
        if md.uid() != uid || !md.file_type().is_file() {
            return Err(refuse(&path, format!("belongs to uid {} (or is not a file)", md.uid())));
        }
        if md.mode() & 0o077 != 0 {
            std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o600))
                .map_err(|e| refuse(&path, format!("cannot make it private: {e}")))?;
        }
    }
    Ok(())
}

/// Create `dir` 0700, or accept it if it is a real directory (not a symlink) owned by `uid` that
/// nobody else can write; else say what is wrong.
fn ensure_private_dir(dir: &std::path::Path, uid: u32) -> Result<(), String> {
    use std::os::unix::fs::{DirBuilderExt, MetadataExt};
    // With a trailing slash, lstat resolves a symlink: look at the name itself.
    let trimmed = dir.to_string_lossy();
    let dir = std::path::Path::new(trimmed.trim_end_matches('/'));
    match std::fs::DirBuilder::new().mode(0o700).create(dir) {
        Ok(()) => {}
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {}
        Err(e) => return Err(format!("cannot create it: {e}")),
    }
    let md = std::fs::symlink_metadata(dir).map_err(|e| format!("cannot read it: {e}"))?;
    if !md.file_type().is_dir() {
        return Err("is not a directory (a symlink or a file someone put there)".into());
    }
    if md.uid() != uid {
        return Err(format!("belongs to uid {}", md.uid()));
    }
    if md.mode() & 0o022 != 0 {
        return Err(format!("others may write to it (mode {:o})", md.mode() & 0o777));
    }
    Ok(())
}

pub type SlotService = iceoryx2::service::port_factory::publish_subscribe::PortFactory<ipc::Service, SlotMsg, ()>;

/// Where this process sits in the ring.
#[derive(Clone, Debug)]
pub struct RingSpec {
    /// Run id: part of every service and node name, so runs never meet.
    pub run: String,
    pub n_members: usize,
    pub n_slots: usize,
    pub role: Stage,
    /// For an env-stage port: its ring member (one sub-batch of an env server process).
    pub member: usize,
}

pub struct Port {
    spec: RingSpec,
    node: Node<ipc::Service>,
    /// Indexed by ring member (an env-stage port has one, its own).
    inbox: Vec<Subscriber<ipc::Service, SlotMsg, ()>>,
    /// The service of each inbox and its name: to find who sent a bad message.
    inbox_services: Vec<(String, SlotService)>,
    outbox: Vec<Publisher<ipc::Service, SlotMsg, ()>>,
    listener: Listener<ipc::Service>,
    /// Env server: [runner]; runner: [trainer]; trainer: one per env server.
    notifiers: Vec<Notifier<ipc::Service>>,
    next_inbox: usize,
    last_check: Instant,
    started: Instant,
    startup: Duration,
    /// Expected peers and whether they have been seen alive.
    peers: HashMap<String, bool>,
    /// Peers that said goodbye (their disappearance is expected).
    departed: HashSet<String>,
    closing: bool,
    /// iceoryx2 reported a dead notifier: check peers before sleeping again.
    dead_notified: bool,
}

/// A slot-message service of the ring, with the settings every peer must open it with (a peer
/// asking for others is refused by iceoryx2).
pub fn pubsub(node: &Node<ipc::Service>, name: &str, n_slots: usize) -> Result<SlotService, RingError> {
    let sname = ServiceName::new(name).map_err(ipc("service name"))?;
    node.service_builder(&sname)
        .publish_subscribe::<SlotMsg>()
        // Every slot can be in flight at once, plus a few start-up tokens.
        .subscriber_max_buffer_size(2 * n_slots + 16)
        .history_size(0)
        .max_publishers(2)
        .max_subscribers(2)
        .enable_safe_overflow(false)
        .open_or_create()
        .map_err(ipc(name))
}

fn event(node: &Node<ipc::Service>, name: &str) -> Result<iceoryx2::service::port_factory::event::PortFactory<ipc::Service>, RingError> {
    let sname = ServiceName::new(name).map_err(ipc("service name"))?;
    // When a notifier's process dies and its resources are cleaned up, iceoryx2 wakes the
    // listener with NOTIFIER_DEAD, so a sleeping process looks at its peers at once.
    node.service_builder(&sname).event().notifier_dead_event(EventId::new(NOTIFIER_DEAD)).open_or_create().map_err(ipc(name))
}

impl Port {
    /// Create this process's node and ports. Nothing is sent yet.
    pub fn new(spec: RingSpec) -> Result<Port, RingError> {
        // Slot messages carry member and slot as u32; at least one of each makes a ring.
        if spec.n_members == 0 || spec.n_members > u32::MAX as usize {
            return Err(RingError::Usage(format!("n_members = {} must be between 1 and {}", spec.n_members, u32::MAX)));
        }
        if spec.n_slots == 0 || spec.n_slots > u32::MAX as usize {
            return Err(RingError::Usage(format!("n_slots = {} must be between 1 and {}", spec.n_slots, u32::MAX)));
        }
        if spec.role == Stage::Env && spec.member >= spec.n_members {
            return Err(RingError::Usage(format!("ring member {} does not exist in a ring of {} members", spec.member, spec.n_members)));
        }
        // iceoryx2 warns on stderr that it runs on its default config; that is intended here.
        set_log_level(LogLevel::Error);
        let run = spec.run.clone();
        let me = node_name(&run, spec.role, spec.member);
        private_namespace()?;
        let node = NodeBuilder::new()
            .config(&ring_config())
            .name(&NodeName::new(&me).map_err(ipc("node name"))?)
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<ipc::Service>()
            .map_err(ipc("node"))?;
        // The node-id counter exists now (the first node creates it).
        private_namespace()?;
        let svc = |s: usize, to: &str| format!("lmac/{run}/s{s}/to_{to}");
        let wake_env = |s: usize| format!("lmac/{run}/wake/env{s}");
        let wake_runner = format!("lmac/{run}/wake/runner");
        let wake_trainer = format!("lmac/{run}/wake/trainer");
        let members: Vec<usize> = match spec.role {
            Stage::Env => vec![spec.member],
            _ => (0..spec.n_members).collect(),
        };
        let (me_to, next_to) = match spec.role {
            Stage::Env => ("env", "runner"),
            Stage::Runner => ("runner", "trainer"),
            Stage::Trainer => ("trainer", "env"),
        };
        let mut inbox = Vec::new();
        let mut inbox_services = Vec::new();
        let mut outbox = Vec::new();
        for &s in &members {
            let name = svc(s, me_to);
            let f = pubsub(&node, &name, spec.n_slots)?;
            inbox.push(f.subscriber_builder().create().map_err(ipc("subscriber"))?);
            inbox_services.push((name, f));
        }
        for &s in &members {
            let f = pubsub(&node, &svc(s, next_to), spec.n_slots)?;
            outbox.push(f.publisher_builder().max_loaned_samples(2).create().map_err(ipc("publisher"))?);
        }
        let my_wake = match spec.role {
            Stage::Env => wake_env(spec.member),
            Stage::Runner => wake_runner.clone(),
            Stage::Trainer => wake_trainer.clone(),
        };
        let listener = event(&node, &my_wake)?.listener_builder().create().map_err(ipc("listener"))?;
        let notify_names: Vec<String> = match spec.role {
            Stage::Env => vec![wake_runner],
            Stage::Runner => vec![wake_trainer],
            Stage::Trainer => members.iter().map(|&s| wake_env(s)).collect(),
        };
        let mut notifiers = Vec::new();
        for n in &notify_names {
            notifiers.push(event(&node, n)?.notifier_builder().create().map_err(ipc("notifier"))?);
        }
        let mut peers = HashMap::new();
        match spec.role {
            Stage::Env => {
                peers.insert(node_name(&run, Stage::Runner, 0), false);
                peers.insert(node_name(&run, Stage::Trainer, 0), false);
            }
            Stage::Runner | Stage::Trainer => {
                for s in 0..spec.n_members {
                    peers.insert(node_name(&run, Stage::Env, s), false);
                }
                let other = if spec.role == Stage::Runner { Stage::Trainer } else { Stage::Runner };
                peers.insert(node_name(&run, other, 0), false);
            }
        }
        Ok(Port {
            spec,
            node,
            inbox,
            inbox_services,
            outbox,
            listener,
            notifiers,
            next_inbox: 0,
            last_check: Instant::now(),
            started: Instant::now(),
            startup: DEFAULT_STARTUP,
            peers,
            departed: HashSet::new(),
            closing: false,
            dead_notified: false,
        })
    }

    pub fn spec(&self) -> &RingSpec {
        &self.spec
    }

    /// How long peers may take to appear before [`RingError::PeerMissing`].
    pub fn set_startup_timeout(&mut self, d: Duration) {
        self.startup = d;
    }

    fn out_index(&self, member: usize) -> usize {
        if self.spec.role == Stage::Env {
            0
        } else {
            member
        }
    }

    fn post(&self, msg: SlotMsg) -> Result<(), RingError> {
        // The receiver refuses out-of-range messages; refusing them here names the culprit.
        let (member, slot) = (msg.member as usize, msg.slot as usize);
        if member >= self.spec.n_members || (self.spec.role == Stage::Env && member != self.spec.member) {
            return Err(RingError::Usage(format!(
                "the {} cannot send for ring member {member} (ring of {} members)",
                self.spec.role.name(),
                self.spec.n_members
            )));
        }
        if slot >= self.spec.n_slots {
            return Err(RingError::Usage(format!("cannot send slot {slot}: each ring member has {} slots", self.spec.n_slots)));
        }
        let i = self.out_index(member);
        self.outbox[i].send_copy(msg).map_err(ipc("send"))?;
        let n = if self.spec.role == Stage::Trainer { i } else { 0 };
        self.notifiers[n].notify().map_err(ipc("notify"))?;
        Ok(())
    }

    /// Hand slot `slot` of `member` to the next stage.
    pub fn send_slot(&self, member: usize, slot: usize, seq: u64) -> Result<(), RingError> {
        self.post(SlotMsg { kind: KIND_SLOT, member: member as u32, slot: slot as u32, _pad: 0, seq })
    }

    /// Say goodbye to the next stage for `member` (trainer: to that env server; env server: to
    /// the runner). After a goodbye, peers vanishing is expected.
    pub fn send_bye(&mut self, member: usize) -> Result<(), RingError> {
        self.closing = true;
        self.post(SlotMsg { kind: KIND_BYE, member: member as u32, slot: 0, _pad: 0, seq: 0 })
    }

    /// Env servers: send start-up tokens until one comes back around the ring, which proves
    /// every hop of this member's ring is connected and listening.
    pub fn handshake(&mut self, timeout: Duration) -> Result<(), RingError> {
        if self.spec.role != Stage::Env {
            return Err(RingError::Usage(format!("the {} cannot start the handshake: only env servers do", self.spec.role.name())));
        }
        let t0 = Instant::now();
        let s = self.spec.member as u32;
        loop {
            self.post(SlotMsg { kind: KIND_HELLO, member: s, slot: 0, _pad: 0, seq: 0 })?;
            let wait_until = Instant::now() + Duration::from_millis(20);
            while let Some(m) = self.recv_raw(wait_until)? {
                if m.kind == KIND_HELLO && m.member == s {
                    // Drain the tokens still in flight so they cannot be mistaken later.
                    return Ok(());
                }
            }
            if t0.elapsed() > timeout {
                return Err(RingError::Handshake { member: self.spec.member, waited: timeout });
            }
        }
    }

    /// Wait up to `timeout` for the next slot message addressed to this process.
    /// Start-up tokens are forwarded transparently; a goodbye is returned (kind KIND_BYE) after
    /// being forwarded by env servers. Returns Ok(None) on timeout (or a signal, see `recv_raw`).
    pub fn recv(&mut self, timeout: Duration) -> Result<Option<SlotMsg>, RingError> {
        let deadline = Instant::now() + timeout;
        loop {
            let Some(m) = self.recv_raw(deadline)? else { return Ok(None) };
            match m.kind {
                KIND_HELLO => {
                    // Runner and trainer pass the token on; an env server drops stale tokens.
                    if self.spec.role != Stage::Env {
                        self.post(m)?;
                    }
                }
                KIND_BYE => {
                    self.closing = true;
                    match self.spec.role {
                        Stage::Env => {
                            self.departed.insert(node_name(&self.spec.run, Stage::Trainer, 0));
                            self.post(m)?;
                        }
                        Stage::Runner => {
                            self.departed.insert(node_name(&self.spec.run, Stage::Env, m.member as usize));
                        }
                        Stage::Trainer => {}
                    }
                    return Ok(Some(m));
                }
                _ => return Ok(Some(m)),
            }
        }
    }

    /// Next message of any kind, sleeping on the event listener, checking liveness while idle.
    /// Ok(None) at the deadline or when a signal interrupted the sleep.
    fn recv_raw(&mut self, deadline: Instant) -> Result<Option<SlotMsg>, RingError> {
        loop {
            let n = self.inbox.len();
            for k in 0..n {
                let i = (self.next_inbox + k) % n;
                if let Some(sample) = self.inbox[i].receive().map_err(ipc("receive"))? {
                    self.next_inbox = (i + 1) % n;
                    let (msg, origin) = (*sample, sample.origin());
                    drop(sample);
                    if let Err((field, value, problem)) = check_slot_msg(&self.spec, i, &msg) {
                        let (service, _) = &self.inbox_services[i];
                        return Err(RingError::BadMessage {
                            peer: self.sender(i, origin),
                            service: service.clone(),
                            field,
                            value,
                            problem,
                        });
                    }
                    return Ok(Some(msg));
                }
            }
            if stop_requested() {
                return Err(RingError::Stopped);
            }
            let now = Instant::now();
            if self.dead_notified || now.duration_since(self.last_check) >= LIVENESS_PERIOD {
                self.dead_notified = false;
                self.check_peers()?;
                self.last_check = now;
            }
            if now >= deadline {
                return Ok(None);
            }
            let wait = (deadline - now).min(LIVENESS_PERIOD);
            let mut dead = false;
            match self.listener.timed_wait(|ev| dead |= ev.id == EventId::new(NOTIFIER_DEAD), wait) {
                // A signal (Ctrl-C, SIGCHLD, a debugger or profiler attaching) cut the wait short:
                // return as on a timeout so the caller can look at it; nothing was lost.
                Err(ListenerWaitError::InterruptSignal) => return Ok(None),
                r => r.map(|_| ()).map_err(ipc("wait"))?,
            }
            self.dead_notified |= dead;
        }
    }

    /// Who published `origin` on inbox `i`'s service: node name and pid, found through the
    /// service's publisher list and iceoryx2's node list (only on the error path).
    fn sender(&self, i: usize, origin: UniquePublisherId) -> String {
        let expected = match self.spec.role {
            Stage::Env => node_name(&self.spec.run, Stage::Trainer, 0),
            Stage::Runner => node_name(&self.spec.run, Stage::Env, i),
            Stage::Trainer => node_name(&self.spec.run, Stage::Runner, 0),
        };
        let (_, service) = &self.inbox_services[i];
        let mut node_id = None;
        service.dynamic_config().list_publishers(|p| {
            if p.publisher_id == origin {
                node_id = Some(p.node_id);
                return CallbackProgression::Stop;
            }
            CallbackProgression::Continue
        });
        let mut found = None;
        if let Some(id) = node_id {
            let _ = Node::<ipc::Service>::list(self.node.config(), |state| {
                let view: Option<(&UniqueNodeId, &Option<NodeDetails>)> = match &state {
                    NodeState::Alive(v) => Some((v.id(), v.details())),
                    NodeState::Dead(v) => Some((v.id(), v.details())),
                    _ => None,
                };
                if let Some((vid, Some(d))) = view {
                    if *vid == id {
                        found = Some(format!("node {} (pid {})", d.name(), d.process_id().value()));
                        return CallbackProgression::Stop;
                    }
                }
                CallbackProgression::Continue
            });
        }
        found.unwrap_or_else(|| format!("an unknown publisher (the sender there should be {expected})"))
    }

    /// Look for dead or vanished peers of this run; report the first by name.
    pub fn check_peers(&mut self) -> Result<(), RingError> {
        let run = &self.spec.run;
        let mut alive = HashSet::new();
        let mut dead = Vec::new();
        let _ = Node::<ipc::Service>::list(self.node.config(), |state| {
            match &state {
                NodeState::Alive(v) => {
                    if let Some(d) = v.details() {
                        alive.insert(d.name().to_string());
                    }
                }
                NodeState::Dead(v) => {
                    if let Some(d) = v.details() {
                        let name = d.name().to_string();
                        if is_run_node(run, &name) {
                            dead.push((name, d.process_id().value() as u32, v.clone()));
                        }
                    }
                }
                _ => {}
            }
            CallbackProgression::Continue
        });
        let mut report = None;
        for (name, pid, view) in dead {
            // Remove its stale iceoryx2 resources so nothing is left behind.
            let _ = view.try_remove_stale_resources();
            if self.peers.contains_key(&name) && !self.departed.contains(&name) && !self.closing && report.is_none() {
                report = Some(RingError::PeerDied { name, pid });
            }
        }
        if let Some(e) = report {
            return Err(e);
        }
        let startup_over = self.started.elapsed() > self.startup;
        for (name, seen) in self.peers.iter_mut() {
            if alive.contains(name) {
                *seen = true;
            } else if self.closing || self.departed.contains(name) {
            } else if *seen {
                return Err(RingError::PeerGone { name: name.clone() });
            } else if startup_over {
                return Err(RingError::PeerMissing { name: name.clone(), waited: self.startup });
            }
        }
        Ok(())
    }

    /// After goodbyes: wait until no expected peer is alive any more (or `timeout`), so the
    /// messages this process published stay readable until they are taken.
    pub fn wait_peers_gone(&mut self, timeout: Duration) -> bool {
        let peers: Vec<String> = self.peers.keys().cloned().collect();
        self.wait_gone(&peers, timeout)
    }

    /// After forwarding a goodbye: wait until the stage this process posts to (an env server's
    /// protocol runner, a runner's trainer, the trainer's env servers) is gone, or `timeout`.
    /// The goodbye stays readable only while its publisher lives, and a runner that has not
    /// yet taken it when the env server exits reports the env server gone without one (seen
    /// with the machine loaded). Waiting on the upstream too would wait on the trainer, which
    /// waits for its env servers to exit.
    pub fn wait_downstream_gone(&mut self, timeout: Duration) -> bool {
        let (run, n) = (self.spec.run.clone(), self.spec.n_members);
        let downstream: Vec<String> = match self.spec.role {
            Stage::Env => vec![node_name(&run, Stage::Runner, 0)],
            Stage::Runner => vec![node_name(&run, Stage::Trainer, 0)],
            Stage::Trainer => (0..n).map(|m| node_name(&run, Stage::Env, m)).collect(),
        };
        self.wait_gone(&downstream, timeout)
    }

    /// Wait until none of the nodes `names` is alive (true), or `timeout` (false).
    fn wait_gone(&mut self, names: &[String], timeout: Duration) -> bool {
        let t0 = Instant::now();
        loop {
            let mut any = false;
            let _ = Node::<ipc::Service>::list(self.node.config(), |state| {
                if let NodeState::Alive(v) = &state {
                    if let Some(d) = v.details() {
                        let name = d.name().to_string();
                        if names.contains(&name) {
                            any = true;
                        }
                    }
                }
                CallbackProgression::Continue
            });
            if !any {
                return true;
            }
            if t0.elapsed() >= timeout {
                return false;
            }
            // Drain (and drop) whatever still arrives; keep the ring moving for peers.
            let _ = self.listener.timed_wait(|_| {}, Duration::from_millis(20));
            for sub in &self.inbox {
                while let Ok(Some(_)) = sub.receive() {}
            }
        }
    }

    pub fn node(&self) -> &Node<ipc::Service> {
        &self.node
    }
}

/// Check a slot message taken from inbox `inbox` of a port with `spec` against the ring's sizes,
/// before anyone indexes with it: (field, value, what is wrong) for the first field that does
/// not fit. `Port::recv` applies it to every message; public so it can be fuzzed on its own.
pub fn check_slot_msg(spec: &RingSpec, inbox: usize, m: &SlotMsg) -> Result<(), (&'static str, u64, String)> {
    if !matches!(m.kind, KIND_SLOT | KIND_HELLO | KIND_BYE) {
        return Err(("kind", m.kind as u64, format!("is not a message kind (slot {KIND_SLOT}, hello {KIND_HELLO}, goodbye {KIND_BYE})")));
    }
    let n_members = spec.n_members;
    if m.member as usize >= n_members {
        return Err(("member", m.member as u64, format!("is out of range: the ring has {n_members} member(s)")));
    }
    // Each inbox is the service of one ring member; a message there speaks of that member only.
    let expect = if spec.role == Stage::Env { spec.member } else { inbox };
    if m.member as usize != expect {
        return Err(("member", m.member as u64, format!("does not match the service it came on, which is ring member {expect}'s")));
    }
    if m.slot as usize >= spec.n_slots {
        return Err(("slot", m.slot as u64, format!("is out of range: each ring member has {} slot(s)", spec.n_slots)));
    }
    Ok(())
}

/// Remove the iceoryx2 resources of run `run`'s dead nodes (after a crash); returns how many
/// were cleaned. Dead nodes of other runs and other applications are left alone: they are not
/// ours to judge (their owner may still want to inspect or clean them itself).
pub fn cleanup_dead_nodes(run: &str) -> usize {
    set_log_level(LogLevel::Error);
    let mut n = 0;
    let _ = Node::<ipc::Service>::list(&ring_config(), |state| {
        if let NodeState::Dead(v) = state {
            let ours = v.details().as_ref().is_some_and(|d| is_run_node(run, &d.name().to_string()));
            if ours && v.try_remove_stale_resources().is_ok() {
                n += 1;
            }
        }
        CallbackProgression::Continue
    });
    n
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::unix::fs::PermissionsExt;

    /// iceoryx2's default root, /tmp/iceoryx2, is one directory for every user; lmac's
    /// own is used only when it is this user's alone.
    #[test]
    fn the_namespace_root_is_used_only_when_it_is_private() {
        let uid = current_uid();
        let base = std::env::temp_dir().join(format!("lmac-private-dir-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&base);
        std::fs::create_dir_all(&base).unwrap();
        // Created 0700 when missing; accepted again.
        let fresh = base.join("fresh");
        ensure_private_dir(&fresh, uid).unwrap();
        assert_eq!(std::fs::metadata(&fresh).unwrap().permissions().mode() & 0o777, 0o700);
        ensure_private_dir(&fresh, uid).unwrap();
        // A symlink planted in its place (to a directory of the planter's choosing) is refused.
        let link = base.join("link");
        std::os::unix::fs::symlink(&fresh, &link).unwrap();
        assert!(ensure_private_dir(&link, uid).unwrap_err().contains("not a directory"));
        // Also when named with a trailing slash, as the namespace root is: lstat would follow it.
        let slashed = std::path::PathBuf::from(format!("{}/", link.display()));
        assert!(ensure_private_dir(&slashed, uid).unwrap_err().contains("not a directory"));
        assert_eq!(private_root(uid).trim_end_matches('/'), format!("/tmp/lmac-iox2-{uid}"));
        // A directory others may write to is refused; so is someone else's.
        let open = base.join("open");
        std::fs::create_dir(&open).unwrap();
        std::fs::set_permissions(&open, std::fs::Permissions::from_mode(0o777)).unwrap();
        assert!(ensure_private_dir(&open, uid).unwrap_err().contains("others may write"));
        assert!(ensure_private_dir(&fresh, uid.wrapping_add(4242)).unwrap_err().contains("belongs to uid"));
        let _ = std::fs::remove_dir_all(&base);
    }
}
