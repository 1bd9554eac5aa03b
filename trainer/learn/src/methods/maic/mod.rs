//! MAIC, multi-agent incentive communication (Yuan et al. 2022, "Multi-Agent Incentive
//! Communication via Decentralized Teammate Modeling"), as in the authors' released code
//! (mansicer/MAIC: `maic_agent.py`, `maic_learner.py`, `maic.yaml`), on lmac's learner. The
//! network is in `module.rs`.
//!
//! Each agent i runs pymarl's RNN agent (local Q_i from its GRU state h_i) and models every
//! teammate j with a Gaussian latent z_ij (h_i -> K -> batch norm -> leaky ReLU -> n*L means and
//! n*L log-variances, variance floored at `var_floor`; K = 64, L = 8). From (h_i, z_ij) it makes
//! an incentive message m_ij (-> K -> leaky ReLU -> one value per action), weighted by attention
//! alpha_ij = softmax_j(W_q h_i . W_k z_ij / sqrt(att)) over the teammates (self excluded).
//! Agent j's Q-values are Q_j + sum_i alpha_ij m_ij. In training the latents are reparameterised
//! samples; outside training the means, and attention weights below `prune / n` are set to 0.
//!
//! Losses (with the TD loss, means over the trained steps):
//! - mutual information (weight `mi_weight`, 1e-3): KL(N(z_ij) || q(z | h_i, a_j)) summed over
//!   the latent dims, averaged over the pairs i != j, where q is an inference net
//!   ([h_i | one-hot a_j] -> K -> batch norm -> leaky ReLU -> L means, L log-variances);
//! - attention entropy (weight `entropy_weight`, 1e-2): the entropy (bits) of each agent's
//!   attention over its teammates, computed from detached h and z (only W_q and W_k learn from
//!   it) with weights clamped at 1e-4 as in the released code.
//!
//! Randomness: the latent samples come from a host-side [`LearnRng`](crate::LearnRng)
//! seeded from the update's seed, so an update is reproducible; acting is deterministic.
//!
//! Decisions where the released code differs from the paper, and other differences:
//! - Message input (`message_input`): the paper's m_ij reads the sender's h_i; the released code
//!   builds the pairs with `h.repeat(1, n, 1)`, which gives the message net the *receiver's* h_j
//!   (its MI loss builds h_i correctly with a different repeat). Default `sender`; `receiver`
//!   keeps the code's behaviour.
//! - Batch norm (`batch_norm`): the released code never switches its batch norms to eval mode,
//!   so they always normalise with the statistics of the rows in the forward pass: in acting
//!   (its episode runner steps one environment) over the n agents of that environment, which
//!   with n = 2 turns every feature into +-1 and lets teammates' hidden states leak into each
//!   agent's latents. Default `running`: batch statistics in training updates (over the trained
//!   rows of each step), running statistics (momentum 0.1, unbiased variance, as torch) when
//!   acting and in the target network. `batch` keeps the code's behaviour: statistics of each
//!   environment's n agents when acting and in the target network (the released target network
//!   normalises over the whole padded batch at each step), of the batch's trained rows in
//!   updates.
//! - MI action (`mi_action`): the paper's a_j is the action teammate j takes; the released code
//!   uses the argmax of j's current Q-values (availability ignored). Default `taken` (the
//!   batch's action); `greedy` keeps the code's.
//! - Outside updates (acting in every episode, test episodes, the target network) the network is
//!   in test mode: latent means and pruned attention. The released code samples latents and
//!   does not prune in its training episodes and in the target network. Not an option: the
//!   seam's acting step is deterministic.
//! - The losses are masked over padded steps and averaged over the trained steps
//!   (`mask_losses = true`); the released code averages the per-step losses over every step of
//!   the padded batch (`maic_learner.py:140-151` divides by `max_seq_length`, the row after the
//!   longest episode included; lmac's batch holds that row only when the episode was
//!   truncated): `mask_losses = false`. Either way the batch norms' training statistics are
//!   those of the trained rows (see `batch_norm`).
//! - The MI loss leaves out the pairs i = i (`mi_pairs = "teammates"`, the paper's teammate
//!   models); the released code averages over all n^2 pairs, z_ii included, which no message
//!   reads (`maic_agent.py:101-113`): `mi_pairs = "all"`.
//! - The entropy is that of the attention actually used (scaled by 1/sqrt(att), self excluded;
//!   `entropy_attention = "used"`); the released code recomputes it unscaled with the agent
//!   itself among the candidates (`maic_agent.py:93-96`): `entropy_attention = "released"`.
//!   With n agents a uniform attention is log2(n - 1) bits in the first and log2(n) in the
//!   second.
//! - Loss reductions otherwise as released (`docs/reference/fidelity.md`): the MI is the KL summed over
//!   the latent dims and averaged over pairs, the entropy summed over the candidates and
//!   averaged over agents (`maic_agent.py:113,118`), each times its weight.
//! - The optimizer and the mixer are the run's `[learn]` settings. lmac's default QMIX (2-layer
//!   hypernetworks of width 64, mixing width 32) is the released config's; its optimizer is
//!   RMSprop (`learn.optimizer = "rmsprop"`).
//!
//! Measured so far only on the speaker/listener game of `tests/comm_game.rs` (RMSprop, 300
//! rounds of random play, seeds 1-4): the default and each of the released code's choices
//! (`message_input = "receiver"`, `batch_norm = "batch"`, `mi_action = "greedy"`, and all three
//! together) solve it in 4 of 4 seeds, so the game does not tell them apart; their effect on LBF
//! and SMAClite is still to be measured through `lmac experiment`.

pub mod module;

pub use module::MaicAgent;

use serde::{Deserialize, Serialize};

use super::{bad, parse_settings, AgentConfig, Messages, MethodContext, MethodSpec};
use crate::config::ConfigError;

pub const MAIC: MethodSpec = MethodSpec {
    name: "maic",
    about: "MAIC: teammate models and attention-weighted incentive messages added to the receivers' Q-values",
    messages: Messages::Optional,
    mixer: None,
    agent_sees_state: false,
    configure,
    settings: Some(|| schemars::schema_for!(MaicSettings)),
};

/// The numbers a MAIC update logs, in order: the two losses (unweighted), the share of
/// teammate attention weights below the pruning threshold, and the mean |incoming message|.
pub const STAT_NAMES: &[&str] = &["maic_mi", "maic_entropy", "maic_pruned_share", "maic_msg_abs"];

/// Whose hidden state the message net reads next to z_ij.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum MessageInput {
    /// The sender's h_i (the paper).
    Sender,
    /// The receiver's h_j (the released code).
    Receiver,
}

/// How the batch norms normalise outside training updates.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum BatchNormMode {
    /// Running statistics (torch's eval mode).
    Running,
    /// The statistics of each environment's agents (the released code, always in training mode).
    Batch,
}

/// Which action of teammate j the MI loss's inference net reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum MiAction {
    /// The action j took (the batch's).
    Taken,
    /// The argmax of j's current Q-values (the released code).
    Greedy,
}

/// Which teammate models the MI loss averages over.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum MiPairs {
    /// The pairs i != j: agent i's models of its teammates (the paper).
    Teammates,
    /// Every pair, i = i included (the released code: z_ii, which no message reads, is
    /// regularised too, and the mean is over n^2 pairs).
    All,
}

/// Which attention weights the entropy loss reads (both from detached h and z).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum EntropyAttention {
    /// The attention the messages are weighted with: scores scaled by 1/sqrt(att), softmax over
    /// the teammates j != i.
    Used,
    /// The released code's recomputation: unscaled scores, softmax over all n agents, the agent
    /// itself included.
    Released,
}

/// The `[method]` settings of `--algo maic` (defaults: the released `maic.yaml`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct MaicSettings {
    /// Latent dims per teammate model (`latent_dim`: 8).
    pub latent_dim: usize,
    /// Hidden width of the embedding, inference and message nets (`nn_hidden_size`: 64).
    pub hidden: usize,
    /// Query/key width (`attention_dim`: 32).
    pub attention_dim: usize,
    /// Floor of the latent variances (`var_floor`: 0.002).
    pub var_floor: f32,
    /// Weight of the mutual-information loss (`mi_loss_weight`: 1e-3).
    pub mi_weight: f32,
    /// Weight of the attention-entropy loss (`entropy_loss_weight`: 1e-2).
    pub entropy_weight: f32,
    /// Outside training, attention weights below `prune / n` are set to 0 (0.25; 0 = none).
    pub prune: f32,
    pub message_input: MessageInput,
    pub batch_norm: BatchNormMode,
    pub mi_action: MiAction,
    pub mi_pairs: MiPairs,
    pub entropy_attention: EntropyAttention,
    /// Average the losses over the trained steps (default). `false` is the released reduction:
    /// the mean over every step of the padded batch (the learner divides the per-step sums by
    /// `max_seq_length`), padded steps and the row after the last step included.
    pub mask_losses: bool,
}

impl Default for MaicSettings {
    fn default() -> Self {
        MaicSettings {
            latent_dim: 8,
            hidden: 64,
            attention_dim: 32,
            var_floor: 0.002,
            mi_weight: 1e-3,
            entropy_weight: 1e-2,
            prune: 0.25,
            message_input: MessageInput::Sender,
            batch_norm: BatchNormMode::Running,
            mi_action: MiAction::Taken,
            mi_pairs: MiPairs::Teammates,
            entropy_attention: EntropyAttention::Used,
            mask_losses: true,
        }
    }
}

/// The settings: saved in checkpoints, so a resumed run rebuilds the same network.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MaicConfig {
    pub settings: MaicSettings,
}

impl MaicConfig {
    pub fn validate(&self) -> Result<(), ConfigError> {
        let s = &self.settings;
        for (field, v, max) in [
            ("method.latent_dim", s.latent_dim, 256),
            ("method.hidden", s.hidden, 1 << 14),
            ("method.attention_dim", s.attention_dim, 1 << 14),
        ] {
            if v == 0 || v > max {
                return Err(bad(field, format!("must be in 1..={max}, got {v}")));
            }
        }
        if !(s.var_floor.is_finite() && s.var_floor > 0.0) {
            return Err(bad("method.var_floor", format!("must be positive, got {}", s.var_floor)));
        }
        for (field, v) in [("method.mi_weight", s.mi_weight), ("method.entropy_weight", s.entropy_weight)] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(bad(field, format!("must be a non-negative number, got {v}")));
            }
        }
        if !(s.prune.is_finite() && (0.0..=1.0).contains(&s.prune)) {
            return Err(bad("method.prune", format!("must be in [0, 1] (weights below prune / n are cut), got {}", s.prune)));
        }
        Ok(())
    }
}

/// With `run.protocol`, the protocol's message columns join the observation (as for QMIX);
/// MAIC's own messages are made inside the network either way.
fn configure(table: &toml::Table, _ctx: &MethodContext) -> Result<AgentConfig, ConfigError> {
    let settings: MaicSettings = parse_settings(table)?;
    let cfg = MaicConfig { settings };
    cfg.validate()?;
    Ok(AgentConfig::Maic(cfg))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn settings_are_checked_and_errors_name_the_field() {
        let ctx = MethodContext::default();
        let parse = |s: &str| configure(&toml::from_str(s).unwrap(), &ctx);
        assert!(matches!(parse("").unwrap(), AgentConfig::Maic(c) if c.settings == MaicSettings::default()));
        let c = parse("message_input = \"receiver\"\nbatch_norm = \"batch\"\nmi_action = \"greedy\"").unwrap();
        assert!(matches!(c, AgentConfig::Maic(c) if c.settings.message_input == MessageInput::Receiver
            && c.settings.batch_norm == BatchNormMode::Batch && c.settings.mi_action == MiAction::Greedy));
        let c = parse("mi_pairs = \"all\"\nentropy_attention = \"released\"\nmask_losses = false").unwrap();
        assert!(matches!(c, AgentConfig::Maic(c) if c.settings.mi_pairs == MiPairs::All
            && c.settings.entropy_attention == EntropyAttention::Released && !c.settings.mask_losses));
        assert_eq!(parse("prune = 2.0").unwrap_err().field, "method.prune");
        assert_eq!(parse("latent_dim = 0").unwrap_err().field, "method.latent_dim");
        assert_eq!(parse("var_floor = 0.0").unwrap_err().field, "method.var_floor");
        assert_eq!(parse("mi_weight = -1.0").unwrap_err().field, "method.mi_weight");
        let e = parse("batch_norm = \"eval\"").unwrap_err();
        assert!(e.field == "method" && e.reason.contains("eval"), "{e}");
    }
}

impl MaicConfig {
    /// [`UpdateShape::plain`](crate::flops::UpdateShape::plain) of a MAIC update (`self`: its settings): the plain
    /// agent's count plus, in the online network (forward and backward) and the target network,
    /// per agent row the teammate model (GRU -> hidden -> 2 n latent), the messages' first layer
    /// on the GRU state (computed once per agent) and the attention query, and per agent pair
    /// its first layer on the latent, the message head (hidden -> actions), the attention key and
    /// score and the weighted sum; in the online network only, the MI loss's inference net (its
    /// first layer on the GRU state per row and on the one-hot action per pair, no input
    /// gradient for the one-hot; then hidden -> 2 latent per pair).
    pub fn update_flops(&self, shape: &crate::flops::UpdateShape, mixer: crate::MixerKind, cfg: &crate::LearnConfig) -> f64 {
        let s = &self.settings;
        let rows = (shape.batch * shape.steps * shape.agents) as f64;
        let pairs = rows * shape.agents as f64;
        let (h, kh, l, att, n, a) =
            (shape.hidden as f64, s.hidden as f64, s.latent_dim as f64, s.attention_dim as f64, shape.agents as f64, shape.actions as f64);
        let heads = rows * (2.0 * h * kh + 2.0 * kh * 2.0 * n * l + 2.0 * h * kh + 2.0 * h * att)
            + pairs * (2.0 * l * kh + 2.0 * kh * a + 2.0 * l * att + 2.0 * att + 2.0 * a);
        let onehot_first = pairs * 2.0 * a * kh;
        let mi = rows * 2.0 * h * kh + onehot_first + pairs * 2.0 * kh * 2.0 * l;
        shape.plain(mixer, cfg) + 3.0 * (heads + mi) - onehot_first + heads
    }
}
