//! Episode replay (pymarl `ReplayBuffer`): a ring of whole episodes, uniform sampling without
//! replacement, and padded, time-major batches with masks.

use crate::episode::{Episode, EpisodeDims};

use super::{InputLayout, LearnRng, RowParts};

pub struct ReplayBuffer {
    capacity: usize,
    episodes: Vec<Episode>,
    /// Slot the next episode overwrites once full.
    next: usize,
}

impl ReplayBuffer {
    pub fn new(capacity: usize) -> Self {
        ReplayBuffer { capacity, episodes: Vec::new(), next: 0 }
    }

    pub fn capacity(&self) -> usize {
        self.capacity
    }

    pub fn len(&self) -> usize {
        self.episodes.len()
    }

    pub fn is_empty(&self) -> bool {
        self.episodes.is_empty()
    }

    pub fn push(&mut self, ep: Episode) {
        if self.episodes.len() < self.capacity {
            self.episodes.push(ep);
        } else {
            self.episodes[self.next] = ep;
        }
        self.next = (self.next + 1) % self.capacity;
    }

    /// Rebuild from storage order (`episodes[i]` is slot i) and the next slot to overwrite.
    pub fn from_parts(capacity: usize, mut episodes: Vec<Episode>, next: usize) -> Self {
        episodes.truncate(capacity);
        let next = if capacity == 0 { 0 } else { next % capacity };
        ReplayBuffer { capacity, episodes, next }
    }

    /// Episodes in storage (slot) order, and the next slot to overwrite.
    pub fn slots(&self) -> (&[Episode], usize) {
        (&self.episodes, self.next)
    }

    /// Episodes in insertion order, oldest first.
    pub fn iter_ordered(&self) -> impl Iterator<Item = &Episode> {
        let (a, b) = if self.episodes.len() < self.capacity {
            (&self.episodes[..], &self.episodes[..0])
        } else {
            (&self.episodes[self.next..], &self.episodes[..self.next])
        };
        a.iter().chain(b.iter())
    }

    /// `k` distinct indices (partial Fisher-Yates); `k <= len()`.
    pub fn sample_indices(&self, k: usize, rng: &mut LearnRng) -> Vec<usize> {
        let n = self.episodes.len();
        assert!(k <= n, "sampling {k} episodes from a buffer of {n}");
        let mut idx: Vec<usize> = (0..n).collect();
        for i in 0..k {
            let j = i + rng.below(n - i);
            idx.swap(i, j);
        }
        idx.truncate(k);
        idx
    }

    pub fn get(&self, i: usize) -> &Episode {
        &self.episodes[i]
    }
}

/// A padded batch of `b` episodes over `t` steps (the longest episode, counting a truncated
/// episode's next step), time-major.
#[derive(Clone, Debug)]
pub struct Batch {
    pub b: usize,
    pub t: usize,
    pub n_agents: usize,
    pub n_actions: usize,
    pub state_dim: usize,
    pub input_dim: usize,
    /// [t, b, n, input_dim]: agent network inputs (obs | state? | last action | id).
    pub inputs: Vec<f32>,
    /// [t, b, state_dim]
    pub state: Vec<f32>,
    /// [t, b, n]; padding 0.
    pub actions: Vec<i32>,
    /// [t, b, n, n_actions]; 1 = available; padded steps have every action available.
    pub avail: Vec<u8>,
    /// [t, b]
    pub reward: Vec<f32>,
    /// [t, b]: 1 where the transition ends the episode by termination (target = reward).
    pub terminated: Vec<f32>,
    /// [t, b]: 1 where the transition is trained on (real, and with a successor or terminal).
    pub mask: Vec<f32>,
    /// [t, b]: 1 where a successor step t+1 exists in the same episode.
    pub has_next: Vec<f32>,
}

impl Batch {
    pub fn from_episodes(eps: &[&Episode], dims: &EpisodeDims, layout: &InputLayout) -> Batch {
        let b = eps.len();
        let t = eps.iter().map(|e| e.len + e.next.is_some() as usize).max().unwrap_or(0);
        let (n, a, s, ow) = (dims.n_agents, dims.n_actions, dims.state_dim, dims.obs_width);
        let iw = layout.width();
        let mut batch = Batch {
            b,
            t,
            n_agents: n,
            n_actions: a,
            state_dim: s,
            input_dim: iw,
            inputs: vec![0.0; t * b * n * iw],
            state: vec![0.0; t * b * s],
            actions: vec![0; t * b * n],
            avail: vec![1; t * b * n * a],
            reward: vec![0.0; t * b],
            terminated: vec![0.0; t * b],
            mask: vec![0.0; t * b],
            has_next: vec![0.0; t * b],
        };
        for (bi, ep) in eps.iter().enumerate() {
            debug_assert_eq!(ep.obs.len(), ep.len * n * ow);
            for ti in 0..ep.len {
                let tb = ti * b + bi;
                let st = &ep.state[ti * s..(ti + 1) * s];
                batch.state[tb * s..(tb + 1) * s].copy_from_slice(st);
                for ag in 0..n {
                    let row = tb * n + ag;
                    let obs = &ep.obs[(ti * n + ag) * ow..(ti * n + ag + 1) * ow];
                    let last = if ti == 0 { -1 } else { ep.actions[(ti - 1) * n + ag] };
                    layout.write(&mut batch.inputs[row * iw..(row + 1) * iw], RowParts::step(obs, Some(st), last, ag));
                    batch.actions[row] = ep.actions[ti * n + ag];
                    batch.avail[row * a..(row + 1) * a].copy_from_slice(&ep.avail[(ti * n + ag) * a..(ti * n + ag + 1) * a]);
                }
                batch.reward[tb] = ep.reward[ti];
                let last_step = ti + 1 == ep.len;
                let succeeded = !last_step || ep.next.is_some();
                batch.has_next[tb] = if succeeded { 1.0 } else { 0.0 };
                // Terminated: the target is the reward alone. Truncated with its next step: the
                // target bootstraps from it. Cut without a known successor: masked.
                if last_step && ep.terminated {
                    batch.terminated[tb] = 1.0;
                }
                if succeeded || ep.terminated {
                    batch.mask[tb] = 1.0;
                }
            }
            if let Some(next) = &ep.next {
                // The step after the last: inputs, state and avail for the target only (mask 0).
                let tb = ep.len * b + bi;
                batch.state[tb * s..(tb + 1) * s].copy_from_slice(&next.state);
                for ag in 0..n {
                    let row = tb * n + ag;
                    let last = ep.actions[(ep.len - 1) * n + ag];
                    let obs = &next.obs[ag * ow..(ag + 1) * ow];
                    layout.write(&mut batch.inputs[row * iw..(row + 1) * iw], RowParts::step(obs, Some(&next.state), last, ag));
                    batch.avail[row * a..(row + 1) * a].copy_from_slice(&next.avail[ag * a..(ag + 1) * a]);
                }
            }
        }
        batch
    }

    /// The number of trained steps (the mask's sum), at least 1: what every mean over trained
    /// steps divides by.
    pub fn trained_steps(&self) -> f32 {
        self.mask.iter().sum::<f32>().max(1.0)
    }

    /// Episodes `range` of this batch as a batch of their own, over the same T steps (so a part's
    /// padding, and every per-step quantity, is the whole batch's).
    pub fn episodes(&self, range: std::ops::Range<usize>) -> Batch {
        assert!(range.start < range.end && range.end <= self.b, "episodes {range:?} of a batch of {}", self.b);
        let (t, b, nb) = (self.t, self.b, range.len());
        let (n, a) = (self.n_agents, self.n_actions);
        Batch {
            b: nb,
            t,
            n_agents: n,
            n_actions: a,
            state_dim: self.state_dim,
            input_dim: self.input_dim,
            inputs: episode_rows(&self.inputs, t, b, n * self.input_dim, &range),
            state: episode_rows(&self.state, t, b, self.state_dim, &range),
            actions: episode_rows(&self.actions, t, b, n, &range),
            avail: episode_rows(&self.avail, t, b, n * a, &range),
            reward: episode_rows(&self.reward, t, b, 1, &range),
            terminated: episode_rows(&self.terminated, t, b, 1, &range),
            mask: episode_rows(&self.mask, t, b, 1, &range),
            has_next: episode_rows(&self.has_next, t, b, 1, &range),
        }
    }
}

/// Episodes `range` of a [t, b, width] array (time-major, as a [`Batch`] holds its data): per
/// step, those episodes' rows.
pub fn episode_rows<T: Copy>(v: &[T], t: usize, b: usize, width: usize, range: &std::ops::Range<usize>) -> Vec<T> {
    assert_eq!(v.len(), t * b * width, "a [t, b, width] array");
    let mut out = Vec::with_capacity(t * range.len() * width);
    for ti in 0..t {
        out.extend_from_slice(&v[(ti * b + range.start) * width..(ti * b + range.end) * width]);
    }
    out
}
