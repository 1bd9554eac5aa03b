//! How to reach a model, and how patiently: [`LlmConfig`], parsed from a `PROVIDER:MODEL` spec
//! (each provider's wire format, default server, key variable and structured output), with the
//! URL checks the key policy relies on ([`LlmConfig::is_local`], [`LlmConfig::key_transport_ok`]).

use super::{LlmError, LlmMode, Provider, StructuredOutput};
use serde::Serialize;
use std::path::PathBuf;
use std::time::Duration;

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

    /// Read the key from `var`, e.g. for a local or third-party server that needs one; the
    /// variable must then be set. None keeps what [`LlmConfig::from_spec`] chose: the provider's
    /// own variable for its own server, no key for a custom base URL.
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
}
