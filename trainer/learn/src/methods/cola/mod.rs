//! COLA, consensus learning (Xu et al. 2023, "Consensus Learning for Cooperative Multi-Agent
//! Reinforcement Learning", AAAI), as in the authors' released code (deligentfool/COLA:
//! `cola_learner.py`, `basic_controller.py`, `consensus_builder.py`, `rnn_agent.py`,
//! `cola.yaml`), on lmac's learner. The network is in `module.rs`.
//!
//! No messages. Every agent maps what it sees to one of K consensus classes with a *student*
//! network (its input row -> 2W -> ReLU -> W -> W -> ReLU -> K; W = 64, K = 4; as in the released
//! code there is no activation between the "view" MLP's output and the "projection" MLP's first
//! layer). The class is the argmax of the student's logits; a dead agent gets the extra class K.
//! The class is looked up in an embedding table ((K + 1) x E, E = 4), encoded (E -> H -> ReLU -> H)
//! and concatenated with the agent's GRU state before the Q head ([h | code] -> actions): pymarl's
//! RNN agent with a consensus code next to its hidden state. The argmax is not differentiable, so
//! the TD loss trains the GRU, the embedding, the encoder and the Q head, never the student.
//!
//! The student is trained DINO-style so that agents at the same step pick the same class. A
//! *teacher* of the same shape (initialised independently, not trained by gradients) follows the
//! student by an exponential moving average after every update (momentum `teacher_momentum`,
//! 0.996). With teacher logits g and student logits s, the consensus loss of one step is
//! `sum_{i != j} -softmax((g_i - c) / teacher_temp) . log_softmax(s_j / student_temp)` over the
//! ordered pairs of alive agents (teacher of agent i supervises the student of agent j),
//! averaged over all such pairs of the trained steps of the batch (temperatures 0.04 and 0.1).
//! The center c (K values) follows the mean teacher logits of the batch's alive agent-rows
//! (momentum `center_momentum`, 0.9), once per update; centering and the sharper teacher keep
//! the classes from collapsing into one.
//!
//! Dead agents: an agent-row whose observation (the first `obs_width - msg_cols` columns of its
//! input row: the environment's observation without the protocol's message columns, which a dead
//! agent may still receive) is all zeros is dead. lmac's environments write zeros for dead agents
//! (SMAC, SMAClite, PettingZoo's dead slots); the input row holds no availability mask, and the
//! last action and agent id columns are non-zero for dead agents too. A live agent whose
//! observation happens to be all zeros is treated as dead as well (it acts on the dead class's
//! code and takes no part in the consensus loss); LBF's never is (it holds the agent's own level).
//! With a single agent there are no pairs: the loss is 0 and the student keeps its initial
//! weights.
//!
//! Loss reduction, checked against the released learner (`docs/reference/fidelity.md`): the cross-entropy
//! of a pair is summed over the K classes (`cola_learner.py:114`, a batched matrix product) and
//! averaged over the ordered pairs i != j of alive agents (`:116-121`). The same here.
//!
//! Differences from the released code:
//! - Optimizer: the released code trains the student with an RMSprop of its own (its own
//!   gradient-norm clip of 10), before and apart from the TD step. Here the consensus loss,
//!   weighted by `consensus_weight` (1), is added to the TD loss and the run's one optimizer
//!   steps every parameter. The two losses reach disjoint parameters (the student only gets the
//!   consensus gradient; with `input = "hidden"` it reads detached GRU states), and Adam and
//!   RMSprop keep per-parameter statistics, so this equals two optimizers with the same settings
//!   except for the clip: one global clip over both gradients instead of one per loss. The run's
//!   optimizer is `[learn]`'s (lmac's default Adam; `learn.optimizer = "rmsprop"` is the released
//!   one).
//! - Dead agents are found from the observation (above); the released code reads SMAC's
//!   `alive_allies`, which lmac's input row does not carry.
//! - The loss and the center are guarded against empty batches: a batch without a pair of alive
//!   agents gives a zero loss (the released code divides by zero: NaN), and without an alive row
//!   the center stays as it was (the released code: NaN).
//! - The loss and the center are masked over padded steps by the learner's mask of trained
//!   steps; the released code uses its alive mask (zero on padded steps of its zero-filled batch)
//!   cut after a termination, which selects the same rows.
//! - Order within an update: as in the released code, the Q-values of an update use the classes
//!   of the student before that update, and the center and the teacher move after the student's
//!   step (here in `after_update`, which the learner calls after every optimizer step).
//! - The mixer is the run's `[learn]` QMIX (`learn.mixer`); the released config mixes with width
//!   64 and 2-layer hypernetworks of width 32, lmac's default is 32 and 64:
//!   `learn.mixing_embed_dim = 64`, `learn.hypernet_embed = 32` reproduce it. The released
//!   learner also computes a team-level class (the argmax of the agents' summed softmaxes) that
//!   nothing reads except a logged count of used classes; it is not computed here (see
//!   [`STAT_NAMES`] for what is logged instead).

pub mod module;

pub use module::ColaAgent;

use serde::{Deserialize, Serialize};

use super::{bad, parse_settings, AgentConfig, Messages, MethodContext, MethodSpec};
use crate::config::ConfigError;

pub const COLA: MethodSpec = MethodSpec {
    name: "cola",
    about: "COLA: agents agree on a consensus class of the step (DINO student/teacher) and act on it, no messages",
    messages: Messages::Optional,
    mixer: None,
    agent_sees_state: false,
    configure,
    settings: Some(|| schemars::schema_for!(ColaSettings)),
};

/// The numbers a COLA update logs, in order: the consensus loss (unweighted), the share of the
/// trained steps' ordered pairs of alive agents whose classes agree (chance with K equally used
/// classes: 1/K), and the entropy in bits of the class usage over the alive agent-rows (at most
/// log2 K; 0 = collapsed into one class).
pub const STAT_NAMES: &[&str] = &["cola_consensus", "cola_agreement", "cola_class_entropy"];

/// What the student and the teacher read.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum ConsensusInput {
    /// The agent's input row (the released `input: "obs"`: observation, last action, agent id).
    Obs,
    /// The agent's GRU state after this step, detached (the released `input: "hidden"`).
    Hidden,
}

/// The `[method]` settings of `--algo cola` (defaults: the released `cola.yaml`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct ColaSettings {
    /// Consensus classes K (`consensus_builder_dim`: 4).
    pub classes: usize,
    /// Width W of the student and teacher (`consensus_builder_hidden_dim`: 64; first layer 2W).
    pub hidden: usize,
    /// Width of a class's embedding (`consensus_builder_embedding_dim`: 4).
    pub embed_dim: usize,
    /// Student softmax temperature (`online_temp`: 0.1).
    pub student_temp: f32,
    /// Teacher softmax temperature (`target_temp`: 0.04).
    pub teacher_temp: f32,
    /// Momentum of the teacher's moving average of the student (`tau`: 0.996).
    pub teacher_momentum: f32,
    /// Momentum of the center's moving average of the teacher logits (`center_tau`: 0.9).
    pub center_momentum: f32,
    /// Weight of the consensus loss in the update's loss (1; see the module doc).
    pub consensus_weight: f32,
    /// What the student and the teacher read (`input`: "obs").
    pub input: ConsensusInput,
}

impl Default for ColaSettings {
    fn default() -> Self {
        ColaSettings {
            classes: 4,
            hidden: 64,
            embed_dim: 4,
            student_temp: 0.1,
            teacher_temp: 0.04,
            teacher_momentum: 0.996,
            center_momentum: 0.9,
            consensus_weight: 1.0,
            input: ConsensusInput::Obs,
        }
    }
}

/// The settings and what the run tells the network: saved in checkpoints, so a resumed run
/// rebuilds the same network.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ColaConfig {
    pub settings: ColaSettings,
    /// Message columns at the end of each observation (the protocol's; left out when looking
    /// for dead agents).
    pub msg_cols: usize,
}

impl ColaConfig {
    pub fn validate(&self) -> Result<(), ConfigError> {
        let s = &self.settings;
        for (field, v, min, max) in
            [("method.classes", s.classes, 2, 256), ("method.hidden", s.hidden, 1, 1 << 14), ("method.embed_dim", s.embed_dim, 1, 1 << 14)]
        {
            if v < min || v > max {
                return Err(bad(field, format!("must be in {min}..={max}, got {v}")));
            }
        }
        for (field, v) in [("method.student_temp", s.student_temp), ("method.teacher_temp", s.teacher_temp)] {
            if !(v.is_finite() && v >= 1e-4) {
                return Err(bad(field, format!("must be a temperature of at least 1e-4, got {v}")));
            }
        }
        for (field, v) in [("method.teacher_momentum", s.teacher_momentum), ("method.center_momentum", s.center_momentum)] {
            if !(v.is_finite() && (0.0..=1.0).contains(&v)) {
                return Err(bad(field, format!("must be a momentum in [0, 1], got {v}")));
            }
        }
        if !(s.consensus_weight.is_finite() && s.consensus_weight >= 0.0) {
            return Err(bad("method.consensus_weight", format!("must be a non-negative number, got {}", s.consensus_weight)));
        }
        if self.msg_cols > 1 << 20 {
            return Err(bad("method.msg_cols", format!("must be at most 1048576, got {}", self.msg_cols)));
        }
        Ok(())
    }
}

/// With `run.protocol`, the protocol's message columns join the observation (as for QMIX) and
/// are left out of the dead-agent test.
fn configure(table: &toml::Table, ctx: &MethodContext) -> Result<AgentConfig, ConfigError> {
    let settings: ColaSettings = parse_settings(table)?;
    let cfg = ColaConfig { settings, msg_cols: ctx.msg_cols };
    cfg.validate()?;
    Ok(AgentConfig::Cola(cfg))
}

/// The class of each agent-row: the argmax of its logits (`logits` row-major, `k` per row; the
/// first of equal maxima), or `k` (the dead class) where `alive` is false.
pub fn classes(logits: &[f32], k: usize, alive: &[bool]) -> Vec<usize> {
    logits
        .chunks(k)
        .zip(alive)
        .map(|(row, &a)| {
            if !a {
                return k;
            }
            let mut best = 0;
            for (i, v) in row.iter().enumerate() {
                if *v > row[best] {
                    best = i;
                }
            }
            best
        })
        .collect()
}

/// The agreement and class-usage statistics of one batch: `cls` [G * n] (G groups of n agents:
/// one environment's step), `weight` [G] (1 on trained steps). Returns (the share of ordered pairs
/// i != j of alive agents of a trained step with the same class, the entropy in bits of the
/// classes of the trained alive rows); 0 where there is nothing to count.
pub fn agreement_and_entropy(cls: &[usize], k: usize, n: usize, weight: &[f32]) -> (f32, f32) {
    let (mut pairs, mut same) = (0.0f64, 0.0f64);
    let mut usage = vec![0.0f64; k];
    for (g, agents) in cls.chunks(n).enumerate() {
        let w = weight.get(g).copied().unwrap_or(0.0) as f64;
        if w <= 0.0 {
            continue;
        }
        for (i, &ci) in agents.iter().enumerate() {
            if ci >= k {
                continue;
            }
            usage[ci] += w;
            for (j, &cj) in agents.iter().enumerate() {
                if i != j && cj < k {
                    pairs += w;
                    same += w * (ci == cj) as u8 as f64;
                }
            }
        }
    }
    let total: f64 = usage.iter().sum();
    let entropy =
        if total > 0.0 { usage.iter().filter(|&&u| u > 0.0).map(|&u| -(u / total) * (u / total).log2()).sum::<f64>() } else { 0.0 };
    let agreement = if pairs > 0.0 { same / pairs } else { 0.0 };
    (agreement as f32, entropy as f32)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn settings_are_checked_and_errors_name_the_field() {
        let ctx = MethodContext { msg_cols: 3, ..MethodContext::default() };
        let parse = |s: &str| configure(&toml::from_str(s).unwrap(), &ctx);
        assert!(matches!(parse("").unwrap(), AgentConfig::Cola(c) if c.settings == ColaSettings::default() && c.msg_cols == 3));
        assert!(matches!(parse("input = \"hidden\"\nclasses = 8").unwrap(),
            AgentConfig::Cola(c) if c.settings.input == ConsensusInput::Hidden && c.settings.classes == 8));
        assert_eq!(parse("classes = 1").unwrap_err().field, "method.classes");
        assert_eq!(parse("hidden = 0").unwrap_err().field, "method.hidden");
        assert_eq!(parse("embed_dim = 0").unwrap_err().field, "method.embed_dim");
        assert_eq!(parse("teacher_temp = 0.0").unwrap_err().field, "method.teacher_temp");
        assert_eq!(parse("student_temp = -1.0").unwrap_err().field, "method.student_temp");
        assert_eq!(parse("teacher_momentum = 1.5").unwrap_err().field, "method.teacher_momentum");
        assert_eq!(parse("center_momentum = -0.1").unwrap_err().field, "method.center_momentum");
        assert_eq!(parse("consensus_weight = -1.0").unwrap_err().field, "method.consensus_weight");
        let e = parse("input = \"state\"").unwrap_err();
        assert!(e.field == "method" && e.reason.contains("state"), "{e}");
        let e = parse("center_tau = 0.9").unwrap_err();
        assert!(e.field == "method" && e.reason.contains("center_tau"), "{e}");
    }

    #[test]
    fn classes_are_the_first_argmax_and_dead_rows_get_the_extra_class() {
        let logits = [0.1, 0.7, 0.7, -1.0, /* row 2 */ 2.0, 0.0, 0.0, 0.0, /* row 3 */ 5.0, 9.0, 1.0, 1.0];
        assert_eq!(classes(&logits, 4, &[true, true, false]), vec![1, 0, 4]);
    }

    #[test]
    fn agreement_counts_ordered_pairs_of_alive_agents_on_trained_steps() {
        // Three agents, K = 4. Step 0: classes 1, 1, 2 -> pairs (0,1), (1,0) agree of 6.
        // Step 1: agent 2 dead (class 4): classes 3, 3 -> 2 of 2 agree. Step 2 is padding.
        let cls = [1, 1, 2, 3, 3, 4, 0, 0, 0];
        let (agree, entropy) = agreement_and_entropy(&cls, 4, 3, &[1.0, 1.0, 0.0]);
        assert!((agree - 4.0 / 8.0).abs() < 1e-6, "{agree}");
        // Usage over the 5 alive trained rows: class 1 twice, 2 once, 3 twice.
        let p = [0.4f64, 0.2, 0.4];
        let want: f64 = p.iter().map(|p| -p * p.log2()).sum();
        assert!((entropy as f64 - want).abs() < 1e-5, "{entropy} vs {want}");
        // Nothing trained: zeros.
        assert_eq!(agreement_and_entropy(&cls, 4, 3, &[0.0; 3]), (0.0, 0.0));
    }
}

impl ColaConfig {
    /// [`UpdateShape::plain`](crate::flops::UpdateShape::plain) of a COLA update (`self`: its settings): the plain
    /// agent's count with the Q head reading [h | code] (twice its input), plus per agent row, in
    /// the online network (forward and backward) and the target network, the student (input or
    /// GRU state -> 2W -> W -> W -> K; no input gradient: the input, or the detached state) and
    /// the class code (a one-hot row times the K + 1 encoded codes; the gradient reaches only the
    /// table); in the online network only, the teacher (the student's shape, forward only) and
    /// the cross-entropy of every teacher with every student of an environment's step (n K per
    /// row, forward and the student side's gradient).
    pub fn update_flops(&self, shape: &crate::flops::UpdateShape, mixer: crate::MixerKind, cfg: &crate::LearnConfig) -> f64 {
        let s = &self.settings;
        let rows = (shape.batch * shape.steps * shape.agents) as f64;
        let (h, a, w, k, n) = (shape.hidden as f64, shape.actions as f64, s.hidden as f64, s.classes as f64, shape.agents as f64);
        let d_in = match s.input {
            ConsensusInput::Obs => shape.input as f64,
            ConsensusInput::Hidden => h,
        };
        let q_code = 2.0 * h * a;
        let student_first = 2.0 * d_in * 2.0 * w;
        let student = student_first + 2.0 * 2.0 * w * w + 2.0 * w * w + 2.0 * w * k;
        let code = 2.0 * (k + 1.0) * h;
        let fwd = q_code + student + code;
        let bwd = 2.0 * q_code + 2.0 * student - student_first + code;
        let consensus = student + 2.0 * 2.0 * n * k;
        shape.plain(mixer, cfg) + rows * (fwd + bwd + fwd + consensus)
    }
}
