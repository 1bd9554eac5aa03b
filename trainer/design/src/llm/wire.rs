//! The two wire formats, OpenAI-style chat completions and Anthropic Messages: the request body
//! (the reply's JSON Schema as the provider's structured output; Anthropic's system prompt apart
//! from the turns), the authentication headers, and the reading of a 2xx response body, which is
//! untrusted.

use super::{excerpt, ApiKey, ChatMessage, LlmConfig, Provider, Role, StructuredOutput};

const ANTHROPIC_VERSION: &str = "2023-06-01";

/// The request body for these messages (and the reply's JSON Schema, sent as `c.structured` says).
pub(super) fn request_body(c: &LlmConfig, messages: &[ChatMessage], schema: Option<&serde_json::Value>) -> serde_json::Value {
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

/// The request with the provider's authentication headers (and Anthropic's version header).
pub(super) fn authorize(
    mut req: reqwest::blocking::RequestBuilder,
    provider: Provider,
    key: Option<&ApiKey>,
) -> reqwest::blocking::RequestBuilder {
    match (provider, key) {
        (Provider::OpenAi, Some(k)) => req = req.bearer_auth(&k.0),
        (Provider::Anthropic, k) => {
            req = req.header("anthropic-version", ANTHROPIC_VERSION);
            if let Some(k) = k {
                req = req.header("x-api-key", &k.0);
            }
        }
        (Provider::OpenAi, None) => {}
    }
    req
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

#[cfg(test)]
mod tests {
    use super::*;

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
}
