//! The slot layout computed from a schema: offsets and strides of every section of one batched
//! step, each section 64-byte aligned, and the slab (a header page followed by K slots).

use crate::schema::EnvSchema;
use serde::Serialize;
use sha2::{Digest, Sha256};

/// Bumped whenever the byte layout below changes; peers with another version are refused.
pub const LAYOUT_VERSION: u32 = 1;
pub const ALIGN: usize = 64;
/// The slab header occupies the first page.
pub const SLAB_HEADER_BYTES: usize = 4096;
/// Bytes of the per-slot header (sequence number, step, stage, ...).
pub const SLOT_HEADER_BYTES: usize = 64;
/// Per env: episode id (u64), step in episode (u32), flags (u32).
pub const ENV_META_BYTES: usize = 16;

/// `flags` bit: this row's observation is the first of a new episode.
pub const FLAG_FIRST: u32 = 1;
/// `flags` bit: the episode that ended at this row was won (SMAC win, LBF all food eaten).
pub const FLAG_PREV_WON: u32 = 2;
/// `flags` bit: the episode was truncated (time limit) at this row, and this row's observation,
/// state and available actions are what followed its last step, so the learner can bootstrap
/// from them; reward and `truncated` belong to that last step. The actions chosen on this row
/// are ignored and the next row starts a new episode. (A terminated episode has no such row:
/// the row carrying `terminated` is already the next episode's first.)
pub const FLAG_FINAL: u32 = 4;

/// Run-time parameters that, with the schema, fix the byte layout.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct LayoutParams {
    pub num_envs: usize,
    /// Message columns reserved after each observation row.
    pub msg_dim: usize,
    pub n_slots: usize,
}

/// A section's place inside a slot: byte offset and length.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Section {
    pub offset: usize,
    pub bytes: usize,
}

#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SlotLayout {
    pub num_envs: usize,
    pub n_agents: usize,
    pub obs_dim: usize,
    pub msg_dim: usize,
    pub state_dim: usize,
    pub n_actions: usize,
    pub n_slots: usize,
    /// f32 per observation row: obs_dim + msg_dim.
    pub row_width: usize,
    pub env_meta: Section,
    /// f32 [num_envs, n_agents, row_width]
    pub obs: Section,
    /// f32 [num_envs, state_dim]
    pub state: Section,
    /// u8 [num_envs, n_agents, n_actions]
    pub avail: Section,
    /// f32 [num_envs]
    pub reward: Section,
    /// u8 [num_envs]
    pub terminated: Section,
    /// u8 [num_envs]
    pub truncated: Section,
    /// i32 [num_envs, n_agents]: the actions applied on the step that led to this one (-1 at a first step)
    pub last_actions: Section,
    /// i32 [num_envs, n_agents]: written by the trainer, applied by the env server
    pub actions: Section,
    /// Bytes from one slot to the next (multiple of 64).
    pub slot_stride: usize,
    /// Total slab size: header page + n_slots * slot_stride.
    pub slab_bytes: usize,
    /// SHA-256 over the schema and the layout parameters.
    pub hash: [u8; 32],
}

impl SlotLayout {
    /// The layout of `schema` with `p`. Panics only if the sizes do not fit in memory, which
    /// [`SlotLayout::try_new`] reports instead (for parameters read from another process).
    pub fn new(schema: &EnvSchema, p: LayoutParams) -> SlotLayout {
        Self::try_new(schema, p).expect("the slab layout's size overflows usize")
    }

    /// The layout of `schema` with `p`, or None when a size overflows: every product is checked
    /// because the parameters may come from a slab header written by another process.
    pub fn try_new(schema: &EnvSchema, p: LayoutParams) -> Option<SlotLayout> {
        let (b, n) = (p.num_envs, schema.n_agents);
        let row_width = schema.obs_dim.checked_add(p.msg_dim)?;
        let mut at = SLOT_HEADER_BYTES;
        let mut overflow = false;
        let mut section = |dims: &[usize]| {
            let bytes = dims.iter().try_fold(1usize, |a, &d| a.checked_mul(d));
            let end = bytes.and_then(|x| at.checked_add(x)).and_then(|e| e.checked_next_multiple_of(ALIGN));
            match (bytes, end) {
                (Some(bytes), Some(end)) => {
                    let s = Section { offset: at, bytes };
                    at = end;
                    s
                }
                _ => {
                    overflow = true;
                    Section { offset: 0, bytes: 0 }
                }
            }
        };
        let env_meta = section(&[b, ENV_META_BYTES]);
        let obs = section(&[b, n, row_width, 4]);
        let state = section(&[b, schema.state_dim, 4]);
        let avail = section(&[b, n, schema.n_actions]);
        let reward = section(&[b, 4]);
        let terminated = section(&[b]);
        let truncated = section(&[b]);
        let last_actions = section(&[b, n, 4]);
        let actions = section(&[b, n, 4]);
        if overflow {
            return None;
        }
        let slot_stride = at.checked_next_multiple_of(ALIGN)?;
        let slab_bytes = p.n_slots.checked_mul(slot_stride)?.checked_add(SLAB_HEADER_BYTES)?;
        let mut h = Sha256::new();
        h.update(LAYOUT_VERSION.to_le_bytes());
        h.update(serde_json::to_vec(schema).expect("schema serializes"));
        h.update(serde_json::to_vec(&p).expect("params serialize"));
        Some(SlotLayout {
            num_envs: b,
            n_agents: n,
            obs_dim: schema.obs_dim,
            msg_dim: p.msg_dim,
            state_dim: schema.state_dim,
            n_actions: schema.n_actions,
            n_slots: p.n_slots,
            row_width,
            env_meta,
            obs,
            state,
            avail,
            reward,
            terminated,
            truncated,
            last_actions,
            actions,
            slot_stride,
            slab_bytes,
            hash: h.finalize().into(),
        })
    }

    pub fn params(&self) -> LayoutParams {
        LayoutParams { num_envs: self.num_envs, msg_dim: self.msg_dim, n_slots: self.n_slots }
    }

    /// Byte offset of slot `i` from the start of the slab.
    pub fn slot_offset(&self, i: usize) -> usize {
        SLAB_HEADER_BYTES + i * self.slot_stride
    }

    pub fn hash_hex(&self) -> String {
        self.hash.iter().map(|b| format!("{b:02x}")).collect()
    }
}
