//! Recordings: `<dir>/<sha256 of the canonical request>.json`, one file per distinct request
//! holding every response it got, in order. The canonical request is the wire format, the model,
//! the temperature, the token limit, the messages and the reply's JSON Schema when one is sent
//! (not the key, not the base URL: the same model behind another server replays the same).
//! Replay serves the n-th occurrence of a request in a session from the n-th recorded response,
//! so a design that asked the same thing twice replays both answers.
//!
//! [`CanonicalRequest`] is what is hashed, [`Recording`] one file, [`Recorder`] one directory.

use super::{ChatMessage, LlmError, Provider};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

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
        let text = match lmac_shm_schema::safe_fs::read_text_capped(&path, lmac_shm_schema::safe_fs::TEXT_CAP) {
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
    pub fn next_recorded(&mut self, req: &CanonicalRequest) -> Result<Option<RecordedResponse>, LlmError> {
        let key = req.key();
        let n = self.seen.get(&key).copied().unwrap_or(0);
        let Some(mut rec) = self.load(&key)? else { return Ok(None) };
        if n >= rec.responses.len() {
            return Ok(None);
        }
        self.seen.insert(key, n + 1);
        Ok(Some(rec.responses.swap_remove(n)))
    }

    /// How many times the request was recorded, and how many of those this session used.
    pub(super) fn occurrences(&self, req: &CanonicalRequest) -> (usize, usize) {
        let key = req.key();
        let recorded = self.load(&key).ok().flatten().map_or(0, |r| r.responses.len());
        (recorded, self.seen.get(&key).copied().unwrap_or(0))
    }

    /// Append a response (atomically: written to a temporary file, then renamed), under an
    /// exclusive lock on the directory's `.lock` file: designs running side by side (processes or
    /// threads) that record into one directory each read, extend and replace a recording in turn,
    /// so no paid response is lost to a concurrent writer.
    pub fn append(&mut self, req: &CanonicalRequest, resp: RecordedResponse) -> Result<(), LlmError> {
        let key = req.key();
        let path = self.path(&key);
        std::fs::create_dir_all(&self.dir)
            .map_err(|e| LlmError::Recording { path: self.dir.clone(), problem: format!("cannot create the directory: {e}") })?;
        let lock_path = self.dir.join(".lock");
        let lock = std::fs::OpenOptions::new()
            .create(true)
            .truncate(false)
            .write(true)
            .open(&lock_path)
            .and_then(|f| lmac_run::safe_fs::lock_exclusive(&f, true).map(|()| f))
            .map_err(|e| LlmError::Recording { path: lock_path.clone(), problem: format!("cannot lock: {e}") })?;
        let mut rec = self.load(&key)?.unwrap_or_else(|| Recording { key: key.clone(), request: req.clone(), responses: Vec::new() });
        rec.responses.push(resp);
        let n = rec.responses.len();
        let text = serde_json::to_string_pretty(&rec).expect("a recording serializes");
        // The lock keeps writers apart, in this process too (flock locks belong to open files).
        let tmp = self.dir.join(format!(".{key}.json.tmp{}", std::process::id()));
        std::fs::write(&tmp, text).map_err(|e| LlmError::Recording { path: tmp.clone(), problem: format!("cannot write: {e}") })?;
        std::fs::rename(&tmp, &path)
            .map_err(|e| LlmError::Recording { path: path.clone(), problem: format!("cannot rename {} into place: {e}", tmp.display()) })?;
        drop(lock);
        // This answer is the session's occurrence n-1 of the request.
        self.seen.insert(key, n);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An OpenAI request for model `m` at temperature 0.6 with one user message.
    fn request(text: &str) -> CanonicalRequest {
        CanonicalRequest {
            provider: Provider::OpenAi,
            model: "m".into(),
            temperature: 0.6,
            max_tokens: None,
            messages: vec![ChatMessage::user(text)],
            response_schema: None,
        }
    }

    #[test]
    fn canonical_key_ignores_nothing_that_matters() {
        let r = request("hi");
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

    /// Designs recording into one directory side by side (threads here; processes take the same
    /// lock) lose no response: each append reads, extends and replaces the file in turn.
    #[test]
    fn concurrent_appends_to_one_recording_keep_every_response() {
        let dir = std::env::temp_dir().join(format!("lmac-recording-race-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let req = request("the same question");
        let (writers, each) = (4, 25);
        std::thread::scope(|s| {
            for w in 0..writers {
                let (dir, req) = (dir.clone(), req.clone());
                s.spawn(move || {
                    let mut r = Recorder::new(dir);
                    for i in 0..each {
                        let resp = RecordedResponse {
                            text: format!("{w}-{i}"),
                            endpoint: "e".into(),
                            served_model: None,
                            usage: serde_json::Value::Null,
                            finish_reason: None,
                            elapsed_ms: 0,
                            unix_time: 0,
                        };
                        r.append(&req, resp).unwrap();
                    }
                });
            }
        });
        let rec = Recorder::new(&dir).load(&req.key()).unwrap().unwrap();
        let mut texts: Vec<String> = rec.responses.iter().map(|r| r.text.clone()).collect();
        texts.sort();
        texts.dedup();
        assert_eq!(texts.len(), writers * each, "responses lost to concurrent writers");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
