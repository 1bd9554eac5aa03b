//! Validation errors: what kind, where (the JSON path) and a message written to be handed back
//! verbatim to the LLM that wrote the protocol.

use std::fmt;

/// What kind of mistake an error reports (for programs; people read the Display text).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ErrorKind {
    /// Could not read the file.
    Io,
    /// Not JSON, or JSON that does not match the schema (unknown key, wrong type, missing key).
    Parse,
    /// The environment itself cannot carry messages (e.g. a single agent).
    Env,
    /// A required text or list is empty.
    Empty,
    /// An identifier is malformed or repeated.
    Name,
    /// An agent index is out of range, repeated, or a sender/receiver rule is broken.
    Agent,
    /// An observation dim or slice is out of range.
    ObsDim,
    /// A state dim is out of range or repeated.
    StateDim,
    /// Operand widths do not fit together.
    Width,
    /// A window is malformed (k out of range, nested windows).
    Window,
    /// A number is not finite or a clip range is empty.
    Number,
    /// The protocol is too large (nesting, nodes, fields).
    Size,
    /// The message is wider than the budget.
    Budget,
    /// Phases given to the compiler do not fit together.
    Phases,
}

/// One validation error: where (a JSON path such as `fields[2].value.add[1].obs[0]`) and what.
#[derive(Debug, Clone, PartialEq)]
pub struct ValidationError {
    pub kind: ErrorKind,
    /// JSON path of the offending element; empty for whole-protocol errors.
    pub path: String,
    /// The field's name when the error is inside a field.
    pub field: Option<String>,
    pub message: String,
}

impl ValidationError {
    pub fn new(kind: ErrorKind, path: impl Into<String>, message: impl Into<String>) -> Self {
        ValidationError { kind, path: path.into(), field: None, message: message.into() }
    }
}

impl fmt::Display for ValidationError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match (&self.path.is_empty(), &self.field) {
            (true, _) => write!(f, "{}", self.message),
            (false, None) => write!(f, "{}: {}", self.path, self.message),
            (false, Some(n)) => write!(f, "{} (field \"{}\"): {}", self.path, n, self.message),
        }
    }
}

impl std::error::Error for ValidationError {}

/// All errors as one text, one per line, ready to hand to an LLM for correction.
pub fn errors_to_text(errors: &[ValidationError]) -> String {
    let mut s = format!("The protocol has {} error(s):\n", errors.len());
    for e in errors {
        s.push_str("- ");
        s.push_str(&e.to_string());
        s.push('\n');
    }
    s
}
