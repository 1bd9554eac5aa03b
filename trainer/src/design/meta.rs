//! (being written: the meta-information; placeholder so the crate builds meanwhile)

/// One line for logs.
pub fn summary_line(meta: &serde_json::Value) -> String {
    meta["summary"].to_string()
}
