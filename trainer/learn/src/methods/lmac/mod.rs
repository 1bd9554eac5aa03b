//! LMAC (paper section 4.2, appendix B.3, Algorithm 1 lines 13-20): agents read the designed
//! protocol's messages through a meta-cognitive latent module (`module.rs`) whose latent z joins
//! each agent's RNN input; the module is trained with state reconstruction, a reliability
//! ("meta") loss and cycle consistency, jointly with the TD loss.
//!
//! Differences from the authors' released code, each kept as an option where it changes
//! results:
//! - The consistency loss is masked over padded steps like every other loss
//!   (`mask_consistency = true`); the released code averages it over padding too (`false`).
//!   Both average over the latent's dims (`consistency_over_latent = "mean"`, the released
//!   `F.mse_loss`); lmac before this setting existed summed over them ("sum"), which weighs
//!   the term `latent_dim` (20) times more.
//! - Dropout acts only in training updates; acting, test episodes and the target network use the
//!   deterministic module (`dropout_when_acting = false`): a greedy test episode with random
//!   units switched off is not the policy being tested. The released code never puts its
//!   modules in eval mode, so the embedding's dropout acts in every forward (`true`).
//! - The encoder variant follows the paper's wording by default (`window`: scaled dot-product
//!   attention over the last W steps) or the released code (`gru-gate`). `window` is the
//!   default because with `gru-gate` the consistency loss drives the latent to zero (measured on
//!   LBF 8x8: mean ||z||^2 from 22 to ~1e-8), after which the agent reads nothing from its
//!   messages; the window encoder's latent stays alive (||z||^2 about 0.3 at 500k steps), it
//!   reaches the same return (0.80 vs 0.81, seed 0) and its update is about 25% faster.

pub mod module;

pub use module::LmacAgent;

use serde::{Deserialize, Serialize};

use super::{bad, parse_settings, AgentConfig, Messages, MethodContext, MethodSpec};
use crate::config::ConfigError;

pub const LMAC: MethodSpec = MethodSpec {
    name: "lmac",
    about: "LMAC: a designed protocol read through the meta-cognitive latent module (needs --protocol)",
    messages: Messages::Designed,
    mixer: None,
    agent_sees_state: false,
    configure,
    settings: Some(|| schemars::schema_for!(LmacSettings)),
};

/// The numbers an LMAC update logs, in order (see `module.rs`).
pub const STAT_NAMES: &[&str] = &["lmac_recon_mse", "lmac_meta_bce", "lmac_cons", "lmac_recovered", "lmac_reliability", "lmac_z_sq"];

/// How the encoder attends to the agent's trajectory.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum EncoderKind {
    /// The authors' code: a GRU over the step embeddings gives the keys and values; z is the
    /// value gated by sigmoid(query . key).
    GruGate,
    /// The paper's wording: multi-head scaled dot-product attention from the current step's
    /// embedding to the embeddings of the agent's last `window` steps.
    Window,
}

/// How the consistency loss reduces over the latent's dims.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum LatentReduction {
    /// Mean over the latent dims (the released code's `F.mse_loss`; the paper's ||z_hat - z||^2
    /// at the scale its lambda_cons = 1 was tuned for).
    Mean,
    /// Sum over the latent dims (lmac's earlier runs: `latent_dim` times the weight).
    Sum,
}

/// The decoder's and the cycle encoder's layers.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum AuxLayout {
    /// As the released code (`meta.py`): dropout after the decoder's first layer; the cycle
    /// encoder is linear -> ReLU -> LayerNorm -> linear -> ReLU -> dropout -> linear.
    Released,
    /// lmac's earlier layout: no dropout in the decoder, cycle encoder linear -> ReLU -> linear.
    Compact,
}

/// The `[method]` settings of `--algo lmac` (defaults: the paper's Table C.3 and the authors'
/// code).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct LmacSettings {
    /// How the encoder attends to the agent's trajectory and messages.
    pub encoder: EncoderKind,
    /// Width of the step embedding and the encoder GRU (Table C.3: attention hidden 64).
    pub embed_dim: usize,
    /// Latent z per agent (Table C.3: 20).
    pub latent_dim: usize,
    /// Query/key width.
    pub attention_dim: usize,
    /// Attention heads (`window` only; must divide attention_dim).
    pub heads: usize,
    /// Steps the `window` encoder attends to, the current one included.
    pub window: usize,
    /// Dropout after the step embedding (Table C.3: 0.1), in training updates only unless
    /// `dropout_when_acting`.
    pub dropout: f32,
    /// The embedding's dropout also acts outside training updates: when acting (exploring and
    /// test episodes alike) and in the target network's unroll, as in the released code, whose
    /// modules are never put in eval mode. Off by default: a greedy test episode with random
    /// units switched off is not the policy being tested.
    pub dropout_when_acting: bool,
    /// Hidden width of the decoder and the cycle encoder.
    pub decoder_hidden: usize,
    /// Weight of the reliability loss inside L_recon (Table C.3: 0.1); 0 = "w/o meta".
    pub lambda_meta: f32,
    /// Weight of the cycle-consistency loss (Table C.3: 1); 0 = "w/o consistency".
    pub lambda_cons: f32,
    /// Let the TD gradient reach the encoder through z (the released code detaches z).
    pub td_to_encoder: bool,
    /// The agent network also reads the raw message columns (the released code: only through z).
    pub raw_messages: bool,
    /// Mask the consistency loss over padded steps (the released code does not).
    pub mask_consistency: bool,
    /// Mean (default, the released code) or sum of the consistency loss over the latent dims.
    pub consistency_over_latent: LatentReduction,
    /// The decoder's and cycle encoder's layers: `released` (default) or `compact`.
    pub aux_layout: AuxLayout,
    /// Standardise rewards with running statistics before the TD target, as the released
    /// LMAC config does (`standardise_rewards: True`; the paper does not mention it, and
    /// EPyMARL's QMIX config leaves rewards as they are). Off by default: at the paper's
    /// schedule on smaclite:1o_10b_vs_1r with the authors' design (seed 0, 300k steps) LMAC
    /// with it collapsed after 100k steps (final test return 0.40, Q-values growing to 32)
    /// where LMAC without it ended at 7.95, and QMIX with it fell to 1.76 against 4.78 raw
    /// (docs/results/reproduction.md). `learn.reward_standardisation` overrides it unless
    /// `method`.
    pub standardise_rewards: bool,
    /// Regress z_hat onto a detached z, so the consistency loss trains the decoder and the cycle
    /// encoder but cannot shrink z itself. With the paper's loss (false) the encoder can lower
    /// ||z_hat - z||^2 by scaling z towards 0, which it does: measured on LBF 8x8, mean ||z||^2
    /// falls from 5e-3 to 2e-8 within 600k steps and the agent's latent input carries nothing.
    /// Not the default: on 1o_10b (window encoder, 3 seeds) the detached target keeps z large
    /// (||z||^2 23-58 against 0.3-1.8) but the cycle then bends the reconstruction (MSE 0.15-0.17
    /// against 0.085-0.11) and the return falls (5.05 ± 1.88 against 6.63 ± 0.91).
    pub detach_consistency_target: bool,
    /// Recovery threshold for the meta target; absent = the environment schema's alpha.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub alpha: Option<f64>,
}

impl Default for LmacSettings {
    fn default() -> Self {
        LmacSettings {
            encoder: EncoderKind::Window,
            embed_dim: 64,
            latent_dim: 20,
            attention_dim: 64,
            heads: 4,
            window: 10,
            dropout: 0.1,
            dropout_when_acting: false,
            decoder_hidden: 64,
            lambda_meta: 0.1,
            lambda_cons: 1.0,
            td_to_encoder: false,
            raw_messages: false,
            mask_consistency: true,
            consistency_over_latent: LatentReduction::Mean,
            aux_layout: AuxLayout::Released,
            standardise_rewards: false,
            detach_consistency_target: false,
            alpha: None,
        }
    }
}

/// The settings plus what the run resolved: saved in checkpoints, so a resumed run rebuilds the
/// same module.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LmacConfig {
    pub settings: LmacSettings,
    /// Message columns after each agent's observation.
    pub msg_cols: usize,
    /// The meta target's threshold in use.
    pub alpha: f64,
    /// State dims the decoder reconstructs (the protocol's task-critical set, or all).
    pub critical_dims: Vec<usize>,
}

impl LmacConfig {
    pub fn validate(&self) -> Result<(), ConfigError> {
        let s = &self.settings;
        for (field, v) in [
            ("method.embed_dim", s.embed_dim),
            ("method.latent_dim", s.latent_dim),
            ("method.attention_dim", s.attention_dim),
            ("method.heads", s.heads),
            ("method.window", s.window),
            ("method.decoder_hidden", s.decoder_hidden),
        ] {
            if v == 0 || v > 1 << 14 {
                return Err(bad(field, format!("must be in 1..=16384, got {v}")));
            }
        }
        if s.attention_dim % s.heads != 0 {
            return Err(bad("method.heads", format!("({}) must divide method.attention_dim ({})", s.heads, s.attention_dim)));
        }
        if s.window > 256 {
            return Err(bad("method.window", format!("must be at most 256, got {}", s.window)));
        }
        if !(s.dropout.is_finite() && (0.0..1.0).contains(&s.dropout)) {
            return Err(bad("method.dropout", format!("must be in [0, 1), got {}", s.dropout)));
        }
        for (field, v) in [("method.lambda_meta", s.lambda_meta), ("method.lambda_cons", s.lambda_cons)] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(bad(field, format!("must be a non-negative number, got {v}")));
            }
        }
        if !(self.alpha.is_finite() && self.alpha > 0.0) {
            return Err(bad("method.alpha", format!("must be positive, got {}", self.alpha)));
        }
        if self.critical_dims.is_empty() {
            return Err(bad("method.critical_dims", "no state dim to reconstruct"));
        }
        Ok(())
    }
}

fn configure(table: &toml::Table, ctx: &MethodContext) -> Result<AgentConfig, ConfigError> {
    let settings: LmacSettings = parse_settings(table)?;
    if ctx.msg_cols == 0 {
        return Err(bad("run.protocol", "lmac needs a designed protocol (a design directory or phase files); it has no message columns"));
    }
    let alpha = settings.alpha.unwrap_or(ctx.alpha);
    // No task-critical dims named: reconstruct the whole state.
    let critical_dims = if ctx.critical_dims.is_empty() { (0..ctx.state_dim).collect() } else { ctx.critical_dims.clone() };
    if let Some(&d) = critical_dims.iter().find(|&&d| d >= ctx.state_dim) {
        return Err(bad("run.protocol", format!("critical state dim {d} is outside the state (state_dim {})", ctx.state_dim)));
    }
    let cfg = LmacConfig { alpha, msg_cols: ctx.msg_cols, critical_dims, settings };
    cfg.validate()?;
    Ok(AgentConfig::Lmac(cfg))
}

impl LmacConfig {
    /// [`UpdateShape::plain`](crate::flops::UpdateShape::plain) of an LMAC update (`self`: its resolved settings): the
    /// plain agent's count with the agent's first layer reading [own row | z] instead of the
    /// row, plus per agent-row the module: embedding, encoder (window: q, k, v, attention over W
    /// entries, output; gru-gate: the GRU and the gate), and in the online network only the
    /// decoder and the cycle encoder. The window's attention (scores and weighted values) is
    /// counted though it is not a matmul. The target network runs embedding, encoder and agent.
    pub fn update_flops(&self, shape: &crate::flops::UpdateShape, mixer: crate::MixerKind, cfg: &crate::LearnConfig) -> f64 {
        let s = &self.settings;
        let rows = (shape.batch * shape.steps * shape.agents) as f64;
        let (e, l, att, hd, dc) =
            (s.embed_dim as f64, s.latent_dim as f64, s.attention_dim as f64, s.decoder_hidden as f64, self.critical_dims.len() as f64);
        let input = shape.input as f64;
        let agent_in = input - if s.raw_messages { 0.0 } else { self.msg_cols as f64 } + l;
        // the plain agent's count, with its first layer's width changed
        let plain = crate::flops::UpdateShape { input: agent_in as usize, ..*shape }.plain(mixer, cfg);
        let embed_first = 2.0 * input * e;
        let embed_rest = 2.0 * e * e;
        let encoder = match s.encoder {
            EncoderKind::Window => 3.0 * 2.0 * e * att + 2.0 * 2.0 * (s.window.min(shape.steps) as f64) * att + 2.0 * att * l,
            EncoderKind::GruGate => 2.0 * e * 3.0 * e * 2.0 + 2.0 * 2.0 * e * att + 2.0 * e * l,
        };
        let cycle_mid = if s.aux_layout == AuxLayout::Released { 2.0 * hd * hd } else { 0.0 };
        let heads = 2.0 * l * hd + 2.0 * hd * hd + 2.0 * 2.0 * hd * dc + 2.0 * 2.0 * dc * hd + cycle_mid + 2.0 * hd * l;
        let module_fwd = rows * (embed_first + embed_rest + encoder);
        // online forward + backward (no input gradient for the embedding's first layer) + target
        plain + module_fwd + rows * heads + (2.0 * (module_fwd + rows * heads) - rows * embed_first) + module_fwd
    }
}
