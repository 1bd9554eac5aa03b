//! The trajectory dataset B of protocol design: episodes collected through the real pipeline
//! (a short QMIX run's epsilon-greedy policy with phase 0's protocol fixed), holding per step
//! every agent's raw observation, its action, the global state and the team reward.
//!
//! Messages are not stored: a protocol's messages are a pure function of the observation
//! history, the last actions and the episode starts, so [`Dataset::messages`] recomputes them
//! for any phase with the runner's own compiled plan, exactly as the runner would have written
//! them. One dataset therefore serves every phase.
//!
//! # On-disk format (a directory)
//! - `header.json`: `{"format": "lmac-trajectories", "version": 1, "env", "n_agents",
//!   "obs_dim", "state_dim", "n_actions", "episode_limit", "protocol", "policy", "seed",
//!   "episodes", "steps", "episodes_bytes", "episodes_crc32c"}`: the last two are the size and
//!   CRC-32C of `episodes.bin`, checked before it is parsed (datasets written before they
//!   existed load without the check).
//! - `episodes.bin`: the 8 bytes `LMACTRJ1`, then per episode a record, all little-endian:
//!   `u32 len`, `u8 terminated`, `u8 truncated`, `u16 0`, then `len*n_agents*obs_dim` f32
//!   observations (step, agent, dim), `len*state_dim` f32 states, `len*n_agents` i32 actions,
//!   `len` f32 rewards.
//!
//! Saving writes a sibling `<dir>.partial-<pid>` and renames it into place, so a crash never
//! leaves a half-written dataset under the final name.

use crate::episode::Episode;
use anyhow::{bail, Context, Result};
use lmac_protocol_runner::plan::{MessagePlan, StepView};
use serde::{Deserialize, Serialize};
use std::io::{BufWriter, Read, Write};
use std::path::{Path, PathBuf};

const MAGIC: &[u8; 8] = b"LMACTRJ1";
const FORMAT: &str = "lmac-trajectories";
const VERSION: u32 = 1;

/// A writer that keeps the CRC-32C and length of what passes through it.
struct Crc32cWriter {
    inner: std::fs::File,
    crc: u32,
    bytes: u64,
}

impl Write for Crc32cWriter {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.crc = crc32c::crc32c_append(self.crc, &buf[..n]);
        self.bytes += n as u64;
        Ok(n)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.inner.flush()
    }
}

/// What the dataset holds and how it was collected.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DatasetHeader {
    pub env: String,
    pub n_agents: usize,
    pub obs_dim: usize,
    pub state_dim: usize,
    pub n_actions: usize,
    pub episode_limit: usize,
    /// The protocol the runner applied while collecting (its messages shaped the policy).
    pub protocol: String,
    /// The policy that acted (algorithm, training steps, epsilon).
    pub policy: String,
    pub seed: u64,
}

/// One episode: `len` steps of raw observations (no message columns), states, actions, rewards.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Trajectory {
    pub len: usize,
    /// len * n_agents * obs_dim
    pub obs: Vec<f32>,
    /// len * state_dim
    pub state: Vec<f32>,
    /// len * n_agents
    pub actions: Vec<i32>,
    /// len
    pub reward: Vec<f32>,
    pub terminated: bool,
    pub truncated: bool,
}

impl Trajectory {
    /// Copy an assembled episode, dropping its message columns (its rows are
    /// `ep.obs.len() / (len * n_agents)` wide, the observation first).
    pub fn from_episode(ep: &Episode, n_agents: usize, obs_dim: usize) -> Self {
        let rows = ep.len * n_agents;
        let width = if rows == 0 { obs_dim } else { ep.obs.len() / rows };
        let mut obs = Vec::with_capacity(rows * obs_dim);
        for r in 0..rows {
            obs.extend_from_slice(&ep.obs[r * width..r * width + obs_dim]);
        }
        Trajectory {
            len: ep.len,
            obs,
            state: ep.state.clone(),
            actions: ep.actions.clone(),
            reward: ep.reward.clone(),
            terminated: ep.terminated,
            truncated: ep.truncated,
        }
    }
}

/// The dataset B.
#[derive(Clone, Debug, PartialEq)]
pub struct Dataset {
    pub header: DatasetHeader,
    pub episodes: Vec<Trajectory>,
}

fn put_f32(w: &mut impl Write, v: &[f32]) -> std::io::Result<()> {
    let mut b = Vec::with_capacity(v.len() * 4);
    v.iter().for_each(|x| b.extend_from_slice(&x.to_le_bytes()));
    w.write_all(&b)
}

impl Dataset {
    /// Total steps over all episodes.
    pub fn steps(&self) -> usize {
        self.episodes.iter().map(|e| e.len).sum()
    }

    fn check_shapes(&self) -> Result<()> {
        let h = &self.header;
        for (k, e) in self.episodes.iter().enumerate() {
            let want = [
                (e.obs.len(), e.len * h.n_agents * h.obs_dim, "obs"),
                (e.state.len(), e.len * h.state_dim, "state"),
                (e.actions.len(), e.len * h.n_agents, "actions"),
                (e.reward.len(), e.len, "reward"),
            ];
            for (got, exp, what) in want {
                if got != exp {
                    bail!("episode {k}: {what} has {got} values, expected {exp} for {} steps", e.len);
                }
            }
        }
        Ok(())
    }

    /// Write the dataset to `dir` atomically (replacing an existing one).
    pub fn save(&self, dir: &Path) -> Result<()> {
        self.check_shapes()?;
        let name = dir.file_name().context("dataset directory needs a name")?.to_string_lossy().to_string();
        let tmp: PathBuf = dir.with_file_name(format!("{name}.partial-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&tmp);
        std::fs::create_dir_all(&tmp).with_context(|| format!("creating {}", tmp.display()))?;
        let mut header = serde_json::to_value(&self.header)?;
        header["format"] = FORMAT.into();
        header["version"] = VERSION.into();
        header["episodes"] = self.episodes.len().into();
        header["steps"] = self.steps().into();
        let f = std::fs::File::create(tmp.join("episodes.bin"))?;
        let mut w = BufWriter::new(Crc32cWriter { inner: f, crc: 0, bytes: 0 });
        w.write_all(MAGIC)?;
        for e in &self.episodes {
            w.write_all(&(e.len as u32).to_le_bytes())?;
            w.write_all(&[e.terminated as u8, e.truncated as u8, 0, 0])?;
            put_f32(&mut w, &e.obs)?;
            put_f32(&mut w, &e.state)?;
            let mut b = Vec::with_capacity(e.actions.len() * 4);
            e.actions.iter().for_each(|x| b.extend_from_slice(&x.to_le_bytes()));
            w.write_all(&b)?;
            put_f32(&mut w, &e.reward)?;
        }
        let body = w.into_inner().map_err(|e| e.into_error())?;
        body.inner.sync_all()?;
        header["episodes_bytes"] = body.bytes.into();
        header["episodes_crc32c"] = format!("{:08x}", body.crc).into();
        std::fs::write(tmp.join("header.json"), serde_json::to_string_pretty(&header)?)?;
        if dir.exists() {
            std::fs::remove_dir_all(dir).with_context(|| format!("replacing {}", dir.display()))?;
        }
        std::fs::rename(&tmp, dir).with_context(|| format!("moving {} to {}", tmp.display(), dir.display()))?;
        Ok(())
    }

    /// Read a dataset written by [`Dataset::save`]; errors name the file and the problem.
    pub fn load(dir: &Path) -> Result<Self> {
        let hp = dir.join("header.json");
        let text = crate::safe_fs::read_text_capped(&hp, crate::safe_fs::TEXT_CAP).context("cannot read the dataset's header")?;
        let v: serde_json::Value = serde_json::from_str(&text).with_context(|| format!("{}: not JSON", hp.display()))?;
        if v["format"] != FORMAT {
            bail!("{}: not an lmac trajectory dataset (format {:?})", hp.display(), v["format"]);
        }
        if v["version"] != VERSION {
            bail!("{}: dataset format version {} (this lmac reads {VERSION})", hp.display(), v["version"]);
        }
        let header: DatasetHeader = serde_json::from_value(v.clone()).with_context(|| format!("{}: bad header", hp.display()))?;
        let n_eps = v["episodes"].as_u64().with_context(|| format!("{}: episodes: missing or not a count", hp.display()))?;
        let bp = dir.join("episodes.bin");
        // A regular file only: a device (a link to /dev/zero) would be read until memory runs out.
        let meta = std::fs::symlink_metadata(&bp).with_context(|| format!("{}: cannot read", bp.display()))?;
        if !meta.is_file() {
            bail!("{}: not a regular file", bp.display());
        }
        if let Some(want) = v.get("episodes_bytes").filter(|x| !x.is_null()) {
            if want.as_u64() != Some(meta.len()) {
                bail!(
                    "{}: {} bytes, but {} records episodes_bytes = {want}: the file is truncated or replaced",
                    bp.display(),
                    meta.len(),
                    hp.display()
                );
            }
        }
        let mut data = Vec::new();
        crate::safe_fs::open_regular(&bp)
            .and_then(|f| f.take(crate::safe_fs::DATA_CAP).read_to_end(&mut data))
            .context("cannot read the dataset's episodes")?;
        if let Some(want) = v.get("episodes_crc32c").filter(|x| !x.is_null()) {
            let got = format!("{:08x}", crc32c::crc32c(&data));
            if want.as_str() != Some(got.as_str()) {
                bail!("{}: CRC-32C {got}, but {} records {want}: the file is corrupt", bp.display(), hp.display());
            }
        }
        if data.len() < 8 || &data[..8] != MAGIC {
            bail!("{}: does not start with the dataset magic {:?}", bp.display(), std::str::from_utf8(MAGIC).unwrap_or_default());
        }
        let h = &header;
        // Far above any environment's sizes, far below what would overflow the products that
        // readers of the dataset form (e.g. n_agents * (obs_dim + msg_dim) message rows).
        const MAX_DIM: usize = 1 << 20;
        for (field, value) in [("n_agents", h.n_agents), ("obs_dim", h.obs_dim), ("state_dim", h.state_dim), ("n_actions", h.n_actions)] {
            if value > MAX_DIM {
                bail!("{}: {field}: {value} is not a plausible size (at most {MAX_DIM})", hp.display());
            }
        }
        // Every header number is hostile until checked: sizes are computed with checked
        // arithmetic and compared with the file before anything is allocated, so a corrupt
        // header gives an error naming the field, never an overflow or a huge allocation.
        // An episode record is at least 8 bytes, so the count cannot exceed the file either.
        if n_eps > (data.len() as u64 - 8) / 8 {
            bail!("{}: episodes: {n_eps} episodes cannot fit in the {} bytes of {}", hp.display(), data.len(), bp.display());
        }
        let n_eps = n_eps as usize;
        let per_step = [h.n_agents.checked_mul(h.obs_dim), Some(h.state_dim), Some(h.n_agents), Some(1)]
            .into_iter()
            .try_fold(0usize, |acc, x| x.and_then(|x| acc.checked_add(x)))
            .and_then(|values| values.checked_mul(4))
            .with_context(|| format!("{}: n_agents, obs_dim, state_dim: a step's size overflows", hp.display()))?;
        let mut at = 8usize;
        let mut episodes = Vec::with_capacity(n_eps);
        for k in 0..n_eps {
            if data.len() - at < 8 {
                bail!(
                    "{}: truncated in episode {k}: its 8-byte record header at offset {at} is cut off (file has {} bytes)",
                    bp.display(),
                    data.len()
                );
            }
            let rec = &data[at..at + 8];
            at += 8;
            let len = u32::from_le_bytes([rec[0], rec[1], rec[2], rec[3]]) as usize;
            let (terminated, truncated) = (rec[4] != 0, rec[5] != 0);
            if len == 0 || len > h.episode_limit {
                bail!("{}: episode {k}: len {len} steps (header episode_limit {})", bp.display(), h.episode_limit);
            }
            let need = len.checked_mul(per_step).filter(|&n| n <= data.len() - at).with_context(|| {
                format!(
                    "{}: truncated in episode {k}: {len} steps of {per_step} bytes need more than the {} bytes left at offset {at}",
                    bp.display(),
                    data.len() - at
                )
            })?;
            let body = &data[at..at + need];
            at += need;
            // All four products are at most `len * per_step / 4`, checked above.
            let (n_obs, n_state, n_act) = (len * h.n_agents * h.obs_dim, len * h.state_dim, len * h.n_agents);
            let (obs_b, rest) = body.split_at(4 * n_obs);
            let (state_b, rest) = rest.split_at(4 * n_state);
            let (act_b, reward_b) = rest.split_at(4 * n_act);
            let f32s = |b: &[u8]| b.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect::<Vec<_>>();
            let actions: Vec<i32> = act_b.chunks_exact(4).map(|c| i32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
            if let Some(bad) = actions.iter().find(|&&a| a < 0 || a as usize >= h.n_actions) {
                bail!("{}: episode {k}: action {bad} is not one of the {} actions", bp.display(), h.n_actions);
            }
            episodes.push(Trajectory {
                len,
                obs: f32s(obs_b),
                state: f32s(state_b),
                actions,
                reward: f32s(reward_b),
                terminated,
                truncated,
            });
        }
        if at != data.len() {
            bail!("{}: {} bytes after the {n_eps} episodes the header announces", bp.display(), data.len() - at);
        }
        let dataset = Dataset { header, episodes };
        if let Some(steps) = v.get("steps").filter(|s| !s.is_null()) {
            if steps.as_u64() != Some(dataset.steps() as u64) {
                bail!("{}: steps: the header says {steps} but {} holds {} steps", hp.display(), bp.display(), dataset.steps());
            }
        }
        Ok(dataset)
    }

    /// Run `plan` over episodes `episodes` step by step as the runner would have: over the stored
    /// observations, with the episode-start flag (fresh history at each episode's first step) and
    /// the previous step's actions (-1 on the first step); `f` gets each step's episode, step and
    /// rows (`n_agents x (obs_dim + msg_dim)`, the messages after each agent's observation).
    pub fn replay(&self, episodes: &[usize], plan: &mut dyn MessagePlan, f: &mut dyn FnMut(&Trajectory, usize, &[f32])) {
        let (n, od, md) = (self.header.n_agents, self.header.obs_dim, plan.msg_dim());
        let row = od + md;
        let mut rows = vec![0f32; n * row];
        let mut last = vec![-1i32; n];
        for &k in episodes {
            let e = &self.episodes[k];
            for t in 0..e.len {
                for a in 0..n {
                    rows[a * row..a * row + od].copy_from_slice(&e.obs[(t * n + a) * od..(t * n + a + 1) * od]);
                    rows[a * row + od..(a + 1) * row].fill(0.0);
                    last[a] = if t == 0 { -1 } else { e.actions[(t - 1) * n + a] };
                }
                let first = [t == 0];
                let mut view =
                    StepView { num_envs: 1, n_agents: n, obs_dim: od, msg_dim: md, rows: &mut rows, first: &first, last_actions: &last };
                plan.apply(&mut view);
                f(e, t, &rows);
            }
        }
    }

    /// Each episode's received messages (`len * n_agents * plan.msg_dim()`, by step then agent)
    /// as the runner would have written them ([`Dataset::replay`] over every episode).
    pub fn messages(&self, plan: &mut dyn MessagePlan) -> Vec<Vec<f32>> {
        let (n, od, md) = (self.header.n_agents, self.header.obs_dim, plan.msg_dim());
        let row = od + md;
        (0..self.episodes.len())
            .map(|k| {
                let mut out = Vec::with_capacity(self.episodes[k].len * n * md);
                self.replay(&[k], plan, &mut |_, _, rows| {
                    for a in 0..n {
                        out.extend_from_slice(&rows[a * row + od..(a + 1) * row]);
                    }
                });
                out
            })
            .collect()
    }
}
