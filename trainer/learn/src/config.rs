//! Learner hyperparameters. Defaults follow the LMAC paper's Table C.3 and the pymarl/EPyMARL
//! QMIX conventions where the paper is silent. Every value is configurable (serde, TOML/JSON);
//! `validate()` reports the offending field by name.

use serde::{Deserialize, Serialize};

/// Value-decomposition backbone (the mixer).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum MixerKind {
    /// Q_tot = sum_i Q_i.
    Vdn,
    /// Monotonic hypernetwork mixer (Rashid et al. 2018).
    Qmix,
    /// Duplex dueling mixer with multi-head attention weights (Wang et al. 2021).
    Qplex,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum OptimizerKind {
    Adam,
    Rmsprop,
}

/// Whether TD targets read standardised rewards ((r - mean) / std with running statistics).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum RewardStandardisation {
    /// The method's own choice: raw rewards for every method unless its settings say otherwise
    /// (LMAC's `method.standardise_rewards = true` is the released LMAC config's
    /// `standardise_rewards: True`).
    Method,
    /// Raw rewards.
    Off,
    /// Standardised; statistics over the batch's valid steps.
    ValidSteps,
    /// Standardised as the released code computes its statistics: over every step of the
    /// padded batch, the padding's zero rewards included.
    Released,
}

/// How the TD target treats an episode the time limit cut.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum TimeLimit {
    /// Bootstrap from what the agents saw after the last step, as EPyMARL does for an env that
    /// reports `episode_limit` (and gymnasium's truncation).
    #[default]
    Bootstrap,
    /// The end of the episode, its last target the reward alone: SMAC with
    /// `continuing_episode: False` (the LMAC authors' runs) reports no `episode_limit`, so their
    /// runner never bootstraps at the limit.
    Terminal,
}

/// All learner hyperparameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct LearnConfig {
    pub mixer: MixerKind,
    /// Agent network width (linear -> GRU -> linear), pymarl `rnn_hidden_dim`.
    pub rnn_hidden_dim: usize,
    /// QMIX mixing embedding (Table C.3: 32).
    pub mixing_embed_dim: usize,
    /// Layers of the QMIX/QPLEX hypernetworks (1 or 2), pymarl `hypernet_layers`.
    pub hypernet_layers: usize,
    /// Hidden width of 2-layer hypernetworks, pymarl `hypernet_embed`.
    pub hypernet_embed: usize,
    /// QPLEX: number of attention heads (kernels) of the advantage weights.
    pub qplex_num_kernel: usize,
    /// QPLEX: layers (1..=3) of each attention extractor.
    pub qplex_adv_hypernet_layers: usize,
    /// QPLEX: hidden width of the attention extractors.
    pub qplex_adv_hypernet_embed: usize,
    /// Replay capacity in episodes (Table C.3: 5000).
    pub buffer_size: usize,
    /// Episodes per update (Table C.3: 32).
    pub batch_size: usize,
    /// Discount (Table C.3: 0.99).
    pub gamma: f32,
    /// Learning rate (Table C.3: 5e-4).
    pub lr: f64,
    /// Table C.3: Adam.
    pub optimizer: OptimizerKind,
    /// Adam epsilon (torch default 1e-8).
    pub adam_eps: f32,
    /// RMSprop smoothing (pymarl `optim_alpha`).
    pub rmsprop_alpha: f32,
    /// RMSprop epsilon (pymarl `optim_eps`).
    pub rmsprop_eps: f32,
    /// Global gradient-norm clip (pymarl `grad_norm_clip`: 10).
    pub grad_norm_clip: f32,
    /// Double Q-learning: online-network argmax, target-network value.
    pub double_q: bool,
    /// Target networks are copied every this many collected episodes (Table C.3: 200).
    pub target_update_interval_episodes: u64,
    /// Epsilon-greedy exploration at the first env step (Table C.3: 1.0).
    pub epsilon_start: f32,
    /// Epsilon after `epsilon_anneal_steps`, kept to the end (Table C.3: 0.05).
    pub epsilon_finish: f32,
    /// Env steps over which epsilon is annealed linearly (Table C.3: 50k).
    pub epsilon_anneal_steps: u64,
    /// Agent input gets the last action one-hot.
    pub obs_last_action: bool,
    /// Agent input gets the agent id one-hot.
    pub obs_agent_id: bool,
    /// Agent input gets the global state (the `qmix-state` baseline, an upper bound).
    pub agent_sees_state: bool,
    /// Seed for parameter init, replay sampling and exploration.
    pub seed: u64,
    /// Unroll the target network on a second thread during the online forward pass. On by
    /// default: at one update per collected episode acting waits for the learner, so the
    /// second core is free; `--preset pymarl-parallel` turns it off (at 0.125 updates per
    /// episode acting on small environments keeps both cores busy).
    pub parallel_target: bool,
    /// Each update's batch in two halves of its episodes on two threads (online and target
    /// unroll and backward each), the gradients summed: both cores at work on one update. The
    /// same update up to float summation order (each half's losses are divided by the whole
    /// batch's trained steps, or all its steps) where every loss term of the method is such a
    /// mean: the plain agent's methods and LMAC. Other methods ignore it (and use
    /// `parallel_target`). On by default for the reason `parallel_target` is.
    pub data_parallel: bool,
    /// The agents' recurrence in training unrolls as one fused operation with a hand-written
    /// backward (`learn::gru_sequence`); false: burn's per-step GRU cell, the slower reference.
    pub fused_gru: bool,
    /// Standardised rewards in the TD targets: `method` (default: as the method's reference
    /// code), `off`, `valid-steps` or `released`.
    pub reward_standardisation: RewardStandardisation,
    /// An episode cut by the time limit: `bootstrap` from the step after it (default) or
    /// `terminal`, as the LMAC authors' SMAC runs treat it.
    pub time_limit: TimeLimit,
}

impl Default for LearnConfig {
    fn default() -> Self {
        LearnConfig {
            mixer: MixerKind::Qmix,
            rnn_hidden_dim: 64,
            mixing_embed_dim: 32,
            hypernet_layers: 2,
            hypernet_embed: 64,
            qplex_num_kernel: 10,
            qplex_adv_hypernet_layers: 3,
            qplex_adv_hypernet_embed: 64,
            buffer_size: 5000,
            batch_size: 32,
            gamma: 0.99,
            lr: 5e-4,
            optimizer: OptimizerKind::Adam,
            adam_eps: 1e-8,
            rmsprop_alpha: 0.99,
            rmsprop_eps: 1e-5,
            grad_norm_clip: 10.0,
            double_q: true,
            target_update_interval_episodes: 200,
            epsilon_start: 1.0,
            epsilon_finish: 0.05,
            epsilon_anneal_steps: 50_000,
            obs_last_action: true,
            obs_agent_id: true,
            agent_sees_state: false,
            seed: 0,
            parallel_target: true,
            data_parallel: true,
            fused_gru: true,
            reward_standardisation: RewardStandardisation::Method,
            time_limit: TimeLimit::Bootstrap,
        }
    }
}

/// A configuration value that cannot be used; `field` names it as written in the config file.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("invalid learner config: `{field}` {reason}")]
pub struct ConfigError {
    pub field: &'static str,
    pub reason: String,
}

fn err(field: &'static str, reason: impl Into<String>) -> ConfigError {
    ConfigError { field, reason: reason.into() }
}

impl LearnConfig {
    /// Check every field; the error names the first offending one.
    pub fn validate(&self) -> Result<(), ConfigError> {
        // Upper bounds far above any sensible run, low enough that a corrupt config or checkpoint
        // cannot make building the networks or the buffer exhaust memory.
        // Network widths: a GRU of width w holds 3 w^2 weights (and Adam twice as many again), so
        // 4096 is about 600 MB; 60000 would need over 100 GB and abort the process.
        let pos = |field: &'static str, v: usize| {
            let max = match field {
                "buffer_size" | "batch_size" => 1 << 24,
                "qplex_num_kernel" => 1 << 10,
                _ => 1 << 12,
            };
            if v == 0 {
                Err(err(field, "must be at least 1"))
            } else if v > max {
                Err(err(field, format!("must be at most {max}, got {v}")))
            } else {
                Ok(())
            }
        };
        pos("rnn_hidden_dim", self.rnn_hidden_dim)?;
        pos("mixing_embed_dim", self.mixing_embed_dim)?;
        pos("hypernet_embed", self.hypernet_embed)?;
        pos("qplex_num_kernel", self.qplex_num_kernel)?;
        pos("qplex_adv_hypernet_embed", self.qplex_adv_hypernet_embed)?;
        pos("buffer_size", self.buffer_size)?;
        pos("batch_size", self.batch_size)?;
        if !(1..=2).contains(&self.hypernet_layers) {
            return Err(err("hypernet_layers", format!("must be 1 or 2, got {}", self.hypernet_layers)));
        }
        if !(1..=3).contains(&self.qplex_adv_hypernet_layers) {
            return Err(err("qplex_adv_hypernet_layers", format!("must be 1, 2 or 3, got {}", self.qplex_adv_hypernet_layers)));
        }
        if self.batch_size > self.buffer_size {
            return Err(err("batch_size", format!("({}) must not exceed buffer_size ({})", self.batch_size, self.buffer_size)));
        }
        if !(self.gamma.is_finite() && (0.0..=1.0).contains(&self.gamma)) {
            return Err(err("gamma", format!("must be in [0, 1], got {}", self.gamma)));
        }
        if !(self.lr.is_finite() && self.lr > 0.0 && self.lr <= 10.0) {
            return Err(err("lr", format!("must be positive and at most 10, got {}", self.lr)));
        }
        if !(self.adam_eps.is_finite() && self.adam_eps > 0.0 && self.adam_eps <= 1.0) {
            return Err(err("adam_eps", format!("must be in (0, 1], got {}", self.adam_eps)));
        }
        if !(self.rmsprop_eps.is_finite() && self.rmsprop_eps > 0.0 && self.rmsprop_eps <= 1.0) {
            return Err(err("rmsprop_eps", format!("must be in (0, 1], got {}", self.rmsprop_eps)));
        }
        if !(self.rmsprop_alpha.is_finite() && self.rmsprop_alpha > 0.0 && self.rmsprop_alpha < 1.0) {
            return Err(err("rmsprop_alpha", format!("must be in (0, 1), got {}", self.rmsprop_alpha)));
        }
        if !(self.grad_norm_clip.is_finite() && self.grad_norm_clip > 0.0) {
            return Err(err("grad_norm_clip", format!("must be positive, got {}", self.grad_norm_clip)));
        }
        if !(1..=1 << 40).contains(&self.target_update_interval_episodes) {
            return Err(err(
                "target_update_interval_episodes",
                format!("must be between 1 and 2^40, got {}", self.target_update_interval_episodes),
            ));
        }
        if self.epsilon_anneal_steps > 1 << 48 {
            return Err(err("epsilon_anneal_steps", format!("must be at most 2^48, got {}", self.epsilon_anneal_steps)));
        }
        for (field, v) in [("epsilon_start", self.epsilon_start), ("epsilon_finish", self.epsilon_finish)] {
            if !(v.is_finite() && (0.0..=1.0).contains(&v)) {
                return Err(err(field, format!("must be in [0, 1], got {v}")));
            }
        }
        Ok(())
    }

    /// Parse a TOML table (unknown keys are errors) and validate it.
    pub fn from_toml_str(s: &str) -> Result<Self, anyhow::Error> {
        let cfg: LearnConfig = toml::from_str(s)?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// Linear epsilon schedule over environment steps (pymarl `DecayThenFlatSchedule`, linear).
    pub fn epsilon_at(&self, t_env: u64) -> f32 {
        if self.epsilon_anneal_steps == 0 {
            return self.epsilon_finish;
        }
        let frac = (t_env as f64 / self.epsilon_anneal_steps as f64).min(1.0) as f32;
        self.epsilon_start + (self.epsilon_finish - self.epsilon_start) * frac
    }

    /// Width of one agent's network input for the given episode sizes.
    pub fn agent_input_dim(&self, dims: &crate::episode::EpisodeDims) -> usize {
        dims.obs_width
            + if self.obs_last_action { dims.n_actions } else { 0 }
            + if self.obs_agent_id { dims.n_agents } else { 0 }
            + if self.agent_sees_state { dims.state_dim } else { 0 }
    }
}
