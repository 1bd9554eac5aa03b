//! LLM access: one client trait, two wire formats over reqwest (OpenAI-compatible chat
//! completions, which covers OpenAI, vLLM, llama.cpp's server and Ollama; and Anthropic
//! Messages), and a recorder that keeps every request and response on disk so a design can be
//! replayed exactly, offline and for free.
//!
//! Keys come from the environment (or are handed in by the caller) and live only in memory:
//! they are never part of a recording, an error text or a log line. Each provider reads its own
//! variable (`OPENAI_API_KEY`, `ANTHROPIC_API_KEY`) and only for its own server: a custom base
//! URL (a local llama.cpp, vLLM or Ollama server, a proxy) gets a key only from a variable the
//! user names for it ([`LlmConfig::with_api_key_env`]). A key travels only over https, or over
//! plain http to this machine (loopback); anything else is refused before any request.
//!
//! Recordings: `<dir>/<sha256 of the canonical request>.json`, one file per distinct request
//! holding every response it got, in order. The canonical request is the wire format, the model,
//! the temperature, the token limit and the messages (not the key, not the base URL: the same
//! model behind another server replays the same). Replay serves the n-th occurrence of a request
//! in a session from the n-th recorded response, so a design that asked the same thing twice
//! replays both answers.

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

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

/// How to reach a model, and how patiently.
#[derive(Clone, Debug, Serialize)]
pub struct LlmConfig {
    /// The spec as given (`openai:gpt-4.1`); the client's name.
    pub spec: String,
    pub provider: Provider,
    pub model: String,
    /// OpenAI style includes the version (`https://api.openai.com/v1`); Anthropic style does not
    /// (`https://api.anthropic.com`), as in the vendors' own SDKs.
    pub base_url: String,
    /// The environment variable holding the key; None sends no key. [`LlmConfig::from_spec`]
    /// names the provider's own variable only when requests go to the provider's own server; a
    /// custom base URL gets a key only through [`LlmConfig::with_api_key_env`], so an OpenAI key
    /// is never handed to a local or third-party server by accident. A named variable must be
    /// set; with none named, a local base URL (loopback) works without a key and a remote one is
    /// an error.
    pub api_key_env: Option<String>,
    /// Sampling temperature (the paper: 0.6).
    pub temperature: f64,
    /// Reply token limit. Anthropic requires one (default 8192 there); OpenAI-style requests omit
    /// it unless set (newer OpenAI models reject `max_tokens`).
    pub max_tokens: Option<u32>,
    /// Whole-request timeout (connect, send, wait, read).
    pub timeout: Duration,
    /// Most attempts per request (429, 5xx, timeouts and connection failures are retried).
    pub max_attempts: u32,
    /// First retry delay; doubles per attempt up to `backoff_max`.
    pub backoff: Duration,
    pub backoff_max: Duration,
    /// A server's Retry-After is honoured up to this long.
    pub retry_after_max: Duration,
    pub mode: LlmMode,
    /// Where requests and responses are recorded (required for replay).
    pub record_dir: Option<PathBuf>,
    /// How a reply's JSON Schema is sent (`complete_with_schema`); by provider by default.
    pub structured: StructuredOutput,
}

const ANTHROPIC_VERSION: &str = "2023-06-01";

impl LlmConfig {
    /// Parse `PROVIDER:MODEL` (`openai:gpt-4.1`, `anthropic:claude-opus-4-1`, `gemini:gemini-2.5-pro`
    /// through Google's OpenAI-compatible endpoint with `GEMINI_API_KEY`; also `vllm:`, `ollama:`,
    /// `llamacpp:` for OpenAI-compatible local servers at their usual ports). The
    /// model may itself contain ':' (`ollama:llama3:8b`). `base_url` overrides the provider's.
    pub fn from_spec(spec: &str, base_url: Option<&str>) -> Result<Self, LlmError> {
        let err = |problem: &str| LlmError::Spec { spec: spec.to_string(), problem: problem.to_string() };
        let (prov, model) =
            spec.split_once(':').ok_or_else(|| err("expected PROVIDER:MODEL, e.g. openai:gpt-4.1 or anthropic:claude-opus-4-1"))?;
        if model.trim().is_empty() {
            return Err(err("the model name is empty"));
        }
        let (provider, default_base, key_env) = match prov.to_ascii_lowercase().as_str() {
            "openai" => (Provider::OpenAi, "https://api.openai.com/v1", "OPENAI_API_KEY"),
            "anthropic" => (Provider::Anthropic, "https://api.anthropic.com", "ANTHROPIC_API_KEY"),
            "vllm" => (Provider::OpenAi, "http://127.0.0.1:8000/v1", "OPENAI_API_KEY"),
            "ollama" => (Provider::OpenAi, "http://127.0.0.1:11434/v1", "OPENAI_API_KEY"),
            "gemini" => (Provider::OpenAi, "https://generativelanguage.googleapis.com/v1beta/openai", "GEMINI_API_KEY"),
            "llamacpp" | "llama.cpp" => (Provider::OpenAi, "http://127.0.0.1:8080/v1", "OPENAI_API_KEY"),
            _ => return Err(err(&format!("unknown provider {prov:?}: use openai, anthropic, gemini, vllm, ollama or llamacpp"))),
        };
        let structured = match prov.to_ascii_lowercase().as_str() {
            "anthropic" => StructuredOutput::Off,
            "llamacpp" | "llama.cpp" => StructuredOutput::JsonObject,
            _ => StructuredOutput::JsonSchema,
        };
        let base = base_url.unwrap_or(default_base).trim_end_matches('/').to_string();
        // The provider's own key goes to the provider's own server only.
        let own_server =
            base == default_base && matches!(provider, Provider::OpenAi | Provider::Anthropic) && !default_base.starts_with("http:");
        let key_env = own_server.then(|| key_env.to_string());
        let parsed = reqwest::Url::parse(&base).map_err(|e| err(&format!("base URL {base:?} is not a URL: {e}")))?;
        if !matches!(parsed.scheme(), "http" | "https") {
            return Err(err(&format!("base URL {base:?} must be http or https")));
        }
        if !parsed.username().is_empty() || parsed.password().is_some() || parsed.query().is_some() {
            // Credentials in the URL would end up in recordings and error texts.
            return Err(err("the base URL must not carry credentials or a query: keys come from the environment"));
        }
        Ok(LlmConfig {
            spec: spec.to_string(),
            provider,
            model: model.to_string(),
            base_url: base,
            api_key_env: key_env,
            temperature: 0.6,
            max_tokens: match provider {
                Provider::Anthropic => Some(8192),
                Provider::OpenAi => None,
            },
            timeout: Duration::from_secs(300),
            max_attempts: 6,
            backoff: Duration::from_secs(2),
            backoff_max: Duration::from_secs(60),
            retry_after_max: Duration::from_secs(300),
            mode: LlmMode::Live,
            record_dir: None,
            structured,
        })
    }

    /// Read the key from `var` (None: send no key), e.g. for a local or third-party server that
    /// needs one; the variable must then be set.
    pub fn with_api_key_env(mut self, var: Option<&str>) -> Self {
        if let Some(v) = var {
            self.api_key_env = Some(v.to_string());
        }
        self
    }

    /// Whether a key may travel to the base URL: https anywhere, plain http only to loopback.
    pub fn key_transport_ok(&self) -> bool {
        reqwest::Url::parse(&self.base_url).is_ok_and(|u| u.scheme() == "https") || self.is_local()
    }

    /// The URL requests go to.
    pub fn endpoint(&self) -> String {
        match self.provider {
            Provider::OpenAi => format!("{}/chat/completions", self.base_url),
            Provider::Anthropic => format!("{}/v1/messages", self.base_url),
        }
    }

    /// Whether the base URL is this machine (no key needed, no proxy).
    pub fn is_local(&self) -> bool {
        reqwest::Url::parse(&self.base_url)
            .ok()
            .and_then(|u| u.host_str().map(|h| h.trim_matches(|c| c == '[' || c == ']').to_string()))
            .is_some_and(|h| h == "localhost" || h.parse::<std::net::IpAddr>().is_ok_and(|ip| ip.is_loopback()))
    }
}

/// A key held in memory only; its Debug form is redacted so it cannot leak through `{:?}`.
#[derive(Clone)]
pub struct ApiKey(String);

impl ApiKey {
    pub fn new(key: impl Into<String>) -> Self {
        ApiKey(key.into())
    }
}

impl std::fmt::Debug for ApiKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("ApiKey(<redacted>)")
    }
}

/// The key to use, given the value of `cfg.api_key_env` (when one is named): that value (it must
/// be set), none for a local server when no variable is named, else an error. A key that would
/// travel over plain http to another host is refused.
pub fn resolve_key(var_value: Option<String>, cfg: &LlmConfig) -> Result<Option<ApiKey>, LlmError> {
    let key = match &cfg.api_key_env {
        Some(var) => match var_value.filter(|v| !v.trim().is_empty()) {
            Some(v) => Some(ApiKey(v.trim().to_string())),
            None => return Err(LlmError::MissingKey { endpoint: cfg.endpoint(), var: var.clone() }),
        },
        None if cfg.is_local() => None,
        None => return Err(LlmError::NoKeyVariable { endpoint: cfg.endpoint() }),
    };
    if key.is_some() && !cfg.key_transport_ok() {
        return Err(LlmError::InsecureKeyTransport { endpoint: cfg.endpoint() });
    }
    Ok(key)
}

/// The request as it is hashed and recorded: everything that decides the answer, nothing secret.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CanonicalRequest {
    pub provider: Provider,
    pub model: String,
    pub temperature: f64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_tokens: Option<u32>,
    pub messages: Vec<ChatMessage>,
    /// The reply's JSON Schema when the request sent one (part of the recording key).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub response_schema: Option<serde_json::Value>,
}

impl CanonicalRequest {
    /// Hex SHA-256 of the canonical JSON (field order fixed by the struct).
    pub fn key(&self) -> String {
        let bytes = serde_json::to_vec(self).expect("a request serializes");
        Sha256::digest(&bytes).iter().map(|b| format!("{b:02x}")).collect()
    }
}

/// One recorded response.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct RecordedResponse {
    pub text: String,
    /// Where it came from (base URL path only; never a key).
    pub endpoint: String,
    /// The model the server said it used, when it said.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub served_model: Option<String>,
    /// Token usage as the server reported it.
    #[serde(default, skip_serializing_if = "serde_json::Value::is_null")]
    pub usage: serde_json::Value,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub finish_reason: Option<String>,
    pub elapsed_ms: u64,
    pub unix_time: u64,
}

/// A recording file: one request and every response it got.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Recording {
    pub key: String,
    pub request: CanonicalRequest,
    pub responses: Vec<RecordedResponse>,
}

/// Reads and appends recordings in one directory and counts occurrences per request within this
/// session (so replay walks the recorded responses in order).
#[derive(Debug)]
pub struct Recorder {
    dir: PathBuf,
    seen: HashMap<String, usize>,
}

impl Recorder {
    pub fn new(dir: impl Into<PathBuf>) -> Self {
        Recorder { dir: dir.into(), seen: HashMap::new() }
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    fn path(&self, key: &str) -> PathBuf {
        self.dir.join(format!("{key}.json"))
    }

    /// The recording of this request, if any.
    pub fn load(&self, key: &str) -> Result<Option<Recording>, LlmError> {
        let path = self.path(key);
        let text = match std::fs::read_to_string(&path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(LlmError::Recording { path, problem: format!("cannot read: {e}") }),
        };
        let rec: Recording = serde_json::from_str(&text)
            .map_err(|e| LlmError::Recording { path: path.clone(), problem: format!("not a recording: {e}") })?;
        if rec.key != key {
            return Err(LlmError::Recording { path, problem: format!("holds key {} instead of {key}", rec.key) });
        }
        Ok(Some(rec))
    }

    /// The recorded response for this request's next occurrence in the session, if recorded;
    /// advances the occurrence counter only when it answers.
    pub fn next_recorded(&mut self, req: &CanonicalRequest) -> Result<Option<String>, LlmError> {
        let key = req.key();
        let n = self.seen.get(&key).copied().unwrap_or(0);
        let Some(rec) = self.load(&key)? else { return Ok(None) };
        match rec.responses.get(n) {
            Some(r) => {
                self.seen.insert(key, n + 1);
                Ok(Some(r.text.clone()))
            }
            None => Ok(None),
        }
    }

    /// How many times the request was recorded, and how many of those this session used.
    fn occurrences(&self, req: &CanonicalRequest) -> (usize, usize) {
        let key = req.key();
        let recorded = self.load(&key).ok().flatten().map_or(0, |r| r.responses.len());
        (recorded, self.seen.get(&key).copied().unwrap_or(0))
    }

    /// Append a response (atomically: written to a temporary file, then renamed).
    pub fn append(&mut self, req: &CanonicalRequest, resp: RecordedResponse) -> Result<(), LlmError> {
        let key = req.key();
        let path = self.path(&key);
        std::fs::create_dir_all(&self.dir)
            .map_err(|e| LlmError::Recording { path: self.dir.clone(), problem: format!("cannot create the directory: {e}") })?;
        let mut rec = self.load(&key)?.unwrap_or_else(|| Recording { key: key.clone(), request: req.clone(), responses: Vec::new() });
        rec.responses.push(resp);
        let n = rec.responses.len();
        let text = serde_json::to_string_pretty(&rec).expect("a recording serializes");
        let tmp = self.dir.join(format!(".{key}.json.tmp{}", std::process::id()));
        std::fs::write(&tmp, text).map_err(|e| LlmError::Recording { path: tmp.clone(), problem: format!("cannot write: {e}") })?;
        std::fs::rename(&tmp, &path)
            .map_err(|e| LlmError::Recording { path: path.clone(), problem: format!("cannot rename {} into place: {e}", tmp.display()) })?;
        // This answer is the session's occurrence n-1 of the request.
        self.seen.insert(key, n);
        Ok(())
    }
}

/// The LLM client over HTTP, with recording and replay.
pub struct HttpLlm {
    cfg: LlmConfig,
    key: Option<ApiKey>,
    http: Option<reqwest::blocking::Client>,
    recorder: Option<Recorder>,
}

impl std::fmt::Debug for HttpLlm {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("HttpLlm").field("cfg", &self.cfg).field("key", &self.key.as_ref().map(|_| "<redacted>")).finish()
    }
}

fn excerpt(text: &str, n: usize) -> String {
    let t = text.trim();
    match t.char_indices().nth(n) {
        Some((i, _)) => format!("{}... ({} bytes in all)", &t[..i], t.len()),
        None => t.to_string(),
    }
}

impl HttpLlm {
    /// A client whose key comes from `cfg.api_key_env` (not read in replay mode).
    pub fn new(cfg: LlmConfig) -> Result<Self, LlmError> {
        let key = match cfg.mode {
            LlmMode::Replay => None,
            _ => resolve_key(cfg.api_key_env.as_ref().and_then(|v| std::env::var(v).ok()), &cfg)?,
        };
        Self::build(cfg, key)
    }

    /// A client with a key handed in by the caller (e.g. from a secret store).
    pub fn with_api_key(cfg: LlmConfig, key: ApiKey) -> Result<Self, LlmError> {
        Self::build(cfg, Some(key))
    }

    fn build(cfg: LlmConfig, key: Option<ApiKey>) -> Result<Self, LlmError> {
        // Checked here too, for keys handed in by the caller: before any connection is made.
        if key.is_some() && !cfg.key_transport_ok() {
            return Err(LlmError::InsecureKeyTransport { endpoint: cfg.endpoint() });
        }
        let recorder = cfg.record_dir.as_ref().map(Recorder::new);
        if cfg.mode != LlmMode::Live && recorder.is_none() {
            return Err(LlmError::Spec { spec: cfg.spec.clone(), problem: format!("{:?} mode needs a recording directory", cfg.mode) });
        }
        if cfg.max_attempts == 0 {
            return Err(LlmError::Spec { spec: cfg.spec.clone(), problem: "max_attempts must be at least 1".into() });
        }
        let http = if cfg.mode == LlmMode::Replay {
            None
        } else {
            // No redirects: reqwest strips `Authorization` on a cross-host hop but not
            // `x-api-key`, and it would resend the whole prompt; a redirect is an error instead.
            let mut b = reqwest::blocking::Client::builder()
                .timeout(cfg.timeout)
                .connect_timeout(cfg.timeout.min(Duration::from_secs(30)))
                .redirect(reqwest::redirect::Policy::none());
            if cfg.is_local() {
                // A local server is reached directly even when a proxy is configured.
                b = b.no_proxy();
            }
            Some(b.build().map_err(|e| LlmError::Transport {
                endpoint: cfg.endpoint(),
                problem: format!("cannot build the HTTP client: {e}"),
                attempts: 0,
                timed_out: false,
            })?)
        };
        Ok(HttpLlm { cfg, key, http, recorder })
    }

    pub fn config(&self) -> &LlmConfig {
        &self.cfg
    }

    /// Send a reply's JSON Schema this way (see [`StructuredOutput`]).
    pub fn set_structured(&mut self, s: StructuredOutput) {
        self.cfg.structured = s;
    }

    /// The canonical form of a request for these messages (and the reply's schema, when this
    /// client sends one).
    pub fn canonical(&self, messages: &[ChatMessage], schema: Option<&serde_json::Value>) -> CanonicalRequest {
        CanonicalRequest {
            provider: self.cfg.provider,
            model: self.cfg.model.clone(),
            temperature: self.cfg.temperature,
            max_tokens: self.cfg.max_tokens,
            messages: messages.to_vec(),
            response_schema: schema.filter(|_| self.cfg.structured != StructuredOutput::Off).cloned(),
        }
    }

    /// Remove the key from any text that might leave this struct (error bodies can echo it).
    fn redact(&self, text: &str) -> String {
        match &self.key {
            Some(k) if !k.0.is_empty() => text.replace(&k.0, "<redacted>"),
            _ => text.to_string(),
        }
    }

    fn body(&self, messages: &[ChatMessage], schema: Option<&serde_json::Value>) -> serde_json::Value {
        let c = &self.cfg;
        match c.provider {
            Provider::OpenAi => {
                let mut b = serde_json::json!({ "model": c.model, "messages": messages, "temperature": c.temperature });
                if let Some(m) = c.max_tokens {
                    b["max_tokens"] = m.into();
                }
                match (schema, c.structured) {
                    (Some(s), StructuredOutput::JsonSchema) => {
                        b["response_format"] = serde_json::json!({"type": "json_schema", "json_schema": {"name": "reply", "schema": s}});
                    }
                    (Some(s), StructuredOutput::JsonObject) => {
                        b["response_format"] = serde_json::json!({"type": "json_object", "schema": s});
                    }
                    _ => {}
                }
                b
            }
            Provider::Anthropic => {
                // Anthropic takes the system prompt apart from the turns.
                let system: Vec<&str> = messages.iter().filter(|m| m.role == Role::System).map(|m| m.content.as_str()).collect();
                let turns: Vec<&ChatMessage> = messages.iter().filter(|m| m.role != Role::System).collect();
                let mut b = serde_json::json!({ "model": c.model, "messages": turns, "temperature": c.temperature, "max_tokens": c.max_tokens.unwrap_or(8192) });
                if !system.is_empty() {
                    b["system"] = system.join("\n\n").into();
                }
                b
            }
        }
    }

    /// The delay before attempt `attempt + 1`: the server's Retry-After when it gave one (capped),
    /// else exponential backoff with a little jitter so parallel clients do not retry in step.
    fn delay(&self, attempt: u32, retry_after: Option<Duration>) -> Duration {
        if let Some(d) = retry_after {
            return d.min(self.cfg.retry_after_max);
        }
        let base = self.cfg.backoff.saturating_mul(1u32 << (attempt - 1).min(20)).min(self.cfg.backoff_max);
        base.mul_f64(1.0 + 0.25 * rand::random::<f64>())
    }

    /// POST the body, retrying 429, 5xx, timeouts and connection failures; returns the 2xx body.
    fn post(&self, body: &serde_json::Value) -> Result<String, LlmError> {
        let endpoint = self.cfg.endpoint();
        let http = self.http.as_ref().expect("an HTTP client outside replay mode");
        let max = self.cfg.max_attempts;
        let mut attempt = 0u32;
        loop {
            attempt += 1;
            let mut req = http.post(&endpoint).json(body);
            match (self.cfg.provider, &self.key) {
                (Provider::OpenAi, Some(k)) => req = req.bearer_auth(&k.0),
                (Provider::Anthropic, k) => {
                    req = req.header("anthropic-version", ANTHROPIC_VERSION);
                    if let Some(k) = k {
                        req = req.header("x-api-key", &k.0);
                    }
                }
                (Provider::OpenAi, None) => {}
            }
            let (retryable, retry_after, err) = match req.send() {
                Ok(resp) => {
                    let status = resp.status();
                    if status.is_redirection() {
                        let location = resp.headers().get(reqwest::header::LOCATION).map_or_else(
                            || "nowhere (no Location header)".to_string(),
                            |l| String::from_utf8_lossy(l.as_bytes()).into_owned(),
                        );
                        return Err(LlmError::Redirect {
                            endpoint,
                            status: status.as_u16(),
                            location: self.redact(&excerpt(&location, 300)),
                        });
                    }
                    let retry_after = retry_after(resp.headers());
                    match read_body(resp) {
                        Ok(text) if status.is_success() => return Ok(text),
                        Ok(text) => {
                            let retryable = status.as_u16() == 429 || status.is_server_error();
                            let e = LlmError::Status {
                                endpoint: endpoint.clone(),
                                status: status.as_u16(),
                                attempts: attempt,
                                body: self.redact(&excerpt(&text, 600)),
                            };
                            (retryable, retry_after, e)
                        }
                        Err(BodyError::TooLarge) => {
                            return Err(LlmError::Response {
                                endpoint: endpoint.clone(),
                                problem: format!("the response body is over {MAX_BODY_BYTES} bytes"),
                                body: String::new(),
                            })
                        }
                        Err(BodyError::Read(e)) => {
                            let timed_out = e.kind() == std::io::ErrorKind::TimedOut
                                || e.get_ref().and_then(|i| i.downcast_ref::<reqwest::Error>()).is_some_and(|r| r.is_timeout());
                            let problem = if timed_out {
                                format!("timed out after {:.1}s reading the response", self.cfg.timeout.as_secs_f64())
                            } else {
                                format!("failed reading the response: {e}")
                            };
                            let e = LlmError::Transport {
                                endpoint: endpoint.clone(),
                                problem: self.redact(&problem),
                                attempts: attempt,
                                timed_out,
                            };
                            (true, None, e)
                        }
                    }
                }
                Err(e) => (
                    e.is_timeout() || e.is_connect() || e.is_request(),
                    None,
                    self.transport_error(&endpoint, &e, attempt, "sending the request"),
                ),
            };
            if !retryable || attempt >= max {
                return Err(err);
            }
            let wait = self.delay(attempt, retry_after);
            eprintln!("lmac: LLM {endpoint}: {err}; retrying in {:.1}s (attempt {}/{max})", wait.as_secs_f64(), attempt + 1);
            std::thread::sleep(wait);
        }
    }

    fn transport_error(&self, endpoint: &str, e: &reqwest::Error, attempts: u32, doing: &str) -> LlmError {
        let timed_out = e.is_timeout();
        let mut problem = if timed_out {
            format!("timed out after {:.1}s {doing}", self.cfg.timeout.as_secs_f64())
        } else {
            format!("failed {doing}: {e}")
        };
        let mut src = std::error::Error::source(e);
        while let Some(s) = src {
            problem.push_str(&format!(": {s}"));
            src = s.source();
        }
        LlmError::Transport { endpoint: endpoint.to_string(), problem: self.redact(&problem), attempts, timed_out }
    }

    /// Ask the server (no recording).
    fn ask(&self, messages: &[ChatMessage], schema: Option<&serde_json::Value>) -> Result<RecordedResponse, LlmError> {
        let endpoint = self.cfg.endpoint();
        let started = Instant::now();
        let raw = self.post(&self.body(messages, schema))?;
        let reply = parse_response(self.cfg.provider, &raw).map_err(|problem| LlmError::Response {
            endpoint: endpoint.clone(),
            problem,
            body: self.redact(&excerpt(&raw, 600)),
        })?;
        let unix_time = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_secs());
        Ok(RecordedResponse {
            text: reply.text,
            endpoint,
            served_model: reply.served_model,
            usage: reply.usage,
            finish_reason: reply.finish_reason,
            elapsed_ms: started.elapsed().as_millis() as u64,
            unix_time,
        })
    }
}

/// What a 2xx response body says.
#[derive(Clone, Debug, PartialEq)]
pub struct ParsedResponse {
    /// The reply text (never empty).
    pub text: String,
    pub finish_reason: Option<String>,
    pub served_model: Option<String>,
    pub usage: serde_json::Value,
}

/// Read a 2xx response body of the given wire format. The body is untrusted: anything that is
/// not a JSON object of the expected shape is an error naming the missing or mistyped field.
pub fn parse_response(provider: Provider, raw: &str) -> Result<ParsedResponse, String> {
    let v: serde_json::Value = serde_json::from_str(raw).map_err(|e| format!("not JSON ({e})"))?;
    if !v.is_object() {
        return Err(format!("the body is JSON but not an object (it is {})", json_kind(&v)));
    }
    if let Some(err) = v.get("error").filter(|e| !e.is_null()) {
        return Err(format!("the server reported an error: {}", excerpt(&err.to_string(), 300)));
    }
    let (text, finish) = match provider {
        Provider::OpenAi => {
            let choice = v.get("choices").and_then(|c| c.get(0)).ok_or("no choices[0]")?;
            let content = &choice["message"]["content"];
            let text = match content {
                serde_json::Value::String(s) => s.clone(),
                // Some servers answer with content parts.
                serde_json::Value::Array(parts) => {
                    parts.iter().filter_map(|p| p.get("text").and_then(|t| t.as_str())).collect::<Vec<_>>().join("")
                }
                serde_json::Value::Null => {
                    let refusal = choice["message"]["refusal"].as_str().unwrap_or("");
                    return Err(format!(
                        "choices[0].message.content is missing{}",
                        if refusal.is_empty() { String::new() } else { format!(" (refusal: {})", excerpt(refusal, 300)) }
                    ));
                }
                other => return Err(format!("choices[0].message.content is {}, not text", json_kind(other))),
            };
            (text, choice["finish_reason"].as_str().map(str::to_string))
        }
        Provider::Anthropic => {
            let blocks = v.get("content").and_then(|c| c.as_array()).ok_or("no content array")?;
            let text = blocks.iter().filter(|b| b["type"] == "text").filter_map(|b| b["text"].as_str()).collect::<Vec<_>>().join("");
            (text, v["stop_reason"].as_str().map(str::to_string))
        }
    };
    if text.trim().is_empty() {
        return Err(format!(
            "the reply text is empty (finish reason {:?})",
            finish.as_deref().map_or("unknown".into(), |f| excerpt(f, 80))
        ));
    }
    Ok(ParsedResponse {
        text,
        finish_reason: finish,
        served_model: v["model"].as_str().map(str::to_string),
        usage: v.get("usage").cloned().unwrap_or(serde_json::Value::Null),
    })
}

fn json_kind(v: &serde_json::Value) -> &'static str {
    match v {
        serde_json::Value::Null => "null",
        serde_json::Value::Bool(_) => "a boolean",
        serde_json::Value::Number(_) => "a number",
        serde_json::Value::String(_) => "a string",
        serde_json::Value::Array(_) => "an array",
        serde_json::Value::Object(_) => "an object",
    }
}

impl LlmClient for HttpLlm {
    fn name(&self) -> String {
        self.cfg.spec.clone()
    }

    fn complete(&mut self, messages: &[ChatMessage]) -> Result<String, LlmError> {
        self.request(messages, None)
    }

    fn complete_with_schema(&mut self, messages: &[ChatMessage], schema: &serde_json::Value) -> Result<String, LlmError> {
        self.request(messages, Some(schema))
    }
}

impl HttpLlm {
    /// One request, answered from the recordings or the server (and recorded).
    fn request(&mut self, messages: &[ChatMessage], schema: Option<&serde_json::Value>) -> Result<String, LlmError> {
        if messages.is_empty() {
            return Err(LlmError::Spec { spec: self.cfg.spec.clone(), problem: "a request needs at least one message".into() });
        }
        let req = self.canonical(messages, schema);
        if self.cfg.mode != LlmMode::Live {
            let rec = self.recorder.as_mut().expect("checked at construction");
            if let Some(text) = rec.next_recorded(&req)? {
                return Ok(text);
            }
            if self.cfg.mode == LlmMode::Replay {
                let (recorded, used) = rec.occurrences(&req);
                let last_user = messages.iter().rev().find(|m| m.role == Role::User).map_or(String::new(), |m| excerpt(&m.content, 120));
                let problem = if recorded == 0 {
                    format!(
                        "no recording of this request (key {}, model {}, temperature {}, {} message(s), last user message begins {last_user:?}); record it by running live with this directory",
                        req.key(),
                        req.model,
                        req.temperature,
                        messages.len()
                    )
                } else {
                    format!("the request (key {}) was recorded {recorded} time(s) and this session already replayed {used}", req.key())
                };
                return Err(LlmError::ReplayMiss { dir: rec.dir().to_path_buf(), key: req.key(), problem });
            }
        }
        let resp = self.ask(messages, req.response_schema.as_ref())?;
        let text = resp.text.clone();
        if let Some(rec) = self.recorder.as_mut() {
            rec.append(&req, resp)?;
        }
        Ok(text)
    }
}

/// The most bytes of a response body read: far above any chat reply, small enough that a hostile
/// or broken server cannot make the client buffer gigabytes.
pub const MAX_BODY_BYTES: u64 = 32 << 20;

/// Why a body could not be had.
enum BodyError {
    TooLarge,
    Read(std::io::Error),
}

/// The body as text (invalid UTF-8 replaced), at most [`MAX_BODY_BYTES`]; a longer body is an
/// error rather than silently cut JSON.
fn read_body(resp: reqwest::blocking::Response) -> Result<String, BodyError> {
    use std::io::Read;
    let mut raw = Vec::new();
    resp.take(MAX_BODY_BYTES + 1).read_to_end(&mut raw).map_err(BodyError::Read)?;
    if raw.len() as u64 > MAX_BODY_BYTES {
        return Err(BodyError::TooLarge);
    }
    Ok(String::from_utf8(raw).unwrap_or_else(|e| String::from_utf8_lossy(e.as_bytes()).into_owned()))
}

/// `Retry-After` (seconds or an HTTP date) or `retry-after-ms` (OpenAI sends it), if present.
fn retry_after(h: &reqwest::header::HeaderMap) -> Option<Duration> {
    if let Some(ms) = h.get("retry-after-ms").and_then(|v| v.to_str().ok()).and_then(|s| s.trim().parse::<f64>().ok()) {
        if ms.is_finite() && ms >= 0.0 {
            return Some(Duration::from_secs_f64(ms / 1000.0));
        }
    }
    let v = h.get(reqwest::header::RETRY_AFTER)?.to_str().ok()?.trim();
    if let Ok(s) = v.parse::<f64>() {
        return (s.is_finite() && s >= 0.0).then(|| Duration::from_secs_f64(s));
    }
    let at = parse_http_date(v)?;
    let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).ok()?.as_secs();
    Some(Duration::from_secs(at.saturating_sub(now)))
}

/// Seconds since 1970 of an IMF-fixdate (`Sun, 06 Nov 1994 08:49:37 GMT`), the form HTTP
/// servers send; other forms give None (and the client falls back to its own backoff).
fn parse_http_date(s: &str) -> Option<u64> {
    let parts: Vec<&str> = s.split_whitespace().collect();
    if parts.len() != 6 || parts[5] != "GMT" {
        return None;
    }
    let day: i64 = parts[1].parse().ok()?;
    const MONTHS: [&str; 12] = ["Jan", "Feb", "Mar", "Apr", "May", "Jun", "Jul", "Aug", "Sep", "Oct", "Nov", "Dec"];
    let month = MONTHS.iter().position(|m| *m == parts[2])? as i64 + 1;
    let year: i64 = parts[3].parse().ok()?;
    let hms: Vec<i64> = parts[4].split(':').map(|x| x.parse().ok()).collect::<Option<_>>()?;
    if hms.len() != 3 {
        return None;
    }
    // Days from civil (proleptic Gregorian), the inverse of the usual civil-from-days.
    let y = if month <= 2 { year - 1 } else { year };
    let era = y.div_euclid(400);
    let yoe = y - era * 400;
    let mp = (month + 9) % 12;
    let doy = (153 * mp + 2) / 5 + day - 1;
    let doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
    let days = era * 146_097 + doe - 719_468;
    u64::try_from(days * 86_400 + hms[0] * 3600 + hms[1] * 60 + hms[2]).ok()
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spec_parsing() {
        let c = LlmConfig::from_spec("openai:gpt-4.1", None).unwrap();
        assert_eq!(
            (c.provider, c.model.as_str(), c.endpoint().as_str()),
            (Provider::OpenAi, "gpt-4.1", "https://api.openai.com/v1/chat/completions")
        );
        assert!(!c.is_local());
        let c = LlmConfig::from_spec("anthropic:claude-opus-4-1", None).unwrap();
        assert_eq!(c.endpoint(), "https://api.anthropic.com/v1/messages");
        assert_eq!(c.api_key_env.as_deref(), Some("ANTHROPIC_API_KEY"));
        assert_eq!(LlmConfig::from_spec("openai:m", None).unwrap().api_key_env.as_deref(), Some("OPENAI_API_KEY"));
        // A custom base URL or a local server never gets the provider's key by default.
        for (spec, base) in
            [("openai:m", Some("http://127.0.0.1:8080/v1")), ("openai:m", Some("https://proxy.example/v1")), ("vllm:m", None)]
        {
            assert_eq!(LlmConfig::from_spec(spec, base).unwrap().api_key_env, None, "{spec} {base:?}");
        }
        let named = LlmConfig::from_spec("llamacpp:m", None).unwrap().with_api_key_env(Some("LOCAL_KEY"));
        assert_eq!(named.api_key_env.as_deref(), Some("LOCAL_KEY"));
        let c = LlmConfig::from_spec("ollama:llama3:8b", Some("http://localhost:11434/v1/")).unwrap();
        assert_eq!(c.model, "llama3:8b");
        assert_eq!(c.endpoint(), "http://localhost:11434/v1/chat/completions");
        assert!(c.is_local());
        assert!(LlmConfig::from_spec("openai:m", Some("http://[::1]:9/v1")).unwrap().is_local());
        for bad in ["gpt-4.1", "openai:", "bard:x"] {
            let e = LlmConfig::from_spec(bad, None).unwrap_err().to_string();
            assert!(e.contains(bad), "{e}");
        }
        assert!(LlmConfig::from_spec("openai:m", Some("https://u:p@example.com/v1")).is_err());
        assert!(LlmConfig::from_spec("openai:m", Some("https://example.com/v1?key=x")).is_err());
    }

    #[test]
    fn key_resolution() {
        let remote = LlmConfig::from_spec("openai:gpt-4.1", None).unwrap();
        let e = resolve_key(None, &remote).unwrap_err().to_string();
        assert!(e.contains("OPENAI_API_KEY") && e.contains("api.openai.com"), "{e}");
        assert!(resolve_key(Some("sk-1".into()), &remote).unwrap().is_some());
        let local = LlmConfig::from_spec("openai:m", Some("http://127.0.0.1:8080/v1")).unwrap();
        assert!(resolve_key(None, &local).unwrap().is_none());
        // A named variable must be set.
        let named = local.clone().with_api_key_env(Some("LOCAL_KEY"));
        assert!(resolve_key(None, &named).unwrap_err().to_string().contains("LOCAL_KEY"));
        assert!(resolve_key(Some("k".into()), &named).unwrap().is_some());
        // A custom remote server without a named variable: an error that says what to do.
        let proxy = LlmConfig::from_spec("openai:m", Some("https://proxy.example/v1")).unwrap();
        assert!(matches!(resolve_key(None, &proxy), Err(LlmError::NoKeyVariable { .. })));
        // Plain http with a key: loopback only.
        let plain = LlmConfig::from_spec("openai:m", Some("http://10.1.2.3:8000/v1")).unwrap().with_api_key_env(Some("K"));
        assert!(matches!(resolve_key(Some("k".into()), &plain), Err(LlmError::InsecureKeyTransport { .. })));
        for base in ["http://localhost:1/v1", "http://127.9.9.9:1/v1", "http://[::1]:1/v1"] {
            let c = LlmConfig::from_spec("openai:m", Some(base)).unwrap().with_api_key_env(Some("K"));
            assert!(resolve_key(Some("k".into()), &c).unwrap().is_some(), "{base}");
        }
        assert_eq!(format!("{:?}", ApiKey::new("sk-secret")), "ApiKey(<redacted>)");
    }

    #[test]
    fn canonical_key_ignores_nothing_that_matters() {
        let r = CanonicalRequest {
            provider: Provider::OpenAi,
            model: "m".into(),
            temperature: 0.6,
            max_tokens: None,
            messages: vec![ChatMessage::user("hi")],
            response_schema: None,
        };
        let mut r2 = r.clone();
        assert_eq!(r.key(), r2.key());
        r2.temperature = 0.7;
        assert_ne!(r.key(), r2.key());
        // The reply's schema is part of the request; without one the key is what it always was.
        let mut r3 = r.clone();
        r3.response_schema = Some(serde_json::json!({"type": "object"}));
        assert_ne!(r.key(), r3.key());
        assert!(!serde_json::to_string(&r).unwrap().contains("response_schema"));
        assert_eq!(r.key().len(), 64);
    }

    #[test]
    fn hostile_response_bodies_are_errors() {
        let ok = parse_response(Provider::OpenAi, r#"{"choices": [{"message": {"content": "hi"}, "finish_reason": "stop"}]}"#).unwrap();
        assert_eq!((ok.text.as_str(), ok.finish_reason.as_deref()), ("hi", Some("stop")));
        let cases = [
            (Provider::OpenAi, "[1, 2]", "not an object"),
            (Provider::OpenAi, "\"text\"", "not an object"),
            (Provider::OpenAi, "{}", "choices[0]"),
            (Provider::OpenAi, r#"{"choices": "x"}"#, "choices[0]"),
            (Provider::OpenAi, r#"{"choices": [7]}"#, "content is missing"),
            (Provider::OpenAi, r#"{"choices": [{"message": {"content": 5}}]}"#, "a number, not text"),
            (Provider::OpenAi, r#"{"choices": [{"message": {"content": "  "}}]}"#, "empty"),
            (Provider::Anthropic, r#"{"content": {"type": "text"}}"#, "no content array"),
            (Provider::Anthropic, r#"{"content": [{"type": "text", "text": 3}]}"#, "empty"),
            (Provider::Anthropic, "{\"content\": [", "not JSON"),
        ];
        for (p, body, want) in cases {
            let e = parse_response(p, body).unwrap_err();
            assert!(e.contains(want), "{body}: {e}");
        }
    }

    #[test]
    fn http_dates() {
        assert_eq!(parse_http_date("Sun, 06 Nov 1994 08:49:37 GMT"), Some(784_111_777));
        assert_eq!(parse_http_date("Thu, 01 Jan 1970 00:00:00 GMT"), Some(0));
        assert_eq!(parse_http_date("soon"), None);
    }
}
