//! API keys. Keys come from the environment (or are handed in by the caller) and live only in
//! memory: they are never part of a recording, an error text or a log line. Each provider reads
//! its own variable (`OPENAI_API_KEY`, `ANTHROPIC_API_KEY`) and only for its own server: a custom
//! base URL (a local llama.cpp, vLLM or Ollama server, a proxy) gets a key only from a variable
//! the user names for it ([`LlmConfig::with_api_key_env`]). A key travels only over https, or
//! over plain http to this machine (loopback); anything else is refused before any request.
//!
//! [`ApiKey`] holds a key (its Debug form redacted); [`resolve_key`] applies the policy. Only this
//! module folder sees the key's text: the client sends it and redacts it from error texts.

use super::{LlmConfig, LlmError};

/// A key held in memory only; its Debug form is redacted so it cannot leak through `{:?}`.
#[derive(Clone)]
pub struct ApiKey(pub(super) String);

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

#[cfg(test)]
mod tests {
    use super::*;

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
}
