//! The protocol description language: plain serde types (the JSON an LLM writes), with a JSON
//! Schema generated from them (`schemars`). Doc comments here become the schema's descriptions,
//! so they are written for the reader of the schema (a person or an LLM).

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// A communication protocol for one design phase. Every agent (sender) computes, each step, the
/// value of every message field from its own observation history; every other agent (receiver)
/// gets those values appended to its observation.
///
/// Message layout received by agent i (`layout`, default `compact`): for every other agent j in
/// increasing order that sends i at least one field, one sender block = [one-hot of j (n_agents
/// columns, unless `sender_one_hot` is false) | the values of the fields j sends to i, in the
/// order of `fields`]; senders and fields that do not reach i take no columns. Every receiver's
/// message has the same width (the widest receiver's; the others end in zero padding). The final
/// protocol of several phases concatenates the phases' messages (phase 0 first).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Protocol {
    /// Short identifier (letters, digits, `_`, `-`), e.g. `lbf_8x8_phase0`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub name: Option<String>,
    /// Design phase: 0 initialization, 1 recognition enhancement, 2 sharing enhancement.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub phase: Option<u32>,
    /// The human-readable design description (what is shared, with whom, and why).
    pub message_design_instruction: String,
    /// The global-state dims the protocol intends to make recoverable (the task-critical state
    /// dims): indices in 0..state_dim, or ranges `{"start": a, "end": b}` (end exclusive).
    pub critical_state_dims: Vec<DimSpec>,
    /// Optional reasoning about why those state dims are task-critical.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub critical_state_reasoning: Option<String>,
    /// Whether each sender block starts with the sender's one-hot id (n_agents columns). Default
    /// true (the design principle: sender identity in every message).
    #[serde(default = "default_true")]
    pub sender_one_hot: bool,
    /// How window aggregates see the steps before the episode started. Default `minus_one`.
    #[serde(default)]
    pub history_padding: HistoryPadding,
    /// Column layout of the message. Default `compact` (columns only for what reaches each
    /// receiver); `sender_blocks` is the earlier fixed layout (kept to reproduce old results).
    #[serde(default, skip_serializing_if = "MessageLayout::is_compact")]
    pub layout: MessageLayout,
    /// The message fields, in column order. At least one.
    pub fields: Vec<Field>,
    /// The environment the protocol was designed for (`family:variant`), recorded by lmac when
    /// it saves a design (not part of what an LLM writes). Used on another environment, or after
    /// that environment's schema changed, the protocol still compiles when its indices fit, but
    /// `lmac train` and `lmac protocol check` warn.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(skip)]
    pub env: Option<String>,
    /// That environment's schema fingerprint when the protocol was saved.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(skip)]
    pub schema_fingerprint: Option<String>,
}

fn default_true() -> bool {
    true
}

/// A state dim index, or a half-open range of them.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(untagged, expecting = "a state dim index such as 12, or a range such as {\"start\": 0, \"end\": 100}")]
pub enum DimSpec {
    /// One dim.
    Dim(usize),
    /// Dims start..end (end exclusive).
    Range(Slice),
}

impl DimSpec {
    /// The dims this spec names.
    pub fn dims(&self) -> std::ops::Range<usize> {
        match *self {
            DimSpec::Dim(d) => d..d.saturating_add(1),
            DimSpec::Range(s) => s.start..s.end.max(s.start),
        }
    }
}

/// How a phase's fields are laid out in each receiver's message columns.
///
/// `compact` gives a receiver columns only for the (sender, field) pairs that reach it; each
/// sender that reaches it keeps its one-hot id once, in front of its values. The one-hot (not a
/// fixed column position per sender) carries the identity because the agents share one network:
/// in the compact layout a column's sender differs between receivers, so without the id the
/// shared network could not tell whose value it reads (the paper's principle: sender identity in
/// every message). Receivers reached by fewer senders end in zero padding up to the widest one.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum MessageLayout {
    /// For each sender that reaches the receiver (increasing index): [sender one-hot | the fields
    /// it sends to this receiver]; then zeros up to the widest receiver's width.
    #[default]
    Compact,
    /// Every receiver gets a block per other agent, [one-hot | every field], whether or not that
    /// agent sends it anything (unsent columns zero); width (n_agents - 1) x (n_agents + fields).
    SenderBlocks,
}

impl MessageLayout {
    pub fn is_compact(&self) -> bool {
        *self == MessageLayout::Compact
    }
}

/// Padding of the observation history before the first step of an episode.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum HistoryPadding {
    /// Steps before the episode hold observation -1 and last-action -1 in every column (as the
    /// paper's reference code pads its 10-step window); a window's expression is evaluated on them.
    #[default]
    MinusOne,
    /// Steps before the episode hold observation 0 and a zero last-action one-hot (index -1).
    Zero,
    /// Steps before the episode repeat the episode's first step.
    Repeat,
}

/// One named message field.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Field {
    /// Unique identifier of the field (letters, digits, `_`, `-`).
    pub name: String,
    /// What the value means, in plain words.
    pub description: String,
    /// Which agents send this field. Default `"all"`.
    #[serde(default)]
    pub senders: Senders,
    /// Which agents receive it from each sender. Default `"broadcast"`.
    #[serde(default)]
    pub receivers: Receivers,
    /// The value, computed by the sender from its own observation history.
    pub value: Expr,
}

/// The senders of a field: `"all"` (every agent, the default) or a list of agent indices such
/// as `[0, 2]`, each in 0..n_agents.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub enum Senders {
    #[default]
    All,
    List(Vec<usize>),
}

impl Serialize for Senders {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match self {
            Senders::All => s.serialize_str("all"),
            Senders::List(v) => v.serialize(s),
        }
    }
}

impl<'de> Deserialize<'de> for Senders {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        use serde::de;
        struct V;
        impl<'de> de::Visitor<'de> for V {
            type Value = Senders;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("\"all\" or a list of agent indices such as [0, 2]")
            }
            fn visit_str<E: de::Error>(self, v: &str) -> Result<Senders, E> {
                if v == "all" {
                    Ok(Senders::All)
                } else {
                    Err(E::invalid_value(de::Unexpected::Str(v), &self))
                }
            }
            fn visit_seq<A: de::SeqAccess<'de>>(self, mut seq: A) -> Result<Senders, A::Error> {
                let mut out = Vec::new();
                while let Some(x) = seq.next_element::<usize>()? {
                    out.push(x);
                }
                Ok(Senders::List(out))
            }
        }
        d.deserialize_any(V)
    }
}

impl JsonSchema for Senders {
    fn schema_name() -> std::borrow::Cow<'static, str> {
        "Senders".into()
    }
    fn json_schema(_g: &mut schemars::SchemaGenerator) -> schemars::Schema {
        schemars::json_schema!({
            "description": "The senders of a field: \"all\" (every agent) or a list of agent indices, each in 0..n_agents.",
            "oneOf": [
                { "type": "string", "const": "all" },
                { "type": "array", "items": { "type": "integer", "format": "uint", "minimum": 0 } }
            ]
        })
    }
}

/// The receivers of a field. A sender never receives its own message: the sender is always
/// left out of its receiver set, and a sender whose receiver set would then be empty is an error.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum Receivers {
    /// `"broadcast"`: every other agent receives it.
    #[default]
    Broadcast,
    /// `{"agents": [1, 2]}`: the listed agents receive it from every sender (except a sender
    /// listed itself, who does not receive its own message).
    Agents(Vec<usize>),
    /// `{"peer": [{"from": 0, "to": [1]}, {"from": 1, "to": [0]}]}`: peer-to-peer links; each
    /// sender sends only to its listed peers. Every sender of the field needs exactly one entry.
    Peer(Vec<PeerLink>),
}

/// Peer-to-peer links of one sender.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct PeerLink {
    /// The sending agent.
    pub from: usize,
    /// The agents it sends to (never itself).
    pub to: Vec<usize>,
}

/// A value expression over the sender's observation history. Each expression has a width (a
/// number of columns). Elementwise operators need equal widths, or one side of width 1, which
/// is broadcast.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum Expr {
    /// `{"obs": [3, 4, 10]}`: the listed dims of the current observation (width = list length).
    Obs(Vec<usize>),
    /// `{"obs_slice": {"start": 0, "end": 9}}`: observation dims start..end, end exclusive
    /// (width end - start).
    ObsSlice(Slice),
    /// `{"last_action": "one_hot"}` (width n_actions; all zero when there was no previous action)
    /// or `{"last_action": "index"}` (width 1; -1 when there was no previous action): the
    /// sender's action on the previous step.
    LastAction(ActionEncoding),
    /// `"sender_one_hot"`: the sender's own one-hot id (width n_agents).
    SenderOneHot,
    /// `{"const": 0.5}`: a constant (width 1).
    Const(f64),
    /// `{"window": {"op": "mean", "k": 10, "of": EXPR}}`: aggregate of EXPR over the last k steps
    /// (the current step and the k-1 before it), elementwise. EXPR cannot contain a window.
    Window(Window),
    /// `{"add": [A, B]}`: A + B elementwise.
    Add(Box<Expr>, Box<Expr>),
    /// `{"sub": [A, B]}`: A - B elementwise.
    Sub(Box<Expr>, Box<Expr>),
    /// `{"mul": [A, B]}`: A * B elementwise.
    Mul(Box<Expr>, Box<Expr>),
    /// `{"div": [A, B]}`: A / B elementwise; 0 where |B| < 1e-6.
    Div(Box<Expr>, Box<Expr>),
    /// `{"min": [A, B]}`: elementwise minimum.
    Min(Box<Expr>, Box<Expr>),
    /// `{"max": [A, B]}`: elementwise maximum.
    Max(Box<Expr>, Box<Expr>),
    /// `{"gt": [A, B]}`: 1 where A > B, else 0.
    Gt(Box<Expr>, Box<Expr>),
    /// `{"lt": [A, B]}`: 1 where A < B, else 0.
    Lt(Box<Expr>, Box<Expr>),
    /// `{"eq": [A, B]}`: 1 where |A - B| < 1e-6, else 0.
    Eq(Box<Expr>, Box<Expr>),
    /// `{"neg": A}`: -A.
    Neg(Box<Expr>),
    /// `{"abs": A}`: |A|.
    Abs(Box<Expr>),
    /// `{"clip": {"of": A, "min": 0, "max": 1}}`: A clamped to [min, max] elementwise.
    Clip(Clip),
    /// `{"reduce": {"op": "sum", "of": A}}`: reduces A's columns to one (sum, mean, min, max).
    Reduce(Reduce),
    /// `{"concat": [A, B, ...]}`: the columns of A, then B, ... (width = sum of widths).
    Concat(Vec<Expr>),
}

/// The elementwise binary operators of [`Expr`], named as in the JSON.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BinOp {
    Add,
    Sub,
    Mul,
    Div,
    Min,
    Max,
    Gt,
    Lt,
    Eq,
}

impl BinOp {
    /// The JSON key: `add`, `sub`, ...
    pub fn name(self) -> &'static str {
        match self {
            BinOp::Add => "add",
            BinOp::Sub => "sub",
            BinOp::Mul => "mul",
            BinOp::Div => "div",
            BinOp::Min => "min",
            BinOp::Max => "max",
            BinOp::Gt => "gt",
            BinOp::Lt => "lt",
            BinOp::Eq => "eq",
        }
    }
}

/// Every elementwise binary variant of [`Expr`] as one pattern binding its two operands, so a
/// `match` over expressions stays exhaustive without listing the nine variants again; the
/// operator itself comes from [`Expr::binary`].
macro_rules! any_binary {
    ($a:pat, $b:pat) => {
        Expr::Add($a, $b)
            | Expr::Sub($a, $b)
            | Expr::Mul($a, $b)
            | Expr::Div($a, $b)
            | Expr::Min($a, $b)
            | Expr::Max($a, $b)
            | Expr::Gt($a, $b)
            | Expr::Lt($a, $b)
            | Expr::Eq($a, $b)
    };
}
pub(crate) use any_binary;

impl Expr {
    /// The operator and operands of an elementwise binary expression (None for the others).
    pub fn binary(&self) -> Option<(BinOp, &Expr, &Expr)> {
        let op = match self {
            Expr::Add(..) => BinOp::Add,
            Expr::Sub(..) => BinOp::Sub,
            Expr::Mul(..) => BinOp::Mul,
            Expr::Div(..) => BinOp::Div,
            Expr::Min(..) => BinOp::Min,
            Expr::Max(..) => BinOp::Max,
            Expr::Gt(..) => BinOp::Gt,
            Expr::Lt(..) => BinOp::Lt,
            Expr::Eq(..) => BinOp::Eq,
            _ => return None,
        };
        let any_binary!(a, b) = self else { return None };
        Some((op, a, b))
    }
}

/// A half-open range of observation dims.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Slice {
    /// First dim (inclusive).
    pub start: usize,
    /// One past the last dim (exclusive), at most obs_dim.
    pub end: usize,
}

/// How the previous action is encoded.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum ActionEncoding {
    /// n_actions columns, 1 at the action taken.
    OneHot,
    /// One column holding the action index.
    Index,
}

/// A window aggregate.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Window {
    /// The aggregate.
    pub op: WindowOp,
    /// Number of steps, the current one included (1..=64).
    pub k: usize,
    /// The per-step expression aggregated (it cannot contain another window).
    pub of: Box<Expr>,
}

/// Aggregates over the last k steps x[t-k+1], ..., x[t].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum WindowOp {
    /// Mean of the k values.
    Mean,
    /// Sum of the k values (e.g. an action histogram over the window).
    Sum,
    /// Elementwise minimum.
    Min,
    /// Elementwise maximum.
    Max,
    /// The value k-1 steps back, x[t-k+1] (the oldest step of the window; k=2: previous step).
    Last,
    /// The change across the window, x[t] - x[t-k+1].
    Delta,
    /// Elementwise, the most recent non-zero value in the window (0 if none), e.g. the level of
    /// a food last seen in a cell; padding steps before the episode count as values.
    LastNonzero,
}

/// Clamping.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Clip {
    /// The expression clamped.
    pub of: Box<Expr>,
    /// Lower bound.
    pub min: f64,
    /// Upper bound (>= min).
    pub max: f64,
}

/// A reduction over the columns of one expression.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Reduce {
    /// The reduction.
    pub op: ReduceOp,
    /// The expression reduced to one column.
    pub of: Box<Expr>,
}

/// Reductions over columns.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum ReduceOp {
    Sum,
    Mean,
    Min,
    Max,
}
