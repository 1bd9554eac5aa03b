//! lmac's learning core (burn only: no shared memory, no network, no CLI): episodes, shared-parameter RNN agents, VDN/QMIX/QPLEX mixers, an episode replay
//! buffer, a double-Q TD(0) learner with a global gradient-norm clip, an acting controller and
//! atomic checkpoints. Runs on burn 0.22 (flex CPU backend by default, `ndarray` by feature).
//!
//! How the pipeline drives it:
//! ```ignore
//! let cfg = LearnConfig::from_toml_str(&text)?;                  // or LearnConfig { .. }; validated
//! let mut learner = Learner::new(dims, cfg, Device::default())?;  // validates again
//! let mut ctl = Controller::new(&learner, n_envs);                // acting copy, per-env GRU state
//! // per batched env step (obs: n_envs*n*obs_width, avail: n_envs*n*n_actions, first: n_envs):
//! let eps = learner.epsilon();                                     // from t_env of added episodes
//! let acts = ctl.select_actions(&obs, state, &last, &avail, &first, eps, learner.rng_mut());
//! // per finished episode:
//! learner.add_episode(episode)?;                                   // advances t_env, episodes
//! if learner.can_train() {
//!     let stats = learner.train_step()?;   // Err(LearnError::NonFinite{update,..}) stops the run
//!     ctl.sync_weights(&learner);
//! }
//! learner.save_checkpoint(&dir, true)?;                            // atomic; true = with replay
//! let learner = Learner::load_checkpoint(&dir, Device::default())?;
//! ```

pub mod agent;
pub mod agent_input;
pub mod buffer;
pub mod checkpoint;
pub mod config;
pub mod controller;
pub mod dense;
pub mod episode;
pub mod flops;
pub mod gru_sequence;
mod host_kernel;
pub mod input_row;
pub mod latent_gate;
pub mod learner;
pub mod methods;
pub mod mixer;
pub mod qmix_mix;
pub mod stats;
pub mod window_attention;

pub use buffer::{Batch, ReplayBuffer};
pub use config::{ConfigError, LearnConfig, MixerKind, OptimizerKind, RewardStandardisation, TimeLimit};
pub use controller::Controller;
pub use input_row::{InputLayout, RowParts};
pub use learner::{Counters, LearnError, Learner, QNet, RewardStats, TrainStats};
pub use methods::{AgentConfig, AgentNet};

/// Most env steps a run, or an interval of one, may ask for (2^48, about 2.8e14): the bound on a
/// run's settings and on a checkpoint's counters.
pub const MAX_ENV_STEPS: u64 = 1 << 48;

/// Keep freed memory in the heap instead of handing it back to the kernel (glibc `mallopt`).
///
/// An update allocates and frees tens of megabytes of tensors; with glibc's defaults, blocks
/// above the mmap threshold come back as fresh pages that fault and get zeroed on first write
/// every update (the learner bench's gain: `docs/results/performance.md`). Costs resident memory (up to the
/// trim threshold, 1 GiB, stays mapped). Called once at start by the `lmac` binary and the
/// learner benches; a no-op off glibc.
pub fn tune_allocator() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only changes allocator parameters; called before heavy allocation starts.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 256 << 20);
        libc::mallopt(libc::M_TRIM_THRESHOLD, 1 << 30);
        libc::mallopt(libc::M_TOP_PAD, 64 << 20);
    }
}

/// The burn device type (re-exported so callers need no direct burn dependency).
pub use burn::tensor::Device;
use serde::{Deserialize, Serialize};

/// Small, fast, serializable PRNG (xoshiro256++), so checkpoints can hold the exact RNG state.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct LearnRng {
    s: [u64; 4],
}

impl LearnRng {
    pub fn seed_from(seed: u64) -> Self {
        let mut x = seed;
        let mut next = || {
            x = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = x;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^ (z >> 31)
        };
        LearnRng { s: [next(), next(), next(), next()] }
    }

    /// Uniform in [0, 1).
    pub fn uniform(&mut self) -> f32 {
        (rand::RngCore::next_u64(self) >> 40) as f32 / (1u64 << 24) as f32
    }

    /// Uniform integer in 0..n (n > 0).
    pub fn below(&mut self, n: usize) -> usize {
        ((rand::RngCore::next_u64(self) as u128 * n as u128) >> 64) as usize
    }
}

impl rand::RngCore for LearnRng {
    fn next_u32(&mut self) -> u32 {
        (self.next_u64() >> 32) as u32
    }

    fn next_u64(&mut self) -> u64 {
        let s = &mut self.s;
        let result = s[0].wrapping_add(s[3]).rotate_left(23).wrapping_add(s[0]);
        let t = s[1] << 17;
        s[2] ^= s[0];
        s[3] ^= s[1];
        s[1] ^= s[2];
        s[0] ^= s[3];
        s[2] ^= t;
        s[3] = s[3].rotate_left(45);
        result
    }

    fn fill_bytes(&mut self, dst: &mut [u8]) {
        for chunk in dst.chunks_mut(8) {
            let v = self.next_u64().to_le_bytes();
            chunk.copy_from_slice(&v[..chunk.len()]);
        }
    }
}

/// Parameter initialization from a [`LearnRng`] on the host, so a seed fixes the initial
/// weights exactly (burn's device RNG is process-global and initializes lazily, so it depends on
/// whatever else drew from it). Bounds follow torch's `nn.Linear`: U(-1/sqrt(fan_in), +).
pub mod init {
    use burn::module::Param;
    use burn::nn::Linear;
    use burn::tensor::{Device, Tensor, TensorData};

    use super::LearnRng;

    pub fn uniform<const D: usize>(rng: &mut LearnRng, shape: [usize; D], bound: f32, device: &Device) -> Param<Tensor<D>> {
        let n: usize = shape.iter().product();
        let v: Vec<f32> = (0..n).map(|_| (rng.uniform() * 2.0 - 1.0) * bound).collect();
        Param::from_tensor(Tensor::from_data(TensorData::new(v, shape), device))
    }

    /// A `Linear` (row layout, weight [d_in, d_out]) with bias, torch's default init.
    pub fn linear(rng: &mut LearnRng, d_in: usize, d_out: usize, device: &Device) -> Linear {
        let bound = 1.0 / (d_in as f32).sqrt();
        Linear { weight: uniform(rng, [d_in, d_out], bound, device), bias: Some(uniform(rng, [d_out], bound, device)) }
    }
}
