//! MASIA, multi-agent communication via self-supervised information aggregation (Guan et al.
//! 2022, "Efficient Multi-agent Communication via Self-supervised Information Aggregation"), as
//! in the authors' released code (chenf-ai/MASIA: `masia_agent.py`, `ob_attn_ae.py`,
//! `latent_models/mlp.py`, `masia_learner.py`, `masia.yaml`), on lmac's learner. The network is
//! in `module.rs`.
//!
//! Every agent's input row u_i (its observation and id) is shared. One encoder aggregates them:
//! scaled dot-product self-attention over the n agents of an environment (query/key width 16,
//! value width 32), a GRU per agent (width 32) over the attention output, and a linear map to 8
//! latent dims per agent, concatenated into the joint representation z (8n wide), the same for
//! every agent of the environment. Agent i gates z with sigmoid(W_g u_i) and feeds
//! [W_o obs_i (32) | gated z | id_i] to pymarl's RNN agent (linear, ReLU, GRU, linear).
//!
//! Losses, joined to the TD loss from the first update, each a mean over the trained steps:
//! - reconstruction (`recon_weight`, 1): a linear decoder from z to the global state, the squared
//!   error averaged over the state dims;
//! - latent prediction (`latent_weight`, 1): a transition model over the joint action predicts
//!   z k = 1..`pred_len` (2) steps ahead (ẑ_{t+k} = ẑ_{t+k-1} + f(ẑ_{t+k-1}, a_{t+k-1}), from
//!   ẑ_t = z_t); a projection (8n -> 64 -> 32) and a prediction head (32 -> 64 -> 32) of ẑ_{t+k}
//!   are regressed (squared error summed over the 32 dims) onto the projection of z'_{t+k} made
//!   by a momentum target encoder and target projection (non-gradient copies of the encoder and
//!   the projection), for k = 0..`pred_len`, the k-th term averaged over the steps whose target
//!   step t + k is trained;
//! - reward prediction (`reward_weight`, 1): a head (8n -> 64 -> 1) regresses the reward of step
//!   t + k from ẑ_{t+k}, for the same k and steps (as in the released code, from the latent of
//!   the step before its action: the head reads no action).
//!
//! The TD gradient reaches the encoder through z (the released `rl_signal: True`). The momentum
//! copies are refreshed after optimizer steps (`AgentNet::after_update`): every
//! `momentum_interval` updates, target <- tau * online + (1 - tau) * target with tau =
//! `momentum_tau`. They do not require grad, so the optimizer leaves them alone, and they are
//! saved in checkpoints with the rest of the network (with the count of updates since the last
//! refresh).
//!
//! Inputs: the released config has `obs_last_action: False`. lmac's learner and controller write
//! one row layout for every method (`learn.obs_last_action`, default on), so MASIA reads only the
//! columns it needs: the row's last-action block is dropped before anything reads the row (a
//! field on `MethodSpec` would have changed every method's spec for one column block). With
//! `learn.obs_last_action = false` nothing is dropped. A protocol's message columns
//! (`run.protocol`), if any, are part of the observation, as for QMIX.
//!
//! Differences from the released code:
//! - Refresh schedule of the momentum target (`momentum_interval`, `momentum_tau`): the released
//!   learner refreshes it when it copies the TD target network, every 200 updates (its
//!   `target_update_interval_or_tau` counts updates), with `momentum_tau: 1` (a hard copy). The
//!   defaults (200, 1) reproduce that; lmac's TD target is copied every
//!   `learn.target_update_interval_episodes` episodes, which is every 200 updates only at one
//!   update per episode (`--preset epymarl`). `momentum_interval = 1` with `momentum_tau < 1`
//!   gives an EMA target as in SPR/BYOL.
//! - The self-supervised losses are masked to the trained steps (`TrainContext::mask`). The
//!   released code also trains them on the row after a truncated episode's last step (its
//!   reward there is a 0 that no transition earned, and the row exists only for the TD
//!   target), so here a k-step term's last target is the episode's last trained step. Not a
//!   setting: it is one row per truncated episode, and its reward target is not a reward.
//! - Each term's mean over steps divides by at least 1 (the released code divides by the mask's
//!   sum, NaN when a k-step term has no step, e.g. one-step episodes).
//! - The encoder runs once per update: its z feeds the TD loss and the self-supervised losses
//!   (the released code runs it twice with the same weights and inputs: the same values and the
//!   same summed gradient).
//! - TD-side settings are the run's `[learn]` ones: the released `masia.yaml` standardises the
//!   rewards of the TD target (`standardise_rewards: True`; lmac's learner does not; the reward
//!   prediction reads raw rewards in both) and copies the TD target every 200 updates; its
//!   optimizer (Adam, lr 5e-4), its mixer (QMIX, 2-layer hypernetworks of width 64, mixing width
//!   32) and its agent width (64) are lmac's defaults.
//! - The encoder's query, key and value maps are one fused linear layer (the same function and
//!   initial distribution: each reads the same input width). The unused parts of the released
//!   code (its VAE encoders, observation noise, the decoder copy inside the target encoder) are
//!   left out.
//!
//! Loss reductions, checked against the released code (`docs/reference/fidelity.md`): reconstruction is
//! the squared error averaged over the state dims (`ob_attn_ae.py:128`), latent prediction the
//! squared error summed over the projection's dims (`masia_learner.py:138`), reward prediction
//! the squared error of the one reward (`:130`); each is a masked mean over steps, and the
//! latent and reward terms are summed over k (`:95-107`). The same here.
//!
//! Measured so far only on the speaker/listener game of `tests/comm_game.rs` (one-step episodes,
//! so only the k = 0 terms train; 4 episodes of random play per round, seeds 1-4): 4 of 4 seeds
//! reach the greedy return 1 within 500 rounds with RMSprop and with Adam (seeds 1-3 within
//! 100-300 rounds, seed 4 at 400-500), and 4 of 4 within 400 with an EMA target
//! (`momentum_interval = 1`, `momentum_tau = 0.01`); QMIX stays at 0.5. Its effect on LBF and
//! SMAClite is still to be measured through `lmac experiment`.

pub mod module;

pub use module::MasiaAgent;

use serde::{Deserialize, Serialize};

use super::{bad, parse_settings, AgentConfig, Messages, MethodContext, MethodSpec};
use crate::config::ConfigError;

pub const MASIA: MethodSpec = MethodSpec {
    name: "masia",
    about: "MASIA: every agent's input aggregated by a self-supervised attention encoder, gated per agent",
    messages: Messages::Optional,
    mixer: None,
    agent_sees_state: false,
    configure,
    settings: Some(|| schemars::schema_for!(MasiaSettings)),
};

/// The numbers a MASIA update logs, in order: the three losses (unweighted; the latent and
/// reward losses summed over k = 0..pred_len) and the mean gate value over the trained rows.
pub const STAT_NAMES: &[&str] = &["masia_recon", "masia_latent", "masia_reward", "masia_gate_mean"];

/// The `[method]` settings of `--algo masia` (defaults: the released `masia.yaml`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct MasiaSettings {
    /// Latent dims per agent; z is `n * latent_dim` wide (`state_repre_dim`: 8).
    pub latent_dim: usize,
    /// Query/key width of the encoder's attention (`attn_embed_dim`: 16).
    pub attention_dim: usize,
    /// Value width of the attention and width of the encoder's GRU (`encoder_hidden_dim`: 32).
    pub encoder_hidden: usize,
    /// Width of the observation embedding in the agent's input (`ob_embed_dim`: 32).
    pub obs_embed: usize,
    /// Hidden width of the transition model and the reward head (`model_hidden_dim`: 64).
    pub model_hidden: usize,
    /// Per-agent action embedding of the transition model (`action_embed_dim`: 8).
    pub action_embed: usize,
    /// Output width of the projection and prediction heads (`spr_dim`: 32).
    pub projection_dim: usize,
    /// Hidden width of the projection and prediction heads (64, fixed in the released code).
    pub projection_hidden: usize,
    /// Steps the transition model predicts ahead (`pred_len`: 2; 0 = none, only k = 0).
    pub pred_len: usize,
    /// Weight of the state reconstruction loss (1). The released learner weighs all three
    /// losses by `repr_coef` and the latter two by `spr_coef` / `rew_pred_coef` on top
    /// (`masia_learner.py:110,218`): its weights are `recon_weight = repr_coef`,
    /// `latent_weight = repr_coef * spr_coef`, `reward_weight = repr_coef * rew_pred_coef`
    /// (all 1 in `masia.yaml`).
    pub recon_weight: f32,
    /// Weight of the latent prediction loss (1; `repr_coef * spr_coef`).
    pub latent_weight: f32,
    /// Weight of the reward prediction loss (1; `repr_coef * rew_pred_coef`).
    pub reward_weight: f32,
    /// Share of the online weights in each refresh of the momentum target (`momentum_tau`: 1, a
    /// copy; 0 keeps the initial copy).
    pub momentum_tau: f32,
    /// Updates between refreshes of the momentum target (200: the released code's target
    /// interval in updates).
    pub momentum_interval: u64,
}

impl Default for MasiaSettings {
    fn default() -> Self {
        MasiaSettings {
            latent_dim: 8,
            attention_dim: 16,
            encoder_hidden: 32,
            obs_embed: 32,
            model_hidden: 64,
            action_embed: 8,
            projection_dim: 32,
            projection_hidden: 64,
            pred_len: 2,
            recon_weight: 1.0,
            latent_weight: 1.0,
            reward_weight: 1.0,
            momentum_tau: 1.0,
            momentum_interval: 200,
        }
    }
}

/// The settings: saved in checkpoints, so a resumed run rebuilds the same network.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MasiaConfig {
    pub settings: MasiaSettings,
}

impl MasiaConfig {
    pub fn validate(&self) -> Result<(), ConfigError> {
        let s = &self.settings;
        for (field, v, max) in [
            ("method.latent_dim", s.latent_dim, 256),
            ("method.attention_dim", s.attention_dim, 1 << 14),
            ("method.encoder_hidden", s.encoder_hidden, 1 << 14),
            ("method.obs_embed", s.obs_embed, 1 << 14),
            ("method.model_hidden", s.model_hidden, 1 << 14),
            ("method.action_embed", s.action_embed, 1 << 10),
            ("method.projection_dim", s.projection_dim, 1 << 14),
            ("method.projection_hidden", s.projection_hidden, 1 << 14),
        ] {
            if v == 0 || v > max {
                return Err(bad(field, format!("must be in 1..={max}, got {v}")));
            }
        }
        if s.pred_len > 64 {
            return Err(bad("method.pred_len", format!("must be in 0..=64, got {}", s.pred_len)));
        }
        for (field, v) in
            [("method.recon_weight", s.recon_weight), ("method.latent_weight", s.latent_weight), ("method.reward_weight", s.reward_weight)]
        {
            if !(v.is_finite() && v >= 0.0) {
                return Err(bad(field, format!("must be a non-negative number, got {v}")));
            }
        }
        if !(s.momentum_tau.is_finite() && (0.0..=1.0).contains(&s.momentum_tau)) {
            return Err(bad("method.momentum_tau", format!("must be in [0, 1], got {}", s.momentum_tau)));
        }
        if s.momentum_interval == 0 || s.momentum_interval > 1 << 30 {
            return Err(bad("method.momentum_interval", format!("must be in 1..={}, got {}", 1u64 << 30, s.momentum_interval)));
        }
        Ok(())
    }
}

/// With `run.protocol`, the protocol's message columns join the observation (as for QMIX);
/// MASIA shares every agent's input inside the network either way.
fn configure(table: &toml::Table, _ctx: &MethodContext) -> Result<AgentConfig, ConfigError> {
    let settings: MasiaSettings = parse_settings(table)?;
    let cfg = MasiaConfig { settings };
    cfg.validate()?;
    Ok(AgentConfig::Masia(cfg))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn settings_are_checked_and_errors_name_the_field() {
        let ctx = MethodContext::default();
        let parse = |s: &str| configure(&toml::from_str(s).unwrap(), &ctx);
        assert!(matches!(parse("").unwrap(), AgentConfig::Masia(c) if c.settings == MasiaSettings::default()));
        let c = parse("momentum_interval = 1\nmomentum_tau = 0.01\npred_len = 0").unwrap();
        assert!(matches!(c, AgentConfig::Masia(c) if c.settings.momentum_interval == 1 && c.settings.pred_len == 0));
        assert_eq!(parse("latent_dim = 0").unwrap_err().field, "method.latent_dim");
        assert_eq!(parse("pred_len = 1000").unwrap_err().field, "method.pred_len");
        assert_eq!(parse("reward_weight = -1.0").unwrap_err().field, "method.reward_weight");
        assert_eq!(parse("momentum_tau = 1.5").unwrap_err().field, "method.momentum_tau");
        assert_eq!(parse("momentum_interval = 0").unwrap_err().field, "method.momentum_interval");
        let e = parse("spr_coef = 1.0").unwrap_err();
        assert!(e.field == "method" && e.reason.contains("spr_coef"), "{e}");
    }
}

impl MasiaConfig {
    /// [`UpdateShape::plain`](crate::flops::UpdateShape::plain) of a MASIA update (`self`: its settings), the row
    /// without its last-action block (observation o, id e; u = [o | e]). Per agent row, in the
    /// online network (forward and backward, no input gradient for the layers reading u or o) and
    /// the target network: the encoder (fused q, k, v; attention over the environment's n agents;
    /// the GRU; the latent map), the gate (u -> n L), the observation embedding and the plain
    /// agent on [W_o o | gated z | e]. In the online network only, per environment step: the
    /// decoder (n L -> state) and, for k = 0 ..= pred_len steps ahead over the T - k steps that
    /// have a target, projection, predictor and reward head (forward and backward) and for k >= 1
    /// the transition model (action embedding per agent, joint action, latent embedding,
    /// transition; no input gradient for the one-hot actions); the momentum target encoder and
    /// projection run forward only.
    pub fn update_flops(&self, shape: &crate::flops::UpdateShape, mixer: crate::MixerKind, cfg: &crate::LearnConfig) -> f64 {
        let s = &self.settings;
        let n = shape.agents as f64;
        let rows = (shape.batch * shape.steps * shape.agents) as f64;
        let own = (shape.input - shape.actions - shape.agents) as f64;
        let u = own + n;
        let (d, g, l) = (s.attention_dim as f64, s.encoder_hidden as f64, s.latent_dim as f64);
        let (nl, sd, a) = (n * l, shape.state as f64, shape.actions as f64);
        let (mh, ph, pd, ae) = (s.model_hidden as f64, s.projection_hidden as f64, s.projection_dim as f64, s.action_embed as f64);
        let qkv = 2.0 * u * (2.0 * d + g);
        let encoder = qkv + 2.0 * n * (d + g) + 2.0 * g * 3.0 * g * 2.0 + 2.0 * g * l;
        let (gate, embed) = (2.0 * u * nl, 2.0 * own * s.obs_embed as f64);
        let row_fwd = encoder + gate + embed;
        let row_first = qkv + gate + embed;
        let agent_in = s.obs_embed + shape.agents * s.latent_dim + shape.agents;
        let plain = crate::flops::UpdateShape { input: agent_in, ..*shape }.plain(mixer, cfg);
        // the plain count's first layer has no input gradient; here its input is trained
        let agent_input_grad = rows * 2.0 * agent_in as f64 * shape.hidden as f64;
        // per environment step
        let groups = |k: usize| (shape.batch * shape.steps.saturating_sub(k)) as f64;
        let projection = 2.0 * nl * ph + 2.0 * ph * pd;
        let heads = projection + 2.0 * pd * ph + 2.0 * ph * pd + 2.0 * nl * mh + 2.0 * mh;
        let action_first = n * 2.0 * a * ae;
        let transition =
            action_first + 2.0 * n * ae * mh + 2.0 * mh * mh + 2.0 * nl * mh + 2.0 * mh * mh + 2.0 * 2.0 * mh * mh + 2.0 * mh * nl;
        let ahead = s.pred_len.min(shape.steps.saturating_sub(1));
        let mut trained = groups(0) * 2.0 * nl * sd;
        let mut trained_first = 0.0;
        for k in 0..=ahead {
            trained += groups(k) * (heads + if k > 0 { transition } else { 0.0 });
            trained_first += if k > 0 { groups(k) * action_first } else { 0.0 };
        }
        let momentum = rows * encoder + groups(0) * projection;
        plain + agent_input_grad + rows * (row_fwd + (2.0 * row_fwd - row_first) + row_fwd) + 3.0 * trained - trained_first + momentum
    }
}
