//! The offline designer: the embedded default that needs no network. It is not an LLM and
//! does not pretend to be one; every protocol it writes says "offline designer: ..." and
//! explains its numbers. It designs from the data, deterministically.
//!
//! **By default** ([`OfflineConfig::default`]) it designs for the task:
//! - phase 0's critical dims are the few state dims the dataset's policy's actions depend on
//!   most and agents recover poorly without messages ([`CriticalBy::Action`]; by the return's
//!   value model where the action models explain too little);
//! - one agent sends: the one whose view most helps the others predict the team's return
//!   ([`SendersBy::Return`]); it sends whole entities of its view (a unit, an object), the one
//!   that most raises the others' recovery of the critical dims per value first
//!   ([`ValuesBy::Recovery`]); where a discriminator cannot read even its whole view (the
//!   receivers recover the critical dims with it no better than a constant guess), the
//!   per-entity ranking would measure noise, and every agent sends its whole view instead
//!   ([`OfflineConfig::whole_view_when_blind`]);
//! - phase 1 sends the values of that sender's view that place each receiver in the sender's
//!   frame ([`Phase1By::Frame`]), so the receivers can use phase 0's entity;
//! - phase 2, and any rule the data cannot support, by the greedy least squares below.
//!
//! [`OfflineConfig::least_squares_rules`] designs every phase by least squares:
//!
//! 1. **Targets and weights.** Phase 0 trains the no-message discriminator on B and takes the
//!    state dims agents recover worst without messages as the task-critical set: mean E_t[chi]
//!    over agents relative to a constant guess ([`meta::skill`]) below
//!    [`OfflineConfig::poor_threshold`] (raw rates mislead on sparse dims: an LBF cell that is
//!    empty 97% of the time is "recovered" 97% of the time by guessing 0). Phase 1
//!    (recognition) takes the dims the meta-information shows still poorly recovered *with* the
//!    messages; phase 2 (sharing) the dims with the largest variance of recovery across agents.
//!    Each (receiving agent i, dim d) gets a weight: its failure rate 1 - E_t[chi] divided by
//!    the constant guess's (phases 0, 1), or in phase 2 its gap to the best agent plus a tenth
//!    of its failure rate, on the same scale (so lagging agents count most).
//! 2. **Candidate features**, each computed by the runner's own compiled plan on B (a probe
//!    protocol, so values match what the runner would send exactly): phase 0 the sender's
//!    current observation dims and its last action; phase 1 also history aggregates of each
//!    observation dim (max, mean and most recent non-zero over 5 steps, the previous step, the
//!    change over 3 steps); phase 2 temporal cues over the last 10 steps (max, mean, most recent
//!    non-zero, and the action histogram), as the paper's reference phase-2 protocol uses.
//! 3. **Greedy least-squares selection.** On a sample of steps, the covariance of every agent's
//!    own observation, the messages it already receives, every sender's candidates and the
//!    target dims is computed once. For each receiver, what it already knows (own observation
//!    and earlier phases' messages) is partialled out (the sweep operator); a candidate's gain
//!    is the weighted fraction of target variance the other agents' values of it explain on
//!    top (linear R^2). The candidate with the best gain per message column is added while it
//!    fits this phase's share of the budget (the budget left divided by the phases left) and
//!    gains at least [`OfflineConfig::min_gain`] per column. A candidate is broadcast when every
//!    sender -> receiver link helps; otherwise only the helping links are kept (peer to peer).
//!
//! Feedback is generated from the meta-information as text with the actual numbers.

use super::discriminator::DiscriminatorConfig;
use super::meta::{self, Recovery};
use super::meta_info::MetaInfo;
use super::{DesignContext, Designer, Feedback, PhaseProtocol, TranscriptEntry};
use anyhow::{anyhow, bail, Context, Result};
use lmac_protocol_runner::protocol::{
    self, ActionEncoding, DimSpec, Expr, Field, HistoryPadding, MessageLayout, PeerLink, Protocol, ProtocolEnv, Receivers, Senders,
    ValidatedProtocol, Window, WindowOp,
};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

mod assemble;
mod candidates;
mod frame;
mod meta_dims;
mod select;
use assemble::*;
use candidates::*;
pub use frame::{frame_fit, FrameFit, FrameFitConfig};
use meta_dims::*;
use select::*;

/// The offline designer's knobs.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OfflineConfig {
    /// The discriminator that measures no-message recovery for phase 0.
    pub discriminator: DiscriminatorConfig,
    /// A dim is poorly recovered when its mean E_t[chi] over agents, relative to a constant
    /// guess ([`meta::skill`]: 0 = no better than guessing, 1 = always right), is below this.
    pub poor_threshold: f64,
    /// Most critical dims phase 0 lists.
    pub max_critical_dims: usize,
    /// Most target dims one phase's feature selection aims at (the worst ones).
    pub max_targets: usize,
    /// Most steps of B the statistics use (a deterministic spread of episodes).
    pub max_samples: usize,
    /// Candidates kept after the marginal-correlation prescreen.
    pub prescreen: usize,
    /// Smallest weighted R^2 gain per message column worth sending (0.004: a column must explain
    /// at least 0.4% of the weighted target variance; below that the picks were artefacts such
    /// as padding-driven "first step" indicators in the synthetic tests).
    pub min_gain: f64,
    /// A sender -> receiver link is kept when it explains at least this fraction of the best
    /// link's gain for the candidate.
    pub link_fraction: f64,
    /// Phases the budget is shared between (the paper's 3).
    pub phases: usize,
    /// Count a candidate's cost as the message columns its receivers get (its values on every
    /// link, plus each new sender's one-hot), so one sender of 3 values (14 columns per receiver
    /// on 1o_10b) is preferred to a value broadcast by 10 senders (120); false: its width in one
    /// sender block, as the designer did first (it sent 183 columns in phase 0 on 1o_10b).
    pub count_sender_columns: bool,
    /// Most agents that send one field (0: any number). 1 is the paper's "unique" principle as
    /// the authors' designs follow it: each piece of information has one sender, the agent
    /// that observes it best (on 1o_10b the Overseer alone reports the Roach); the sender whose
    /// links explain the most of the targets summed over its receivers is kept.
    pub senders_per_field: usize,
    /// How phase 0 chooses its message fields.
    pub fields_by: FieldsBy,
    /// Most observation values [`FieldsBy::ObservationRelevance`] sends in phase 0 (the
    /// authors' 1o_10b design sends 3, one agent's).
    pub max_relevant_values: usize,
    /// Most agents that send in phase 0 with [`FieldsBy::ObservationRelevance`] (the authors'
    /// 1o_10b design: 1, the Overseer).
    pub relevant_senders: usize,
    /// How [`FieldsBy::ObservationRelevance`] ranks the agents as senders.
    pub senders_by: SendersBy,
    /// What of a sender's view [`FieldsBy::ObservationRelevance`] sends.
    pub values_by: ValuesBy,
    /// How phase 1 (recognition enhancement) chooses its fields.
    pub phase1_by: Phase1By,
    /// [`Phase1By::Frame`]: smallest share of a receiver's view of phase 0's entity a further
    /// value of the sender's must explain to be sent.
    pub frame_min_gain: f64,
    /// [`Phase1By::Frame`]: most values one receiver's fit takes.
    pub frame_values_per_receiver: usize,
    /// [`Phase1By::Frame`]: fit on top of the receiver's own observation too
    /// ([`FrameFitConfig::given_own_view`]).
    pub frame_given_own_view: bool,
    /// How phase 0 chooses the task-critical dims.
    pub critical_by: CriticalBy,
    /// The value model behind [`CriticalBy::Relevance`].
    pub relevance: super::relevance::RelevanceConfig,
    /// A dim is task-relevant when shuffling it costs at least this fraction of the held-out
    /// return's variance ([`super::relevance`]).
    pub min_relevance: f64,
    /// Most critical dims [`CriticalBy::Relevance`] lists (the authors' GPT-4.1 designs name
    /// 4-12; a short list keeps the decoder's target and the messages compact).
    pub max_relevant_dims: usize,
    /// Below this held-out R^2 the value model explains too little of the return to rank dims
    /// by, and phase 0 falls back to [`CriticalBy::Recovery`] (saying so).
    pub min_value_r2: f64,
    /// [`CriticalBy::Action`]: below this held-out R^2 the linear action models explain too
    /// little of the policy to rank dims by, and phase 0 ranks them by the return instead
    /// ([`CriticalBy::Relevance`], saying so). Measured: 46% on 1o_10b's QMIX+State dataset,
    /// whose ranking is the authors' four dims 8x above the fifth; 18% on its QMIX dataset and
    /// 8% on LBF 8x8's QMIX+State one (the way to a food is not linear in grid cells), where
    /// the ranking after the first one or two dims is noise.
    pub min_action_r2: f64,
    /// [`ValuesBy::Recovery`]: first probe the best sender's whole view; where the receivers
    /// recover the critical dims with it no better than a constant guess of each dim, the
    /// discriminator cannot see what a message adds on this map, its per-entity gains are noise
    /// and a compact pick would follow the cost per value, not the task. Then every agent sends
    /// all of its view that varies on B to every other agent (FullComm's message, as far as the
    /// budget allows), saying why. On LBF 8x8 the grid state is read no better than the guess
    /// even with the partner's whole view; the default design with both whole views (34
    /// columns) trained LMAC (messages read directly) to 0.907 against 0.781-0.809 for
    /// 8-column ranked picks and 0.815 for the authors' design (5 seeds). False: rank the
    /// entities anyway (the designs before 2026-12-06's second session; designs recorded before
    /// it parse as false).
    #[serde(default)]
    pub whole_view_when_blind: bool,
}

/// How phase 0 chooses the task-critical dims.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum CriticalBy {
    /// What the return depends on and agents cannot see: relevance to the return
    /// (a value model's permutation importance on B) x how badly agents recover the dim
    /// without messages; only dims that are both relevant and poorly recovered.
    Relevance,
    /// What B's policy's actions depend on and agents cannot see: the state dims a linear
    /// model of each agent's action leans on most ([`super::relevance::measure_actions`]) x how
    /// badly agents recover them without messages. The LMAC agent reads its messages only
    /// through a latent trained to reconstruct the critical dims, so these dims are what the
    /// messages can tell the policy: where the units are rather than how the episode goes
    /// (on 1o_10b the return's value model ranks the Roach's health and the Banelings' alive
    /// bits first). Meaningful when B's policy could act on the state (`--collect-with
    /// qmix-state`); where the linear action models explain less than
    /// [`OfflineConfig::min_action_r2`] of it, the dims are ranked as by [`CriticalBy::Relevance`].
    Action,
    /// The hardest to recover without messages, whatever their bearing on the task (the
    /// designer's first rule, kept as an option: it picked 48 dims on 1o_10b, 33 of them
    /// teammates' last actions).
    Recovery,
}

/// How phase 0 chooses its message fields.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum FieldsBy {
    /// Greedy least squares: the sender features that best explain the critical dims beyond
    /// what each receiver sees (the module doc, step 3).
    LeastSquares,
    /// One agent sends what the return depends on: for each agent, a discriminator measures how
    /// much all it sees, sent to the others, raises their recovery of the critical dims
    /// (nonlinear, so an offset the agent sees counts however the state writes positions,
    /// where least squares on absolute state dims cannot use it); the best agent(s) send their
    /// observation values that a value model of the team's joint observation finds the return
    /// depends on most (permutation importance), to every other agent.
    ObservationRelevance,
}

/// How [`FieldsBy::ObservationRelevance`] ranks the agents as senders.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SendersBy {
    /// By how much all an agent sees, sent to the others, raises their recovery of the
    /// critical dims (a discriminator per candidate sender).
    Recovery,
    /// By how much all an agent sees, put beside another agent's own observation, raises a
    /// value model's held-out R^2 of the team's return ([`super::relevance::receiver_return_gains`]):
    /// what the others need of it for the task, whatever the state's dims.
    Return,
}

/// What of a sender's view [`FieldsBy::ObservationRelevance`] sends.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ValuesBy {
    /// Its values one by one, most relevant first.
    Value,
    /// Whole entities (the schema's units, slots, objects: [`EnvSchema::obs_entities`]), the
    /// entity whose values shuffled together cost the receivers' value model most first, every
    /// value of it that varies for the sender on B. A value model of the return reads progress
    /// (a unit's health) before where things are, and correlated values (a unit's distance and
    /// offset) share their importance one by one; an entity keeps them together, so the
    /// receivers learn where the unit whose state the return follows is. Needs
    /// [`SendersBy::Return`].
    ///
    /// [`EnvSchema::obs_entities`]: lmac_shm_schema::schema::EnvSchema::obs_entities
    Entity,
    /// Whole entities as with [`ValuesBy::Entity`], ranked instead by what each, sent alone to
    /// the others, adds to their recovery of the critical dims per value sent (a discriminator
    /// per sender and entity, nonlinear like the LMAC decoder it stands for). A value model of
    /// the return cannot rank where a teammate is when the state writes it as grid cells (on
    /// LBF 8x8 it ranked the view's top row first), but the teammate's own row and column make
    /// its cell recoverable, so on LBF-shaped random walks this rule sends them first. On LBF
    /// 8x8's real B every entity's gain is within the discriminator's noise (+0.0024 to
    /// +0.0038: it does not gain even from the partner's whole view), so there the order
    /// follows the cost per value. An entity that alone adds more than everything the
    /// per-value order fits in `max_relevant_values` goes first (on 1o_10b the Roach, +0.37 for
    /// 5 values, over the Overseer's move feature, +0.33 for 4). Works with either `--senders-by`.
    Recovery,
}

/// How phase 1 (recognition enhancement) chooses its fields.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Phase1By {
    /// Greedy least squares on the state dims phase 0's messages leave poorly recovered.
    LeastSquares,
    /// The sender's further values that place each receiver in its view, so a receiver can
    /// turn phase 0's entity, seen in the sender's frame, into its own (module `frame`),
    /// never an exact copy of a value the receiver sees itself; least squares when none adds
    /// enough. Needs [`ValuesBy::Entity`] or [`ValuesBy::Recovery`].
    Frame,
}

/// `FromStr` for an option enum through its serde (kebab-case) names, for the CLI.
/// `Display` the same names, so the CLI can show the library's defaults as its own.
macro_rules! option_from_str {
    ($t:ty, $choices:literal) => {
        impl std::str::FromStr for $t {
            type Err = String;
            fn from_str(s: &str) -> Result<Self, String> {
                serde_json::from_value(serde_json::Value::String(s.into())).map_err(|_| format!("{s:?}: use {}", $choices))
            }
        }
        impl std::fmt::Display for $t {
            fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                match serde_json::to_value(self) {
                    Ok(serde_json::Value::String(name)) => f.write_str(&name),
                    _ => write!(f, "{self:?}"),
                }
            }
        }
    };
}

option_from_str!(Phase1By, "least-squares or frame");
option_from_str!(ValuesBy, "value, entity or recovery");
option_from_str!(SendersBy, "recovery or return");
option_from_str!(FieldsBy, "least-squares or observation-relevance");
option_from_str!(CriticalBy, "relevance, action or recovery");

impl OfflineConfig {
    /// The designer's first rules, the default until 2026-12-06: the critical dims by what the
    /// return depends on (up to 12), and every phase's fields by greedy least squares on the
    /// state dims. Kept for comparison and for schemas whose observations name no entities.
    pub fn least_squares_rules() -> Self {
        OfflineConfig {
            discriminator: DiscriminatorConfig::default(),
            poor_threshold: 0.8,
            max_critical_dims: 48,
            max_targets: 24,
            max_samples: 20_000,
            prescreen: 48,
            min_gain: 0.004,
            link_fraction: 0.1,
            phases: 3,
            count_sender_columns: true,
            senders_per_field: 0,
            fields_by: FieldsBy::LeastSquares,
            max_relevant_values: 6,
            relevant_senders: 1,
            senders_by: SendersBy::Recovery,
            values_by: ValuesBy::Value,
            phase1_by: Phase1By::LeastSquares,
            frame_min_gain: 0.05,
            frame_values_per_receiver: 4,
            frame_given_own_view: false,
            critical_by: CriticalBy::Relevance,
            relevance: Default::default(),
            min_relevance: 0.01,
            max_relevant_dims: 12,
            min_value_r2: 0.05,
            min_action_r2: 0.25,
            whole_view_when_blind: false,
        }
    }

    /// Combinations of options that cannot work, refused before anything is collected.
    pub fn check(&self) -> Result<()> {
        if self.values_by == ValuesBy::Entity && self.senders_by != SendersBy::Return {
            bail!("offline designer: sending whole entities (--values-by entity) needs --senders-by return: the entities are ranked in the receivers' value model of the return");
        }
        if self.phase1_by == Phase1By::Frame && (self.values_by == ValuesBy::Value || self.fields_by != FieldsBy::ObservationRelevance) {
            bail!("offline designer: phase 1 by the sender's frame (--phase1-by frame) places the receivers in the view of the sender of phase 0's entity, so it needs --fields-by observation-relevance --values-by entity (or recovery)");
        }
        if self.frame_given_own_view && self.phase1_by != Phase1By::Frame {
            bail!("offline designer: --frame-given-own-view changes how phase 1's frame fit is made, so it needs --phase1-by frame");
        }
        Ok(())
    }
}

/// The default is the rule set measured best on SMAC-Comm's 1o_10b and LBF 8x8: the
/// critical dims by what a state-seeing policy's actions depend on (4 of them), one sender
/// chosen by what its view adds to the others' prediction of the return, whole entities of its
/// view by what each adds to the others' recovery, and phase 1 placing each receiver in the
/// sender's frame. On 1o_10b its design trained LMAC to a best-checkpoint IQM of 9.59 against
/// 9.01 for the authors' design and 7.26 for [`OfflineConfig::least_squares_rules`] on a QMIX
/// dataset (3 seeds). On LBF 8x8 the discriminator reads the grid worse than a constant guess
/// even with the partner's whole view, so every agent sends its whole view
/// ([`OfflineConfig::whole_view_when_blind`]), which trained LMAC (messages read directly) to
/// 0.907 against 0.815 for the authors' design (5 seeds, intervals apart). Every rule falls
/// back, saying so, where the data cannot support it (no entities in the schema, an action
/// model that explains too little, a discriminator that cannot read a message).
impl Default for OfflineConfig {
    fn default() -> Self {
        OfflineConfig {
            fields_by: FieldsBy::ObservationRelevance,
            senders_by: SendersBy::Return,
            values_by: ValuesBy::Recovery,
            phase1_by: Phase1By::Frame,
            critical_by: CriticalBy::Action,
            max_relevant_dims: 4,
            whole_view_when_blind: true,
            ..OfflineConfig::least_squares_rules()
        }
    }
}

/// The embedded designer (see the module doc).
pub struct OfflineDesigner {
    cfg: OfflineConfig,
    transcript: Vec<TranscriptEntry>,
    /// Phase 0's relevance measurement (None before it, or with [`CriticalBy::Recovery`]) and
    /// what it models: [`CriticalBy::Action`] or [`CriticalBy::Relevance`] (the return).
    relevance: Option<(super::relevance::Relevance, CriticalBy)>,
    /// Phase 0's recovery of every state dim without messages (None before it).
    without: Option<Recovery>,
    /// E_t[chi] of a constant guess of each dim of `without`, in its order.
    guess: Vec<f64>,
    /// Factor on [`OfflineConfig::min_gain`]: doubled each time a phase added nothing to the
    /// phases before it, so the next one sends only what explains more per column.
    gain_scale: f64,
    /// The first entity phase 0 sent whole ([`ValuesBy::Entity`], [`ValuesBy::Recovery`]), for
    /// [`Phase1By::Frame`].
    sent_entity: Option<SentEntity>,
}

/// What one probe message measured: how much it raises the receivers' recovery of the critical
/// dims over no messages, and that recovery (mean E_t[chi] over the dims and the receivers).
#[derive(Clone, Copy, Debug)]
struct Probe {
    gain: f64,
    recovery: f64,
}

/// An entity phase 0 sent: by whom, which of its values, and its name.
#[derive(Clone, Debug)]
struct SentEntity {
    sender: usize,
    values: Vec<usize>,
    name: String,
}

impl OfflineDesigner {
    pub fn new(cfg: OfflineConfig) -> Self {
        OfflineDesigner {
            cfg,
            transcript: Vec::new(),
            relevance: None,
            without: None,
            guess: Vec::new(),
            gain_scale: 1.0,
            sent_entity: None,
        }
    }

    pub fn config(&self) -> &OfflineConfig {
        &self.cfg
    }

    /// Phase 0's relevance measurement, once made.
    pub fn relevance(&self) -> Option<&super::relevance::Relevance> {
        self.relevance.as_ref().map(|r| &r.0)
    }

    fn log(&mut self, phase: usize, kind: &str, prompt: String, reply: String) {
        self.transcript.push(TranscriptEntry { phase, kind: kind.into(), prompt, reply });
    }
}

impl Default for OfflineDesigner {
    fn default() -> Self {
        Self::new(OfflineConfig::default())
    }
}

// ------------------------------------------------------------------------------------------
// The designer

/// Targets with their per-agent rates, ordered as chosen.
struct Targets {
    dims: Vec<usize>,
    /// weights[i][k] for receiver i and target k.
    weights: Vec<Vec<f64>>,
    why: String,
}

impl OfflineDesigner {
    /// Build, validate and explain one phase's protocol for `targets`.
    fn design(
        &mut self,
        ctx: &DesignContext,
        phase: usize,
        previous: &[PhaseProtocol],
        targets: Targets,
        critical: &[usize],
    ) -> Result<PhaseProtocol> {
        let env = ctx.env;
        let n = env.n_agents;
        if n < 2 {
            // Every width below is per other agent; with one agent there is no one to talk to.
            bail!("offline designer: {} has {n} agent(s); a communication protocol needs at least 2", ctx.env_name);
        }
        let prev: Vec<ValidatedProtocol> = previous.iter().map(|p| p.validated.clone()).collect();
        let left = super::prompts::budget_left(env, &prev);
        let phases_left = self.cfg.phases.saturating_sub(phase).max(1);
        let share = left / phases_left;
        let per_block = (share / n.saturating_sub(1).max(1)).saturating_sub(n);
        if per_block == 0 {
            bail!(
                "offline designer: no message budget for phase {phase}: {left} of {} columns are left, this phase's share is {share}, and one sender block needs {n} one-hot columns plus at least one value column for each of the {} other agents",
                env.message_budget,
                n - 1
            );
        }
        let kinds = kinds_for(phase);
        let (probe_v, probe_env, cands) = probe(&kinds, env)?;
        let width = probe_v.width / (n - 1);
        let mut s = sample(ctx, &prev, &probe_v, &probe_env, width, &targets.dims, self.cfg.max_samples)?;
        let rows = s.rows();
        if rows < 2 {
            bail!("offline designer: the dataset has {rows} usable steps; it needs at least 2");
        }
        // The fields, and how they were chosen: (in the instruction, in the reasoning).
        let (chosen, chosen_by) = if phase == 0 && self.cfg.fields_by == FieldsBy::ObservationRelevance {
            let by = (
                "by the relevance of what each agent sees to the return",
                "the relevance of each agent's observation to the return, from a value model fitted on the dataset",
            );
            (self.fields_by_observation_relevance(ctx, &cands, per_block, critical)?, by)
        } else if phase == 1 && self.cfg.phase1_by == Phase1By::Frame {
            let by = (
                "by where each receiver is in the sender's view",
                "linear fits on the dataset of each receiver's own view of phase 0's entity on the sender's view",
            );
            // One sender: its block may take this phase's whole share but its one-hot.
            (self.fields_by_frame(ctx, &cands, share.saturating_sub(n))?, by)
        } else {
            (None, ("", ""))
        };
        let chosen_by = if chosen.is_some() {
            chosen_by
        } else {
            ("by greedy least squares", "greedy least-squares feature selection over the dataset")
        };
        let (picks, steps, kept_count, how) = if let Some((picks, steps, how)) = chosen {
            (picks, steps, cands.len(), how)
        } else {
            let kept = prescreen(&mut s, &cands, &targets.weights, self.cfg.prescreen)?;
            let mut cols: Vec<usize> = kept.iter().flat_map(|&k| cands[k].col..cands[k].col + cands[k].width).collect();
            cols.sort_unstable();
            let stats = covariance(&mut s, cols)?;
            let cfg = OfflineConfig { min_gain: self.cfg.min_gain * self.gain_scale, ..self.cfg.clone() };
            let (picks, steps) = select(stats, &cands, &kept, &targets.weights, per_block, &cfg);
            let total_gain: f64 = picks.iter().map(|p| p.gain).sum();
            let how = format!(
                "Together these explain an estimated {:.1}% of the weighted variance of the {} target state dims that receivers could not explain from their own observation{} (linear R^2 on {} sampled steps).",
                100.0 * total_gain,
                targets.dims.len(),
                if prev.is_empty() { "" } else { " and the earlier phases' messages" },
                rows,
            );
            (picks, steps, kept.len(), how)
        };
        drop(s);
        if picks.is_empty() {
            bail!(
                "offline designer: phase {phase} has nothing to send: no candidate feature that fits its {per_block} value columns per sender block explains any of its {} target dims beyond what the receivers already know ({})",
                targets.dims.len(),
                steps.join("; ")
            );
        }
        let fields = fields_from(&picks, &cands, env);
        let names = ctx.schema.state_meanings();
        let target_text: Vec<String> = targets.dims.iter().take(8).map(|&d| meta::dim_label(d, &names)).map(|l| short(&l)).collect();
        let goal = match phase {
            0 => "initialization",
            1 => "recognition enhancement",
            _ => "sharing enhancement",
        };
        let field_text: Vec<String> = fields.iter().map(|f| format!("'{}': {}", f.name, f.description)).collect();
        let instruction = format!(
            "offline designer: phase {phase} ({goal}), chosen {} on the dataset, not by an LLM. {} Each agent sends: {}. {how} Each sender's values reach a receiver after the sender's one-hot id (once per sender in the compact layout).",
            chosen_by.0,
            targets.why,
            field_text.join("; "),
        );
        let mut crit: Vec<usize> = critical.to_vec();
        crit.sort_unstable();
        crit.dedup();
        let p = Protocol {
            name: Some(format!("offline_phase{phase}")),
            phase: Some(phase as u32),
            message_design_instruction: instruction,
            critical_state_dims: crit.iter().map(|&d| DimSpec::Dim(d)).collect(),
            critical_state_reasoning: Some(format!("offline designer: {} Targets (first 8): {}.", targets.why, target_text.join("; "))),
            sender_one_hot: true,
            history_padding: HistoryPadding::default(),
            layout: MessageLayout::default(),
            fields,
            env: None,
            schema_fingerprint: None,
        };
        let validated = protocol::validate_phase(&p, env, &prev)
            .map_err(|e| anyhow!("offline designer: its phase {phase} protocol is invalid (a bug): {}", protocol::errors_to_text(&e)))?;
        let reasoning = format!(
            "# Offline designer, phase {phase} ({goal})\n\nThis protocol was built by a deterministic algorithm ({}), not by a language model.\n\n## Targets\n{}\n\n{}\n\n## Budget\n{left} message columns left of {}; this phase's share is {share} ({phases_left} phase(s) left), i.e. {per_block} value columns per sender block after the {n}-column sender one-hot.\n\n## Candidates\n{} candidate features ({}), {} kept by the marginal-correlation prescreen, {} sampled steps.\n\n## Selection\n{}\n\nResulting width: {} columns per receiving agent.\n",
            chosen_by.1,
            targets.dims.iter().map(|&d| format!("- {}", meta::dim_label(d, &names))).collect::<Vec<_>>().join("\n"),
            targets.why,
            env.message_budget,
            cands.len(),
            kinds.iter().map(|k| k.words().0).collect::<Vec<_>>().join(", "),
            kept_count,
            rows,
            steps.iter().map(|l| format!("- {l}")).collect::<Vec<_>>().join("\n"),
            validated.width,
        );
        self.log(
            phase,
            "protocol",
            format!(
                "offline designer: select features for phase {phase} ({goal}); targets {:?}; {per_block} value columns per sender block",
                targets.dims
            ),
            serde_json::to_string_pretty(&p)?,
        );
        Ok(PhaseProtocol { protocol: p, validated, reasoning })
    }
}

/// Whether agent `j`'s o[d] takes more than one value on B (a value constant for the sender
/// would be a dead message field).
fn varies_for(data: &lmac_run::dataset::Dataset, j: usize, d: usize) -> bool {
    let (n, od) = (data.header.n_agents, data.header.obs_dim);
    let mut first = None;
    data.episodes.iter().flat_map(|ep| (0..ep.len).map(move |t| ep.obs[(t * n + j) * od + d])).any(|v| *first.get_or_insert(v) != v)
}

/// An entity's name: what its values' meanings share at the start, up to the labels ("enemy 0
/// (Roach) as seen by this agent"), or its one value's meaning.
fn entity_name(meanings: &[String]) -> String {
    let Some(first) = meanings.first() else { return "unnamed".into() };
    let mut len = first.len();
    for m in &meanings[1..] {
        len = first
            .char_indices()
            .zip(m.chars())
            .take_while(|((_, a), b)| a == b)
            .map(|((i, a), _)| i + a.len_utf8())
            .last()
            .unwrap_or(0)
            .min(len);
    }
    // Up to the last ": " of the shared start (the labels follow it), else all of it.
    let shared = &first[..len];
    let name = shared.rfind(": ").map_or(shared, |i| &shared[..i]).trim_end_matches(|c: char| c.is_whitespace() || c == ',' || c == '(');
    if name.is_empty() || meanings.len() == 1 {
        first.clone()
    } else {
        name.to_string()
    }
}

impl OfflineDesigner {
    /// [`FieldsBy::ObservationRelevance`]: phase 0's picks (one sender per value, to every other
    /// agent), the selection's log and the sentence saying how they were chosen; None (said in
    /// the log and the transcript) when the value model explains too little of the return or
    /// no observation value is relevant, and least squares chooses instead.
    #[allow(clippy::type_complexity)]
    fn fields_by_observation_relevance(
        &mut self,
        ctx: &DesignContext,
        cands: &[Candidate],
        per_block: usize,
        critical: &[usize],
    ) -> Result<Option<(Vec<Pick>, Vec<String>, String)>> {
        let data = ctx.dataset.context("offline designer: ranking observation values by relevance needs the dataset B")?;
        let (n, od) = (data.header.n_agents, data.header.obs_dim);
        let entities = ctx.schema.obs_entities();
        let rel = super::relevance::measure_joint_observation(data, &self.cfg.relevance, ctx.seed ^ 0x0B5E_0000_0000_0001)
            .context("offline designer: measuring each agent's observation values' relevance to the return")?;
        let obs_cand = |d: usize| cands.iter().position(|c| c.kind == Kind::Obs && c.dim == Some(d));
        let label = |col: usize| {
            let (j, d) = (col / od, col % od);
            format!("agent {j}'s o[{d}] ({})", ctx.env.obs_names.get(d).map(|s| short(s)).unwrap_or_else(|| "unnamed".into()))
        };
        let mut per_sender = vec![0usize; n];
        let mut picks: Vec<Pick> = Vec::new();
        let mut lines = Vec::new();
        let usable = rel.held_out_r2 >= self.cfg.min_value_r2;
        // The senders, by `--senders-by`: `recovery`, the agents whose whole observation, sent
        // to the others, makes the critical dims most recoverable (a discriminator trained per
        // candidate sender: what an agent sees counts in whatever frame it sees it, where least
        // squares on the state's frame cannot use an offset), their values ranked by the joint
        // observation's value model; `return`, the agents whose whole observation most helps
        // the others predict the team's return, their values ranked by what that receivers'
        // model uses of them (importance per sender and observation dim).
        let mut value_importance: Option<Vec<Vec<f64>>> = None;
        // Per sender and entity (SendersBy::Return only).
        let mut entity_importance: Vec<Vec<f64>> = Vec::new();
        // Per agent, its whole view sent to the others (SendersBy::Recovery only; the check
        // below reuses it).
        let mut whole_views: Option<Vec<Probe>> = None;
        let (gains, gain_text): (Vec<f64>, Vec<String>) = match self.cfg.senders_by {
            SendersBy::Recovery => {
                let probes = self.whole_view_probes(ctx, critical)?;
                let g: Vec<f64> = probes.iter().map(|p| p.gain).collect();
                whole_views = Some(probes);
                let text = g
                    .iter()
                    .map(|x| format!("all it sees, sent to the others, raises their recovery of the critical dims by {x:+.3}"))
                    .collect();
                (g, text)
            }
            SendersBy::Return => {
                let g = super::relevance::receiver_return_gains(data, &entities, &self.cfg.relevance, ctx.seed ^ 0x0B5E_0000_0000_0002)
                    .context("offline designer: measuring what each agent's observation adds to the others' prediction of the return")?;
                let text = g
                    .iter()
                    .map(|x| {
                        format!(
                            "all it sees, beside another agent's own observation, raises a value model's held-out R^2 of the return by {:+.3} ({:.3} -> {:.3})",
                            x.gain(),
                            x.r2_without,
                            x.r2_with
                        )
                    })
                    .collect();
                value_importance = Some(g.iter().map(|x| x.sender_importance.clone()).collect());
                entity_importance = g.iter().map(|x| x.entity_importance.clone()).collect();
                (g.iter().map(|x| x.gain()).collect(), text)
            }
        };
        // Importance of column j * od + d (agent j's o[d]) by the measure in use.
        let importance = |col: usize| match &value_importance {
            Some(v) => v[col / od][col % od],
            None => rel.importance[col],
        };
        let rank_of = |col: usize| {
            let x = importance(col);
            1 + (0..n * od).filter(|&c| importance(c) > x || (importance(c) == x && c < col)).count()
        };
        let mut agents: Vec<usize> = (0..n).collect();
        agents.sort_by(|&a, &b| gains[b].total_cmp(&gains[a]).then(a.cmp(&b)));
        let senders: Vec<usize> = agents.iter().copied().filter(|&j| gains[j] > 0.0).take(self.cfg.relevant_senders.max(1)).collect();
        let mut agent_lines: Vec<String> = agents
            .iter()
            .map(|&j| {
                let verdict = if senders.contains(&j) { "a SENDER".to_string() } else { "not a sender".to_string() };
                format!("agent {j}: {}; relevance of all it sees to the return {:.4}; {verdict}", gain_text[j], rel.groups[j])
            })
            .collect();
        lines.append(&mut agent_lines);
        // Can the discriminator see a message here at all? The most one agent can send is all it
        // sees; when the receivers recover the critical dims with it no better than a constant
        // guess, every entity's probe below would measure noise, and a compact pick would follow
        // the cost per value rather than the task. Then every agent sends its whole view.
        let mut blind: Option<String> = None;
        if self.cfg.whole_view_when_blind && self.cfg.values_by == ValuesBy::Recovery {
            let best = agents[0];
            let whole = match &whole_views {
                Some(probes) => probes[best],
                None => self.probe_gains(ctx, critical, &[(best, (0..od).collect())])?[0],
            };
            let guess = self.guess_rate(critical)?;
            let measured = format!(
                "with all agent {best} sees (the agent ranked first as a sender), the others recover the critical dims at {:.3} ({:+.4} over no messages) against {guess:.3} for a constant guess of each dim",
                whole.recovery, whole.gain
            );
            if whole.recovery <= guess {
                blind = Some(measured);
            } else {
                lines.push(format!("the discriminator can read a message here: {measured}; the entities are ranked"));
            }
        }
        // Entities ranked and shown: every probe's with `recovery` (each cost a discriminator).
        let shown_entities = if self.cfg.values_by == ValuesBy::Recovery { 12 } else { 8 };
        if let Some(measured) = &blind {
            // FullComm's message, each agent's block cut to what the whole budget gives one
            // sender (its values the return's model uses most kept first).
            let block = (ctx.env.message_budget / (n - 1)).saturating_sub(n);
            lines.push(format!(
                "the discriminator cannot read a message here: {measured}, so its gains per entity would be noise; every agent sends all of its view that varies on B, to every other agent"
            ));
            for &j in &agents {
                let mut varying: Vec<usize> = (0..od).filter(|&d| varies_for(data, j, d) && obs_cand(d).is_some()).collect();
                let cut = varying.len().saturating_sub(block);
                varying.sort_by(|&a, &b| importance(j * od + b).total_cmp(&importance(j * od + a)).then(a.cmp(&b)));
                varying.truncate(block);
                varying.sort_unstable();
                for &d in &varying {
                    let cand = obs_cand(d).context("offline designer: a varying value has no candidate (a bug)")?;
                    per_sender[j] += 1;
                    picks.push(Pick { cand, links: to_everyone_from(n, j), gain: importance(j * od + d) });
                }
                let left_out = if cut > 0 {
                    format!(" ({cut} least relevant left out: a sender's block holds {block} values)")
                } else {
                    String::new()
                };
                lines.push(format!(
                    "agent {j}: CHOSEN: o[{}] sent to every other agent{left_out}",
                    varying.iter().map(|d| d.to_string()).collect::<Vec<_>>().join(", ")
                ));
            }
        } else if self.cfg.values_by != ValuesBy::Value {
            // The senders' entities, best first: by `entity`, the costliest to shuffle in the
            // receivers' value model; by `recovery`, the most added to the receivers' recovery
            // of the critical dims per value sent. Each sends every value of it that varies for
            // its sender on B, whole, while the budget has room for it (the first entity chosen
            // fills what room there is with its most relevant values).
            let meanings = &ctx.env.obs_names;
            // varying_by[j][k]: the values of entity k that vary for sender j on B (each a scan of B,
            // so once per sender).
            let mut varying_by: Vec<Vec<Vec<usize>>> = vec![Vec::new(); n];
            for &j in &senders {
                varying_by[j] =
                    entities.iter().map(|e| e.clone().filter(|&d| varies_for(data, j, d) && obs_cand(d).is_some()).collect()).collect();
            }
            let by_recovery = self.cfg.values_by == ValuesBy::Recovery;
            // score[j][k] and what it measured, per sender j (others stay empty).
            let mut score = vec![Vec::new(); n];
            let mut score_text = vec![Vec::new(); n];
            // probe_gain[j][k]: with `recovery`, what entity k of sender j adds in all.
            let mut probe_gain = vec![Vec::new(); n];
            for &j in &senders {
                if by_recovery {
                    let probes: Vec<(usize, Vec<usize>)> = varying_by[j].iter().map(|v| (j, v.clone())).collect();
                    probe_gain[j] = self.probe_gains(ctx, critical, &probes)?.into_iter().map(|p| p.gain).collect();
                    for (g, (_, sent)) in probe_gain[j].iter().zip(&probes) {
                        let per_value = if sent.is_empty() { 0.0 } else { g / sent.len() as f64 };
                        score[j].push(per_value);
                        score_text[j].push(format!(
                            "sent alone to the others, it raises their recovery of the critical dims by {g:+.4} ({per_value:+.4} per value sent)"
                        ));
                    }
                } else {
                    for k in 0..entities.len() {
                        let imp = entity_importance[j][k];
                        score[j].push(imp);
                        let e = entities[k].clone();
                        score_text[j].push(format!(
                            "relevance {imp:.4} (its values one by one: {})",
                            e.map(|d| format!("{:.3}", importance(j * od + d))).collect::<Vec<_>>().join(", ")
                        ));
                    }
                }
            }
            let mut ranked: Vec<(usize, usize)> = senders.iter().flat_map(|&j| (0..entities.len()).map(move |k| (j, k))).collect();
            ranked.sort_by(|&(a, x), &(b, y)| score[b][y].total_cmp(&score[a][x]).then((a, x).cmp(&(b, y))));
            if by_recovery {
                let budget = self.cfg.max_relevant_values;
                let useful: Vec<(usize, usize)> =
                    ranked.iter().copied().filter(|&(j, k)| score[j][k] > 0.0 && !varying_by[j][k].is_empty()).collect();
                let items: Vec<(f64, usize)> = useful.iter().map(|&(j, k)| (probe_gain[j][k], varying_by[j][k].len())).collect();
                if let Some((i, greedy)) = worth_more_alone(&items, budget) {
                    let best = useful[i];
                    ranked.retain(|p| *p != best);
                    ranked.insert(0, best);
                    score_text[best.0][best.1].push_str(&format!(
                        "; first: alone it adds more ({:+.4}) than the entities that fit the {budget} values by gain per value together ({greedy:+.4})",
                        items[i].0
                    ));
                }
            }
            for &(j, k) in ranked.iter().take(shown_entities) {
                let e = entities[k].clone();
                let x = score[j][k];
                let mut varying = varying_by[j][k].clone();
                let room = self.cfg.max_relevant_values.saturating_sub(picks.len()).min(per_block.saturating_sub(per_sender[j]));
                let verdict = if !usable && !by_recovery {
                    "not chosen: the value model explains too little".to_string()
                } else if by_recovery && x <= 0.0 {
                    "not chosen: it adds nothing to the receivers' recovery".to_string()
                } else if !by_recovery && x < self.cfg.min_relevance {
                    format!("not chosen: shuffling it costs less than {}", self.cfg.min_relevance)
                } else if varying.is_empty() {
                    format!("not chosen: none of its values varies for agent {j} on B")
                } else if room == 0 {
                    format!("not chosen: the {} values kept are chosen", picks.len())
                } else if varying.len() > room && !picks.is_empty() {
                    format!("not chosen: its {} varying values do not fit the {room} left", varying.len())
                } else {
                    varying.sort_by(|&a, &b| importance(j * od + b).total_cmp(&importance(j * od + a)).then(a.cmp(&b)));
                    varying.truncate(room);
                    varying.sort_unstable();
                    if self.sent_entity.is_none() {
                        let name = short(&entity_name(meanings.get(e.clone()).unwrap_or(&[])));
                        self.sent_entity = Some(SentEntity { sender: j, values: varying.clone(), name });
                    }
                    for &d in &varying {
                        let cand = obs_cand(d).context("offline designer: a varying value has no candidate (a bug)")?;
                        per_sender[j] += 1;
                        picks.push(Pick {
                            cand,
                            links: to_everyone_from(n, j),
                            gain: if by_recovery { x } else { importance(j * od + d) },
                        });
                    }
                    format!(
                        "CHOSEN: o[{}] sent by this agent to every other agent",
                        varying.iter().map(|d| d.to_string()).collect::<Vec<_>>().join(", ")
                    )
                };
                lines.push(format!(
                    "agent {j}'s {} (o[{}..{}]): {}; {verdict}",
                    short(&entity_name(meanings.get(e.clone()).unwrap_or(&[]))),
                    e.start,
                    e.end,
                    score_text[j][k]
                ));
            }
        } else {
            let mut ranked: Vec<usize> = (0..n * od).filter(|c| senders.contains(&(c / od))).collect();
            ranked.sort_by(|&a, &b| importance(b).total_cmp(&importance(a)).then(a.cmp(&b)));
            for col in ranked.into_iter().take(3 * self.cfg.max_relevant_values) {
                let (j, d) = (col / od, col % od);
                let imp = importance(col);
                let verdict = if !usable {
                    "not chosen: the value model explains too little".to_string()
                } else if picks.len() >= self.cfg.max_relevant_values {
                    format!("not chosen: beyond the {} values kept", self.cfg.max_relevant_values)
                } else if imp <= 0.0 {
                    "not chosen: shuffling it costs nothing".to_string()
                } else if per_sender[j] >= per_block {
                    format!("not chosen: agent {j}'s block is full ({per_block} values)")
                } else if let Some(k) = obs_cand(d) {
                    per_sender[j] += 1;
                    picks.push(Pick { cand: k, links: to_everyone_from(n, j), gain: imp });
                    "CHOSEN: sent by this agent to every other agent".into()
                } else {
                    "not chosen: constant on the dataset".into()
                };
                lines.push(format!("{}. {}: relevance {imp:.4}; {verdict}", rank_of(col), label(col)));
            }
        }
        let head = format!(
            "A value model of the team's joint observation (every agent's observation side by side; {} predicting the return-to-go, gamma {}) explains {:.1}% of the held-out return's variance ({} training, {} held-out episodes of B); an observation value's relevance is the share of that variance lost when it is shuffled across {} held-out steps, an agent's when all it sees is shuffled at once.{} The senders are the {} agent(s) whose whole observation {}.",
            rel.model.describe(),
            rel.gamma,
            100.0 * rel.held_out_r2,
            rel.train_episodes,
            rel.held_out_episodes,
            rel.eval_rows,
            rel.model_choice(),
            senders.len(),
            match self.cfg.senders_by {
                SendersBy::Recovery => "sent to the others most raises their recovery of the critical dims; each sends its values most relevant to the joint observation's value model",
                SendersBy::Return => "most helps the others predict the team's return (a value model on a receiver's observation with and without it); each sends the values of its view that model uses most (their relevance below is in that model)",
            }
        );
        self.log(
            0,
            "observation_relevance",
            "offline designer: fit a value model of the joint observation on B and rank every agent's observation values by permutation importance".into(),
            format!("{head}\nMost relevant observation values:\n{}", lines.join("\n")),
        );
        eprintln!("lmac: offline designer: {head}");
        for line in lines.iter().take(n + 9) {
            eprintln!("lmac:   {line}");
        }
        if picks.is_empty() {
            let reason = if usable && senders.is_empty() {
                match self.cfg.senders_by {
                    SendersBy::Recovery => {
                        "no agent's observation, sent to the others, raises their recovery of the critical dims".to_string()
                    }
                    SendersBy::Return => "no agent's observation helps the others predict the return".to_string(),
                }
            } else if self.cfg.values_by == ValuesBy::Recovery {
                "no entity of the senders' view, sent alone, adds to the others' recovery of the critical dims".to_string()
            } else if usable {
                "no value of the senders' observation costs the value model anything when shuffled".to_string()
            } else {
                format!("the value model explains less than {:.1}%", 100.0 * self.cfg.min_value_r2)
            };
            eprintln!("lmac: offline designer: phase 0's fields by least squares instead: {reason}");
            self.log(0, "fields_by", "offline designer: choose phase 0's fields".into(), format!("By least squares instead: {reason}."));
            return Ok(None);
        }
        let total: f64 = picks.iter().map(|p| p.gain).sum();
        let how = match (&blind, self.cfg.values_by) {
            (Some(measured), _) => format!(
                "{head} Phase 0 sends every agent's whole view ({} values in all, each from the agent that sees it to every other agent): a discriminator could not read even the best sender's whole view ({measured}), so no finer choice could be measured on this map.",
                picks.len()
            ),
            (None, ValuesBy::Value) => format!(
                "{head} Phase 0 sends the {} most relevant values of agent(s) {} (relevance {total:.3} summed), each from the agent that sees it to every other agent.",
                picks.len(),
                senders.iter().map(|j| j.to_string()).collect::<Vec<_>>().join(", ")
            ),
            (None, ValuesBy::Entity) => format!(
                "{head} Phase 0 sends whole entities (the schema's units and objects as the sender sees them), the one whose values shuffled together cost that model most first: {} value(s) of agent(s) {}, from the agent that sees them to every other agent.",
                picks.len(),
                senders.iter().map(|j| j.to_string()).collect::<Vec<_>>().join(", ")
            ),
            (None, ValuesBy::Recovery) => format!(
                "{head} Phase 0 sends whole entities (the schema's units and objects as the sender sees them), the one that, sent alone to the others, most raises their recovery of the critical dims per value sent first (a discriminator trained per sender and entity on B, measured on held-out episodes): {} value(s) of agent(s) {}, from the agent that sees them to every other agent.",
                picks.len(),
                senders.iter().map(|j| j.to_string()).collect::<Vec<_>>().join(", ")
            ),
        };
        let steps = lines.into_iter().take(n + picks.len().max(shown_entities)).collect();
        Ok(Some((picks, steps, how)))
    }

    /// Per agent j: how much sending all of j's observation to every other agent raises their
    /// recovery of `dims` ([`Self::probe_gains`] with one probe per agent).
    fn whole_view_probes(&self, ctx: &DesignContext, dims: &[usize]) -> Result<Vec<Probe>> {
        let od = ctx.env.obs_dim;
        let probes: Vec<(usize, Vec<usize>)> = (0..ctx.env.n_agents).map(|j| (j, (0..od).collect())).collect();
        self.probe_gains(ctx, dims, &probes)
    }

    /// Mean E_t[chi] of a constant guess of each of `dims` (phase 0's measurement).
    fn guess_rate(&self, dims: &[usize]) -> Result<f64> {
        let without = self.without.as_ref().context("offline designer: phase 0's recovery without messages is not measured yet")?;
        let rates = dims
            .iter()
            .map(|&d| without.position(d).and_then(|k| self.guess.get(k).copied()))
            .collect::<Option<Vec<f64>>>()
            .context("offline designer: a critical dim has no constant-guess rate (a bug)")?;
        Ok(meta::mean(&rates))
    }

    /// Per probe (j, values): how much agent j sending its o[values] to every other agent
    /// raises their recovery of `dims` (mean E_t[chi] over the dims and the receivers, with
    /// against without messages; a discriminator trained per probe on B's training episodes,
    /// measured on the held-out ones; "without" is phase 0's own measurement), and the
    /// receivers' recovery with the probe. 0 for a probe with no values.
    fn probe_gains(&self, ctx: &DesignContext, dims: &[usize], probes: &[(usize, Vec<usize>)]) -> Result<Vec<Probe>> {
        let env = ctx.env;
        let n = env.n_agents;
        let disc = &self.cfg.discriminator;
        let without = self.without.as_ref().context("offline designer: phase 0's recovery without messages is not measured yet")?;
        let mut gains = Vec::with_capacity(probes.len());
        for (j, values) in probes.iter().map(|(j, v)| (*j, v)) {
            if values.is_empty() {
                gains.push(Probe { gain: 0.0, recovery: 0.0 });
                continue;
            }
            let what = if values.len() == env.obs_dim {
                "its whole observation".to_string()
            } else {
                format!("its o[{}]", values.iter().map(|d| d.to_string()).collect::<Vec<_>>().join(", "))
            };
            let p = Protocol {
                name: Some(format!("offline_probe_{j}")),
                phase: Some(0),
                message_design_instruction: format!("probe: agent {j} sends {what}"),
                critical_state_dims: dims.iter().map(|&d| DimSpec::Dim(d)).collect(),
                critical_state_reasoning: None,
                sender_one_hot: true,
                history_padding: HistoryPadding::default(),
                layout: MessageLayout::default(),
                fields: vec![Field {
                    name: "probe".into(),
                    description: "probe".into(),
                    senders: Senders::List(vec![j]),
                    receivers: Receivers::Peer(vec![PeerLink { from: j, to: (0..n).filter(|&i| i != j).collect() }]),
                    value: Expr::Obs(values.clone()),
                }],
                env: None,
                schema_fingerprint: None,
            };
            let v = protocol::validate_phase(&p, env, &[])
                .map_err(|e| anyhow!("offline designer: its probe is invalid (a bug): {}", protocol::errors_to_text(&e)))?;
            let with = meta::recovery_with(ctx, &[v], disc, dims)
                .with_context(|| format!("offline designer: recovery with agent {j} sending {what}"))?;
            let (mut sum, mut recovered) = (0.0, 0.0);
            for (k, &d) in dims.iter().enumerate() {
                let kw = without.position(d).with_context(|| format!("offline designer: s[{d}] has no recovery without messages"))?;
                for i in (0..n).filter(|&i| i != j) {
                    sum += with.rate(k, i) - without.rate(kw, i);
                    recovered += with.rate(k, i);
                }
            }
            let cells = (dims.len() * (n - 1)).max(1) as f64;
            let gain = sum / cells;
            gains.push(Probe { gain, recovery: recovered / cells });
            eprintln!("lmac: offline designer: agent {j} sending {what} to the others: recovery of the critical dims {gain:+.4}");
        }
        Ok(gains)
    }

    /// [`CriticalBy::Relevance`]: the dims that are relevant to the return and poorly recovered
    /// without messages, most relevant x worst recovered first, with the reason (Err: why the
    /// ranking cannot be used). `all` is (dim, skill without messages, per-agent failures).
    /// The ranking with the reason for each of its top dims goes to the transcript and the log.
    fn by_relevance(
        &mut self,
        ctx: &DesignContext,
        rel: &super::relevance::Relevance,
        by: CriticalBy,
        all: &[(usize, f64, Vec<f64>)],
    ) -> std::result::Result<(Vec<usize>, String), String> {
        let (thr, min_rel) = (self.cfg.poor_threshold, self.cfg.min_relevance);
        let names = ctx.schema.state_meanings();
        let skill_of = |d: usize| all.iter().find(|x| x.0 == d).map(|x| x.1);
        let priority = |d: usize| rel.importance[d] * (1.0 - skill_of(d).unwrap_or(1.0).clamp(0.0, 1.0));
        let mut chosen: Vec<usize> = all.iter().filter(|x| rel.importance[x.0] >= min_rel && x.1 < thr).map(|x| x.0).collect();
        chosen.sort_by(|&a, &b| priority(b).total_cmp(&priority(a)).then(a.cmp(&b)));
        chosen.truncate(self.cfg.max_relevant_dims);
        let relevant = rel.importance.iter().filter(|&&x| x >= min_rel).count();
        let head = if by == CriticalBy::Action {
            format!(
                "A linear model of each agent's action (one-hot) on the state, fitted at the steps where the agent observes anything, explains {:.1}% of the held-out actions' variance on average over the agents ({} training, {} held-out episodes of B); a dim's relevance is the expected share of that variance lost when the dim is shuffled ({} held-out agent-steps), averaged over the agents. {relevant} dim(s) have a relevance of at least {min_rel}.",
                100.0 * rel.held_out_r2,
                rel.train_episodes,
                rel.held_out_episodes,
                rel.eval_rows
            )
        } else {
            format!(
                "A value model of the state ({} predicting the return-to-go, gamma {}) explains {:.1}% of the held-out return's variance ({} training, {} held-out episodes of B); a dim's relevance is the share of that variance lost when the dim is shuffled across {} held-out steps.{} {relevant} dim(s) have a relevance of at least {min_rel}.",
                rel.model.describe(),
                rel.gamma,
                100.0 * rel.held_out_r2,
                rel.train_episodes,
                rel.held_out_episodes,
                rel.eval_rows,
                rel.model_choice()
            )
        };
        let ranking: Vec<String> = rel
            .ranking()
            .into_iter()
            .take(15)
            .map(|d| {
                let verdict = match skill_of(d) {
                    None => "not chosen: constant on B".to_string(),
                    Some(_) if chosen.contains(&d) => "CHOSEN: relevant and poorly recovered without messages".into(),
                    Some(_) if rel.importance[d] < min_rel => format!("not chosen: relevance below {min_rel}"),
                    Some(k) if k >= thr => format!("not chosen: agents recover it without messages (skill {k:.2} >= {thr})"),
                    Some(_) => format!("not chosen: beyond the {} dims kept", self.cfg.max_relevant_dims),
                };
                format!(
                    "{}. {}: relevance {:.4}, skill without messages {}; {verdict}",
                    rel.rank_of(d),
                    meta::dim_label(d, &names),
                    rel.importance[d],
                    skill_of(d).map_or("-".into(), |k| format!("{k:.2}"))
                )
            })
            .collect();
        self.log(
            0,
            "relevance",
            "offline designer: fit a value model of the state on B and rank every state dim by its permutation importance".into(),
            format!("{head}\nMost relevant dims:\n{}", ranking.join("\n")),
        );
        eprintln!("lmac: offline designer: {head}");
        for line in ranking.iter().take(8) {
            eprintln!("lmac:   {line}");
        }
        let floor = if by == CriticalBy::Action { self.cfg.min_action_r2 } else { self.cfg.min_value_r2 };
        if rel.held_out_r2 < floor {
            return Err(format!(
                "The model explains only {:.1}% of the held-out {} variance (below {:.1}%), too little to rank dims by.",
                100.0 * rel.held_out_r2,
                if by == CriticalBy::Action { "actions'" } else { "return's" },
                100.0 * floor
            ));
        }
        if chosen.is_empty() {
            return Err(format!(
                "No dim is both relevant (at least {min_rel}) and poorly recovered without messages (skill below {thr}): agents already see what the return depends on."
            ));
        }
        let why = format!(
            "{head} The task-critical dims are the {} that are relevant and recovered with a skill below {thr} over a constant guess without messages, ordered by relevance x (1 - skill); each receiver's weight on a dim is its failure rate relative to the guess's times the dim's relevance.",
            chosen.len()
        );
        Ok((chosen, why))
    }
}

/// Targets from the worst entries of `scored` (dim, score, per-agent weights), ascending score.
fn worst(mut scored: Vec<(usize, f64, Vec<f64>)>, max: usize) -> (Vec<usize>, Vec<Vec<f64>>) {
    scored.sort_by(|a, b| a.1.partial_cmp(&b.1).unwrap_or(std::cmp::Ordering::Equal).then(a.0.cmp(&b.0)));
    scored.truncate(max);
    let n = scored.first().map(|s| s.2.len()).unwrap_or(0);
    let dims = scored.iter().map(|s| s.0).collect();
    let weights = (0..n).map(|i| scored.iter().map(|s| s.2[i]).collect()).collect();
    (dims, weights)
}

impl Designer for OfflineDesigner {
    fn name(&self) -> String {
        "offline".into()
    }

    fn needs_data_for_initial(&self) -> bool {
        true
    }

    fn initial(&mut self, ctx: &DesignContext) -> Result<PhaseProtocol> {
        self.cfg.check()?;
        self.sent_entity = None;
        let m = meta::measure(ctx, &[], &self.cfg.discriminator, &[]).context("offline designer: measuring recovery without messages")?;
        let r: &Recovery = &m.without;
        let n = r.n_agents;
        let thr = self.cfg.poor_threshold;
        let g = &m.guess;
        // Constant dims (the guess is always right) can never be critical.
        let all: Vec<(usize, f64, Vec<f64>)> = (0..r.dims.len())
            .filter(|&k| g[k] < 1.0 - 1e-9)
            .map(|k| (r.dims[k], meta::skill(r.mean_rate(k), g[k]), r.rates(k).iter().map(|&x| failure(x, g[k])).collect()))
            .collect();
        if all.is_empty() {
            bail!("offline designer: every state dim is constant on the dataset, so there is nothing for messages to recover");
        }
        let poor: Vec<_> = all.iter().filter(|x| x.1 < thr).cloned().collect();
        let max_critical = self.cfg.max_critical_dims;
        let by_recovery = || -> (Vec<usize>, String) {
            if poor.is_empty() {
                let (d, _) = worst(all.clone(), 8.min(all.len()));
                (d, format!("Without messages every varying state dim is recovered with a skill of at least {thr} over a constant guess (E_t[chi], alpha {}), so the 8 least recovered are targeted.", ctx.schema.alpha))
            } else {
                let (d, _) = worst(poor.clone(), max_critical);
                let why = format!(
                    "Without messages, {} of {} varying state dims are recovered with a skill below {thr} (mean E_t[chi] over agents on held-out steps, alpha {}, relative to always guessing the dim's median: 0 = no better than the guess); the {} worst are taken as task-critical.",
                    poor.len(), all.len(), ctx.schema.alpha, d.len()
                );
                (d, why)
            }
        };
        // (dims, why, per-dim factor on the receivers' weights)
        let (critical, why, importance) = match self.cfg.critical_by {
            CriticalBy::Recovery => {
                let (d, why) = by_recovery();
                (d, why, None)
            }
            CriticalBy::Relevance | CriticalBy::Action => {
                let data = ctx.dataset.context("offline designer: ranking dims by relevance needs the dataset B")?;
                // By the policy's actions first when asked; when their models explain too
                // little of the policy, by the return; when that explains too little, by recovery.
                let mut fell_back = String::new();
                let mut by = self.cfg.critical_by;
                let (rel, choice) = loop {
                    let rel = if by == CriticalBy::Action {
                        super::relevance::measure_actions(data, &self.cfg.relevance, ctx.seed)
                            .context("offline designer: measuring what each agent's actions depend on")?
                    } else {
                        super::relevance::measure(data, &self.cfg.relevance, ctx.seed)
                            .context("offline designer: measuring each state dim's relevance to the return")?
                    };
                    match self.by_relevance(ctx, &rel, by, &all) {
                        Err(reason) if by == CriticalBy::Action => {
                            eprintln!("lmac: offline designer: ranking by the return instead: {reason}");
                            fell_back = format!("By the policy's actions: {reason} So the dims are ranked by the return instead. ");
                            by = CriticalBy::Relevance;
                        }
                        choice => break (rel, choice),
                    }
                };
                self.relevance = Some((rel.clone(), by));
                match choice {
                    Ok((d, why)) => (d, format!("{fell_back}{why}"), Some(rel.importance)),
                    Err(reason) => {
                        let (d, why) = by_recovery();
                        (d, format!("{fell_back}{reason} So phase 0 falls back to the hardest dims to recover: {why}"), None)
                    }
                }
            }
        };
        let pool: Vec<_> = all
            .iter()
            .filter(|x| critical.contains(&x.0))
            .map(|x| {
                let f = importance.as_ref().map_or(1.0, |imp| imp[x.0]);
                // Relevance mode ranks by relevance x failure; the weights carry both.
                let score = if importance.is_some() { -f * (1.0 - x.1.clamp(0.0, 1.0)) } else { x.1 };
                (x.0, score, x.2.iter().map(|w| w * f).collect::<Vec<f64>>())
            })
            .collect();
        let (dims, weights) = worst(pool, self.cfg.max_targets);
        debug_assert_eq!(weights.len(), n);
        let names = ctx.schema.state_meanings();
        let listing: Vec<String> = critical
            .iter()
            .map(|&d| {
                let k = r.position(d).unwrap_or(0);
                let rel = self.relevance.as_ref().map(|r| &r.0).filter(|_| importance.is_some());
                let rel = rel.map_or(String::new(), |x| format!("relevance {:.4} (rank {}), ", x.importance[d], x.rank_of(d)));
                format!(
                    "{} ({rel}mean E_t[chi] without messages {:.3}, constant guess {:.3})",
                    meta::dim_label(d, &names),
                    r.mean_rate(k),
                    g[k]
                )
            })
            .collect();
        self.log(
            0,
            "critical_dims",
            format!("offline designer: train the no-message discriminator on {} training episodes and measure E_t[chi] on {} held-out episodes for every state dim", m.without_report.train_episodes, m.held_out.len()),
            format!("{why}\n{}", listing.join("\n")),
        );
        self.without = Some(m.without);
        self.guess = m.guess;
        self.design(ctx, 0, &[], Targets { dims, weights, why }, &critical)
    }

    fn feedback(&mut self, ctx: &DesignContext, phase: usize, _previous: &[PhaseProtocol], meta_v: &MetaInfo) -> Result<Feedback> {
        let dims = meta_dims(meta_v)?;
        let names = ctx.schema.state_meanings();
        let (w, o) = (&meta_v.summary.with_communication, &meta_v.summary.without_communication);
        let (rw, ro, vw, vo) = (w.mean_recovery, o.mean_recovery, w.mean_variance_across_agents, o.mean_variance_across_agents);
        let mut by_rate: Vec<&MetaDim> = dims.iter().collect();
        by_rate.sort_by(|a, b| a.skill().partial_cmp(&b.skill()).unwrap_or(std::cmp::Ordering::Equal));
        let mut by_gain: Vec<&MetaDim> = dims.iter().collect();
        let gain = |d: &MetaDim| meta::mean(&d.rates) - meta::mean(&d.rates_without);
        by_gain.sort_by(|a, b| gain(b).partial_cmp(&gain(a)).unwrap_or(std::cmp::Ordering::Equal));
        let mut by_var: Vec<&MetaDim> = dims.iter().collect();
        by_var.sort_by(|a, b| b.variance.partial_cmp(&a.variance).unwrap_or(std::cmp::Ordering::Equal));
        let label = |d: usize| short(&meta::dim_label(d, &names));
        let worst3: Vec<String> = by_rate
            .iter()
            .take(3)
            .map(|d| {
                format!(
                    "{} with {} / without {} (constant guess {:.2})",
                    label(d.dim),
                    fmt_rates(&d.rates),
                    fmt_rates(&d.rates_without),
                    d.guess
                )
            })
            .collect();
        let best3: Vec<String> =
            by_gain.iter().take(3).filter(|d| gain(d) > 0.0).map(|d| format!("{} (+{:.2})", label(d.dim), gain(d))).collect();
        let evaluation = format!(
            "offline designer: over {} target state dims (alpha {}), agents recover {:.3} of held-out steps with the messages against {:.3} without; the variance of recovery across agents is {:.4} with and {:.4} without. Largest gains from the messages: {}. Worst recovered with messages relative to a constant guess: {}.",
            dims.len(),
            meta_v.alpha,
            rw,
            ro,
            vw,
            vo,
            if best3.is_empty() { "none (the messages do not raise recovery of any target dim)".into() } else { best3.join("; ") },
            worst3.join("; ")
        );
        let thr = self.cfg.poor_threshold;
        let poor: Vec<&&MetaDim> = by_rate.iter().filter(|d| d.skill() < thr).collect();
        let lagging = |d: &MetaDim| -> String {
            let (i, r) = d.rates.iter().enumerate().fold((0, f64::MAX), |a, (i, &r)| if r < a.1 { (i, r) } else { a });
            format!("agent {i} at {r:.2}")
        };
        let missing = if phase <= 1 {
            if poor.is_empty() {
                format!("Every target dim is recovered with a skill of at least {thr} over a constant guess with the messages; what remains is mostly noise in the reconstruction.")
            } else {
                let list: Vec<String> = poor.iter().take(6).map(|d| format!("{} (worst: {})", label(d.dim), lagging(d))).collect();
                format!(
                    "{} target dims stay below a skill of {} over a constant guess with the messages: {}. The senders' current observation does not carry them; they are likely seen only at some steps (when in view) and need to be remembered, so history aggregates of the observation dims that predict them are missing.",
                    poor.len(),
                    thr,
                    list.join("; ")
                )
            }
        } else {
            let list: Vec<String> = by_var
                .iter()
                .take(6)
                .map(|d| {
                    format!(
                        "{} (variance {:.4}, largest in the {} third at {:.4}; {})",
                        label(d.dim),
                        d.variance,
                        d.worst_third.1,
                        d.worst_third.0,
                        lagging(d)
                    )
                })
                .collect();
            format!("Recovery is uneven across agents on: {}. The lagging agents depend on what their teammates saw earlier, which the current messages do not keep once it leaves the teammate's view.", list.join("; "))
        };
        let suggestions = if phase <= 1 {
            "1. Add, for the still poorly recovered dims, the sender features that best predict them beyond what receivers already know: window aggregates over the last 5 steps (max, mean, most recent non-zero), the previous step and short-term changes. 2. Send each only where it helps (peer to peer when only some senders observe the dim). 3. Keep the message compact: stop adding features once they explain little extra variance.".to_string()
        } else {
            "1. Add temporal cues over the last 10 steps (max, mean, most recent non-zero of the observation dims that predict the uneven dims, and the sender's action histogram) so agents that missed an event can still infer it. 2. Weight the choice towards the agents that lag on each dim. 3. Keep the sender one-hot so the receivers know whose history they read.".to_string()
        };
        let fb = Feedback { evaluation, missing_information_hypothesis: missing, improvement_suggestions: suggestions };
        self.log(
            phase,
            "feedback",
            format!("offline designer: feedback from the meta-information of phases 0..={}: {}", phase - 1, meta_v.summary_line()),
            serde_json::to_string_pretty(&fb)?,
        );
        Ok(fb)
    }

    fn refine(
        &mut self,
        ctx: &DesignContext,
        phase: usize,
        previous: &[PhaseProtocol],
        _feedback: &Feedback,
        meta_v: &MetaInfo,
    ) -> Result<PhaseProtocol> {
        if phase == 0 {
            bail!("offline designer: refine is for phases 1 and later (phase 0 is `initial`)");
        }
        let dims = meta_dims(meta_v)?;
        if dims.is_empty() {
            bail!("offline designer: the meta-information lists no target dims to improve");
        }
        let n = ctx.env.n_agents;
        if let Some(d) = dims.iter().find(|d| d.rates.len() != n) {
            bail!(
                "offline designer: the meta-information has {} agent rates for s[{}], the environment has {n} agents",
                d.rates.len(),
                d.dim
            );
        }
        let thr = self.cfg.poor_threshold;
        let targets = if phase == 1 {
            let scored: Vec<_> = dims.iter().map(|d| (d.dim, d.skill(), d.rates.iter().map(|&r| failure(r, d.guess)).collect())).collect();
            let poor = scored.iter().filter(|s| s.1 < thr).count();
            let (t, w) = worst(scored, self.cfg.max_targets);
            let why = if poor > 0 {
                format!("Recognition: {poor} target dim(s) are still recovered with a skill below {thr} over a constant guess (held-out steps) with the messages of the earlier phase(s); the {} worst are targeted, each receiver weighted by its failure rate relative to the guess's.", t.len())
            } else {
                format!("Recognition: every target dim is already recovered with a skill of at least {thr} over a constant guess; the {} least recovered are targeted for the remaining errors.", t.len())
            };
            Targets { dims: t, weights: w, why }
        } else {
            // Sharing: largest variance across agents first (score = -variance), weights put on
            // the agents behind the best one.
            let scored: Vec<_> = dims
                .iter()
                .map(|d| {
                    let best = d.rates.iter().cloned().fold(0f64, f64::max);
                    let weights =
                        d.rates.iter().map(|&r| (failure(r, d.guess) - failure(best, d.guess)) + 0.1 * failure(r, d.guess)).collect();
                    (d.dim, -d.variance.max(d.worst_third.0), weights)
                })
                .collect();
            let uneven = dims.iter().filter(|d| d.variance.max(d.worst_third.0) > 1e-4).count();
            let (t, w) = worst(scored, self.cfg.max_targets);
            let why = format!(
                "Sharing: {uneven} target dim(s) show a variance of recovery across agents above 1e-4 (overall or in one third of the episodes); the {} most uneven are targeted, each receiver weighted by its gap to the best agent plus a tenth of its failure rate, with temporal cues over the last 10 steps as candidates.",
                t.len()
            );
            Targets { dims: t, weights: w, why }
        };
        // The design loop said the newest phase added nothing: its columns did not pay, so this
        // phase asks twice the gain per column of every candidate.
        let mut targets = targets;
        if meta_v.newest_phase_added == Some(false) {
            self.gain_scale *= 2.0;
            targets.why.push_str(&format!(
                " Phase {} added nothing to the phases before it on the fixed dims, so this phase sends only candidates that explain at least {:.4} of the weighted target variance per column ({}x min_gain).",
                phase - 1,
                self.cfg.min_gain * self.gain_scale,
                self.gain_scale
            ));
        }
        let critical = targets.dims.clone();
        self.design(ctx, phase, previous, targets, &critical)
    }

    fn transcript(&self) -> Vec<TranscriptEntry> {
        self.transcript.clone()
    }

    fn settings(&self) -> Option<serde_json::Value> {
        serde_json::to_value(&self.cfg).ok()
    }

    fn measurements(&self) -> Option<serde_json::Value> {
        let (r, by) = self.relevance.as_ref()?;
        let ranking: Vec<serde_json::Value> = r
            .ranking()
            .into_iter()
            .take(30)
            .map(|d| serde_json::json!({ "dim": d, "rank": r.rank_of(d), "relevance": (r.importance[d] * 1e4).round() / 1e4 }))
            .collect();
        Some(serde_json::json!({
            "relevance": {
                "what": if *by == CriticalBy::Action {
                    "importance of each state dim for a linear model of each agent's action fitted on B: the expected share of the held-out actions' variance lost when the dim is shuffled, averaged over the agents"
                } else {
                    "permutation importance of each state dim for a value model of the return-to-go fitted on B: the share of the held-out return's variance lost when the dim is shuffled"
                },
                "held_out_r2": (r.held_out_r2 * 1e4).round() / 1e4,
                "model": r.model,
                "check_r2": r.check_r2.iter().map(|(k, v)| serde_json::json!({ "model": k, "r2": (v * 1e4).round() / 1e4 })).collect::<Vec<_>>(),
                "gamma": r.gamma,
                "train_episodes": r.train_episodes,
                "held_out_episodes": r.held_out_episodes,
                "eval_rows": r.eval_rows,
                "top": ranking,
                "importance": r.importance.iter().map(|x| (x * 1e4).round() / 1e4).collect::<Vec<f64>>(),
            }
        }))
    }
}

/// Gain per value is the greedy order of a knapsack, which can pass over one item worth more
/// than everything that order fits: on 1o_10b the Overseer's move feature (+0.33 of recovery
/// for 4 values) fills the 6 values before the Roach (+0.37 for 5). The usual guard: when one
/// item that fits alone gains more than the greedy selection in total, it goes first. `items`:
/// (total gain, values) in gain-per-value order. Returns (that item's index, the greedy total).
fn worth_more_alone(items: &[(f64, usize)], budget: usize) -> Option<(usize, f64)> {
    let (mut used, mut greedy) = (0, 0.0);
    for &(gain, size) in items {
        if used + size <= budget {
            used += size;
            greedy += gain;
        }
    }
    let best = (0..items.len()).filter(|&i| items[i].1 <= budget).max_by(|&a, &b| items[a].0.total_cmp(&items[b].0).then(b.cmp(&a)))?;
    (items[best].0 > greedy).then_some((best, greedy))
}

#[cfg(test)]
mod knapsack_tests {
    use super::worth_more_alone;

    /// The probes the designer measured on 1o_10b (the Overseer's move feature, the Roach, a
    /// Baneling's slot) and on LBF 8x8 (the partner's column, row and view rows).
    #[test]
    fn one_entity_worth_more_than_the_greedy_fill_goes_first() {
        let one_o_ten_b = [(0.3300, 4), (0.3667, 5), (0.0348, 6), (0.0308, 6)];
        assert_eq!(worth_more_alone(&one_o_ten_b, 6), Some((1, 0.33)));
        // With room for both, the greedy order takes both and stays.
        assert_eq!(worth_more_alone(&one_o_ten_b, 9), None);
        let lbf = [(0.0027, 1), (0.0026, 1), (0.0026, 2), (0.0025, 2), (0.0036, 3)];
        assert_eq!(worth_more_alone(&lbf, 6), None);
        // An item too big for the budget is never put first.
        assert_eq!(worth_more_alone(&[(0.1, 2), (0.5, 7)], 6), None);
        assert_eq!(worth_more_alone(&[], 6), None);
    }
}
