//! The offline designer's knobs: [`OfflineConfig`] and the strategy each phase chooses by.

use crate::discriminator::DiscriminatorConfig;
use anyhow::{bail, Result};
use serde::{Deserialize, Serialize};

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
    /// Whom the senders of [`FieldsBy::ObservationRelevance`] (phases 0 and 1) send to.
    pub receivers_by: ReceiversBy,
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
    pub relevance: crate::relevance::RelevanceConfig,
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
    /// even with the partner's whole view, and the design with both whole views trains LMAC
    /// above ranked picks and the authors' design (`docs/results/design.md`). False: rank the
    /// entities anyway (designs recorded without this setting parse as false).
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
    /// model of each agent's action leans on most ([`crate::relevance::measure_actions`]) x how
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
    /// value model's held-out R^2 of the team's return ([`crate::relevance::receiver_return_gains`]):
    /// what the others need of it for the task, whatever the state's dims.
    Return,
    /// By what it can supply of what the others need: for each other agent and critical dim,
    /// that agent's need times how much better this agent recovers the dim without messages
    /// than that agent does, summed. Needs the actions' models ([`CriticalBy::Action`]); by
    /// `return` where they were not used.
    Need,
}

/// Whom [`FieldsBy::ObservationRelevance`]'s senders send to.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ReceiversBy {
    /// Every other agent.
    Everyone,
    /// The agents that need the critical dims: those whose total need (their own actions'
    /// dependence on each critical dim times their failure to recover it without messages,
    /// summed over the dims) is at least a tenth of the neediest agent's. Needs the actions'
    /// models ([`CriticalBy::Action`]); every other agent where they were not used.
    Need,
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
option_from_str!(SendersBy, "recovery, return or need");
option_from_str!(ReceiversBy, "everyone or need");
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
            receivers_by: ReceiversBy::Everyone,
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
            bail!("offline designer: sending whole entities (--values-by entity) needs --senders-by return (the default is need): the entities are ranked in the receivers' value model of the return");
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
/// chosen by what it can supply of what the others need and sending only to the agents that
/// need it, whole entities of its view by what each adds to the others' recovery, and phase 1
/// placing each receiver in the sender's frame. On those two maps routing by need gives the
/// protocol that the sender by the return and every agent as receiver gave (the Overseer to the
/// ten Banelings; on LBF the dims are not ranked by the actions, so it falls back to those); on
/// a game where agents differ it sends only to the agents that act on the message. On 1o_10b its design trains LMAC as well as the authors' design and above
/// [`OfflineConfig::least_squares_rules`]; on LBF 8x8 the discriminator reads the grid worse
/// than a constant guess even with the partner's whole view, so every agent sends its whole
/// view ([`OfflineConfig::whole_view_when_blind`]), above the authors' design (the figures:
/// `docs/results/design.md`). Every rule falls
/// back, saying so, where the data cannot support it (no entities in the schema, an action
/// model that explains too little, a discriminator that cannot read a message).
impl Default for OfflineConfig {
    fn default() -> Self {
        OfflineConfig {
            fields_by: FieldsBy::ObservationRelevance,
            senders_by: SendersBy::Need,
            receivers_by: ReceiversBy::Need,
            values_by: ValuesBy::Recovery,
            phase1_by: Phase1By::Frame,
            critical_by: CriticalBy::Action,
            max_relevant_dims: 4,
            whole_view_when_blind: true,
            ..OfflineConfig::least_squares_rules()
        }
    }
}
