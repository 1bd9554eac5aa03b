//! The slot ring's control plane over iceoryx2: small fixed-size slot messages over
//! publish-subscribe, one event listener per process for wake-ups (no busy spinning), a start-up
//! handshake so no slot message is lost, shutdown messages, and liveness (a dead peer is found
//! through iceoryx2's node list and reported by name).
//!
//! Ownership of a slot travels env server -> protocol runner -> trainer -> env server. Per env
//! server `s` there are three publish-subscribe services `lmac/<run>/s<s>/to_<stage>`; each
//! process has one event service `lmac/<run>/wake/<process>` it sleeps on.

use crate::slab::Stage;
use iceoryx2::node::NodeView;
use iceoryx2::port::listener::{Listener, ListenerWaitError};
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use std::collections::{HashMap, HashSet};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

/// What travels on the ring: which slot of which server, and what kind of message it is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ZeroCopySend)]
#[repr(C)]
pub struct SlotMsg {
    pub kind: u32,
    pub server: u32,
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
pub fn stop_requested() -> bool {
    STOP.load(Ordering::SeqCst)
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
    #[error("the start-up handshake of env server {server} did not complete within {waited:?}")]
    Handshake { server: usize, waited: Duration },
}

fn ipc<E: std::fmt::Debug>(what: &str) -> impl FnOnce(E) -> RingError + '_ {
    move |e| RingError::Ipc(format!("{what}: {e:?}"))
}

/// Name of a process's iceoryx2 node (also what errors report).
pub fn node_name(run: &str, role: Stage, server: usize) -> String {
    match role {
        Stage::Env => format!("lmac-{run}-env{server}"),
        Stage::Runner => format!("lmac-{run}-runner"),
        Stage::Trainer => format!("lmac-{run}-trainer"),
    }
}

/// Where this process sits in the ring.
#[derive(Clone, Debug)]
pub struct RingSpec {
    /// Run id: part of every service and node name, so runs never meet.
    pub run: String,
    pub n_servers: usize,
    pub n_slots: usize,
    pub role: Stage,
    /// For an env server: its index.
    pub server: usize,
}

pub struct Port {
    spec: RingSpec,
    node: Node<ipc::Service>,
    /// Indexed by server (an env server has one, its own).
    inbox: Vec<Subscriber<ipc::Service, SlotMsg, ()>>,
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

fn pubsub(
    node: &Node<ipc::Service>,
    name: &str,
    n_slots: usize,
) -> Result<iceoryx2::service::port_factory::publish_subscribe::PortFactory<ipc::Service, SlotMsg, ()>, RingError> {
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
        // iceoryx2 warns on stderr that it runs on its default config; that is intended here.
        set_log_level(LogLevel::Error);
        let run = spec.run.clone();
        let me = node_name(&run, spec.role, spec.server);
        let node = NodeBuilder::new()
            .name(&NodeName::new(&me).map_err(ipc("node name"))?)
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<ipc::Service>()
            .map_err(ipc("node"))?;
        let svc = |s: usize, to: &str| format!("lmac/{run}/s{s}/to_{to}");
        let wake_env = |s: usize| format!("lmac/{run}/wake/env{s}");
        let wake_runner = format!("lmac/{run}/wake/runner");
        let wake_trainer = format!("lmac/{run}/wake/trainer");
        let servers: Vec<usize> = match spec.role {
            Stage::Env => vec![spec.server],
            _ => (0..spec.n_servers).collect(),
        };
        let (me_to, next_to) = match spec.role {
            Stage::Env => ("env", "runner"),
            Stage::Runner => ("runner", "trainer"),
            Stage::Trainer => ("trainer", "env"),
        };
        let mut inbox = Vec::new();
        let mut outbox = Vec::new();
        for &s in &servers {
            let f = pubsub(&node, &svc(s, me_to), spec.n_slots)?;
            inbox.push(f.subscriber_builder().create().map_err(ipc("subscriber"))?);
        }
        for &s in &servers {
            let f = pubsub(&node, &svc(s, next_to), spec.n_slots)?;
            outbox.push(f.publisher_builder().max_loaned_samples(2).create().map_err(ipc("publisher"))?);
        }
        let my_wake = match spec.role {
            Stage::Env => wake_env(spec.server),
            Stage::Runner => wake_runner.clone(),
            Stage::Trainer => wake_trainer.clone(),
        };
        let listener = event(&node, &my_wake)?.listener_builder().create().map_err(ipc("listener"))?;
        let notify_names: Vec<String> = match spec.role {
            Stage::Env => vec![wake_runner],
            Stage::Runner => vec![wake_trainer],
            Stage::Trainer => servers.iter().map(|&s| wake_env(s)).collect(),
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
                for s in 0..spec.n_servers {
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

    fn out_index(&self, server: usize) -> usize {
        if self.spec.role == Stage::Env {
            0
        } else {
            server
        }
    }

    fn post(&self, msg: SlotMsg) -> Result<(), RingError> {
        let i = self.out_index(msg.server as usize);
        self.outbox[i].send_copy(msg).map_err(ipc("send"))?;
        let n = if self.spec.role == Stage::Trainer { i } else { 0 };
        self.notifiers[n].notify().map_err(ipc("notify"))?;
        Ok(())
    }

    /// Hand slot `slot` of `server` to the next stage.
    pub fn send_slot(&self, server: usize, slot: usize, seq: u64) -> Result<(), RingError> {
        self.post(SlotMsg { kind: KIND_SLOT, server: server as u32, slot: slot as u32, _pad: 0, seq })
    }

    /// Say goodbye to the next stage for `server` (trainer: to that env server; env server: to
    /// the runner). After a goodbye, peers vanishing is expected.
    pub fn send_bye(&mut self, server: usize) -> Result<(), RingError> {
        self.closing = true;
        self.post(SlotMsg { kind: KIND_BYE, server: server as u32, slot: 0, _pad: 0, seq: 0 })
    }

    /// Env servers: send start-up tokens until one comes back around the ring, which proves
    /// every hop of this server's ring is connected and listening.
    pub fn handshake(&mut self, timeout: Duration) -> Result<(), RingError> {
        assert_eq!(self.spec.role, Stage::Env, "only env servers start the handshake");
        let t0 = Instant::now();
        let s = self.spec.server as u32;
        loop {
            self.post(SlotMsg { kind: KIND_HELLO, server: s, slot: 0, _pad: 0, seq: 0 })?;
            let wait_until = Instant::now() + Duration::from_millis(20);
            while let Some(m) = self.recv_raw(wait_until)? {
                if m.kind == KIND_HELLO && m.server == s {
                    // Drain the tokens still in flight so they cannot be mistaken later.
                    return Ok(());
                }
            }
            if t0.elapsed() > timeout {
                return Err(RingError::Handshake { server: self.spec.server, waited: timeout });
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
                            self.departed.insert(node_name(&self.spec.run, Stage::Env, m.server as usize));
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
                    return Ok(Some(*sample));
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

    /// Look for dead or vanished peers of this run; report the first by name.
    pub fn check_peers(&mut self) -> Result<(), RingError> {
        let prefix = format!("lmac-{}-", self.spec.run);
        let mut alive = HashSet::new();
        let mut dead = Vec::new();
        let _ = Node::<ipc::Service>::list(Config::global_config(), |state| {
            match &state {
                NodeState::Alive(v) => {
                    if let Some(d) = v.details() {
                        alive.insert(d.name().to_string());
                    }
                }
                NodeState::Dead(v) => {
                    if let Some(d) = v.details() {
                        let name = d.name().to_string();
                        if name.starts_with(&prefix) {
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
        let t0 = Instant::now();
        loop {
            let mut any = false;
            let peers = &self.peers;
            let _ = Node::<ipc::Service>::list(Config::global_config(), |state| {
                if let NodeState::Alive(v) = &state {
                    if let Some(d) = v.details() {
                        if peers.contains_key(&d.name().to_string()) {
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

/// Remove the iceoryx2 resources of dead nodes (after a crash); returns how many were cleaned.
pub fn cleanup_dead_nodes() -> usize {
    set_log_level(LogLevel::Error);
    let mut n = 0;
    let _ = Node::<ipc::Service>::list(Config::global_config(), |state| {
        if let NodeState::Dead(v) = state {
            if v.try_remove_stale_resources().is_ok() {
                n += 1;
            }
        }
        CallbackProgression::Continue
    });
    n
}
