//! Atomic checkpoints: a directory holding the online network, the target network, the
//! optimizer state (burnpack files), `state.json` (config, dims, counters, RNG, epsilon),
//! optionally the replay buffer, and last `manifest.json` (every other file's size and CRC-32C,
//! checked on load).
//!
//! The save protocol keeps a complete checkpoint on disk under any sequence of crashes:
//!
//! 1. settle what an earlier crash left: with no `<dir>`, a complete `<dir>.old` (else a
//!    verified `<dir>.tmp`) is renamed to `<dir>`: the same choice [`locate`] makes on load;
//! 2. remove a stale `<dir>.tmp` (`<dir>` now holds any complete checkpoint there is);
//! 3. write `<dir>.tmp`, fsync every file, write the manifest last and fsync it;
//! 4. only while `<dir>` exists: remove `<dir>.old`, rename `<dir>` to `<dir>.old`;
//! 5. rename `<dir>.tmp` to `<dir>`; 6. remove `<dir>.old`.
//!
//! `<dir>` only ever comes from a rename of a complete directory and `<dir>.old` is removed only
//! while `<dir>` exists, so at every point one of `<dir>`, `<dir>.old` or a `<dir>.tmp` whose
//! manifest matches its files is complete. Directories are removed manifest and `state.json`
//! first, so a half-removed one never looks complete. [`fault`] stops a save at any step, as a
//! crash would, for the tests.

use std::fs::{self, File};
use std::io::{BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};

use burn::module::Module;
use burn::tensor::Device;
use lmac_shm_schema::safe_fs::{open_regular, read_capped, DATA_CAP, TEXT_CAP};
use serde::{Deserialize, Serialize};

use super::buffer::ReplayBuffer;
use super::config::LearnConfig;
use super::learner::{make_optimizer, Counters, LearnError, Learner, QNet};
use super::methods::AgentConfig;
use super::LearnRng;
use crate::episode::{Episode, EpisodeDims, NextStep};

const FORMAT_VERSION: u32 = 1;
/// Replay buffer files: format 2 stores truncated episodes' next steps; format 1 is still read.
const BUFFER_MAGIC: &[u8; 8] = b"LMACRB02";
const BUFFER_MAGIC_V1: &[u8; 8] = b"LMACRB01";

#[derive(Serialize, Deserialize)]
struct DimsJson {
    n_agents: usize,
    obs_width: usize,
    state_dim: usize,
    n_actions: usize,
}

#[derive(Serialize, Deserialize)]
struct StateJson {
    format_version: u32,
    config: LearnConfig,
    /// The method's agent network; absent in checkpoints written before methods had settings.
    #[serde(default)]
    agent: AgentConfig,
    dims: DimsJson,
    counters: Counters,
    rng: LearnRng,
    epsilon: f32,
    has_buffer: bool,
    /// The run's whole configuration when the checkpoint was saved (absent before runs
    /// recorded it).
    #[serde(default)]
    run_config: Option<String>,
    /// Written with a manifest (every checkpoint since manifests): one missing was removed, and
    /// the files' sums can no longer be checked, so the checkpoint is refused.
    #[serde(default)]
    manifested: bool,
}

fn ck(e: impl std::fmt::Display, what: &str, path: &Path) -> LearnError {
    LearnError::Checkpoint(format!("{what} {}: {e}", path.display()))
}

fn sibling(dir: &Path, suffix: &str) -> PathBuf {
    let mut s = dir.as_os_str().to_owned();
    s.push(suffix);
    PathBuf::from(s)
}

fn fsync_path(p: &Path) -> Result<(), LearnError> {
    File::open(p).and_then(|f| f.sync_all()).map_err(|e| ck(e, "fsync", p))
}

/// What a checkpoint's `state.json` says, read without building any network.
#[derive(Clone, Debug)]
pub struct CheckpointInfo {
    /// The directory actually read (`<dir>` or, after a crash in the final rename, `<dir>.old`).
    pub dir: PathBuf,
    pub dims: EpisodeDims,
    pub counters: Counters,
    pub has_buffer: bool,
    /// The run's whole configuration the checkpoint was trained with, when it was recorded.
    pub run_config: Option<String>,
}

/// Largest dimension a checkpoint may declare: far above any environment here, low enough that
/// building the networks it implies cannot exhaust memory on a corrupt file.
const MAX_DIM: usize = 1 << 16;

/// The file written last into a checkpoint directory.
const MANIFEST: &str = "manifest.json";

/// Every file of a checkpoint but the manifest, with its size and CRC-32C.
#[derive(Serialize, Deserialize, PartialEq, Debug)]
struct Manifest {
    files: std::collections::BTreeMap<String, FileSum>,
}

#[derive(Serialize, Deserialize, PartialEq, Clone, Copy, Debug)]
struct FileSum {
    bytes: u64,
    crc32c: u32,
}

/// Size and CRC-32C of a regular file (anything else, a device or a fifo, is refused: it could
/// be read forever).
fn file_sum(p: &Path) -> Result<FileSum, LearnError> {
    let meta = fs::symlink_metadata(p).map_err(|e| ck(e, "read", p))?;
    if !meta.is_file() {
        return Err(ck("not a regular file", "read", p));
    }
    let mut f = File::open(p).map_err(|e| ck(e, "read", p))?;
    let (mut crc, mut bytes, mut buf) = (0u32, 0u64, vec![0u8; 1 << 20]);
    loop {
        let n = f.read(&mut buf).map_err(|e| ck(e, "read", p))?;
        if n == 0 {
            break;
        }
        crc = crc32c::crc32c_append(crc, &buf[..n]);
        bytes += n as u64;
    }
    Ok(FileSum { bytes, crc32c: crc })
}

/// Check the files of `dir` against its manifest. `Ok(false)`: no manifest (a checkpoint
/// written before manifests; trusted only as `<dir>` or `<dir>.old`). `only`: check just these
/// files (they must be listed). Errors name the file.
fn verify(dir: &Path, only: Option<&[&str]>) -> Result<bool, LearnError> {
    let mp = dir.join(MANIFEST);
    let bytes = match read_capped(&mp, TEXT_CAP) {
        Ok(b) => b,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(false),
        Err(e) => return Err(ck(e, "read", &mp)),
    };
    let m: Manifest = serde_json::from_slice(&bytes).map_err(|e| ck(e, "parse", &mp))?;
    if !m.files.contains_key("state.json") {
        return Err(ck("lists no state.json", "load", &mp));
    }
    for (name, want) in &m.files {
        if only.is_some_and(|o| !o.contains(&name.as_str())) {
            continue;
        }
        if name.contains('/') || name.starts_with('.') {
            return Err(ck(format!("names {name:?}, not a file of the checkpoint"), "load", &mp));
        }
        let p = dir.join(name);
        let got = file_sum(&p)?;
        if got != *want {
            return Err(ck(
                format!(
                    "{} bytes with CRC-32C {:08x}, but {MANIFEST} records {} bytes with {:08x}: the file is corrupt or truncated",
                    got.bytes, got.crc32c, want.bytes, want.crc32c
                ),
                "check",
                &p,
            ));
        }
    }
    for name in only.unwrap_or(&[]) {
        if !m.files.contains_key(*name) {
            return Err(ck(format!("does not list {name}"), "load", &mp));
        }
    }
    Ok(true)
}

/// Which directory holds the checkpoint of `dir`: `<dir>` when its files match its manifest,
/// else an intact `<dir>.old` (a crash between the two renames of a save, or `<dir>` corrupted
/// since), else `<dir>.tmp` when its manifest verifies (complete, but a crash came before it was
/// renamed into place), else whichever of `<dir>` and `<dir>.old` has a `state.json` (its load
/// then names what is wrong). None when there is no usable checkpoint.
pub fn locate(dir: impl AsRef<Path>) -> Option<PathBuf> {
    let dir = dir.as_ref();
    let old = sibling(dir, ".old");
    let tmp = sibling(dir, ".tmp");
    let present = |d: &Path| d.join("state.json").is_file();
    // A checkpoint whose files fail its manifest gives way to an intact `.old`; with none, it is
    // still the one picked, so the load names its corrupt file. Only then are its files summed:
    // `.old` exists only between the two renames of a save, so a resume normally reads no
    // weights or buffer here.
    let intact = |d: &Path| present(d) && verify(d, None).is_ok();
    if present(dir) && (!present(&old) || intact(dir)) {
        Some(dir.to_path_buf())
    } else if intact(&old) {
        Some(old)
    } else if present(&tmp) && matches!(verify(&tmp, None), Ok(true)) {
        Some(tmp)
    } else if present(dir) {
        Some(dir.to_path_buf())
    } else if present(&old) {
        Some(old)
    } else {
        None
    }
}

/// Whether `dir` holds a usable checkpoint (see [`locate`]).
pub fn checkpoint_exists(dir: impl AsRef<Path>) -> bool {
    locate(dir).is_some()
}

/// Fault injection for tests of the save protocol: stop [`Learner::save_checkpoint`] at a named
/// step as a crash would (nothing after it is done, nothing is cleaned up).
pub mod fault {
    use std::cell::Cell;

    /// The steps of a save, in order (see the module's documentation).
    pub const STEPS: &[&str] = &[
        "begin",
        "settled-old",
        "settled-tmp",
        "removing-stale-tmp",
        "removed-stale-tmp",
        "wrote-networks",
        "wrote-state",
        "wrote-manifest",
        "removing-old",
        "removed-old",
        "moved-dir-to-old",
        "moved-tmp-to-dir",
        "removing-old-after",
        "done",
    ];

    /// The steps every save reaches once a checkpoint exists and no earlier crash left
    /// anything to settle (the others: `settled-old`, `removing-stale-tmp`, `removing-old`,
    /// only after a crash at some step). `lmac chaos --mode save` aborts at one of these.
    pub const EVERY_SAVE: &[&str] = &[
        "begin",
        "settled-tmp",
        "removed-stale-tmp",
        "wrote-networks",
        "wrote-state",
        "wrote-manifest",
        "removed-old",
        "moved-dir-to-old",
        "moved-tmp-to-dir",
        "removing-old-after",
        "done",
    ];

    /// `STEP` or `STEP@N`: the process aborts the N-th time (default 1st) a save of any
    /// checkpoint reaches STEP: a real crash, for end-to-end tests through the trainer child.
    pub const ENV: &str = "LMAC_FAULT_CHECKPOINT";

    /// Times the step named by [`ENV`] was reached in this process.
    static REACHED: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);

    thread_local! {
        static STOP_AT: Cell<Option<&'static str>> = const { Cell::new(None) };
    }

    /// This thread's saves stop at `step` (None: they run through) with an error saying so.
    pub fn stop_at(step: Option<&'static str>) {
        if let Some(s) = step {
            assert!(STEPS.contains(&s), "unknown save step {s:?}");
        }
        STOP_AT.with(|c| c.set(step));
    }

    pub(super) fn point(step: &'static str) -> Result<(), super::LearnError> {
        if let Ok(v) = std::env::var(ENV) {
            let (name, nth) = v.split_once('@').map_or((v.as_str(), Some(1)), |(n, k)| (n, k.parse::<usize>().ok()));
            if name == step && nth == Some(REACHED.fetch_add(1, std::sync::atomic::Ordering::SeqCst) + 1) {
                eprintln!("lmac: {ENV}={v}: aborting inside the checkpoint save");
                std::process::abort();
            }
        }
        if STOP_AT.with(|c| c.get()) == Some(step) {
            return Err(super::LearnError::Checkpoint(format!("stopped by fault injection at save step {step:?}")));
        }
        Ok(())
    }
}

/// Remove a checkpoint directory so that a removal cut short never leaves one that looks
/// complete: its manifest and `state.json` go first (and that is made durable).
fn remove_checkpoint_dir(p: &Path, step: &'static str) -> Result<(), LearnError> {
    // symlink_metadata, not is_dir: a symlink in the way is removed itself, never entered (is_dir
    // would follow it and the removals below would delete files wherever it points). A file in
    // the way is not lmac's: remove_dir_all refuses it, with an error naming it.
    match fs::symlink_metadata(p) {
        Ok(m) if m.file_type().is_symlink() => return fs::remove_file(p).map_err(|e| ck(e, "remove", p)),
        Ok(m) if !m.is_dir() => return fs::remove_dir_all(p).map_err(|e| ck(e, "remove", p)),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
        _ => {}
    }
    for f in [MANIFEST, "state.json"] {
        match fs::remove_file(p.join(f)) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => return Err(ck(e, "remove", &p.join(f))),
            _ => {}
        }
    }
    fsync_path(p)?;
    fault::point(step)?;
    fs::remove_dir_all(p).map_err(|e| ck(e, "remove", p))
}

/// Make a rename in `dir`'s parent durable.
fn fsync_parent(dir: &Path) -> Result<(), LearnError> {
    match dir.parent().filter(|p| !p.as_os_str().is_empty()) {
        Some(parent) => fsync_path(parent),
        None => fsync_path(Path::new(".")),
    }
}

/// Read and check a checkpoint's `state.json` (falls back to `<dir>.old`, see
/// [`Learner::load_checkpoint`]). Errors name the file and the field.
pub fn peek_checkpoint(dir: impl AsRef<Path>) -> Result<CheckpointInfo, LearnError> {
    let (dir, st) = read_state(dir.as_ref())?;
    Ok(CheckpointInfo { dir, dims: st.dims.to_dims(), counters: st.counters, has_buffer: st.has_buffer, run_config: st.run_config })
}

impl DimsJson {
    fn to_dims(&self) -> EpisodeDims {
        EpisodeDims { n_agents: self.n_agents, obs_width: self.obs_width, state_dim: self.state_dim, n_actions: self.n_actions }
    }
}

fn read_state(dir: &Path) -> Result<(PathBuf, StateJson), LearnError> {
    let Some(dir) = locate(dir) else {
        return Err(LearnError::Checkpoint(format!(
            "no checkpoint at {} (nor a complete {} or {})",
            dir.display(),
            sibling(dir, ".old").display(),
            sibling(dir, ".tmp").display()
        )));
    };
    let has_manifest = verify(&dir, Some(&["state.json"][..]))?;
    let p = dir.join("state.json");
    let bytes = read_capped(&p, TEXT_CAP).map_err(|e| ck(e, "read", &p))?;
    let st: StateJson = serde_json::from_slice(&bytes).map_err(|e| ck(e, "parse", &p))?;
    if st.manifested && !has_manifest {
        return Err(ck(format!("was saved with a {MANIFEST}, which is missing: its files cannot be checked"), "load", &p));
    }
    if st.format_version != FORMAT_VERSION {
        return Err(ck(format!("format_version {} (expected {FORMAT_VERSION})", st.format_version), "load", &p));
    }
    let d = &st.dims;
    for (field, v) in [("n_agents", d.n_agents), ("obs_width", d.obs_width), ("state_dim", d.state_dim), ("n_actions", d.n_actions)] {
        if v > MAX_DIM || (v == 0 && field != "state_dim") {
            return Err(ck(format!("dims.{field} is {v}, outside 1..={MAX_DIM}"), "load", &p));
        }
    }
    st.config.validate().map_err(|e| ck(format!("config: {e}"), "load", &p))?;
    // Counters decide where a resumed run stands and whether it is finished: a corrupt t_env of
    // 2^64-1 would mark any run done. Bounded as the config bounds a run's steps.
    let c = &st.counters;
    for (field, v) in
        [("t_env", c.t_env), ("episodes", c.episodes), ("updates", c.updates), ("last_target_update_episode", c.last_target_update_episode)]
    {
        if v > crate::MAX_ENV_STEPS {
            return Err(ck(
                format!("counters.{field} is {v}, more than the {} env steps a run may take", crate::MAX_ENV_STEPS),
                "load",
                &p,
            ));
        }
    }
    st.agent.validate().map_err(|e| ck(format!("agent: {e}"), "load", &p))?;
    Ok((dir, st))
}

/// Run a third-party loader that may panic on corrupt bytes (burn's record loaders do), turning
/// a panic into an error naming the file.
fn guarded<T>(path: &Path, load: impl FnOnce() -> Result<T, LearnError>) -> Result<T, LearnError> {
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(load)) {
        Ok(r) => r,
        Err(panic) => {
            let why = panic.downcast_ref::<&str>().map(|s| s.to_string()).or_else(|| panic.downcast_ref::<String>().cloned());
            Err(ck(format!("corrupt file (its loader failed: {})", why.unwrap_or_else(|| "panic".into())), "load", path))
        }
    }
}

impl Learner {
    /// Write a checkpoint to `dir` atomically. `with_buffer` also stores the replay buffer, so a
    /// resumed run samples from the same data.
    pub fn save_checkpoint(&self, dir: impl AsRef<Path>, with_buffer: bool) -> Result<(), LearnError> {
        use fault::point;
        let dir = dir.as_ref();
        let tmp = sibling(dir, ".tmp");
        let old = sibling(dir, ".old");
        point("begin")?;
        // 1. What an earlier crash left: the checkpoint load would pick becomes `<dir>`.
        if !dir.exists() {
            if old.join("state.json").is_file() {
                fs::rename(&old, dir).map_err(|e| ck(e, "rename into place", &old))?;
                fsync_parent(dir)?;
            }
            point("settled-old")?;
            if !dir.exists() && tmp.join("state.json").is_file() && matches!(verify(&tmp, None), Ok(true)) {
                fs::rename(&tmp, dir).map_err(|e| ck(e, "rename into place", &tmp))?;
                fsync_parent(dir)?;
            }
        }
        point("settled-tmp")?;
        // 2. A stale `.tmp` is not the only complete checkpoint any more (step 1).
        if fs::symlink_metadata(&tmp).is_ok() {
            remove_checkpoint_dir(&tmp, "removing-stale-tmp")?;
        }
        point("removed-stale-tmp")?;
        // 3. The new checkpoint, complete and durable before anything else is touched.
        fs::create_dir(&tmp).map_err(|e| ck(e, "create", &tmp))?;
        let mut files = vec!["net.bpk", "target.bpk", "optim.bpk"];
        self.net.clone().save_file(tmp.join(files[0])).map_err(|e| ck(e, "write", &tmp.join(files[0])))?;
        self.target.clone().save_file(tmp.join(files[1])).map_err(|e| ck(e, "write", &tmp.join(files[1])))?;
        self.optim.save(tmp.join(files[2])).map_err(|e| ck(e, "write", &tmp.join(files[2])))?;
        if with_buffer {
            let p = tmp.join("buffer.bin");
            write_buffer(&self.buffer, &p).map_err(|e| ck(e, "write", &p))?;
            files.push("buffer.bin");
        }
        point("wrote-networks")?;
        let d = self.dims;
        let state = StateJson {
            format_version: FORMAT_VERSION,
            config: self.cfg.clone(),
            agent: self.agent_cfg.clone(),
            dims: DimsJson { n_agents: d.n_agents, obs_width: d.obs_width, state_dim: d.state_dim, n_actions: d.n_actions },
            counters: self.counters,
            rng: self.rng.clone(),
            epsilon: self.epsilon(),
            has_buffer: with_buffer,
            run_config: self.run_config.clone(),
            manifested: true,
        };
        let p = tmp.join("state.json");
        fs::write(&p, serde_json::to_vec_pretty(&state).expect("state serializes")).map_err(|e| ck(e, "write", &p))?;
        files.push("state.json");
        let mut manifest = Manifest { files: Default::default() };
        for f in &files {
            fsync_path(&tmp.join(f))?;
            manifest.files.insert(f.to_string(), file_sum(&tmp.join(f))?);
        }
        point("wrote-state")?;
        // The manifest last: its presence (matching the files) is what makes `.tmp` complete.
        let p = tmp.join(MANIFEST);
        fs::write(&p, serde_json::to_vec_pretty(&manifest).expect("manifest serializes")).map_err(|e| ck(e, "write", &p))?;
        fsync_path(&p)?;
        fsync_path(&tmp)?;
        point("wrote-manifest")?;
        // 4. `.old` goes only while `<dir>` (complete) exists, then `<dir>` becomes `.old`.
        if dir.exists() {
            if fs::symlink_metadata(&old).is_ok() {
                remove_checkpoint_dir(&old, "removing-old")?;
            }
            point("removed-old")?;
            fs::rename(dir, &old).map_err(|e| ck(e, "rename", dir))?;
            fsync_parent(dir)?;
        }
        point("moved-dir-to-old")?;
        // 5. The new checkpoint into place; 6. the previous one goes.
        fs::rename(&tmp, dir).map_err(|e| ck(e, "rename into", dir))?;
        fsync_parent(dir)?;
        point("moved-tmp-to-dir")?;
        if fs::symlink_metadata(&old).is_ok() {
            remove_checkpoint_dir(&old, "removing-old-after")?;
        }
        point("done")
    }

    /// Rebuild a learner from a checkpoint written by [`save_checkpoint`](Self::save_checkpoint),
    /// from the directory [`locate`] picks.
    pub fn load_checkpoint(dir: impl AsRef<Path>, device: Device) -> Result<Learner, LearnError> {
        let (dir, st) = read_state(dir.as_ref())?;
        // Every file against the manifest (when the checkpoint has one), naming a corrupt one.
        verify(&dir, None)?;
        let dims = st.dims.to_dims();
        let mut l = Learner::with_agent(dims, st.config, st.agent, device).map_err(|e| ck(e, "load", &dir.join("state.json")))?;
        let ad = l.device.clone().autodiff();
        let mut scratch = LearnRng::seed_from(0); // initial values are overwritten by the load
                                                  // Whole files into memory: burn's file loader maps tensors to the file lazily, and the
                                                  // next save renames or removes this directory (a resume from `.old` or `.tmp` first
                                                  // renames it into place), after which a lazy read would fail.
        let resident = |p: &Path| read_capped(p, DATA_CAP).map(burn::tensor::Bytes::from_bytes_vec).map_err(|e| ck(e, "read", p));
        let record = |p: &Path| resident(p).and_then(|b| burn::store::ModuleRecord::from_bytes(b).map_err(|e| ck(e, "load", p)));
        let p = dir.join("net.bpk");
        l.net = guarded(&p, || {
            QNet::new(&mut scratch, &l.dims, &l.cfg, &l.agent_cfg, &ad).try_load_record(record(&p)?).map_err(|e| ck(e, "load", &p))
        })?;
        let p = dir.join("target.bpk");
        l.target = guarded(&p, || {
            QNet::new(&mut scratch, &l.dims, &l.cfg, &l.agent_cfg, &l.device).try_load_record(record(&p)?).map_err(|e| ck(e, "load", &p))
        })?
        .valid();
        let p = dir.join("optim.bpk");
        l.optim = guarded(&p, || make_optimizer(&l.cfg).from_bytes(resident(&p)?).map_err(|e| ck(e, "load", &p)))?;
        l.counters = st.counters;
        l.rng = st.rng;
        l.run_config = st.run_config;
        if st.has_buffer {
            let p = dir.join("buffer.bin");
            l.buffer = read_buffer(&p, &l.dims, l.cfg.buffer_size).map_err(|e| ck(e, "read", &p))?;
        }
        Ok(l)
    }
}

fn write_buffer(buf: &ReplayBuffer, path: &Path) -> std::io::Result<()> {
    let mut w = BufWriter::new(File::create(path)?);
    w.write_all(BUFFER_MAGIC)?;
    let (slots, next) = buf.slots();
    w.write_all(&(slots.len() as u64).to_le_bytes())?;
    w.write_all(&(next as u64).to_le_bytes())?;
    for ep in slots {
        w.write_all(&(ep.len as u64).to_le_bytes())?;
        w.write_all(&[ep.terminated as u8, ep.truncated as u8, ep.next.is_some() as u8])?;
        for v in ep.obs.iter().chain(&ep.state).chain(&ep.reward) {
            w.write_all(&v.to_le_bytes())?;
        }
        w.write_all(&ep.avail)?;
        for v in &ep.actions {
            w.write_all(&v.to_le_bytes())?;
        }
        if let Some(n) = &ep.next {
            for v in n.obs.iter().chain(&n.state) {
                w.write_all(&v.to_le_bytes())?;
            }
            w.write_all(&n.avail)?;
        }
    }
    w.flush()?;
    w.into_inner().map_err(|e| e.into_error())?.sync_all()
}

fn invalid(msg: String) -> std::io::Error {
    std::io::Error::new(std::io::ErrorKind::InvalidData, msg)
}

/// Reads a replay buffer file, checking every count against the bytes left in the file before
/// allocating, so a truncated or corrupt file is an error naming the field, never a huge
/// allocation or a panic. Reads format 2 (with truncated episodes' next steps) and format 1.
fn read_buffer(path: &Path, d: &EpisodeDims, capacity: usize) -> std::io::Result<ReplayBuffer> {
    let file = open_regular(path)?;
    // Bytes of the file not read yet (a Cell: the reading closure and the checks share it).
    let left = std::cell::Cell::new(file.metadata()?.len());
    let mut r = BufReader::new(file);
    let take = |r: &mut BufReader<File>, n: u64, field: &str| -> std::io::Result<Vec<u8>> {
        if n > left.get() {
            return Err(invalid(format!("{field}: needs {n} bytes but only {} are left (truncated or corrupt file)", left.get())));
        }
        left.set(left.get() - n);
        let mut raw = vec![0u8; n as usize];
        r.read_exact(&mut raw)?;
        Ok(raw)
    };
    let magic = take(&mut r, 8, "magic")?;
    let has_next_flag = match &magic[..] {
        m if m == BUFFER_MAGIC => true,
        m if m == BUFFER_MAGIC_V1 => false,
        _ => return Err(invalid("magic: not an lmac replay buffer".into())),
    };
    let u64_of = |b: Vec<u8>| u64::from_le_bytes(b.try_into().expect("8 bytes"));
    let count = u64_of(take(&mut r, 8, "episode count")?);
    let next = u64_of(take(&mut r, 8, "next slot")?);
    if count > capacity as u64 {
        return Err(invalid(format!("episode count: {count} exceeds the buffer capacity {capacity}")));
    }
    if next >= capacity.max(1) as u64 {
        return Err(invalid(format!("next slot: {next} outside the buffer capacity {capacity}")));
    }
    let f32s = |raw: Vec<u8>| -> Vec<f32> { raw.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect() };
    let (n, ow, sd, na) = (d.n_agents as u64, d.obs_width as u64, d.state_dim as u64, d.n_actions as u64);
    // Every episode takes at least 12 bytes: never reserve more than the file could hold.
    let mut episodes = Vec::with_capacity(count.min(left.get() / 12) as usize);
    for k in 0..count {
        let len = u64_of(take(&mut r, 8, &format!("episode {k}: length"))?);
        let flags = take(&mut r, if has_next_flag { 3 } else { 2 }, &format!("episode {k}: flags"))?;
        // Sizes multiply a length read from the file: check for overflow before comparing.
        let sized = |per_step: u64, field: &str| -> std::io::Result<u64> {
            len.checked_mul(per_step).ok_or_else(|| invalid(format!("episode {k}: {field}: length {len} overflows")))
        };
        if len == 0 {
            return Err(invalid(format!("episode {k}: length 0")));
        }
        let obs = f32s(take(&mut r, sized(n * ow * 4, "obs")?, &format!("episode {k}: obs"))?);
        let state = f32s(take(&mut r, sized(sd * 4, "state")?, &format!("episode {k}: state"))?);
        let reward = f32s(take(&mut r, sized(4, "reward")?, &format!("episode {k}: reward"))?);
        let avail = take(&mut r, sized(n * na, "avail")?, &format!("episode {k}: avail"))?;
        let raw = take(&mut r, sized(n * 4, "actions")?, &format!("episode {k}: actions"))?;
        let actions = raw.chunks_exact(4).map(|c| i32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
        let next = if has_next_flag && flags[2] != 0 {
            Some(NextStep {
                obs: f32s(take(&mut r, n * ow * 4, &format!("episode {k}: next obs"))?),
                state: f32s(take(&mut r, sd * 4, &format!("episode {k}: next state"))?),
                avail: take(&mut r, n * na, &format!("episode {k}: next avail"))?,
            })
        } else {
            None
        };
        let ep =
            Episode { len: len as usize, obs, state, avail, actions, reward, terminated: flags[0] != 0, truncated: flags[1] != 0, next };
        ep.check(d).map_err(|e| invalid(format!("episode {k}: {e}")))?;
        episodes.push(ep);
    }
    if left.get() != 0 {
        return Err(invalid(format!("{} bytes after the last episode (corrupt file)", left.get())));
    }
    Ok(ReplayBuffer::from_parts(capacity, episodes, next as usize))
}
