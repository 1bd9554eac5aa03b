//! A compact reference of the protocol language for the LLM's prompt (the structured-output
//! part of the design principles). The JSON Schema ([`super::schema_json`]) is the formal
//! definition; this is the same language in prose, with the environment's numbers filled in.

use super::validate::{MAX_DEPTH, MAX_WINDOW};
use super::ProtocolEnv;

/// The language reference text. With an environment, its sizes and the message budget are
/// stated (and the sender one-hot width is a number).
pub fn language_reference(env: Option<&ProtocolEnv>) -> String {
    let (n, na, sd, budget) = match env {
        Some(e) => (e.n_agents.to_string(), e.n_actions.to_string(), e.state_dim.to_string(), e.message_budget.to_string()),
        None => ("n_agents".into(), "n_actions".into(), "state_dim".into(), "the message budget".into()),
    };
    let last = match env {
        Some(e) => format!("{}", e.obs_dim.saturating_sub(1)),
        None => "obs_dim-1".into(),
    };
    format!(
        r#"Answer with one JSON object (no code, nothing is executed):
{{
  "name": "short_identifier",
  "message_design_instruction": "what each agent shares, with whom, and why (the design description)",
  "critical_state_dims": [state dim indices in 0..{sd}, or ranges {{"start": a, "end": b}} with b exclusive],
  "critical_state_reasoning": "why those state dims are task-critical",
  "fields": [
    {{"name": "field_name", "description": "what the value means",
      "senders": "all" | [agent indices],
      "receivers": "broadcast" | {{"agents": [agent indices]}} | {{"peer": [{{"from": 0, "to": [1]}}, ...]}},
      "value": EXPRESSION}}
  ]
}}
Agents are 0..{n} (exclusive); a sender never receives its own message. Each field's value is
computed by the sender from its own observations (dims 0..={last}), its previous action
({na} actions) and its id. EXPRESSION is one of:
  {{"obs": [d, ...]}}                       the listed observation dims (width = number of dims)
  {{"obs_slice": {{"start": a, "end": b}}}}    dims a..b, b exclusive (width b - a)
  {{"last_action": "one_hot"}}              previous action one-hot (width {na}; zeros on the first step)
  {{"last_action": "index"}}                previous action index (width 1; -1 on the first step)
  "sender_one_hot"                        the sender's id one-hot (width {n})
  {{"const": x}}                            a number (width 1)
  {{"window": {{"op": OP, "k": k, "of": E}}}}  E over the last k steps (current included), k in 1..={MAX_WINDOW};
                                          OP: mean, sum, min, max, last (value k-1 steps ago),
                                          delta (now minus k-1 steps ago), last_nonzero (most
                                          recent non-zero value); E cannot contain a window.
                                          Steps before the episode start read observation -1 and
                                          last action -1 (top-level "history_padding": "minus_one",
                                          the default; or "zero", or "repeat" the first step)
  {{"add"|"sub"|"mul"|"div"|"min"|"max"|"gt"|"lt"|"eq": [A, B]}}  elementwise (gt/lt/eq give 1 or 0;
                                          div gives 0 where B is 0); widths equal, or one side width 1
  {{"neg": A}}, {{"abs": A}}, {{"clip": {{"of": A, "min": lo, "max": hi}}}}
  {{"reduce": {{"op": "sum"|"mean"|"min"|"max", "of": A}}}}   one column
  {{"concat": [A, B, ...]}}                 columns of A, then B, ...
Nesting depth at most {MAX_DEPTH}.
Message layout: every receiving agent gets, for every other agent j in order that sends it at
least one field, [one-hot of j ({n} columns) | the values of the fields j sends it, in field
order]; agents and fields that do not reach it take no columns. A receiver's width is the sum
over the agents that reach it of ({n} + the widths of the fields they send it); every receiver is
padded to the widest one, and that width must not exceed {budget} columns (all phases
together). A broadcast of every field by every agent costs ({n} - 1) x ({n} + sum of field
widths); sending a field only where it helps (peer links) costs less.
"#
    )
}
