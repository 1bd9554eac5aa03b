//! The slab: K slots of one env server in POSIX shared memory, mapped read-write by every
//! process of a run. Created owner-only (0600) by the env server; peers open it and are refused
//! unless magic, layout version and schema hash agree. One writer per slot at a time is the only
//! synchronisation; who that writer is travels with the slot messages of the ring (`ring.rs`)
//! and is recorded in each slot's `stage` word so a misuse is caught instead of racing.

use crate::layout::{LayoutParams, SlotLayout, ENV_META_BYTES, LAYOUT_VERSION, SLAB_HEADER_BYTES, SLOT_HEADER_BYTES};
use crate::schema::EnvSchema;
use std::ffi::CString;
use std::sync::atomic::{AtomicU32, Ordering};
use std::time::{Duration, Instant};

const MAGIC: u64 = u64::from_le_bytes(*b"LMACSLAB");
const STATE_READY: u32 = 1;

/// Byte offsets of the slab header's fields (the `SlabHeader` below), for tools and tests that
/// look at a slab from outside.
pub mod header_offsets {
    pub const MAGIC: usize = 0;
    pub const LAYOUT_VERSION: usize = 8;
    pub const STATE: usize = 12;
    pub const HASH: usize = 16;
    pub const NUM_ENVS: usize = 48;
    pub const MSG_DIM: usize = 52;
    pub const N_SLOTS: usize = 56;
    pub const OWNER_PID: usize = 60;
    pub const ENV_NAME: usize = 64;
}

/// Who may write a slot right now.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u32)]
pub enum Stage {
    Env = 0,
    Runner = 1,
    Trainer = 2,
}

impl Stage {
    pub fn from_u32(v: u32) -> Option<Stage> {
        match v {
            0 => Some(Stage::Env),
            1 => Some(Stage::Runner),
            2 => Some(Stage::Trainer),
            _ => None,
        }
    }
    /// The stage a slot goes to after this one.
    pub fn next(self) -> Stage {
        match self {
            Stage::Env => Stage::Runner,
            Stage::Runner => Stage::Trainer,
            Stage::Trainer => Stage::Env,
        }
    }
    pub fn name(self) -> &'static str {
        match self {
            Stage::Env => "env server",
            Stage::Runner => "protocol runner",
            Stage::Trainer => "trainer",
        }
    }
}

#[repr(C)]
struct SlabHeader {
    magic: u64,
    layout_version: u32,
    state: AtomicU32,
    hash: [u8; 32],
    num_envs: u32,
    msg_dim: u32,
    n_slots: u32,
    owner_pid: u32,
    env_name: [u8; 128],
}

// The header is read by other processes (and the Python extension): keep its bytes where
// `header_offsets` says they are.
const _: () = {
    assert!(std::mem::offset_of!(SlabHeader, magic) == header_offsets::MAGIC);
    assert!(std::mem::offset_of!(SlabHeader, layout_version) == header_offsets::LAYOUT_VERSION);
    assert!(std::mem::offset_of!(SlabHeader, state) == header_offsets::STATE);
    assert!(std::mem::offset_of!(SlabHeader, hash) == header_offsets::HASH);
    assert!(std::mem::offset_of!(SlabHeader, num_envs) == header_offsets::NUM_ENVS);
    assert!(std::mem::offset_of!(SlabHeader, msg_dim) == header_offsets::MSG_DIM);
    assert!(std::mem::offset_of!(SlabHeader, n_slots) == header_offsets::N_SLOTS);
    assert!(std::mem::offset_of!(SlabHeader, owner_pid) == header_offsets::OWNER_PID);
    assert!(std::mem::offset_of!(SlabHeader, env_name) == header_offsets::ENV_NAME);
    assert!(std::mem::size_of::<SlabHeader>() <= SLAB_HEADER_BYTES);
};

/// The fields of a slab header as read once from shared memory.
struct HeaderCopy {
    magic: u64,
    version: u32,
    params: LayoutParams,
    hash: [u8; 32],
    env_name: String,
}

/// Per-slot header at the start of every slot.
#[repr(C)]
pub struct SlotHeader {
    /// Sequence number of the batched step written into this slot (per server, from 0).
    pub seq: u64,
    /// Server-level step counter.
    pub step: u64,
    stage: AtomicU32,
    pub server: u32,
}

#[derive(Debug, thiserror::Error)]
pub enum SlabError {
    #[error("shared memory {name}: {op} failed: {err}")]
    Os { name: String, op: &'static str, err: std::io::Error },
    #[error("shared memory {name} is not an lmac slab (bad magic number)")]
    BadMagic { name: String },
    #[error(
        "shared memory {name} has layout version {found}, this build speaks version {ours}; rebuild both sides from the same lmac version"
    )]
    Version { name: String, found: u32, ours: u32 },
    #[error("shared memory {name} was created for {theirs_env:?} with schema hash {theirs}, but this process loaded {ours_env:?} with hash {ours}: the peers disagree on the schema (or on num_envs / msg_dim / slots)")]
    SchemaMismatch { name: String, theirs_env: String, theirs: String, ours_env: String, ours: String },
    #[error("shared memory {name} is {found} bytes, its layout needs {need}")]
    Size { name: String, found: usize, need: usize },
    #[error("shared memory {name} was not initialised by its owner within {0:?}", .waited)]
    NotReady { name: String, waited: Duration },
    #[error("slot {slot} of {name} is owned by the {owner}, not by the {me}: ownership protocol violated")]
    NotOwner { name: String, slot: usize, owner: &'static str, me: &'static str },
    /// /dev/shm cannot hold the slab. Without this check tmpfs hands out the pages lazily and
    /// the first write past the end kills the writer with SIGBUS.
    #[error(
        "shared memory {name} needs {need} bytes but /dev/shm has {free} bytes free (of {total}): free space there (`lmac clean` removes what dead runs left; `df -h /dev/shm` shows what is used) or use fewer environments or slots"
    )]
    NoSpace { name: String, need: usize, free: u64, total: u64 },
    #[error("invalid shared memory name {0:?}: use letters, digits, '-', '_' and '.' only")]
    BadName(String),
    /// A header field written by another process that cannot be right.
    #[error("shared memory {name}: header field {field} {problem}")]
    Corrupt { name: String, field: &'static str, problem: String },
    #[error("slot {slot} of {name} is out of range: the slab has {n_slots} slots")]
    SlotRange { name: String, slot: usize, n_slots: usize },
    /// A stop was requested ([`crate::ring::request_stop`], SIGTERM or Ctrl-C) while waiting for
    /// a peer's slab: the wait ends at once instead of running out its start-up timeout.
    #[error("stopped by request while waiting for shared memory {name}")]
    Stopped { name: String },
}

/// A mapped slab. The creator (`Slab::create`) unlinks the name when dropped.
pub struct Slab {
    name: String,
    base: *mut u8,
    len: usize,
    layout: SlotLayout,
    owner: bool,
}

// The mapping is plain shared memory; slot ownership is what serialises writers.
unsafe impl Send for Slab {}
unsafe impl Sync for Slab {}

fn os_err(name: &str, op: &'static str) -> SlabError {
    SlabError::Os { name: name.to_string(), op, err: std::io::Error::last_os_error() }
}

/// Free and total bytes of the file system behind POSIX shared memory (`/dev/shm`).
pub fn shm_space() -> Option<(u64, u64)> {
    let path = CString::new("/dev/shm").expect("no NUL");
    let mut s: libc::statvfs = unsafe { std::mem::zeroed() };
    if unsafe { libc::statvfs(path.as_ptr(), &mut s) } != 0 {
        return None;
    }
    let unit = s.f_frsize as u64;
    Some((s.f_bavail as u64 * unit, s.f_blocks as u64 * unit))
}

/// Size the new slab's file to `bytes` and reserve its pages now (`posix_fallocate`), so that
/// a /dev/shm without room is an error naming both numbers, not a SIGBUS in whichever process
/// first writes past the free space. A file system without fallocate gets a plain ftruncate
/// after a free-space check.
unsafe fn reserve(fd: libc::c_int, name: &str, bytes: usize) -> Result<(), SlabError> {
    let no_space = || {
        let (free, total) = shm_space().unwrap_or((0, 0));
        SlabError::NoSpace { name: name.to_string(), need: bytes, free, total }
    };
    if let Some((free, _)) = shm_space() {
        if bytes as u64 > free {
            return Err(no_space());
        }
    }
    loop {
        match libc::posix_fallocate(fd, 0, bytes as libc::off_t) {
            0 => return Ok(()),
            libc::EINTR => continue,
            libc::ENOSPC | libc::EFBIG => return Err(no_space()),
            libc::EOPNOTSUPP | libc::EINVAL => break,
            e => return Err(SlabError::Os { name: name.to_string(), op: "posix_fallocate", err: std::io::Error::from_raw_os_error(e) }),
        }
    }
    if libc::ftruncate(fd, bytes as libc::off_t) != 0 {
        return Err(os_err(name, "ftruncate"));
    }
    Ok(())
}

fn shm_name(name: &str) -> Result<CString, SlabError> {
    if name.is_empty() || !name.chars().all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c)) {
        return Err(SlabError::BadName(name.into()));
    }
    Ok(CString::new(format!("/{name}")).expect("no NUL"))
}

/// Name of ring member `member`'s slab in run `run` (its env server process creates it).
pub fn slab_name(run: &str, member: usize) -> String {
    format!("lmac-{run}-s{member}")
}

/// The run and ring member of a slab name as [`slab_name`] spells it with a run id lmac makes
/// (12 lowercase hex digits), or None for any other name: other programs' files in /dev/shm
/// that happen to start with "lmac-" are never lmac's to touch.
pub fn parse_slab_name(name: &str) -> Option<(&str, usize)> {
    let (run, member) = name.strip_prefix("lmac-")?.rsplit_once("-s")?;
    let m: usize = member.parse().ok()?;
    let run_id = run.len() == 12 && run.bytes().all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b));
    // Exactly as spelt: "-s01" or "-s+1" is not a name lmac makes.
    (run_id && m.to_string() == member).then_some((run, m))
}

/// What the header of a slab file says about it, read without mapping it or following a link.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SlabHeaderState {
    /// Complete: the pid of the env server that created it.
    Ready(u32),
    /// lmac's magic number, but its creator never marked it ready.
    Unfinished,
    /// Not an lmac slab (another magic number, too short, unreadable): never lmac's to remove.
    Foreign,
}

/// Read the header of the slab file `name` (see [`SlabHeaderState`]).
pub fn header_state(name: &str) -> SlabHeaderState {
    use std::io::Read;
    use std::os::unix::fs::OpenOptionsExt;
    let open = std::fs::OpenOptions::new().read(true).custom_flags(libc::O_NOFOLLOW | libc::O_NONBLOCK).open(shm_file_path(name));
    let Ok(mut f) = open else { return SlabHeaderState::Foreign };
    let mut h = [0u8; header_offsets::OWNER_PID + 4];
    if f.read_exact(&mut h).is_err() || h[..8] != MAGIC.to_ne_bytes() {
        return SlabHeaderState::Foreign;
    }
    // The header is the creator's in-memory struct: native byte order.
    let word = |at: usize| u32::from_ne_bytes(h[at..at + 4].try_into().expect("4 bytes"));
    if word(header_offsets::STATE) == STATE_READY {
        SlabHeaderState::Ready(word(header_offsets::OWNER_PID))
    } else {
        SlabHeaderState::Unfinished
    }
}

/// Path of a slab's file on Linux (for tests and cleanup).
pub fn shm_file_path(name: &str) -> std::path::PathBuf {
    std::path::PathBuf::from(format!("/dev/shm/{name}"))
}

/// Remove a slab name if it exists (cleanup after a crashed owner). Returns whether it existed.
pub fn unlink(name: &str) -> bool {
    match shm_name(name) {
        Ok(c) => unsafe { libc::shm_unlink(c.as_ptr()) == 0 },
        Err(_) => false,
    }
}

unsafe fn map(fd: i32, len: usize, name: &str) -> Result<*mut u8, SlabError> {
    let p = libc::mmap(std::ptr::null_mut(), len, libc::PROT_READ | libc::PROT_WRITE, libc::MAP_SHARED, fd, 0);
    if p == libc::MAP_FAILED {
        return Err(os_err(name, "mmap"));
    }
    Ok(p as *mut u8)
}

impl Slab {
    /// Create the slab for `schema` with the given parameters: owner-only (0600), zeroed, with a
    /// header carrying magic, layout version and schema hash. Fails if the name exists.
    pub fn create(name: &str, schema: &EnvSchema, params: LayoutParams) -> Result<Slab, SlabError> {
        let cname = shm_name(name)?;
        let layout = SlotLayout::new(schema, params);
        unsafe {
            let fd = libc::shm_open(cname.as_ptr(), libc::O_CREAT | libc::O_EXCL | libc::O_RDWR, 0o600);
            if fd < 0 {
                return Err(os_err(name, "shm_open(create)"));
            }
            // The umask cannot widen 0600, but make the mode explicit whatever the umask is.
            libc::fchmod(fd, 0o600);
            if let Err(e) = reserve(fd, name, layout.slab_bytes) {
                libc::close(fd);
                libc::shm_unlink(cname.as_ptr());
                return Err(e);
            }
            let base = map(fd, layout.slab_bytes, name);
            libc::close(fd);
            let base = match base {
                Ok(b) => b,
                Err(e) => {
                    libc::shm_unlink(cname.as_ptr());
                    return Err(e);
                }
            };
            let h = &mut *(base as *mut SlabHeader);
            h.magic = MAGIC;
            h.layout_version = LAYOUT_VERSION;
            h.hash = layout.hash;
            h.num_envs = params.num_envs as u32;
            h.msg_dim = params.msg_dim as u32;
            h.n_slots = params.n_slots as u32;
            h.owner_pid = std::process::id();
            let nb = schema.name.as_bytes();
            let k = nb.len().min(h.env_name.len());
            h.env_name[..k].copy_from_slice(&nb[..k]);
            h.state.store(STATE_READY, Ordering::Release);
            Ok(Slab { name: name.into(), base, len: layout.slab_bytes, layout, owner: true })
        }
    }

    /// Open a slab created by a peer, waiting up to `wait` for it to appear and be initialised.
    /// The layout parameters are read from its header; the hash must match ours for `schema`.
    pub fn open(name: &str, schema: &EnvSchema, wait: Duration) -> Result<Slab, SlabError> {
        let cname = shm_name(name)?;
        let t0 = Instant::now();
        let fd = loop {
            let fd = unsafe { libc::shm_open(cname.as_ptr(), libc::O_RDWR, 0) };
            if fd >= 0 {
                break fd;
            }
            let err = std::io::Error::last_os_error();
            if err.raw_os_error() != Some(libc::ENOENT) || t0.elapsed() >= wait {
                return Err(SlabError::Os { name: name.into(), op: "shm_open", err });
            }
            // A parent that dies before its env servers made their slabs sends its children
            // SIGTERM (PR_SET_PDEATHSIG): they must not wait out the start-up timeout.
            if crate::ring::stop_requested() {
                return Err(SlabError::Stopped { name: name.into() });
            }
            std::thread::sleep(Duration::from_millis(5));
        };
        let res = unsafe { Self::open_fd(fd, name, schema, wait.saturating_sub(t0.elapsed())) };
        unsafe { libc::close(fd) };
        res
    }

    unsafe fn open_fd(fd: i32, name: &str, schema: &EnvSchema, wait: Duration) -> Result<Slab, SlabError> {
        let t0 = Instant::now();
        // Wait until the owner has sized and initialised it.
        loop {
            let mut st: libc::stat = std::mem::zeroed();
            if libc::fstat(fd, &mut st) != 0 {
                return Err(os_err(name, "fstat"));
            }
            if st.st_size as usize >= SLAB_HEADER_BYTES {
                let hdr = map(fd, SLAB_HEADER_BYTES, name)?;
                let h = &*(hdr as *const SlabHeader);
                let state = h.state.load(Ordering::Acquire);
                let ready = state == STATE_READY;
                // Copy the fields out: the other process may change them while we look.
                let copy = HeaderCopy {
                    magic: h.magic,
                    version: h.layout_version,
                    params: LayoutParams { num_envs: h.num_envs as usize, msg_dim: h.msg_dim as usize, n_slots: h.n_slots as usize },
                    hash: h.hash,
                    env_name: String::from_utf8_lossy(&h.env_name).trim_end_matches('\0').to_string(),
                };
                libc::munmap(hdr as *mut _, SLAB_HEADER_BYTES);
                if ready {
                    return Self::check_header(fd, name, schema, st.st_size as usize, copy);
                }
                if state != 0 {
                    // The owner writes 0 (zeroed memory) until it is done, then STATE_READY.
                    return Err(SlabError::Corrupt {
                        name: name.into(),
                        field: "state",
                        problem: format!("is {state}: neither 0 (initialising) nor {STATE_READY} (ready)"),
                    });
                }
            }
            if t0.elapsed() >= wait {
                return Err(SlabError::NotReady { name: name.into(), waited: wait });
            }
            if crate::ring::stop_requested() {
                return Err(SlabError::Stopped { name: name.into() });
            }
            std::thread::sleep(Duration::from_millis(5));
        }
    }

    /// Check a ready header read from another process's slab against `schema` and the file
    /// size before computing offsets from it or mapping it whole; every refusal names the field.
    unsafe fn check_header(fd: i32, name: &str, schema: &EnvSchema, file_bytes: usize, h: HeaderCopy) -> Result<Slab, SlabError> {
        let HeaderCopy { magic, version, params, hash, env_name } = h;
        let corrupt = |field: &'static str, problem: String| SlabError::Corrupt { name: name.into(), field, problem };
        if magic != MAGIC {
            return Err(SlabError::BadMagic { name: name.into() });
        }
        if version != LAYOUT_VERSION {
            return Err(SlabError::Version { name: name.into(), found: version, ours: LAYOUT_VERSION });
        }
        if params.num_envs == 0 {
            return Err(corrupt("num_envs", "is 0: a slab holds at least one environment".into()));
        }
        if params.n_slots == 0 {
            return Err(corrupt("n_slots", "is 0: a slab holds at least one slot".into()));
        }
        // A parameter beyond what the file can hold (a slot is at least its header, an env at
        // least its metadata, a message column 4 bytes per agent and env) is named as the culprit
        // when the layout cannot be computed or its hash does not match.
        let room = (file_bytes.saturating_sub(SLAB_HEADER_BYTES)) as u128;
        let (slots, envs, msg) = (params.n_slots as u128, params.num_envs as u128, params.msg_dim as u128);
        let beyond_file = || {
            if slots * SLOT_HEADER_BYTES as u128 > room {
                Some(corrupt("n_slots", format!("is {slots}, more than the {file_bytes} bytes of the file can hold")))
            } else if slots * envs * ENV_META_BYTES as u128 > room {
                Some(corrupt("num_envs", format!("is {envs}, more than {slots} slots of the {file_bytes}-byte file can hold")))
            } else if slots * envs * schema.n_agents as u128 * msg * 4 > room {
                Some(corrupt("msg_dim", format!("is {msg}, more than the {file_bytes}-byte file can hold")))
            } else {
                None
            }
        };
        let Some(layout) = SlotLayout::try_new(schema, params) else {
            return Err(beyond_file()
                .unwrap_or_else(|| corrupt("num_envs", format!("with msg_dim {msg} and n_slots {slots}: the layout's size overflows"))));
        };
        if layout.hash != hash {
            if let Some(e) = beyond_file() {
                return Err(e);
            }
            return Err(SlabError::SchemaMismatch {
                name: name.into(),
                theirs_env: env_name,
                theirs: hash.iter().map(|b| format!("{b:02x}")).collect::<String>()[..16].into(),
                ours_env: schema.name.clone(),
                ours: layout.hash_hex()[..16].into(),
            });
        }
        // The owner sizes the file exactly; another size means another writer.
        if file_bytes != layout.slab_bytes {
            return Err(SlabError::Size { name: name.into(), found: file_bytes, need: layout.slab_bytes });
        }
        let base = map(fd, layout.slab_bytes, name)?;
        Ok(Slab { name: name.into(), base, len: layout.slab_bytes, layout, owner: false })
    }

    pub fn name(&self) -> &str {
        &self.name
    }
    pub fn layout(&self) -> &SlotLayout {
        &self.layout
    }
    pub fn is_owner(&self) -> bool {
        self.owner
    }

    fn slot_base(&self, i: usize) -> *mut u8 {
        assert!(i < self.layout.n_slots, "slot {i} out of range (slab has {})", self.layout.n_slots);
        unsafe { self.base.add(self.layout.slot_offset(i)) }
    }

    /// The stage currently recorded as the writer of slot `i`.
    pub fn stage(&self, i: usize) -> Option<Stage> {
        let h = unsafe { &*(self.slot_base(i) as *const SlotHeader) };
        Stage::from_u32(h.stage.load(Ordering::Acquire))
    }

    /// Record `to` as the writer of slot `i` (done by the current writer right before handing
    /// the slot over).
    pub fn set_stage(&self, i: usize, to: Stage) {
        let h = unsafe { &*(self.slot_base(i) as *const SlotHeader) };
        h.stage.store(to as u32, Ordering::Release);
    }

    /// Check that `i` is a slot of this slab and `me` owns it, and give typed access to it.
    /// `i` usually comes from a ring message, so out of range is an error, not a panic.
    pub fn slot(&self, i: usize, me: Stage) -> Result<Slot<'_>, SlabError> {
        if i >= self.layout.n_slots {
            return Err(SlabError::SlotRange { name: self.name.clone(), slot: i, n_slots: self.layout.n_slots });
        }
        let owner = self.stage(i);
        if owner != Some(me) {
            return Err(SlabError::NotOwner {
                name: self.name.clone(),
                slot: i,
                owner: owner.map_or("unknown stage", |s| s.name()),
                me: me.name(),
            });
        }
        Ok(Slot { base: self.slot_base(i), layout: &self.layout })
    }

    /// Raw pointer to slot `i` (for the Python bindings, which build numpy views over it).
    pub fn slot_ptr(&self, i: usize) -> *mut u8 {
        self.slot_base(i)
    }
}

impl Drop for Slab {
    fn drop(&mut self) {
        unsafe {
            libc::munmap(self.base as *mut _, self.len);
        }
        if self.owner {
            unlink(&self.name);
        }
    }
}

/// Typed access to one slot owned by the caller's stage. Obtained from [`Slab::slot`], which
/// checks ownership; holding it while handing the slot over is the caller's bug to avoid.
pub struct Slot<'a> {
    base: *mut u8,
    layout: &'a SlotLayout,
}

macro_rules! section {
    ($get:ident, $get_mut:ident, $field:ident, $t:ty) => {
        pub fn $get(&self) -> &[$t] {
            let s = self.layout.$field;
            unsafe { std::slice::from_raw_parts(self.base.add(s.offset) as *const $t, s.bytes / std::mem::size_of::<$t>()) }
        }
        pub fn $get_mut(&mut self) -> &mut [$t] {
            let s = self.layout.$field;
            unsafe { std::slice::from_raw_parts_mut(self.base.add(s.offset) as *mut $t, s.bytes / std::mem::size_of::<$t>()) }
        }
    };
}

impl<'a> Slot<'a> {
    pub fn layout(&self) -> &SlotLayout {
        self.layout
    }
    pub fn header(&self) -> &SlotHeader {
        unsafe { &*(self.base as *const SlotHeader) }
    }
    pub fn header_mut(&mut self) -> &mut SlotHeader {
        unsafe { &mut *(self.base as *mut SlotHeader) }
    }
    section!(obs, obs_mut, obs, f32);
    section!(state, state_mut, state, f32);
    section!(avail, avail_mut, avail, u8);
    section!(reward, reward_mut, reward, f32);
    section!(terminated, terminated_mut, terminated, u8);
    section!(truncated, truncated_mut, truncated, u8);
    section!(last_actions, last_actions_mut, last_actions, i32);
    section!(actions, actions_mut, actions, i32);

    /// Per env: (episode id, step in episode, flags).
    pub fn env_meta(&self, env: usize) -> (u64, u32, u32) {
        assert!(env < self.layout.num_envs);
        unsafe {
            let p = self.base.add(self.layout.env_meta.offset + env * 16);
            ((p as *const u64).read(), (p.add(8) as *const u32).read(), (p.add(12) as *const u32).read())
        }
    }
    pub fn set_env_meta(&mut self, env: usize, episode: u64, step: u32, flags: u32) {
        assert!(env < self.layout.num_envs);
        unsafe {
            let p = self.base.add(self.layout.env_meta.offset + env * 16);
            (p as *mut u64).write(episode);
            (p.add(8) as *mut u32).write(step);
            (p.add(12) as *mut u32).write(flags);
        }
    }
    /// Mutable observation rows together with read access to the per-env metadata and the
    /// last actions: what the protocol runner needs at once.
    pub fn runner_parts(&mut self) -> (&mut [f32], Vec<bool>, &[i32]) {
        let first: Vec<bool> = (0..self.layout.num_envs).map(|e| self.env_meta(e).2 & crate::layout::FLAG_FIRST != 0).collect();
        let l = self.layout;
        unsafe {
            let obs = std::slice::from_raw_parts_mut(self.base.add(l.obs.offset) as *mut f32, l.obs.bytes / 4);
            let la = std::slice::from_raw_parts(self.base.add(l.last_actions.offset) as *const i32, l.last_actions.bytes / 4);
            (obs, first, la)
        }
    }
}
