//! The LLM designer (paper section 4.1, appendix B.1-B.2): the LLM reasons about the
//! task-critical state dims, writes the phase-0 protocol from the task prompt, turns the
//! meta-information into feedback, and writes the later phases with that feedback appended.
//!
//! Every reply is checked before it is used. An unusable protocol (not JSON, schema errors,
//! validation errors, over the budget) or feedback (not JSON, missing keys) goes back to the LLM
//! with the exact problem, as the paper's Reflexion-style correction, a bounded number of times;
//! then the designer fails with the last problem and the transcript keeps every prompt and reply.

use super::llm::{ChatMessage, LlmClient, LlmMode, StructuredOutput};
use super::meta_info::MetaInfo;
use super::prompts::{budget_left, Templates};
use super::{DesignContext, Designer, Feedback, PhaseProtocol, TranscriptEntry};
use anyhow::{anyhow, bail, Result};
use lmac_protocol_runner::protocol::{self, ValidatedProtocol};
use std::path::PathBuf;

/// How patient the designer is and how much meta-information it shows.
#[derive(Clone, Debug)]
pub struct LlmDesignerOptions {
    /// Corrections per reply before giving up (the first try does not count).
    pub max_retries: usize,
    /// Most characters of meta-information JSON in the feedback prompt.
    pub meta_max_chars: usize,
    /// The environment variable holding the key for a custom base URL (a local llama.cpp, vLLM or
    /// Ollama server, a proxy): without it no key is sent there, not even `OPENAI_API_KEY`. Used
    /// by [`LlmDesigner::from_spec`] (the CLI's `--api-key-env VAR`).
    pub api_key_env: Option<String>,
    /// How the protocol's JSON Schema goes with a generation request (None: the provider's
    /// default, see [`StructuredOutput`]); the CLI's `--structured-output`.
    pub structured: Option<StructuredOutput>,
    /// The reply token limit sent with every request (None: the provider's default, see
    /// [`super::llm::LlmConfig::max_tokens`]); the CLI's `--llm-max-tokens`.
    pub max_tokens: Option<u32>,
}

impl Default for LlmDesignerOptions {
    fn default() -> Self {
        LlmDesignerOptions { max_retries: 3, meta_max_chars: 60_000, api_key_env: None, structured: None, max_tokens: None }
    }
}

/// The designer driven by an LLM client.
pub struct LlmDesigner {
    client: Box<dyn LlmClient>,
    templates: Templates,
    options: LlmDesignerOptions,
    transcript: Vec<TranscriptEntry>,
    system_logged: bool,
    /// The critical-dims exchange of phase 0 (prompt, reply): later generation prompts continue
    /// from it, so "the critical dims identified above" means the same thing in every phase.
    critical: Option<(String, String)>,
}

impl LlmDesigner {
    /// A designer with the templates of `$LMAC_PROMPTS_DIR` or the embedded ones.
    pub fn new(client: Box<dyn LlmClient>) -> Result<Self> {
        Ok(Self::with_templates(client, Templates::from_env()?, LlmDesignerOptions::default()))
    }

    pub fn with_templates(client: Box<dyn LlmClient>, templates: Templates, options: LlmDesignerOptions) -> Self {
        LlmDesigner { client, templates, options, transcript: Vec::new(), system_logged: false, critical: None }
    }

    /// For the CLI: `openai:gpt-4.1` (optional base URL), live or replayed, recorded in
    /// `record_dir`.
    pub fn from_spec(
        spec: &str,
        base_url: Option<&str>,
        mode: LlmMode,
        record_dir: Option<PathBuf>,
        options: LlmDesignerOptions,
    ) -> Result<Self> {
        let mut client = super::llm::client_from_spec(spec, base_url, options.api_key_env.as_deref(), mode, record_dir)?;
        if let Some(s) = options.structured {
            client.set_structured(s);
        }
        if let Some(n) = options.max_tokens {
            client.set_max_tokens(n);
        }
        Ok(Self::with_templates(Box::new(client), Templates::from_env()?, options))
    }

    pub fn options_mut(&mut self) -> &mut LlmDesignerOptions {
        &mut self.options
    }

    fn log(&mut self, phase: usize, kind: &str, prompt: &str, reply: &str) {
        self.transcript.push(TranscriptEntry { phase, kind: kind.to_string(), prompt: prompt.to_string(), reply: reply.to_string() });
    }

    /// One request; the prompt is the last message; `schema`: the JSON Schema the reply must
    /// follow (sent as structured output where the provider has it). A failed request is kept in
    /// the transcript with the error in place of the reply.
    fn ask(&mut self, phase: usize, kind: &str, msgs: &[ChatMessage], what: &str, schema: Option<&serde_json::Value>) -> Result<String> {
        if !self.system_logged {
            if let Some(sys) = msgs.iter().find(|m| m.role == super::llm::Role::System) {
                self.system_logged = true;
                let text = sys.content.clone();
                self.log(phase, "system", &text, "");
            }
        }
        let prompt = msgs.last().map(|m| m.content.clone()).unwrap_or_default();
        let answer = match schema {
            Some(s) => self.client.complete_with_schema(msgs, s),
            None => self.client.complete(msgs),
        };
        match answer {
            Ok(reply) => {
                self.log(phase, kind, &prompt, &reply);
                Ok(reply)
            }
            Err(e) => {
                self.log(phase, kind, &prompt, &format!("(no reply: {e})"));
                Err(anyhow!(e).context(format!("phase {phase}: {what}: asking {}", self.client.name())))
            }
        }
    }

    /// Ask until `accept` takes the reply, handing each problem back through `correction`.
    fn converse<T>(
        &mut self,
        phase: usize,
        kind: &str,
        mut msgs: Vec<ChatMessage>,
        what: &str,
        schema: Option<&serde_json::Value>,
        mut accept: impl FnMut(&str) -> Result<T, String>,
        correction: impl Fn(&Templates, &str) -> Result<String>,
    ) -> Result<T> {
        let mut attempt = 0usize;
        loop {
            let reply = self.ask(phase, if attempt == 0 { kind } else { "correction" }, &msgs, what, schema)?;
            let problem = match accept(&reply) {
                Ok(t) => return Ok(t),
                Err(p) => p,
            };
            if attempt >= self.options.max_retries {
                bail!(
                    "phase {phase}: {what}: {} still gave no usable reply after {} correction(s) (the transcript keeps every prompt and reply); the last problem:\n{problem}",
                    self.client.name(),
                    attempt
                );
            }
            attempt += 1;
            eprintln!("lmac: phase {phase}: {what}: the reply is unusable, asking for correction {attempt}/{}", self.options.max_retries);
            let fix = correction(&self.templates, &problem)?;
            msgs.push(ChatMessage::assistant(reply));
            msgs.push(ChatMessage::user(fix));
        }
    }

    /// Generate and validate phase `phase`'s protocol from a conversation ending in the
    /// generation prompt.
    fn generate(
        &mut self,
        ctx: &DesignContext,
        phase: usize,
        msgs: Vec<ChatMessage>,
        previous: &[ValidatedProtocol],
    ) -> Result<(protocol::Protocol, ValidatedProtocol)> {
        let env = ctx.env;
        let left = budget_left(env, previous);
        // Replies follow the protocol language's JSON Schema by construction where the provider
        // supports structured output; validation still checks what a schema cannot say.
        let schema = protocol::schema::schema_value();
        self.converse(
            phase,
            "protocol",
            msgs,
            "writing the protocol",
            Some(&schema),
            |reply| {
                let mut p = protocol::parse_llm_text(reply).map_err(|e| protocol::errors_to_text(&e))?;
                // The phase number is ours to decide; the LLM's copy of it carries no information.
                p.phase = Some(phase as u32);
                let v = protocol::validate_phase(&p, env, previous).map_err(|e| protocol::errors_to_text(&e))?;
                Ok((p, v))
            },
            |t, problem| t.correction(phase, problem, left),
        )
    }

    fn check_room(ctx: &DesignContext, phase: usize, previous: &[ValidatedProtocol]) -> Result<()> {
        let left = budget_left(ctx.env, previous);
        // The narrowest possible phase: one column per sender block, no one-hot.
        let min = ctx.env.n_agents.saturating_sub(1).max(1);
        if left < min {
            bail!(
                "phase {phase}: no room in the message budget: {} columns per receiving agent, the earlier phases use {}, and even a one-column field needs {min}",
                ctx.env.message_budget,
                ctx.env.message_budget - left
            );
        }
        Ok(())
    }
}

/// The JSON Schema of a feedback reply (B.1's three parts), sent as structured output.
pub fn feedback_schema() -> serde_json::Value {
    let text = serde_json::json!({"type": "string"});
    serde_json::json!({
        "type": "object",
        "properties": {"Evaluation": text, "Missing_Information_Hypothesis": text, "Improvement_Suggestions": text},
        "required": ["Evaluation", "Missing_Information_Hypothesis", "Improvement_Suggestions"]
    })
}

/// The feedback out of a reply: the reply itself, a fenced block or a balanced `{...}` in the
/// prose, with the three keys (spelling of case, spaces and underscores forgiven; lists joined).
pub fn parse_feedback(reply: &str) -> Result<Feedback, String> {
    let mut first_error: Option<String> = None;
    let mut best_missing: Option<String> = None;
    for cand in json_candidates(reply) {
        let v: serde_json::Value = match serde_json::from_str(&protocol::escape_controls_in_strings(cand.trim())) {
            Ok(v) => v,
            Err(e) => {
                // Only text that looks like an object earns a parse error; prose is just skipped.
                if cand.trim_start().starts_with('{') {
                    first_error.get_or_insert_with(|| format!("the JSON object is not valid JSON ({e})"));
                }
                continue;
            }
        };
        let Some(obj) = v.as_object() else { continue };
        let mut fb = [None::<String>, None, None];
        for (k, x) in obj {
            let norm: String = k.chars().filter(|c| c.is_ascii_alphanumeric()).collect::<String>().to_ascii_lowercase();
            let slot = match norm.as_str() {
                "evaluation" => 0,
                "missinginformationhypothesis" => 1,
                "improvementsuggestions" => 2,
                _ => continue,
            };
            fb[slot] = Some(as_text(x));
        }
        const KEYS: [&str; 3] = ["Evaluation", "Missing_Information_Hypothesis", "Improvement_Suggestions"];
        let missing: Vec<&str> =
            KEYS.iter().zip(&fb).filter(|(_, v)| v.as_deref().is_none_or(|s| s.trim().is_empty())).map(|(k, _)| *k).collect();
        if missing.is_empty() {
            let [a, b, c] = fb.map(Option::unwrap_or_default);
            return Ok(Feedback { evaluation: a, missing_information_hypothesis: b, improvement_suggestions: c });
        }
        let found: Vec<&String> = obj.keys().collect();
        best_missing.get_or_insert_with(|| {
            format!("the JSON object lacks (or leaves empty) the key(s) {} (its keys: {found:?})", missing.join(", "))
        });
    }
    Err(best_missing.or(first_error).unwrap_or_else(|| "no JSON object found in the reply".to_string()))
}

/// A JSON value as feedback text: strings as they are, lists one item per line, others as JSON.
fn as_text(v: &serde_json::Value) -> String {
    match v {
        serde_json::Value::String(s) => s.clone(),
        serde_json::Value::Array(a) => a.iter().map(as_text).collect::<Vec<_>>().join("\n"),
        serde_json::Value::Null => String::new(),
        other => serde_json::to_string_pretty(other).unwrap_or_default(),
    }
}

/// Where a JSON object may be in a reply, most likely first: the whole reply, fenced blocks, then
/// every balanced top-level `{...}` (braces inside strings ignored).
fn json_candidates(text: &str) -> Vec<&str> {
    let mut out = vec![text.trim()];
    let mut rest = text;
    while let Some(a) = rest.find("```") {
        let body = &rest[a + 3..];
        // The info string (`json`) is short: look for its newline in the first bytes only, so a
        // reply of many fences and no newline stays linear instead of rescanning to the end.
        let nl = body.as_bytes().iter().take(40).position(|&b| b == b'\n');
        let body = nl.map_or(body, |nl| if body[..nl].trim().chars().all(|c| c.is_ascii_alphanumeric()) { &body[nl + 1..] } else { body });
        match body.find("```") {
            Some(b) => {
                out.push(&body[..b]);
                rest = &body[b + 3..];
            }
            None => break,
        }
    }
    let bytes = text.as_bytes();
    let (mut depth, mut start, mut in_str, mut esc) = (0usize, 0usize, false, false);
    for (i, &c) in bytes.iter().enumerate() {
        if in_str {
            match (esc, c) {
                (true, _) => esc = false,
                (false, b'\\') => esc = true,
                (false, b'"') => in_str = false,
                _ => {}
            }
            continue;
        }
        match c {
            b'"' if depth > 0 => in_str = true,
            b'{' => {
                if depth == 0 {
                    start = i;
                }
                depth += 1;
            }
            b'}' if depth > 0 => {
                depth -= 1;
                if depth == 0 {
                    out.push(&text[start..=i]);
                }
            }
            _ => {}
        }
    }
    out
}

fn feedback_markdown(phase: usize, fb: &Feedback) -> String {
    format!(
        "# Phase {phase}: the feedback this protocol answers\n\n## Evaluation\n{}\n\n## Missing information hypothesis\n{}\n\n## Improvement suggestions\n{}\n",
        fb.evaluation.trim(),
        fb.missing_information_hypothesis.trim(),
        fb.improvement_suggestions.trim()
    )
}

impl Designer for LlmDesigner {
    fn name(&self) -> String {
        self.client.name()
    }

    fn needs_data_for_initial(&self) -> bool {
        false
    }

    fn initial(&mut self, ctx: &DesignContext) -> Result<PhaseProtocol> {
        Self::check_room(ctx, 0, &[])?;
        let system = self.templates.system()?;
        let cd_prompt = format!("{}\n{}", self.templates.task(ctx.env_name, ctx.schema)?, self.templates.critical_dims(ctx.env)?);
        let mut msgs = vec![ChatMessage::system(system), ChatMessage::user(cd_prompt.clone())];
        let cot = self.ask(0, "critical_dims", &msgs, "selecting the task-critical state dims", None)?;
        self.critical = Some((cd_prompt, cot.clone()));
        msgs.push(ChatMessage::assistant(cot.clone()));
        msgs.push(ChatMessage::user(self.templates.protocol_generation(ctx.env, 0, &[])?));
        let (p, v) = self.generate(ctx, 0, msgs, &[])?;
        let reasoning = format!("# Phase 0: task-critical state dims (the LLM's reasoning before the protocol)\n\n{}\n", cot.trim());
        Ok(PhaseProtocol { protocol: p, validated: v, reasoning })
    }

    fn feedback(&mut self, ctx: &DesignContext, phase: usize, previous: &[PhaseProtocol], meta: &MetaInfo) -> Result<Feedback> {
        let prev: Vec<ValidatedProtocol> = previous.iter().map(|p| p.validated.clone()).collect();
        let prompt = self.templates.feedback(ctx.env_name, ctx.schema, ctx.env, phase, &prev, meta, self.options.meta_max_chars)?;
        let msgs = vec![ChatMessage::system(self.templates.system()?), ChatMessage::user(prompt)];
        let schema = feedback_schema();
        self.converse(phase, "feedback", msgs, "writing the feedback", Some(&schema), parse_feedback, |t, problem| {
            t.feedback_correction(problem)
        })
    }

    fn refine(
        &mut self,
        ctx: &DesignContext,
        phase: usize,
        previous: &[PhaseProtocol],
        feedback: &Feedback,
        _meta: &MetaInfo,
    ) -> Result<PhaseProtocol> {
        let prev: Vec<ValidatedProtocol> = previous.iter().map(|p| p.validated.clone()).collect();
        Self::check_room(ctx, phase, &prev)?;
        let generation =
            format!("{}\n{}", self.templates.protocol_generation(ctx.env, phase, &prev)?, self.templates.additional_context(feedback)?);
        let mut msgs = vec![ChatMessage::system(self.templates.system()?)];
        match &self.critical {
            // Continue from the phase-0 reasoning about the critical dims (it holds I_T).
            Some((cd_prompt, cot)) => {
                msgs.push(ChatMessage::user(cd_prompt.clone()));
                msgs.push(ChatMessage::assistant(cot.clone()));
                msgs.push(ChatMessage::user(generation));
            }
            // Phase 0 came from elsewhere: the task prompt goes with the generation prompt.
            None => msgs.push(ChatMessage::user(format!("{}\n{generation}", self.templates.task(ctx.env_name, ctx.schema)?))),
        }
        let (p, v) = self.generate(ctx, phase, msgs, &prev)?;
        Ok(PhaseProtocol { protocol: p, validated: v, reasoning: feedback_markdown(phase, feedback) })
    }

    fn transcript(&self) -> Vec<TranscriptEntry> {
        self.transcript.clone()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn feedback_from_prose_and_fences() {
        let plain = r#"{"Evaluation": "e", "Missing_Information_Hypothesis": "m", "Improvement_Suggestions": "i"}"#;
        assert_eq!(parse_feedback(plain).unwrap().evaluation, "e");
        let fenced = format!("Here is my analysis.\n```json\n{plain}\n```\nThanks.");
        assert_eq!(parse_feedback(&fenced).unwrap().missing_information_hypothesis, "m");
        let prose = r#"Analysis {not json} then {"evaluation": "a {brace} \"q\"", "Missing Information Hypothesis": "b", "improvement_suggestions": ["1. x", "2. y"]} end"#;
        let fb = parse_feedback(prose).unwrap();
        assert_eq!((fb.evaluation.as_str(), fb.improvement_suggestions.as_str()), ("a {brace} \"q\"", "1. x\n2. y"));
        let e = parse_feedback(r#"{"Evaluation": "e", "Improvement_Suggestions": ""}"#).unwrap_err();
        assert!(e.contains("Missing_Information_Hypothesis") && e.contains("Improvement_Suggestions"), "{e}");
        let e = parse_feedback("I think the protocol is fine.").unwrap_err();
        assert!(e.contains("no JSON object"), "{e}");
        let e = parse_feedback("{\"Evaluation\": \"e\",}").unwrap_err();
        assert!(e.contains("not valid JSON"), "{e}");
    }

    #[test]
    fn many_fences_without_newlines_stay_fast() {
        // Found by lmac-fuzz: each fence used to rescan the rest of the reply for a newline, so
        // the time grew with the square of the reply. Checked as a ratio of two sizes measured
        // side by side (linear: 8x for 8x the fences, quadratic: 64x), not as an absolute time,
        // which a busy machine stretches; the fastest of three runs, so a preemption does not count.
        let time = |fences: usize| {
            let reply = "```".repeat(fences);
            let once = || {
                let t = std::time::Instant::now();
                assert!(parse_feedback(&reply).is_err());
                t.elapsed()
            };
            (0..3).map(|_| once()).min().expect("three runs")
        };
        let (small, large) = (time(50_000), time(400_000));
        assert!(large < small * 24 + std::time::Duration::from_millis(20), "{small:?} for 50k fences, {large:?} for 400k");
    }
}
