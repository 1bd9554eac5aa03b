//! Protocols are data: the typed protocol description an LLM writes (JSON, with a published JSON
//! Schema), its validator (errors are precise text to hand back to the LLM), its compiler into a
//! vectorized gather/compute plan ([`MessagePlan`](crate::plan::MessagePlan)), and its
//! human-readable explanation.
//!
//! # The language in one page
//! A protocol (one design phase) has a `message_design_instruction` (the design description),
//! the `critical_state_dims` it targets, and a list of `fields`. Each field has a `name`, a
//! `description`, `senders` (`"all"` or a list of agents), `receivers` (`"broadcast"`,
//! `{"agents": [..]}` or peer-to-peer `{"peer": [{"from": 0, "to": [1]}]}`; a sender never
//! receives its own message) and a `value` expression over the sender's observation history:
//! `{"obs": [dims]}`, `{"obs_slice": {"start", "end"}}`, `{"last_action": "one_hot"|"index"}`,
//! `"sender_one_hot"`, `{"const": x}`, `{"window": {"op": mean|sum|min|max|last|delta|last_nonzero, "k", "of"}}`,
//! elementwise `add sub mul div min max gt lt eq` (`{"add": [A, B]}`, width-1 operands
//! broadcast), `neg`, `abs`, `{"clip": {"of", "min", "max"}}`, `{"reduce": {"op", "of"}}`,
//! `{"concat": [..]}`.
//!
//! # Message layout (one width per receiver)
//! Receiver i gets, for each phase in order, for each other agent j in increasing order that
//! sends i at least one field of the phase, `[one-hot(j) (n_agents columns; on by default,
//! `"sender_one_hot": false` drops it) | the fields j sends i, in field order]`, then zeros up to
//! the phase's width: the widest receiver's ([`receiver_widths`]), so all receivers share one
//! width and each phase starts at the same column for all. `"layout": "sender_blocks"` keeps the
//! earlier layout: a block per other agent with every field, unsent columns zero, width
//! (n_agents - 1) * (n_agents + sum of field widths). Reserved columns past the plan's width are
//! kept at zero.
//!
//! # History
//! Window aggregates see the current step and the k-1 before it. The plan keeps a ring buffer
//! per env and agent; `first[env]` restarts it. Steps before the episode are padded per
//! `history_padding`: `minus_one` (default; observation and last-action one-hot all -1, last-action
//! index -1, as the paper's reference code pads its 10-step window), `zero`, or `repeat` (the
//! episode's first step). The window expression is evaluated on the padding step (so
//! `sender_one_hot` stays the sender's id).

pub mod ast;
pub mod compile;
pub mod constant;
pub mod env;
pub mod error;
pub mod execute;
pub mod explain;
pub mod parse;
pub mod reference;
pub mod schema;
pub mod validate;
pub mod width;

pub use ast::*;
pub use compile::{compile, compile_plan, Column, ProtocolPlan};
pub use constant::{constant_fields, constant_fields_report, ConstantField};
pub use env::ProtocolEnv;
pub use error::{errors_to_text, ErrorKind, ValidationError};
pub use explain::{explain, explain_expr, explain_phases};
pub use parse::{escape_controls_in_strings, parse_llm_text, parse_str, parse_value, read_protocol_file, MAX_FILE_BYTES};
pub use reference::language_reference;
pub use schema::{schema_json, schema_value};
pub use validate::{
    check_file, check_phases, check_str, check_summary, validate, validate_phase, ValidatedProtocol, MAX_DEPTH, MAX_FIELDS, MAX_NODES,
    MAX_WINDOW,
};
pub use width::{combined_receiver_widths, combined_width, message_width, receiver_widths};
