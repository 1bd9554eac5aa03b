//! T2MAC, targeted and trusted communication (Sun et al. 2024, "T2MAC: Targeted and Trusted
//! Multi-Agent Communication through Selective Engagement and Evidence-Driven Integration"), as
//! in the authors' released code (ZangZehua/T2MAC: `tmac_p2p_comm_rnn_msg_agent`,
//! `tmac_p2p_comm_controller`, `tmac_p2p_comm.yaml`), on lmac's learner. The network is in
//! `module.rs`, the evidence fusion (plain host code, it carries no gradient) in `fusion.rs`.
//!
//! Per step, with h_i agent i's GRU state (pymarl's RNN agent):
//! - every agent shares key, value and query projections of h (64 each); agent i's attention
//!   weights over all agents are one linear layer over [q_i | k_1 .. k_n] and a softmax (the
//!   released "additive" attention); c_i = relu(W [sum_j w_ij v_j | h_i]) and q_i = W_out c_i;
//! - q_i, made non-negative (softplus; relu as an option), is Dirichlet evidence e_i over the
//!   actions: belief
//!   b = e / S, uncertainty u = A / S with S = sum(e) + A (a subjective-logic opinion);
//! - a selector (the agent's input row -> 64 -> n, softmax) picks at most one teammate: agent i
//!   sends its opinion to j when p_ij > 0.75, j != i (the slot of i itself means "nobody");
//! - each receiver fuses the opinions sent to it with the reduced Dempster-Shafer combination
//!   rule, starting from the vacuous opinion (b = 0, u = 1), turns the result back into evidence
//!   and forms its utility `own_weight * e_j + fusion_weight * fused_j` (fusion weight 0.1). The
//!   fused part carries no gradient (the released code computes it under `no_grad`).
//!
//! The selector learns what the paper describes: sender i's target class is the teammate j
//! whose uncertainty the fusion of i's opinion with j's own lowers most, when it lowers it by
//! more than `min_uncertainty_drop` (the released `min_uncer`, 0.1), else i itself (send
//! nothing); a cross-entropy on the selector's logits, masked over padded steps, joins the
//! update (`selector_weight`). The selector reads only the input row, so the TD loss does not
//! reach it.
//!
//! Loss reduction (`docs/reference/fidelity.md`): the selector's cross-entropy is summed over the classes
//! (the n candidate receivers) of a sender's row and averaged over the senders of the trained
//! steps, as torch's `CrossEntropyLoss` averages over rows (`tmac_p2p_comm_controller.py:22`).
//! The released call passes a [batch, n, n] tensor, so torch takes dim 1 (the senders) as the
//! class dim, while the selector's softmax runs over the receivers: one more reason its loss
//! carries no gradient (below).
//!
//! Differences from the released code:
//! - The released selector cannot learn: its label is `(u_combined - u_own) > min_uncer`, and
//!   adding evidence never raises the uncertainty, so the label is always 0; the loss is also
//!   called with label and prediction swapped, which makes its gradient exactly zero. The
//!   selector stays at its random initial weights. `selector = "frozen"` keeps that behaviour
//!   (the selector's weights do not train); the default `learnt` trains it on the labels above.
//! - The released label compares a receiver's combined uncertainty with its own, per receiver,
//!   and applies it to the sender's softmax row; here the label is per (sender, receiver) pair:
//!   the drop of j's uncertainty when i's opinion is fused with j's own.
//! - The released utility is `2 e_j + 0.1 fused_j`: `aggregate` adds `combine_message`'s result,
//!   which already contains e_j, to e_j again. `own_weight = 2.0` reproduces it; the default 1.0
//!   is the paper's e_j + 0.1 fused_j (only the relative weight of the fused part changes).
//! - Evidence is softplus(q) by default; the released code clamps q at 0 (`evidence = "relu"`),
//!   so an action whose output is negative gets no TD gradient and its value cannot recover.
//!   Measured on the speaker/listener game of `tests/comm_game.rs` (600 rounds of random play,
//!   seeds 1-4): softplus learns 4 of 4, relu 1 of 4, the released combination (relu, frozen
//!   selector, own weight 2) 2 of 4; softplus with the frozen selector 4 of 4 (the game is
//!   solved through the attention over teammates' states).
//! - The released selector is two linear layers with no nonlinearity between them (one linear
//!   map); here a ReLU separates them, as a two-layer network was evidently meant.
//! - The selector's loss is part of the one update (the learner's optimizer, its clip and
//!   learning rate); the released code steps a separate Adam (lr 1e-3) on it inside every
//!   forward pass of a training batch, the target network's included.
//! - The released p2p agent module does not import `datetime` and fails at its first forward
//!   pass; the fusion loops over environments, agents and senders in Python. Here the fusion
//!   is one pass of plain Rust over every step of the batch at once.
//! - The optimizer and the mixer are the run's `[learn]` settings (lmac's defaults: Adam, QMIX
//!   with 2-layer hypernetworks; the released config: RMSprop, QMIX embed 32, 2-layer
//!   hypernetworks, target update every 200 episodes).

pub mod fusion;
pub mod module;

pub use module::T2macAgent;

use serde::{Deserialize, Serialize};

use super::{bad, parse_settings, AgentConfig, Messages, MethodContext, MethodSpec};
use crate::config::ConfigError;

pub const T2MAC: MethodSpec = MethodSpec {
    name: "t2mac",
    about: "T2MAC: attention over teammates' states, evidential opinions sent to selected teammates and fused",
    messages: Messages::Optional,
    mixer: None,
    agent_sees_state: false,
    configure,
    settings: Some(|| schemars::schema_for!(T2macSettings)),
};

/// The numbers a T2MAC update logs, in order: the selector's cross-entropy, the share of agents
/// that send, the share whose label says send, the mean own uncertainty and the mean drop of a
/// receiver's uncertainty from what it received (over receivers that received something).
pub const STAT_NAMES: &[&str] = &["t2mac_selector_ce", "t2mac_send_rate", "t2mac_label_send_rate", "t2mac_uncertainty", "t2mac_fused_drop"];

/// How the selector that picks the receiver is trained.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum Selector {
    /// Trained to send where the opinion lowers the receiver's uncertainty (the paper).
    Learnt,
    /// Kept at its initial weights (what the released code's selector does in effect).
    Frozen,
}

/// How an agent's output is made non-negative evidence.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum Evidence {
    /// softplus(q): every action's value keeps a gradient.
    Softplus,
    /// max(q, 0) (the released code): an action whose output is negative gets no TD gradient.
    Relu,
}

/// The `[method]` settings of `--algo t2mac` (defaults: the released `tmac_p2p_comm.yaml`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct T2macSettings {
    /// Width of the key, value and query projections (`n_key`, `n_value`, `n_query`: 64).
    pub attention_dim: usize,
    /// Hidden width of the selector (the released code: `rnn_hidden_dim`, 64).
    pub selector_hidden: usize,
    /// Weight of the fused teammates' evidence in the utility (0.1).
    pub fusion_weight: f32,
    /// Weight of the agent's own evidence in the utility (1; the released code in effect 2).
    pub own_weight: f32,
    /// An agent sends to j when its selector's probability for j exceeds this (0.75).
    pub send_threshold: f32,
    /// The uncertainty drop that makes a receiver worth sending to (`min_uncer`: 0.1).
    pub min_uncertainty_drop: f32,
    pub evidence: Evidence,
    pub selector: Selector,
    /// Weight of the selector's cross-entropy in the update (1).
    pub selector_weight: f32,
}

impl Default for T2macSettings {
    fn default() -> Self {
        T2macSettings {
            attention_dim: 64,
            selector_hidden: 64,
            fusion_weight: 0.1,
            own_weight: 1.0,
            send_threshold: 0.75,
            min_uncertainty_drop: 0.1,
            evidence: Evidence::Softplus,
            selector: Selector::Learnt,
            selector_weight: 1.0,
        }
    }
}

/// The settings: saved in checkpoints, so a resumed run rebuilds the same network.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct T2macConfig {
    pub settings: T2macSettings,
}

impl T2macConfig {
    pub fn validate(&self) -> Result<(), ConfigError> {
        let s = &self.settings;
        for (field, v) in [("method.attention_dim", s.attention_dim), ("method.selector_hidden", s.selector_hidden)] {
            if v == 0 || v > 1 << 14 {
                return Err(bad(field, format!("must be in 1..=16384, got {v}")));
            }
        }
        for (field, v) in
            [("method.fusion_weight", s.fusion_weight), ("method.own_weight", s.own_weight), ("method.selector_weight", s.selector_weight)]
        {
            if !(v.is_finite() && v >= 0.0) {
                return Err(bad(field, format!("must be a non-negative number, got {v}")));
            }
        }
        // Above 0.5 at most one receiver can pass (the probabilities sum to 1).
        if !(s.send_threshold.is_finite() && (0.5..1.0).contains(&s.send_threshold)) {
            return Err(bad(
                "method.send_threshold",
                format!("must be in [0.5, 1) so an agent sends to at most one teammate, got {}", s.send_threshold),
            ));
        }
        if !(s.min_uncertainty_drop.is_finite() && (0.0..1.0).contains(&s.min_uncertainty_drop)) {
            return Err(bad(
                "method.min_uncertainty_drop",
                format!("must be in [0, 1) (an uncertainty lies in (0, 1]), got {}", s.min_uncertainty_drop),
            ));
        }
        Ok(())
    }
}

/// With `run.protocol`, the protocol's message columns join the observation (as for QMIX);
/// T2MAC's own communication happens inside the network either way.
fn configure(table: &toml::Table, _ctx: &MethodContext) -> Result<AgentConfig, ConfigError> {
    let settings: T2macSettings = parse_settings(table)?;
    let cfg = T2macConfig { settings };
    cfg.validate()?;
    Ok(AgentConfig::T2mac(cfg))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn settings_are_checked_and_errors_name_the_field() {
        let ctx = MethodContext::default();
        let parse = |s: &str| configure(&toml::from_str(s).unwrap(), &ctx);
        assert!(matches!(parse("").unwrap(), AgentConfig::T2mac(c) if c.settings == T2macSettings::default()));
        let c = parse("selector = \"frozen\"\nown_weight = 2.0").unwrap();
        assert!(matches!(c, AgentConfig::T2mac(c) if c.settings.selector == Selector::Frozen && c.settings.own_weight == 2.0));
        assert_eq!(parse("send_threshold = 0.4").unwrap_err().field, "method.send_threshold");
        assert_eq!(parse("send_threshold = 1.0").unwrap_err().field, "method.send_threshold");
        assert_eq!(parse("attention_dim = 0").unwrap_err().field, "method.attention_dim");
        assert_eq!(parse("fusion_weight = -0.1").unwrap_err().field, "method.fusion_weight");
        assert_eq!(parse("min_uncertainty_drop = 1.5").unwrap_err().field, "method.min_uncertainty_drop");
        let e = parse("selector = \"random\"").unwrap_err();
        assert!(e.field == "method" && e.reason.contains("random"), "{e}");
    }
}

impl T2macConfig {
    /// [`UpdateShape::plain`](crate::flops::UpdateShape::plain) of a T2MAC update (`self`: its settings): the plain
    /// agent's count (fc1, the GRU, the Q head on the merged state) plus per agent row the heads
    /// after the GRU, in the online network (forward and backward) and the target network: key,
    /// query and value (GRU -> attention_dim), the attention logits over the n agents from the
    /// query and every agent's key, the weighted values, the merge (attention + GRU -> GRU
    /// width) and the selector (input -> selector_hidden -> n; no input gradient). The evidence
    /// fusion runs on the host and is not counted.
    pub fn update_flops(&self, shape: &crate::flops::UpdateShape, mixer: crate::MixerKind, cfg: &crate::LearnConfig) -> f64 {
        let s = &self.settings;
        let rows = (shape.batch * shape.steps * shape.agents) as f64;
        let (iw, h, k, n, sh) =
            (shape.input as f64, shape.hidden as f64, s.attention_dim as f64, shape.agents as f64, s.selector_hidden as f64);
        let select_first = 2.0 * iw * sh;
        let heads = 3.0 * 2.0 * h * k + 2.0 * k * (n + 1.0) * n + 2.0 * n * k + 2.0 * (k + h) * h + select_first + 2.0 * sh * n;
        shape.plain(mixer, cfg) + rows * (heads + (2.0 * heads - select_first) + heads)
    }
}
