//! The client over HTTP, [`HttpLlm`]: each request is answered from the recordings or the server
//! (and recorded); a key is checked before any connection is made and redacted from every error
//! text; redirects are refused; 429, 5xx, timeouts and connection failures are retried with
//! backoff or the server's Retry-After; a response body is read up to [`MAX_BODY_BYTES`].

use super::{
    excerpt, finish_reason_is_truncation, parse_response, resolve_key, wire, ApiKey, CanonicalRequest, ChatMessage, LlmClient, LlmConfig,
    LlmError, LlmMode, RecordedResponse, Recorder, Role, StructuredOutput,
};
use std::time::{Duration, Instant};

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

    /// Limit each reply to this many tokens (see [`LlmConfig::max_tokens`]).
    pub fn set_max_tokens(&mut self, n: u32) {
        self.cfg.max_tokens = Some(n);
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
            let req = wire::authorize(http.post(&endpoint).json(body), self.cfg.provider, self.key.as_ref());
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
                            let mut problem = if timed_out {
                                format!("timed out after {:.1}s reading the response", self.cfg.timeout.as_secs_f64())
                            } else {
                                format!("failed reading the response: {e}")
                            };
                            // Retried all the same (a design should not die of one dropped
                            // connection), but the user should know what it may cost.
                            if status.is_success() {
                                problem.push_str(&format!(
                                    " (the server had answered {}: that reply was lost in transit and may have been billed)",
                                    status.as_u16()
                                ));
                            }
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
        let raw = self.post(&wire::request_body(&self.cfg, messages, schema))?;
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
            if let Some(resp) = rec.next_recorded(&req)? {
                return self.whole_reply(resp);
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
        // Recorded even when cut off: it was paid for, and a replay then says the same.
        if let Some(rec) = self.recorder.as_mut() {
            rec.append(&req, resp.clone())?;
        }
        self.whole_reply(resp)
    }

    /// The reply's text, unless it stopped at the token limit.
    fn whole_reply(&self, resp: RecordedResponse) -> Result<String, LlmError> {
        match resp.finish_reason.as_deref() {
            Some(reason) if finish_reason_is_truncation(reason) => {
                let t = resp.text.trim_end();
                let cut = t.char_indices().rev().nth(199).map_or(0, |(i, _)| i);
                Err(LlmError::Truncated {
                    endpoint: resp.endpoint,
                    finish_reason: reason.to_string(),
                    limit: self.cfg.max_tokens,
                    tail: format!("{}{}", if cut > 0 { "..." } else { "" }, &t[cut..]),
                })
            }
            _ => Ok(resp.text),
        }
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
    // A server's number, bounded before it becomes a Duration: `Duration::from_secs_f64` panics
    // past about 1.8e19 s, and `Retry-After: 1e20` is only bytes from outside. A day is far
    // beyond any wait the client would honour anyway.
    const MOST_S: f64 = 86_400.0;
    let secs = |s: f64| (s.is_finite() && s >= 0.0).then(|| Duration::from_secs_f64(s.min(MOST_S)));
    if let Some(ms) = h.get("retry-after-ms").and_then(|v| v.to_str().ok()).and_then(|s| s.trim().parse::<f64>().ok()) {
        if let Some(d) = secs(ms / 1000.0) {
            return Some(d);
        }
    }
    let v = h.get(reqwest::header::RETRY_AFTER)?.to_str().ok()?.trim();
    if let Ok(s) = v.parse::<f64>() {
        return secs(s);
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

#[cfg(test)]
mod tests {
    use super::*;

    /// The rule: never panic on bytes from outside: huge or odd numbers from a server
    /// are bounded or ignored, not turned into a panicking Duration.
    #[test]
    fn hostile_retry_after_headers_do_not_panic() {
        let mut h = reqwest::header::HeaderMap::new();
        for (name, value, want) in [
            ("retry-after", "1e20", Some(86_400.0)),
            ("retry-after-ms", "1e30", Some(86_400.0)),
            ("retry-after", "-1", None),
            ("retry-after", "NaN", None),
            ("retry-after", "2.5", Some(2.5)),
        ] {
            h.clear();
            h.insert(name, value.parse().unwrap());
            assert_eq!(retry_after(&h).map(|d| d.as_secs_f64()), want, "{name}: {value}");
        }
    }

    #[test]
    fn http_dates() {
        assert_eq!(parse_http_date("Sun, 06 Nov 1994 08:49:37 GMT"), Some(784_111_777));
        assert_eq!(parse_http_date("Thu, 01 Jan 1970 00:00:00 GMT"), Some(0));
        assert_eq!(parse_http_date("soon"), None);
    }
}
