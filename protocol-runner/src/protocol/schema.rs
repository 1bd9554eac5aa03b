//! The published JSON Schema of the protocol language, generated from the serde types. The
//! checked-in copy is `protocol-runner/protocol.schema.json` (a test keeps it in sync; regenerate
//! with `LMAC_UPDATE_SCHEMA=1 cargo test -p lmac-protocol-runner --test protocol_schema`).

use super::ast::Protocol;

/// The schema as a JSON value.
pub fn schema_value() -> serde_json::Value {
    serde_json::to_value(schemars::schema_for!(Protocol)).expect("schema serializes")
}

/// The schema as pretty-printed JSON text (with a trailing newline).
pub fn schema_json() -> String {
    let mut s = serde_json::to_string_pretty(&schema_value()).expect("schema serializes");
    s.push('\n');
    s
}
