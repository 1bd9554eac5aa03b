//! LLM access: one client trait, two wire formats over reqwest (OpenAI-compatible chat
//! completions, which covers OpenAI, vLLM, llama.cpp's server and Ollama; and Anthropic
//! Messages), and a recorder that keeps every request and response on disk so a design can be
//! replayed exactly, offline and for free.
//!
//! Keys live only in memory and go only to the server they belong to (`keys.rs`); recordings are
//! keyed by the canonical request, never by the key or the server (`recording.rs`).
//!
//! The rooms: this file holds what every part speaks (chat turns, the client trait, the errors,
//! the choices of wire format, mode and structured output) and the CLI's entry point
//! [`client_from_spec`]; `config.rs` how to reach a model ([`LlmConfig`]: the `PROVIDER:MODEL`
//! spec, each provider's server and key variable, timeouts and retries); `keys.rs` the API-key
//! policy; `recording.rs` record and replay; `wire.rs` the two wire formats (request bodies,
//! headers, reading a response); `http.rs` the client that sends, retries, records and replays
//! ([`HttpLlm`]).

mod config;
mod http;
mod keys;
mod recording;
mod wire;

pub use config::LlmConfig;
pub use http::{HttpLlm, MAX_BODY_BYTES};
pub use keys::{resolve_key, ApiKey};
pub use recording::{CanonicalRequest, RecordedResponse, Recorder, Recording};
pub use wire::{parse_response, ParsedResponse};

use serde::{Deserialize, Serialize};
use std::path::PathBuf;

/// Who speaks in a chat turn.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Role {
    System,
    User,
    Assistant,
}

/// One chat turn.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ChatMessage {
    pub role: Role,
    pub content: String,
}

impl ChatMessage {
    pub fn system(content: impl Into<String>) -> Self {
        ChatMessage { role: Role::System, content: content.into() }
    }
    pub fn user(content: impl Into<String>) -> Self {
        ChatMessage { role: Role::User, content: content.into() }
    }
    pub fn assistant(content: impl Into<String>) -> Self {
        ChatMessage { role: Role::Assistant, content: content.into() }
    }
}

/// Everything that can go wrong talking to an LLM; every variant names where (endpoint, file or
/// spec) and what.
#[derive(Debug, thiserror::Error)]
pub enum LlmError {
    #[error("LLM spec {spec:?}: {problem}")]
    Spec { spec: String, problem: String },
    #[error("{endpoint}: no API key: set the environment variable {var} (keys are read from the environment, never from files or flags)")]
    MissingKey { endpoint: String, var: String },
    #[error("{endpoint}: this server is not the provider's own and not on this machine, and no key variable was named for it: name the environment variable holding its key (api_key_env, the CLI's --api-key-env VAR)")]
    NoKeyVariable { endpoint: String },
    #[error("{endpoint}: refusing to send an API key over plain http to a host that is not this machine: use https (plain http is allowed only to loopback: 127.0.0.0/8, ::1, localhost)")]
    InsecureKeyTransport { endpoint: String },
    #[error("{endpoint}: HTTP {status} after {attempts} attempt(s); response body begins: {body}")]
    Status { endpoint: String, status: u16, attempts: u32, body: String },
    #[error("{endpoint}: HTTP {status} redirects to {location}; lmac does not follow redirects (they would carry the API key and the prompt to another server): set the base URL to the server that answers")]
    Redirect { endpoint: String, status: u16, location: String },
    #[error("{endpoint}: {problem} (after {attempts} attempt(s))")]
    Transport { endpoint: String, problem: String, attempts: u32, timed_out: bool },
    #[error("{endpoint}: unusable response: {problem}; body begins: {body}")]
    Response { endpoint: String, problem: String, body: String },
    /// The reply stopped at the token limit: a cut reply is not a protocol, and asking again with
    /// the same limit would be cut again (and paid again). It is recorded, so a replay says the same.
    #[error("{endpoint}: the reply was cut off at the token limit (finish reason {finish_reason:?}, max_tokens {}): raise the limit (`lmac design --llm-max-tokens N`); the reply ends: {tail}", limit.map_or("not sent: the server's default".to_string(), |m| m.to_string()))]
    Truncated { endpoint: String, finish_reason: String, limit: Option<u32>, tail: String },
    #[error("replay from {dir}: {problem}")]
    ReplayMiss { dir: PathBuf, key: String, problem: String },
    #[error("recording {path}: {problem}")]
    Recording { path: PathBuf, problem: String },
}

/// A chat model: system, user and assistant turns in, the assistant's next reply out.
pub trait LlmClient {
    /// For logs, directory names and the transcript: the spec, e.g. `openai:gpt-4.1`.
    fn name(&self) -> String;
    fn complete(&mut self, messages: &[ChatMessage]) -> Result<String, LlmError>;
    /// Like `complete`, with the JSON Schema the reply must follow, sent as the provider's
    /// structured output where it has one (the caller still validates the reply: a schema cannot
    /// say everything). Without structured output it is `complete`.
    fn complete_with_schema(&mut self, messages: &[ChatMessage], _schema: &serde_json::Value) -> Result<String, LlmError> {
        self.complete(messages)
    }
}

/// How a request asks for a reply that follows a JSON Schema.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum StructuredOutput {
    /// OpenAI's `response_format: {type: "json_schema", json_schema: {name, schema}}` (OpenAI,
    /// Gemini's OpenAI-compatible endpoint, vLLM, Ollama).
    #[default]
    JsonSchema,
    /// `response_format: {type: "json_object", schema}`: llama.cpp's servers (llama-server and
    /// llama-cpp-python) turn the schema into a grammar, so the reply is valid by construction.
    JsonObject,
    /// No schema in the request (Anthropic: its tool input schemas are not used; or a server
    /// that rejects `response_format`).
    Off,
}

impl std::str::FromStr for StructuredOutput {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "json-schema" => Ok(StructuredOutput::JsonSchema),
            "json-object" => Ok(StructuredOutput::JsonObject),
            "off" => Ok(StructuredOutput::Off),
            _ => Err(format!("unknown structured output {s:?}: use json-schema, json-object or off")),
        }
    }
}

/// The wire format.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Provider {
    /// `POST {base}/chat/completions`, `Authorization: Bearer`.
    OpenAi,
    /// `POST {base}/v1/messages`, `x-api-key`, `anthropic-version`.
    Anthropic,
}

/// Where answers come from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LlmMode {
    /// Ask the server every time (and record when a directory is given).
    #[default]
    Live,
    /// Answer from the recordings only; a request that was never recorded is an error. No
    /// network, no key.
    Replay,
    /// Answer from the recordings when they have the request, else ask the server and record
    /// (resumes an interrupted design without paying twice).
    ReplayOrLive,
}

impl std::str::FromStr for LlmMode {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "live" => Ok(LlmMode::Live),
            "replay" => Ok(LlmMode::Replay),
            "replay-or-live" | "replay_or_live" => Ok(LlmMode::ReplayOrLive),
            _ => Err(format!("unknown LLM mode {s:?}: use live, replay or replay-or-live")),
        }
    }
}

/// Whether a finish reason says the reply hit the token limit: `length` (OpenAI-compatible
/// servers: OpenAI, Gemini, vLLM, llama.cpp, Ollama), `max_tokens` and
/// `model_context_window_exceeded` (Anthropic).
pub fn finish_reason_is_truncation(reason: &str) -> bool {
    matches!(reason, "length" | "max_tokens" | "model_context_window_exceeded")
}

/// The text trimmed, cut after `n` characters (saying how long it was): for error texts.
fn excerpt(text: &str, n: usize) -> String {
    let t = text.trim();
    match t.char_indices().nth(n) {
        Some((i, _)) => format!("{}... ({} bytes in all)", &t[..i], t.len()),
        None => t.to_string(),
    }
}

/// A client from a spec, for the CLI: `openai:gpt-4.1` with an optional base URL, a mode and a
/// recording directory.
/// `api_key_env` names the key variable for a custom base URL (see [`LlmConfig::api_key_env`]).
pub fn client_from_spec(
    spec: &str,
    base_url: Option<&str>,
    api_key_env: Option<&str>,
    mode: LlmMode,
    record_dir: Option<PathBuf>,
) -> Result<HttpLlm, LlmError> {
    let mut cfg = LlmConfig::from_spec(spec, base_url)?.with_api_key_env(api_key_env);
    cfg.mode = mode;
    cfg.record_dir = record_dir;
    HttpLlm::new(cfg)
}
