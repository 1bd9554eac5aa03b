//! Reading a protocol: JSON text or values, protocol files (capped, regular files only), and the
//! repair of an LLM's reply (the JSON found in prose or a fenced block, control characters in
//! strings escaped).

use super::ast::Protocol;
use super::error::{ErrorKind, ValidationError};

fn parse_error(e: serde_path_to_error::Error<serde_json::Error>) -> ValidationError {
    let path = e.path().to_string();
    let inner = e.into_inner();
    let mut msg = inner.to_string();
    if msg.contains("unknown variant") && msg.contains("expected one of `obs`") {
        msg.push_str(" (an expression is an object with exactly one key naming its operator, e.g. {\"obs\": [0, 1]}, or the string \"sender_one_hot\")");
    }
    let path = if path == "." { String::new() } else { path };
    ValidationError::new(ErrorKind::Parse, path, format!("invalid protocol JSON: {msg}"))
}

/// Parse protocol JSON text (no validation against an environment yet). A leading byte-order
/// mark, which some editors write, is not part of the JSON.
pub fn parse_str(text: &str) -> Result<Protocol, Vec<ValidationError>> {
    let text = text.strip_prefix('\u{feff}').unwrap_or(text);
    let mut de = serde_json::Deserializer::from_str(text);
    let p: Protocol = serde_path_to_error::deserialize(&mut de).map_err(|e| vec![parse_error(e)])?;
    de.end().map_err(|e| {
        vec![ValidationError::new(ErrorKind::Parse, "", format!("invalid protocol JSON: trailing text after the protocol object ({e})"))]
    })?;
    Ok(p)
}

/// Parse an already-decoded JSON value.
pub fn parse_value(v: &serde_json::Value) -> Result<Protocol, Vec<ValidationError>> {
    serde_path_to_error::deserialize(v).map_err(|e| vec![parse_error(e)])
}

/// Parse the protocol out of an LLM answer: the text itself if it is JSON, else the content of
/// the first ```json fenced block, else the outermost `{ ... }`.
pub fn parse_llm_text(text: &str) -> Result<Protocol, Vec<ValidationError>> {
    let t = text.trim();
    // Models often break a long string over lines: raw control characters inside strings are
    // escaped first (valid JSON has none there, so a valid reply is unchanged).
    let parse = |s: &str| parse_str(&escape_controls_in_strings(s));
    if t.starts_with('{') {
        return parse(t);
    }
    if let Some(start) = t.find("```") {
        let rest = &t[start + 3..];
        let rest = rest.strip_prefix("json").or_else(|| rest.strip_prefix("JSON")).unwrap_or(rest);
        if let Some(end) = rest.find("```") {
            return parse(rest[..end].trim());
        }
    }
    match (t.find('{'), t.rfind('}')) {
        (Some(a), Some(b)) if a < b => parse(&t[a..=b]),
        _ => Err(vec![ValidationError::new(
            ErrorKind::Parse,
            "",
            "no JSON object found in the answer: reply with the protocol as one JSON object",
        )]),
    }
}

/// `text` with every control character inside a JSON string literal written as its escape
/// (`\n`, `\r`, `\t`, `\u00XX`); everything outside strings, and escapes already there, as
/// they are.
pub fn escape_controls_in_strings(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    let (mut in_string, mut escaped) = (false, false);
    for c in text.chars() {
        if in_string && !escaped && (c as u32) < 0x20 {
            match c {
                '\n' => out.push_str("\\n"),
                '\r' => out.push_str("\\r"),
                '\t' => out.push_str("\\t"),
                _ => out.push_str(&format!("\\u{:04x}", c as u32)),
            }
            continue;
        }
        out.push(c);
        if in_string {
            if escaped {
                escaped = false;
            } else if c == '\\' {
                escaped = true;
            } else if c == '"' {
                in_string = false;
            }
        } else if c == '"' {
            in_string = true;
        }
    }
    out
}

/// The largest protocol file read: protocols are a few KiB; the cap keeps a wrong path (a device,
/// a huge log) from being read into memory whole.
pub const MAX_FILE_BYTES: u64 = 16 << 20;

/// A protocol file's text, at most [`MAX_FILE_BYTES`], from a regular file only (a FIFO is
/// refused, not waited on); the error names the file.
pub fn read_protocol_file(path: &std::path::Path) -> Result<String, crate::ProtocolError> {
    lmac_shm_schema::safe_fs::read_text_capped(path, MAX_FILE_BYTES).map_err(|e| crate::ProtocolError::Read(e.to_string()))
}
