//! Atomic checkpoints: a directory holding the online network, the target network, the
//! optimizer state (burnpack files), `state.json` (config, dims, counters, RNG, epsilon) and,
//! optionally, the replay buffer. Everything is written into `<dir>.tmp`, fsynced, then renamed
//! into place; a previous checkpoint at `<dir>` is kept as `<dir>.old` until the rename is done.

use std::fs::{self, File};
use std::io::{BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};

use burn::module::Module;
use burn::tensor::Device;
use serde::{Deserialize, Serialize};

use super::buffer::ReplayBuffer;
use super::config::LearnConfig;
use super::learner::{make_optimizer, Counters, LearnError, Learner, QNet};
use super::LearnRng;
use crate::episode::{Episode, EpisodeDims};

const FORMAT_VERSION: u32 = 1;
const BUFFER_MAGIC: &[u8; 8] = b"LMACRB01";

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
    dims: DimsJson,
    counters: Counters,
    rng: LearnRng,
    epsilon: f32,
    has_buffer: bool,
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

impl Learner {
    /// Write a checkpoint to `dir` atomically. `with_buffer` also stores the replay buffer, so a
    /// resumed run samples from the same data.
    pub fn save_checkpoint(&self, dir: impl AsRef<Path>, with_buffer: bool) -> Result<(), LearnError> {
        let dir = dir.as_ref();
        let tmp = sibling(dir, ".tmp");
        let old = sibling(dir, ".old");
        if tmp.exists() {
            fs::remove_dir_all(&tmp).map_err(|e| ck(e, "remove stale", &tmp))?;
        }
        fs::create_dir_all(&tmp).map_err(|e| ck(e, "create", &tmp))?;

        let files = ["net.bpk", "target.bpk", "optim.bpk"];
        self.net.clone().save_file(tmp.join(files[0])).map_err(|e| ck(e, "write", &tmp.join(files[0])))?;
        self.target.clone().save_file(tmp.join(files[1])).map_err(|e| ck(e, "write", &tmp.join(files[1])))?;
        self.optim.save(tmp.join(files[2])).map_err(|e| ck(e, "write", &tmp.join(files[2])))?;
        if with_buffer {
            let p = tmp.join("buffer.bin");
            write_buffer(&self.buffer, &p).map_err(|e| ck(e, "write", &p))?;
            fsync_path(&p)?;
        }
        let d = self.dims;
        let state = StateJson {
            format_version: FORMAT_VERSION,
            config: self.cfg.clone(),
            dims: DimsJson { n_agents: d.n_agents, obs_width: d.obs_width, state_dim: d.state_dim, n_actions: d.n_actions },
            counters: self.counters,
            rng: self.rng.clone(),
            epsilon: self.epsilon(),
            has_buffer: with_buffer,
        };
        let p = tmp.join("state.json");
        fs::write(&p, serde_json::to_vec_pretty(&state).expect("state serializes")).map_err(|e| ck(e, "write", &p))?;
        for f in files.iter().chain(["state.json"].iter()) {
            fsync_path(&tmp.join(f))?;
        }
        fsync_path(&tmp)?;

        if old.exists() {
            fs::remove_dir_all(&old).map_err(|e| ck(e, "remove", &old))?;
        }
        if dir.exists() {
            fs::rename(dir, &old).map_err(|e| ck(e, "rename", dir))?;
        }
        fs::rename(&tmp, dir).map_err(|e| ck(e, "rename into", dir))?;
        if let Some(parent) = dir.parent().filter(|p| !p.as_os_str().is_empty()) {
            fsync_path(parent)?;
        }
        if old.exists() {
            fs::remove_dir_all(&old).map_err(|e| ck(e, "remove", &old))?;
        }
        Ok(())
    }

    /// Rebuild a learner from a checkpoint written by [`save_checkpoint`](Self::save_checkpoint)
    /// (falls back to `<dir>.old` when a crash interrupted the final rename).
    pub fn load_checkpoint(dir: impl AsRef<Path>, device: Device) -> Result<Learner, LearnError> {
        let mut dir = dir.as_ref().to_path_buf();
        if !dir.join("state.json").exists() {
            let old = sibling(&dir, ".old");
            if old.join("state.json").exists() {
                dir = old;
            } else {
                return Err(LearnError::Checkpoint(format!("no checkpoint at {}", dir.display())));
            }
        }
        let p = dir.join("state.json");
        let bytes = fs::read(&p).map_err(|e| ck(e, "read", &p))?;
        let st: StateJson = serde_json::from_slice(&bytes).map_err(|e| ck(e, "parse", &p))?;
        if st.format_version != FORMAT_VERSION {
            return Err(ck(format!("format version {} (expected {FORMAT_VERSION})", st.format_version), "load", &p));
        }
        let dims = EpisodeDims {
            n_agents: st.dims.n_agents,
            obs_width: st.dims.obs_width,
            state_dim: st.dims.state_dim,
            n_actions: st.dims.n_actions,
        };
        let mut l = Learner::new(dims, st.config, device)?;
        let ad = l.device.clone().autodiff();
        let mut scratch = LearnRng::seed_from(0); // initial values are overwritten by the load
        let p = dir.join("net.bpk");
        l.net = QNet::new(&mut scratch, &l.dims, &l.cfg, &ad).try_load_file(&p).map_err(|e| ck(e, "load", &p))?;
        let p = dir.join("target.bpk");
        l.target = QNet::new(&mut scratch, &l.dims, &l.cfg, &l.device).try_load_file(&p).map_err(|e| ck(e, "load", &p))?.valid();
        let p = dir.join("optim.bpk");
        l.optim = make_optimizer(&l.cfg).load(&p).map_err(|e| ck(e, "load", &p))?;
        l.counters = st.counters;
        l.rng = st.rng;
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
        w.write_all(&[ep.terminated as u8, ep.truncated as u8])?;
        for v in ep.obs.iter().chain(&ep.state).chain(&ep.reward) {
            w.write_all(&v.to_le_bytes())?;
        }
        w.write_all(&ep.avail)?;
        for v in &ep.actions {
            w.write_all(&v.to_le_bytes())?;
        }
    }
    w.flush()?;
    w.into_inner().map_err(|e| e.into_error())?.sync_all()
}

fn read_buffer(path: &Path, d: &EpisodeDims, capacity: usize) -> std::io::Result<ReplayBuffer> {
    let mut r = BufReader::new(File::open(path)?);
    let mut magic = [0u8; 8];
    r.read_exact(&mut magic)?;
    if &magic != BUFFER_MAGIC {
        return Err(std::io::Error::new(std::io::ErrorKind::InvalidData, "not an lmac replay buffer"));
    }
    let mut u = [0u8; 8];
    r.read_exact(&mut u)?;
    let count = u64::from_le_bytes(u);
    r.read_exact(&mut u)?;
    let next = u64::from_le_bytes(u) as usize;
    let mut episodes = Vec::with_capacity(count as usize);
    let f32s = |r: &mut BufReader<File>, n: usize| -> std::io::Result<Vec<f32>> {
        let mut raw = vec![0u8; n * 4];
        r.read_exact(&mut raw)?;
        Ok(raw.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect())
    };
    for _ in 0..count {
        r.read_exact(&mut u)?;
        let len = u64::from_le_bytes(u) as usize;
        let mut flags = [0u8; 2];
        r.read_exact(&mut flags)?;
        let obs = f32s(&mut r, len * d.n_agents * d.obs_width)?;
        let state = f32s(&mut r, len * d.state_dim)?;
        let reward = f32s(&mut r, len)?;
        let mut avail = vec![0u8; len * d.n_agents * d.n_actions];
        r.read_exact(&mut avail)?;
        let mut raw = vec![0u8; len * d.n_agents * 4];
        r.read_exact(&mut raw)?;
        let actions = raw.chunks_exact(4).map(|c| i32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
        episodes.push(Episode { len, obs, state, avail, actions, reward, terminated: flags[0] != 0, truncated: flags[1] != 0 });
    }
    Ok(ReplayBuffer::from_parts(capacity, episodes, next))
}
