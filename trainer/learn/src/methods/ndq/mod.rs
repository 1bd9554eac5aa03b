//! NDQ, nearly decomposable Q-functions (Wang et al. 2020, "Learning Nearly Decomposable Value
//! Functions Via Communication Minimization"), as in the authors' released code
//! (TonghanWang/NDQ: `cate_broadcast_comm_mac_full`, `information_bottleneck_full`,
//! `cate_q_learner`), on lmac's learner. The network is in `module.rs`.
//!
//! Every agent i encodes its input row u_i (input -> H -> H -> n*d, ReLU, H = 64, d = 3) into the
//! means mu_ij of a Gaussian message to every agent j (itself included) with standard deviation
//! fixed at 1; in training the message is the reparameterised sample m_ij = mu_ij + eps. Agent j
//! concatenates the n messages it receives (m_1j .. m_nj) to its input row before its RNN agent.
//! An action-inference head ([u_j | received] -> 4nd -> 4nd -> actions, ReLU, softmax) predicts the
//! target network's greedy action. The extra loss is
//! `c_beta (L_CE + comm_beta L_KL + entropy_beta L_H)` with L_CE = -log(p(a_target) + 1e-6),
//! L_KL = KL(N(mu, 1) || N(0, 1)) = mu^2 / 2 summed over the message dims, and L_H =
//! -log N(m; 0, 1) of the sampled messages summed over their dims (what the released code calls
//! the entropy loss), each summed over the agents and averaged over the trained steps like the
//! TD loss. The TD gradient reaches the message encoder through the messages (the released "full"
//! controller does not detach them).
//!
//! The message cut (NDQ's headline): with `cut = p` the acting network zeroes, in each
//! environment and step, every message dim whose |mu| ranks in the bottom p% of that step's n*n*d
//! message means (rank r of S, 0-based ascending, is cut when 100 r / S < p; self-messages take
//! part as in the released rank cut). `cut = 0` sends everything.
//!
//! Randomness: the training samples come from a host-side [`LearnRng`](crate::LearnRng)
//! seeded from the update's seed (`TrainContext::seed`), so an update is reproducible. Acting is
//! deterministic: it sends the message means (see below).
//!
//! Differences from the released code:
//! - Acting, test episodes and the target network send the mean message instead of a sample
//!   (the released code samples everywhere, the target network included). Not an option: the
//!   seam's acting step is deterministic, and a greedy test with unit-variance noise on every
//!   message dim tests a noisier policy than the one learnt; for the target network the mean is
//!   the lower-variance estimate of the same Q.
//! - The cut ranks the means of one environment's step (the released rank cut ranks all
//!   parallel environments' messages of a step together, 8 with their parallel runner), so an
//!   agent's messages never depend on unrelated episodes. It applies to acting only (`step`),
//!   in every episode of a run with `cut > 0`; the updates and the target network use the full
//!   messages. The released code cuts only in its test episodes; to report returns at several
//!   cuts, evaluate a trained network with `NdqAgent::set_cut`.
//! - The inference, KL and entropy losses are masked over padded steps (`mask_losses = true`);
//!   the released code sums them over every step of the padded batch up to the longest episode
//!   (then divides by the count of trained steps, `categorical_q_learner.py:161-168`), so their
//!   weight grows with the batch's padding: `mask_losses = false` reproduces that.
//! - The message width and encoder width are settings (`msg_dim`, `encoder_hidden`); the released
//!   code ties the encoder width to `rnn_hidden_dim` (64 by default, as here).
//! - The optimizer and the mixer are the run's `[learn]` settings (lmac's defaults: Adam, QMIX
//!   with 2-layer hypernetworks); the released code uses RMSprop (lr 5e-4) and QMIX with 1-layer
//!   hypernetworks: `learn.optimizer = "rmsprop"`, `learn.hypernet_layers = 1` reproduce them.
//!   The released code's distributional ("categorical") Q head is not used by its QMIX config
//!   and is not implemented.
//!
//! Loss reductions, checked against the released learner (`categorical_q_learner.py`, see
//! `docs/reference/fidelity.md`): each term is summed over its feature dims (a message's n*d dims, the
//! one label) and over the agents, then divided by the count of trained steps (not by steps x
//! agents), as the TD loss; c_beta multiplies all three terms, comm_beta the KL and
//! entropy_beta the entropy on top (`:176-177`). Only the padding differs (above).
//!
//! Measured on the speaker/listener game of `tests/comm_game.rs` (RMSprop, 2000 rounds of random
//! play, seeds 1-4): with the default weights (1, 1e-3, 1e-6) the KL term wins over the weak early
//! TD signal, the message means shrink (mean |mu| 0.04 after 600 updates) and 1 seed of 4 learns
//! to send the bit; with the released SMAC weights (`c_beta = 0.1`, `comm_beta = 1e-4`,
//! `entropy_beta = 0`) 4 of 4 do. Without the communication losses (`c_beta = 0`) 4 of 4 learn
//! within 1000 rounds.

pub mod module;

pub use module::NdqAgent;

use serde::{Deserialize, Serialize};

use super::{bad, parse_settings, AgentConfig, Messages, MethodContext, MethodSpec};
use crate::config::ConfigError;

pub const NDQ: MethodSpec = MethodSpec {
    name: "ndq",
    about: "NDQ: learnt Gaussian messages to every teammate, minimised by an information bottleneck",
    messages: Messages::Optional,
    mixer: None,
    agent_sees_state: false,
    configure,
    settings: Some(|| schemars::schema_for!(NdqSettings)),
};

/// The numbers an NDQ update logs, in order: the three losses (unweighted), the inference head's
/// accuracy against the target's greedy actions and the mean |mu| of the messages.
pub const STAT_NAMES: &[&str] = &["ndq_ce", "ndq_kl", "ndq_entropy", "ndq_infer_acc", "ndq_mu_abs"];

/// The `[method]` settings of `--algo ndq` (defaults: the released code's `categorical_qmix`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct NdqSettings {
    /// Message dims per (sender, receiver) pair (`comm_embed_dim`: 3).
    pub msg_dim: usize,
    /// Hidden width of the message encoder (the released code: `rnn_hidden_dim`, 64).
    pub encoder_hidden: usize,
    /// Weight of all communication losses (`c_beta`: 1; their SMAC runs 0.1).
    pub c_beta: f32,
    /// Weight of the KL to N(0, I) (`comm_beta`: 1e-3; SMAC 1e-4).
    pub comm_beta: f32,
    /// Weight of the entropy term (`comm_entropy_beta`: 1e-6; SMAC 0).
    pub entropy_beta: f32,
    /// Acting cuts the message dims whose |mean| is in the bottom `cut` percent (0 = none; the
    /// paper reports 90, 95 and 98).
    pub cut: f32,
    /// Count only the trained steps in the communication losses (default: the mean over real
    /// data that the released learner's division by the count of trained steps intends).
    /// `false` is the released reduction: the terms summed over every step of the padded batch
    /// up to the longest episode's length, divided by the count of trained steps, so the losses
    /// weigh more the more padding a batch holds.
    pub mask_losses: bool,
}

impl Default for NdqSettings {
    fn default() -> Self {
        NdqSettings { msg_dim: 3, encoder_hidden: 64, c_beta: 1.0, comm_beta: 1e-3, entropy_beta: 1e-6, cut: 0.0, mask_losses: true }
    }
}

/// The settings: saved in checkpoints, so a resumed run rebuilds the same network.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NdqConfig {
    pub settings: NdqSettings,
}

impl NdqConfig {
    pub fn validate(&self) -> Result<(), ConfigError> {
        let s = &self.settings;
        if s.msg_dim == 0 || s.msg_dim > 64 {
            return Err(bad("method.msg_dim", format!("must be in 1..=64, got {}", s.msg_dim)));
        }
        if s.encoder_hidden == 0 || s.encoder_hidden > 1 << 14 {
            return Err(bad("method.encoder_hidden", format!("must be in 1..=16384, got {}", s.encoder_hidden)));
        }
        for (field, v) in [("method.c_beta", s.c_beta), ("method.comm_beta", s.comm_beta), ("method.entropy_beta", s.entropy_beta)] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(bad(field, format!("must be a non-negative number, got {v}")));
            }
        }
        if !(s.cut.is_finite() && (0.0..=100.0).contains(&s.cut)) {
            return Err(bad("method.cut", format!("must be a percentage in [0, 100], got {}", s.cut)));
        }
        Ok(())
    }
}

/// With `run.protocol`, the protocol's message columns join the observation (as for QMIX);
/// NDQ's own messages are made inside the network either way.
fn configure(table: &toml::Table, _ctx: &MethodContext) -> Result<AgentConfig, ConfigError> {
    let settings: NdqSettings = parse_settings(table)?;
    let cfg = NdqConfig { settings };
    cfg.validate()?;
    Ok(AgentConfig::Ndq(cfg))
}

/// The cut as a 0/1 keep-mask over `abs_mu`, ranked within each consecutive group of `group`
/// values (one environment's step): the value of ascending rank r (0-based, ties by position)
/// is cut when `100 r / group < percent`.
pub fn cut_mask(abs_mu: &[f32], group: usize, percent: f32) -> Vec<f32> {
    let mut keep = vec![1.0; abs_mu.len()];
    if percent <= 0.0 || group == 0 {
        return keep;
    }
    for (g, chunk) in abs_mu.chunks(group).enumerate() {
        let mut order: Vec<usize> = (0..chunk.len()).collect();
        order.sort_by(|&a, &b| chunk[a].total_cmp(&chunk[b]).then(a.cmp(&b)));
        for (rank, &i) in order.iter().enumerate() {
            if 100.0 * rank as f64 / (chunk.len() as f64) < percent as f64 {
                keep[g * group + i] = 0.0;
            }
        }
    }
    keep
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_cut_zeroes_the_bottom_percent_of_each_group_by_absolute_mean() {
        // Two groups of 4 (size 4: ranks 0..3 are 0, 25, 50, 75 percent).
        let mu = [0.3f32, -0.1, 2.0, -0.5, /* group 2 */ 1.0, 1.0, -3.0, 0.0];
        let abs: Vec<f32> = mu.iter().map(|v| v.abs()).collect();
        // p = 0: nothing cut.
        assert_eq!(cut_mask(&abs, 4, 0.0), vec![1.0; 8]);
        // p = 30: ranks 0 and 1 (0% and 25% < 30%). Group 1 ascending: -0.1, 0.3, -0.5, 2.0;
        // group 2: 0.0, 1.0 (position 4), 1.0 (position 5), -3.0.
        assert_eq!(cut_mask(&abs, 4, 30.0), vec![0.0, 0.0, 1.0, 1.0, 0.0, 1.0, 1.0, 0.0]);
        // p = 50: rank 2 is at exactly 50%, not below: still two cut per group.
        assert_eq!(cut_mask(&abs, 4, 50.0), vec![0.0, 0.0, 1.0, 1.0, 0.0, 1.0, 1.0, 0.0]);
        // p = 51: three per group; p = 100: all.
        assert_eq!(cut_mask(&abs, 4, 51.0), vec![0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]);
        assert_eq!(cut_mask(&abs, 4, 100.0), vec![0.0; 8]);
        // NDQ's 90% of 12 dims (2 agents, d = 3): ranks with 100 r / 12 < 90, i.e. r <= 10: one kept.
        let twelve: Vec<f32> = (0..12).map(|i| ((i * 7) % 12) as f32).collect();
        let keep = cut_mask(&twelve, 12, 90.0);
        assert_eq!(keep.iter().sum::<f32>(), 1.0);
        assert_eq!(keep[twelve.iter().position(|&v| v == 11.0).unwrap()], 1.0, "the largest survives");
    }

    #[test]
    fn settings_are_checked_and_errors_name_the_field() {
        let ctx = MethodContext::default();
        let parse = |s: &str| configure(&toml::from_str(s).unwrap(), &ctx);
        assert!(matches!(parse("").unwrap(), AgentConfig::Ndq(c) if c.settings == NdqSettings::default()));
        assert!(matches!(parse("cut = 95.0\nc_beta = 0.1").unwrap(), AgentConfig::Ndq(c) if c.settings.cut == 95.0));
        assert!(matches!(parse("mask_losses = false").unwrap(), AgentConfig::Ndq(c) if !c.settings.mask_losses));
        assert_eq!(parse("cut = 120.0").unwrap_err().field, "method.cut");
        assert_eq!(parse("msg_dim = 0").unwrap_err().field, "method.msg_dim");
        assert_eq!(parse("comm_beta = -1.0").unwrap_err().field, "method.comm_beta");
        let e = parse("comm_betta = 1.0").unwrap_err();
        assert!(e.field == "method" && e.reason.contains("comm_betta"), "{e}");
    }
}

impl NdqConfig {
    /// [`UpdateShape::plain`](crate::flops::UpdateShape::plain) of an NDQ update (`self`: its settings): the plain
    /// agent's count with its input widened by the n * msg_dim received message dims, plus per
    /// agent row the message encoder (input -> encoder_hidden -> encoder_hidden -> n * msg_dim)
    /// in the online network (forward and backward, no input gradient for its first layer) and
    /// the target network, and the action-inference head (input + n * msg_dim -> 4 n msg_dim ->
    /// 4 n msg_dim -> actions) in the online network only. Routing messages to receivers is a
    /// transpose (no FLOPs).
    pub fn update_flops(&self, shape: &crate::flops::UpdateShape, mixer: crate::MixerKind, cfg: &crate::LearnConfig) -> f64 {
        let s = &self.settings;
        let rows = (shape.batch * shape.steps * shape.agents) as f64;
        let (iw, h, nd, a) = (shape.input as f64, s.encoder_hidden as f64, (shape.agents * s.msg_dim) as f64, shape.actions as f64);
        let plain = crate::flops::UpdateShape { input: shape.input + shape.agents * s.msg_dim, ..*shape }.plain(mixer, cfg);
        let enc_first = 2.0 * iw * h;
        let enc = enc_first + 2.0 * h * h + 2.0 * h * nd;
        let infer = 2.0 * (iw + nd) * 4.0 * nd + 2.0 * 16.0 * nd * nd + 2.0 * 4.0 * nd * a;
        // encoder: online forward + backward + target forward; inference head: online forward + backward
        plain + rows * (enc + (2.0 * enc - enc_first) + enc) + rows * 3.0 * infer
    }
}
