//! What dead lmac runs leave in shared memory, and its removal: `lmac clean`, and every start.
//!
//! A run that ends normally removes its slabs and iceoryx2 resources (the supervisor's
//! `cleanup_run`); a run whose whole process group is killed (`kill -9`, `timeout -s KILL`, a
//! scheduler, the OOM killer) cannot, and leaves its slabs (`/dev/shm/lmac-<run>-s<i>`), its dead
//! iceoryx2 nodes (`lmac-<run>-...`) and the iceoryx2 services only they held. This module finds
//! them and removes them, under three rules:
//!
//! - **never a live run's**: a slab is left alone while any iceoryx2 node of its run is alive
//!   (iceoryx2 decides that with a lock its owner holds, not with a pid that may be reused) or
//!   while the env server recorded in its header lives; a node only when iceoryx2 reports it dead;
//! - **never another user's**: only files owned by this user are touched, and only lmac's names;
//! - **nothing followed**: a slab name that is not a regular file (a planted symlink) is skipped.

use crate::ring::{config_without_machine_wide_cleanup, ring_config, run_of_node};
use crate::slab::{header_state, parse_slab_name, shm_file_path, SlabHeaderState};
use iceoryx2::node::{DeadNodeView, NodeView};
use iceoryx2::prelude::*;
use std::collections::HashSet;
use std::os::unix::fs::MetadataExt;
use std::time::{Duration, SystemTime};

/// A slab whose header is unfinished is left alone this long after its last change: its creator
/// may be between `shm_open` and writing the header (microseconds), or may have died there.
const UNFINISHED_GRACE: Duration = Duration::from_secs(10);

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    /// A slab in /dev/shm.
    Slab,
    /// An iceoryx2 node (and, through it, the services only it held).
    Node,
}

/// One lmac resource found in shared memory, with why it is (or is not) removable.
#[derive(Clone, Debug)]
pub struct Found {
    pub kind: Kind,
    /// The slab's file name or the node's name.
    pub name: String,
    pub run: String,
    /// Why it is dead, or why it is kept.
    pub why: String,
}

/// The lmac resources in shared memory: those of dead owners (`dead`) and those left alone
/// (`kept`: a live run's, another user's, not a regular file, or still being created).
pub struct Survey {
    pub dead: Vec<Found>,
    pub kept: Vec<Found>,
    /// The dead nodes of `dead`, in order, with their directories.
    dead_nodes: Vec<(DeadNodeView<ipc::Service>, Option<std::path::PathBuf>)>,
}

/// What [`Survey::remove`] did with each dead resource.
pub struct Removed {
    pub removed: Vec<Found>,
    /// Resources that could not be removed, with the reason.
    pub failed: Vec<(Found, String)>,
}

fn my_uid() -> u32 {
    // SAFETY: geteuid cannot fail.
    unsafe { libc::geteuid() }
}

/// When process `pid` started, from /proc (boot time plus its start in clock ticks); None when
/// there is no such process or it is a zombie (it only waits to be reaped: dead for our purposes).
fn process_start(pid: u32) -> Option<SystemTime> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // Fields after the parenthesised command name (which may hold spaces): state is the 1st,
    // starttime the 20th.
    let rest: Vec<&str> = stat.rsplit_once(')')?.1.split_whitespace().collect();
    if rest.first() == Some(&"Z") {
        return None;
    }
    let ticks: u64 = rest.get(19)?.parse().ok()?;
    let btime: u64 = std::fs::read_to_string("/proc/stat").ok()?.lines().find_map(|l| l.strip_prefix("btime ")?.trim().parse().ok())?;
    // SAFETY: sysconf has no preconditions.
    let hz = unsafe { libc::sysconf(libc::_SC_CLK_TCK) }.max(1) as u64;
    Some(SystemTime::UNIX_EPOCH + Duration::from_secs(btime) + Duration::from_millis(ticks * 1000 / hz))
}

/// Whether the process that created a slab last changed at `changed` may still be `pid`: a live
/// process that started before then. A pid reused by a process started later is not the creator.
fn creator_alive(pid: u32, changed: SystemTime) -> bool {
    // Boot time is whole seconds and start times are in clock ticks: allow for the rounding.
    process_start(pid).is_some_and(|started| started <= changed + Duration::from_secs(2))
}

/// The iceoryx2 node directory of a node id (iceoryx2 names it by the id in decimal; the id's
/// Display is hex).
fn node_dir(config: &Config, id: &impl std::fmt::Display) -> Option<std::path::PathBuf> {
    let id = u128::from_str_radix(&id.to_string(), 16).ok()?;
    Some(std::path::PathBuf::from(config.global.node_dir().to_string()).join(id.to_string()))
}

/// Look at every lmac slab and iceoryx2 node on this machine and sort them into dead and kept.
/// Nothing is changed.
pub fn survey() -> Survey {
    set_log_level(LogLevel::Error);
    // lmac's own namespace, and iceoryx2's default one, where lmac versions before the
    // namespace kept their nodes: an upgraded machine's leftovers are found too.
    let configs = [ring_config(), config_without_machine_wide_cleanup()];
    let me = my_uid();
    let mut live_runs = HashSet::new();
    let (mut dead, mut kept, mut dead_nodes) = (Vec::new(), Vec::new(), Vec::new());
    let mut dead_views = Vec::new();
    for (c, config) in configs.iter().enumerate() {
        let _ = Node::<ipc::Service>::list(config, |state| {
            match state {
                NodeState::Alive(v) => {
                    if let Some(d) = v.details() {
                        let name = d.name().to_string();
                        if let Some(run) = run_of_node(&name) {
                            live_runs.insert(run.to_string());
                            let why = format!("alive (pid {})", d.process_id().value());
                            kept.push(Found { kind: Kind::Node, run: run.to_string(), name, why });
                        }
                    }
                }
                NodeState::Dead(v) => {
                    if let Some(d) = v.details().clone() {
                        if let Some(run) = run_of_node(&d.name().to_string()) {
                            dead_views.push((run.to_string(), d, v, c));
                        }
                    }
                }
                // Nodes this user may not inspect are not ours to judge.
                NodeState::Inaccessible(_) | NodeState::Undefined(_) => {}
            }
            CallbackProgression::Continue
        });
    }
    for (run, d, v, c) in dead_views {
        let name = d.name().to_string();
        let dir = node_dir(&configs[c], v.id());
        let owner = dir.as_ref().and_then(|p| std::fs::symlink_metadata(p).ok()).map(|m| m.uid());
        let pid = d.process_id().value();
        let found = |why: String| Found { kind: Kind::Node, name: name.clone(), run: run.clone(), why };
        match owner {
            // A live run watches its own peers: it reports the death by name and cleans up.
            _ if live_runs.contains(&run) => kept.push(found(format!("dead (pid {pid}), but its run has live processes"))),
            Some(uid) if uid == me => {
                dead.push(found(format!("its process (pid {pid}) is dead")));
                dead_nodes.push((v, dir));
            }
            Some(uid) => kept.push(found(format!("another user's (uid {uid})"))),
            None => kept.push(found("its owner could not be determined".into())),
        }
    }
    let mut names: Vec<String> =
        std::fs::read_dir("/dev/shm").into_iter().flatten().flatten().map(|e| e.file_name().to_string_lossy().into_owned()).collect();
    names.sort();
    for name in names {
        let Some((run, _)) = parse_slab_name(&name) else { continue };
        let run = run.to_string();
        let Ok(meta) = std::fs::symlink_metadata(shm_file_path(&name)) else { continue };
        let found = |why: String| Found { kind: Kind::Slab, name: name.clone(), run: run.clone(), why };
        let changed = SystemTime::UNIX_EPOCH + Duration::from_secs(meta.ctime().max(0) as u64);
        if meta.uid() != me {
            kept.push(found(format!("another user's (uid {})", meta.uid())));
        } else if !meta.file_type().is_file() {
            kept.push(found("not a regular file".into()));
        } else if live_runs.contains(&run) {
            kept.push(found("its run has live processes".into()));
        } else {
            match header_state(&name) {
                SlabHeaderState::Ready(pid) if creator_alive(pid, changed) => {
                    kept.push(found(format!("its env server (pid {pid}) is alive")))
                }
                SlabHeaderState::Ready(pid) => dead.push(found(format!("its env server (pid {pid}) is dead"))),
                SlabHeaderState::Unfinished if changed.elapsed().unwrap_or_default() < UNFINISHED_GRACE => {
                    kept.push(found("being created".into()))
                }
                SlabHeaderState::Unfinished => dead.push(found("its creator never finished it".into())),
                SlabHeaderState::Foreign => kept.push(found("not an lmac slab (no lmac header)".into())),
            }
        }
    }
    Survey { dead, kept, dead_nodes }
}

impl Survey {
    /// Remove every dead resource of the survey: slabs by name (`shm_unlink` does not follow
    /// links), nodes through iceoryx2, which also removes the services only they held.
    pub fn remove(self) -> Removed {
        let (mut removed, mut failed) = (Vec::new(), Vec::new());
        let mut nodes = self.dead_nodes.into_iter();
        for f in self.dead {
            let result = match f.kind {
                Kind::Slab if crate::slab::unlink(&f.name) => Ok(()),
                Kind::Slab => Err(std::io::Error::last_os_error().to_string()),
                // `dead` lists nodes in the order of `dead_nodes`.
                Kind::Node => match nodes.next() {
                    Some((view, dir)) => match view.try_remove_stale_resources() {
                        Ok(()) => Ok(()),
                        Err(e) => {
                            dir.as_deref().map_or(Err(format!("{e:?}")), |d| remove_orphan_tags(d).map_err(|why| format!("{e:?}; {why}")))
                        }
                    },
                    None => Err("no node view".into()),
                },
            };
            match result {
                Ok(()) => removed.push(f),
                Err(e) => failed.push((f, e)),
            }
        }
        Removed { removed, failed }
    }
}

/// Finish what iceoryx2 could not: a process killed while it was creating a port or opening a
/// service leaves a tag of it in its node directory that no service lists, so iceoryx2's clean-up
/// removes everything else (the node's details, its registered ports and services) and then fails
/// to remove the directory. Only called for a dead node of this user, judged by its name and
/// directory before: the leftover tags (empty files) and the directory, then the node's monitor
/// files beside it, all named by its id.
fn remove_orphan_tags(dir: &std::path::Path) -> Result<(), String> {
    let io = |what: &str, e: std::io::Error| format!("{what} {}: {e}", dir.display());
    for e in std::fs::read_dir(dir).map_err(|e| io("reading", e))? {
        let e = e.map_err(|e| io("reading", e))?;
        let name = e.file_name().to_string_lossy().into_owned();
        if !(name.ends_with(".port_tag") || name.ends_with(".service_tag")) || !e.file_type().is_ok_and(|t| t.is_file()) {
            return Err(format!("{} holds {name}, not only leftover tags; left alone", dir.display()));
        }
        std::fs::remove_file(e.path()).map_err(|err| io("removing a tag in", err))?;
    }
    std::fs::remove_dir(dir).map_err(|e| io("removing", e))?;
    let (Some(parent), Some(id)) = (dir.parent(), dir.file_name().and_then(|n| n.to_str())) else { return Ok(()) };
    for e in std::fs::read_dir(parent).into_iter().flatten().flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        // iox2_<id>.node_monitor, .node_monitor_context, .node_monitor_owner_lock
        if name.split_once('_').is_some_and(|(_, rest)| rest.strip_prefix(id).is_some_and(|r| r.starts_with(".node_monitor"))) {
            std::fs::remove_file(e.path()).map_err(|err| io("removing the monitor of", err))?;
        }
    }
    Ok(())
}

/// Remove this user's dead lmac leftovers (what every start does); returns what was removed.
pub fn reclaim() -> Removed {
    survey().remove()
}
