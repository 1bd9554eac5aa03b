//! The LLM designer over real HTTP on loopback: a scripted server that speaks the OpenAI
//! chat-completions (and once the Anthropic Messages) wire format answers with prepared replies.
//! Covered: the full three-phase loop with an invalid-JSON reply, a protocol that fails validation
//! and is corrected, feedback missing a key, 429 and 503 retried; a timeout that ends in a clear
//! error with the transcript kept; recording and exact offline replay; the API key never written.

use lmac_design::discriminator::{DiscriminatorConfig, TrainReport};
use lmac_design::llm::{ApiKey, ChatMessage, HttpLlm, LlmClient, LlmConfig, LlmError, LlmMode, StructuredOutput};
use lmac_design::llm_designer::{LlmDesigner, LlmDesignerOptions};
use lmac_design::meta_info::{DimRecovery, DiscriminatorReports, EvaluationFacts, MetaInfo, MetaSummary, RecoverySummary, SideRecovery};
use lmac_design::prompts::Templates;
use lmac_design::{DesignContext, Designer, PhaseProtocol};
use lmac_protocol_runner::protocol;
use std::collections::VecDeque;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Duration;

const ENV: &str = "lbf:8x8-2p-2f-s1-coop";
const KEY: &str = "sk-test-0123456789-do-not-leak";
const PHASE0: &str = include_str!("../../../prompts/examples/lbf_8x8_phase0.json");
const PHASE1: &str = include_str!("../../../prompts/examples/lbf_8x8_phase1.json");
const PHASE2: &str = include_str!("../../../prompts/examples/lbf_8x8_phase2.json");

/// What the server does with the next request.
enum Reply {
    /// 200 with an OpenAI chat completion carrying this text.
    Chat(String),
    /// 200 with an Anthropic message carrying this text.
    Anthropic(String),
    /// This status, an optional Retry-After, and this body.
    Status(u16, Option<&'static str>, String),
    /// Read the request, answer nothing for this long, then close.
    Hang(Duration),
    /// 307 Temporary Redirect (method and body kept) to this URL.
    Redirect(String),
    /// 200 whose body is closed half-way (Content-Length promises more than is sent).
    CutBody,
}

#[derive(Debug, Clone)]
struct Captured {
    path: String,
    headers: Vec<(String, String)>,
    body: serde_json::Value,
}

impl Captured {
    fn header(&self, name: &str) -> Option<&str> {
        self.headers.iter().find(|(k, _)| k.eq_ignore_ascii_case(name)).map(|(_, v)| v.as_str())
    }
    /// The text of the last message of an OpenAI-style body.
    fn last_message(&self) -> String {
        self.body["messages"].as_array().and_then(|m| m.last()).and_then(|m| m["content"].as_str()).unwrap_or_default().to_string()
    }
    fn all_text(&self) -> String {
        self.body.to_string()
    }
}

struct Server {
    url: String,
    requests: Arc<Mutex<Vec<Captured>>>,
    script: Arc<Mutex<VecDeque<Reply>>>,
}

impl Server {
    fn start(script: Vec<Reply>) -> Server {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let url = format!("http://{}", listener.local_addr().unwrap());
        let requests = Arc::new(Mutex::new(Vec::new()));
        let script = Arc::new(Mutex::new(script.into_iter().collect::<VecDeque<_>>()));
        let (rq, sc) = (requests.clone(), script.clone());
        std::thread::spawn(move || {
            for stream in listener.incoming().flatten() {
                let (rq, sc) = (rq.clone(), sc.clone());
                std::thread::spawn(move || serve(stream, rq, sc));
            }
        });
        Server { url, requests, script }
    }
    fn requests(&self) -> Vec<Captured> {
        self.requests.lock().unwrap().clone()
    }
    fn remaining(&self) -> usize {
        self.script.lock().unwrap().len()
    }
}

/// One request per connection (the response says `Connection: close`).
fn serve(stream: TcpStream, requests: Arc<Mutex<Vec<Captured>>>, script: Arc<Mutex<VecDeque<Reply>>>) {
    let mut reader = BufReader::new(stream.try_clone().unwrap());
    let mut line = String::new();
    if reader.read_line(&mut line).unwrap_or(0) == 0 {
        return;
    }
    let path = line.split_whitespace().nth(1).unwrap_or("").to_string();
    let mut headers = Vec::new();
    loop {
        let mut h = String::new();
        reader.read_line(&mut h).unwrap();
        let h = h.trim_end();
        if h.is_empty() {
            break;
        }
        if let Some((k, v)) = h.split_once(':') {
            headers.push((k.trim().to_string(), v.trim().to_string()));
        }
    }
    let len: usize = headers.iter().find(|(k, _)| k.eq_ignore_ascii_case("content-length")).map_or(0, |(_, v)| v.parse().unwrap());
    let mut body = vec![0u8; len];
    reader.read_exact(&mut body).unwrap();
    let body: serde_json::Value = serde_json::from_slice(&body).unwrap_or(serde_json::Value::Null);
    requests.lock().unwrap().push(Captured { path, headers, body });
    let reply = script.lock().unwrap().pop_front();
    let (status, extra, text) = match reply {
        Some(Reply::Chat(t)) => (
            200,
            String::new(),
            serde_json::json!({
                "id": "chatcmpl-test", "object": "chat.completion", "model": "scripted-model",
                "choices": [{"index": 0, "message": {"role": "assistant", "content": t}, "finish_reason": "stop"}],
                "usage": {"prompt_tokens": 10, "completion_tokens": 5, "total_tokens": 15}
            })
            .to_string(),
        ),
        Some(Reply::Anthropic(t)) => (
            200,
            String::new(),
            serde_json::json!({
                "id": "msg_test", "type": "message", "role": "assistant", "model": "scripted-claude",
                "content": [{"type": "text", "text": t}], "stop_reason": "end_turn",
                "usage": {"input_tokens": 10, "output_tokens": 5}
            })
            .to_string(),
        ),
        Some(Reply::Status(code, retry, body)) => (code, retry.map_or(String::new(), |r| format!("Retry-After: {r}\r\n")), body),
        Some(Reply::Redirect(to)) => (307, format!("Location: {to}\r\n"), String::new()),
        Some(Reply::CutBody) => {
            let mut out = stream;
            let _ = write!(
                out,
                "HTTP/1.1 200 OK\r\nContent-Type: application/json\r\nContent-Length: 500\r\nConnection: close\r\n\r\n{{\"choices\": ["
            );
            let _ = out.flush();
            return;
        }
        Some(Reply::Hang(d)) => {
            std::thread::sleep(d);
            return;
        }
        None => (400, String::new(), "{\"error\": \"the test script has no more replies\"}".to_string()),
    };
    let mut out = stream;
    let _ = write!(
        out,
        "HTTP/1.1 {status} X\r\nContent-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n{extra}\r\n{text}",
        text.len()
    );
    let _ = out.flush();
}

fn temp_dir(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!(
        "lmac-design-llm-{tag}-{}-{:?}",
        std::process::id(),
        std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_nanos()
    ));
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// A config for the scripted server, fast enough for tests.
fn config(spec: &str, url: &str) -> LlmConfig {
    let base = if spec.starts_with("anthropic") { url.to_string() } else { format!("{url}/v1") };
    let mut c = LlmConfig::from_spec(spec, Some(&base)).unwrap();
    c.timeout = Duration::from_millis(800);
    c.max_attempts = 3;
    c.backoff = Duration::from_millis(10);
    c.backoff_max = Duration::from_millis(50);
    c
}

/// Meta-information in the shape of the paper's Figure B.2 (synthetic numbers) for phases
/// 0..=`phase`.
fn meta(phase: usize) -> MetaInfo {
    let with = SideRecovery::from_rates(&[0.61, 0.42], [&[0.5, 0.3], &[0.6, 0.4], &[0.7, 0.5]]);
    let without = SideRecovery::from_rates(&[0.40, 0.38], [&[0.3, 0.3], &[0.4, 0.4], &[0.5, 0.4]]);
    let dims = [104usize, 105, 116];
    MetaInfo {
        env: ENV.into(),
        alpha: 0.1,
        phases: phase + 1,
        message_columns: 21,
        evaluation: EvaluationFacts { held_out_episodes: 100, held_out_rows: 5000, note: "synthetic".into() },
        discriminators: DiscriminatorReports {
            with_communication: TrainReport::default(),
            without_communication: TrainReport::default(),
            config: DiscriminatorConfig::default(),
        },
        target_dims_selection: "synthetic".into(),
        dimensions: dims
            .iter()
            .map(|&d| DimRecovery {
                dim: d,
                dimension: format!("s[{d}] - food layer of the padded grid, cell {d}"),
                constant_guess_rate: 0.3,
                with_communication: with.clone(),
                without_communication: without.clone(),
            })
            .collect(),
        summary: MetaSummary {
            target_dims: dims.to_vec(),
            with_communication: RecoverySummary { mean_recovery: 0.52, mean_variance_across_agents: 0.009 },
            without_communication: RecoverySummary { mean_recovery: 0.39, mean_variance_across_agents: 0.001 },
        },
        dead_fields: vec!["phase 0 field `x` from agent 0 to agent 1 carries nothing on the dataset: [0] always 0".into()],
        verdicts: vec!["phase 1 does NOT add to the earlier phases (recovery on the 4 fixed dims 0.500 with phases 0..=1 against 0.510 with phases 0..1)".into()],
        newest_phase_added: Some(false),
    }
}

fn feedback_json(tag: &str) -> String {
    serde_json::json!({
        "Evaluation": format!("{tag}: messages help agent 0 more than agent 1 on the food layer."),
        "Missing_Information_Hypothesis": format!("{tag}: agents do not know which food is adjacent to the teammate."),
        "Improvement_Suggestions": format!("{tag}: send an adjacency flag per direction and a food count.")
    })
    .to_string()
}

fn quiet_designer(client: Box<dyn LlmClient>) -> LlmDesigner {
    LlmDesigner::with_templates(
        client,
        Templates::embedded(),
        LlmDesignerOptions { max_retries: 3, meta_max_chars: 20_000, ..Default::default() },
    )
}

/// Phase 0, feedback + phase 1, feedback + phase 2, as `run_design` calls them.
fn run_three_phases(designer: &mut dyn Designer, ctx: &DesignContext) -> anyhow::Result<Vec<PhaseProtocol>> {
    let mut phases = vec![designer.initial(ctx)?];
    for k in 1..=2 {
        let m = meta(k - 1);
        let fb = designer.feedback(ctx, k, &phases, &m)?;
        let next = designer.refine(ctx, k, &phases, &fb, &m)?;
        phases.push(next);
    }
    Ok(phases)
}

fn files_under(dir: &Path) -> Vec<PathBuf> {
    std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().path()).collect()
}

fn example(text: &str) -> protocol::Protocol {
    protocol::parse_str(text).unwrap()
}

#[test]
fn three_phases_with_corrections_retries_recording_and_replay() {
    let schema = lmac_shm_schema::schema::load_env(ENV).unwrap();
    let penv = lmac_protocol_runner::protocol_env(&schema);
    let ctx = DesignContext { env_name: ENV, schema: &schema, env: &penv, dataset: None, seed: 1 };

    let bad_dim = PHASE0.replace("[19, 25, 21, 23]", "[19, 25, 21, 99]");
    assert_ne!(bad_dim, PHASE0);
    let server = Server::start(vec![
        // Phase 0: the critical dims reasoning, then the protocol.
        Reply::Chat("Step by step: food positions and the teammate's position decide success.\n{\"critical_state_dims\": [{\"start\": 0, \"end\": 200}], \"reason\": \"food and agents\"}".into()),
        Reply::Chat("Here is the protocol: {\"name\": \"x\", \"fields\": [}".into()),
        Reply::Chat(bad_dim),
        Reply::Status(429, Some("0"), "{\"error\": {\"message\": \"rate limited\"}}".into()),
        Reply::Chat(format!("Corrected:\n```json\n{PHASE0}\n```")),
        // Phase 1: feedback (first without a key), then the protocol.
        Reply::Chat("My analysis: {\"Evaluation\": \"good\", \"Improvement_Suggestions\": \"more\"}".into()),
        Reply::Chat(format!("```json\n{}\n```", feedback_json("phase1"))),
        Reply::Chat(PHASE1.into()),
        // Phase 2: feedback, a server error, the protocol.
        Reply::Chat(feedback_json("phase2")),
        Reply::Status(503, None, "overloaded".into()),
        Reply::Chat(PHASE2.into()),
    ]);
    let rec_dir = temp_dir("record");
    let mut cfg = config("openai:scripted-model", &server.url);
    cfg.record_dir = Some(rec_dir.clone());
    let client = HttpLlm::with_api_key(cfg, ApiKey::new(KEY)).unwrap();
    let mut designer = quiet_designer(Box::new(client));
    assert_eq!(designer.name(), "openai:scripted-model");
    assert!(!designer.needs_data_for_initial());

    let phases = run_three_phases(&mut designer, &ctx).unwrap();
    assert_eq!(server.remaining(), 0, "every scripted reply was used");
    for (k, (p, ex)) in phases.iter().zip([PHASE0, PHASE1, PHASE2]).enumerate() {
        assert_eq!(p.protocol, example(ex), "phase {k}");
        assert_eq!(p.protocol.phase, Some(k as u32));
    }
    assert_eq!(
        protocol::combined_width(&phases.iter().map(|p| p.validated.clone()).collect::<Vec<_>>()),
        protocol::check_phases(&phases.iter().map(|p| p.validated.clone()).collect::<Vec<_>>(), &penv).unwrap()
    );
    assert!(phases[0].reasoning.contains("food positions"));
    assert!(phases[1].reasoning.contains("phase1: send an adjacency flag"));

    let reqs = server.requests();
    assert_eq!(reqs.len(), 11);
    for r in &reqs {
        assert_eq!(r.path, "/v1/chat/completions");
        assert_eq!(r.header("authorization"), Some(format!("Bearer {KEY}").as_str()));
        assert_eq!(r.body["model"], "scripted-model");
        assert_eq!(r.body["temperature"], 0.6);
        assert_eq!(r.body["messages"][0]["role"], "system");
    }
    // Structured output (OpenAI style): the protocol language's JSON Schema with every protocol
    // request, the feedback's three keys with every feedback request, nothing with the
    // critical-dims reasoning (free text).
    assert!(reqs[0].body.get("response_format").is_none());
    let protocol_schema = protocol::schema::schema_value();
    for i in [1, 2, 3, 7, 10] {
        assert_eq!(reqs[i].body["response_format"]["type"], "json_schema", "request {i}");
        assert_eq!(reqs[i].body["response_format"]["json_schema"]["schema"], protocol_schema, "request {i}");
    }
    for i in [5, 6, 8] {
        let s = &reqs[i].body["response_format"]["json_schema"]["schema"];
        assert_eq!(
            s["required"],
            serde_json::json!(["Evaluation", "Missing_Information_Hypothesis", "Improvement_Suggestions"]),
            "request {i}"
        );
    }
    // I_T: shape, every obs and state dim, then the critical-dims step.
    let first = reqs[0].last_message();
    assert!(first.contains("(batch, 2, 29)") && first.contains("`o[batch][agent_id][28]`") && first.contains("`s[299]`"), "{first}");
    assert!(first.contains("task-critical state dimensions"));
    // I_P with the language reference and the budget, after the reasoning turn.
    let gen = reqs[1].last_message();
    assert!(gen.contains("Design principles") && gen.contains("\"obs_slice\"") && gen.contains("at most 64 message columns"), "{gen}");
    assert_eq!(reqs[1].body["messages"][2]["role"], "assistant");
    // Invalid JSON went back with the parser's text, the failed reply kept in the conversation.
    assert!(reqs[2].last_message().contains("invalid protocol JSON"), "{}", reqs[2].last_message());
    assert!(reqs[2].all_text().contains("Here is the protocol"));
    // The validation error went back verbatim.
    assert!(reqs[3].last_message().contains("observation dim 99 is out of range"), "{}", reqs[3].last_message());
    // The 429 was retried with the same request.
    assert_eq!(reqs[3].body, reqs[4].body);
    // Feedback prompt: phase instruction, protocol under analysis, meta-information, alpha.
    let fb1 = reqs[5].last_message();
    assert!(
        fb1.contains("recognition enhancement")
            && fb1.contains("lbf_8x8_phase0")
            && fb1.contains("s[105] - food layer")
            && fb1.contains("most 0.1"),
        "{fb1}"
    );
    assert!(fb1.contains("Missing_Information_Hypothesis"));
    // No wall-clock figures in a prompt: they would make it unreplayable.
    assert!(!fb1.contains("ms_per_update") && !fb1.contains("\"seconds\""), "{fb1}");
    // Dead fields reach the designer with the meta-information.
    assert!(fb1.contains("carries nothing on the dataset"), "{fb1}");
    // The feedback missing a key went back naming it.
    assert!(reqs[6].last_message().contains("Missing_Information_Hypothesis"), "{}", reqs[6].last_message());
    // Phase 1 generation: continues from the critical-dims reasoning, shows phase 0 and the
    // budget left, and appends the feedback as additional context.
    let g1 = reqs[7].last_message();
    assert!(
        g1.contains("phase 1 (recognition enhancement)")
            && g1.contains("earlier phases use 21")
            && g1.contains("phase1: agents do not know"),
        "{g1}"
    );
    assert!(g1.contains("Additional context"));
    assert_eq!(reqs[7].body["messages"][2]["role"], "assistant");
    let fb2 = reqs[8].last_message();
    assert!(fb2.contains("sharing enhancement") && fb2.contains("last 10 steps") && fb2.contains("lbf_8x8_phase1"), "{fb2}");
    assert_eq!(reqs[9].body, reqs[10].body, "the 503 was retried");

    let kinds: Vec<String> = designer.transcript().iter().map(|e| format!("{}:{}", e.phase, e.kind)).collect();
    assert_eq!(
        kinds,
        [
            "0:system",
            "0:critical_dims",
            "0:protocol",
            "0:correction",
            "0:correction",
            "1:feedback",
            "1:correction",
            "1:protocol",
            "2:feedback",
            "2:protocol"
        ]
    );

    // Recordings: one file per distinct request (the retried ones once) beside the writers'
    // lock, no key anywhere.
    let files = files_under(&rec_dir);
    let recordings = files.iter().filter(|f| f.extension().is_some_and(|e| e == "json")).count();
    assert_eq!(recordings, 9, "{files:?}");
    assert_eq!(files.len(), 10, "{files:?}");
    for f in &files {
        let text = std::fs::read_to_string(f).unwrap();
        assert!(!text.contains(KEY) && !text.contains("sk-test"), "{} holds the key", f.display());
    }
    let transcript = serde_json::to_string(&designer.transcript()).unwrap();
    assert!(!transcript.contains(KEY));

    // Replay: the same design again, offline, from the recordings only.
    let mut rcfg = LlmConfig::from_spec("openai:scripted-model", Some("http://127.0.0.1:9/v1")).unwrap();
    rcfg.mode = LlmMode::Replay;
    rcfg.record_dir = Some(rec_dir.clone());
    let mut replayer = quiet_designer(Box::new(HttpLlm::new(rcfg).unwrap()));
    let again = run_three_phases(&mut replayer, &ctx).unwrap();
    assert_eq!(again.iter().map(|p| p.protocol.clone()).collect::<Vec<_>>(), phases.iter().map(|p| p.protocol.clone()).collect::<Vec<_>>());
    assert_eq!(server.requests().len(), 11, "replay made no request");
    let a: Vec<_> = designer.transcript().iter().map(|e| (e.prompt.clone(), e.reply.clone())).collect();
    let b: Vec<_> = replayer.transcript().iter().map(|e| (e.prompt.clone(), e.reply.clone())).collect();
    assert_eq!(a, b, "the replayed conversation is the recorded one");

    // A request that was never recorded is a clear error.
    let mut rcfg = LlmConfig::from_spec("openai:scripted-model", None).unwrap();
    rcfg.mode = LlmMode::Replay;
    rcfg.record_dir = Some(rec_dir.clone());
    let mut c = HttpLlm::new(rcfg).unwrap();
    let e = c.complete(&[ChatMessage::user("never asked")]).unwrap_err();
    assert!(matches!(e, LlmError::ReplayMiss { .. }));
    let e = e.to_string();
    assert!(e.contains("no recording") && e.contains(&rec_dir.display().to_string()) && e.contains("never asked"), "{e}");
    let _ = std::fs::remove_dir_all(&rec_dir);
}

#[test]
fn corrections_are_bounded_and_the_transcript_is_kept() {
    let schema = lmac_shm_schema::schema::load_env(ENV).unwrap();
    let penv = lmac_protocol_runner::protocol_env(&schema);
    let ctx = DesignContext { env_name: ENV, schema: &schema, env: &penv, dataset: None, seed: 1 };
    let too_wide = PHASE0.replace("{\"obs_slice\": {\"start\": 9, \"end\": 18}}", "{\"concat\": [{\"obs_slice\": {\"start\": 0, \"end\": 27}}, {\"obs_slice\": {\"start\": 0, \"end\": 27}}, {\"obs_slice\": {\"start\": 0, \"end\": 27}}]}");
    assert_ne!(too_wide, PHASE0);
    let server = Server::start(vec![Reply::Chat("reasoning".into()), Reply::Chat("no json at all".into()), Reply::Chat(too_wide)]);
    let client = HttpLlm::new(config("openai:m", &server.url)).unwrap();
    let mut d =
        LlmDesigner::with_templates(Box::new(client), Templates::embedded(), LlmDesignerOptions { max_retries: 1, ..Default::default() });
    let e = format!("{:#}", d.initial(&ctx).unwrap_err());
    assert!(e.contains("phase 0") && e.contains("after 1 correction(s)") && e.contains("columns per receiving agent"), "{e}");
    let reqs = server.requests();
    assert_eq!(reqs.len(), 3);
    if std::env::var_os("OPENAI_API_KEY").is_none() {
        assert!(reqs[0].header("authorization").is_none(), "no key for a local server without one");
    }
    assert!(reqs[2].last_message().contains("no JSON object found"), "{}", reqs[2].last_message());
    let t = d.transcript();
    assert_eq!(t.len(), 4);
    assert!(t[3].reply.contains("\"concat\""), "the last bad reply is kept");
}

#[test]
fn timeout_ends_in_a_clear_error_with_the_transcript_kept() {
    let schema = lmac_shm_schema::schema::load_env(ENV).unwrap();
    let penv = lmac_protocol_runner::protocol_env(&schema);
    let ctx = DesignContext { env_name: ENV, schema: &schema, env: &penv, dataset: None, seed: 1 };
    let server = Server::start(vec![Reply::Hang(Duration::from_secs(3)), Reply::Hang(Duration::from_secs(3))]);
    let mut cfg = config("openai:m", &server.url);
    cfg.timeout = Duration::from_millis(300);
    cfg.max_attempts = 2;
    let started = std::time::Instant::now();
    let mut d = quiet_designer(Box::new(HttpLlm::with_api_key(cfg, ApiKey::new(KEY)).unwrap()));
    let e = format!("{:#}", d.initial(&ctx).unwrap_err());
    assert!(started.elapsed() < Duration::from_secs(3), "gave up within the timeouts");
    assert!(
        e.contains("timed out")
            && e.contains(&format!("{}/v1/chat/completions", server.url))
            && e.contains("2 attempt(s)")
            && e.contains("phase 0"),
        "{e}"
    );
    assert!(!e.contains(KEY));
    let t = d.transcript();
    assert_eq!(t.last().unwrap().kind, "critical_dims");
    assert!(t.last().unwrap().prompt.contains("task-critical") && t.last().unwrap().reply.contains("timed out"));
    assert_eq!(server.requests().len(), 2);
}

#[test]
fn anthropic_wire_format_and_errors() {
    let server = Server::start(vec![
        Reply::Anthropic("hello from claude".into()),
        Reply::Status(401, None, format!("{{\"type\": \"error\", \"error\": {{\"message\": \"invalid x-api-key {KEY}\"}}}}")),
    ]);
    let rec_dir = temp_dir("anthropic");
    let mut cfg = config("anthropic:claude-test", &server.url);
    cfg.record_dir = Some(rec_dir.clone());
    let mut c = HttpLlm::with_api_key(cfg, ApiKey::new(KEY)).unwrap();
    let msgs = [ChatMessage::system("be brief"), ChatMessage::user("hi")];
    assert_eq!(c.complete(&msgs).unwrap(), "hello from claude");
    let r = &server.requests()[0];
    assert_eq!(r.path, "/v1/messages");
    assert_eq!(r.header("x-api-key"), Some(KEY));
    assert_eq!(r.header("anthropic-version"), Some("2023-06-01"));
    assert!(r.header("authorization").is_none());
    assert_eq!(r.body["system"], "be brief");
    assert_eq!(r.body["messages"], serde_json::json!([{"role": "user", "content": "hi"}]));
    assert_eq!(r.body["max_tokens"], 8192);
    assert_eq!(r.body["temperature"], 0.6);
    assert_eq!(r.body["model"], "claude-test");

    // A 401 is not retried; the error names endpoint and status and never shows the key, even
    // when the server echoes it.
    let e = c.complete(&[ChatMessage::user("again")]).unwrap_err().to_string();
    assert_eq!(server.requests().len(), 2);
    assert!(
        e.contains("HTTP 401") && e.contains(&format!("{}/v1/messages", server.url)) && e.contains("<redacted>") && !e.contains(KEY),
        "{e}"
    );
    for f in files_under(&rec_dir) {
        assert!(!std::fs::read_to_string(&f).unwrap().contains(KEY));
    }
    let _ = std::fs::remove_dir_all(&rec_dir);
}

/// Environment variables are process-wide: the key tests take turns.
static ENV_LOCK: Mutex<()> = Mutex::new(());

fn one_reply_server() -> Server {
    Server::start(vec![Reply::Chat("hello".into())])
}

#[test]
fn openai_key_is_not_sent_to_a_local_server_unless_a_variable_is_named() {
    let _guard = ENV_LOCK.lock().unwrap_or_else(|e| e.into_inner());
    std::env::set_var("OPENAI_API_KEY", KEY);
    std::env::remove_var("LMAC_TEST_LOCAL_KEY");

    // OPENAI_API_KEY is set, but the request goes to a custom (local) base URL: no key on it.
    let server = one_reply_server();
    let mut c = HttpLlm::new(config("openai:m", &server.url)).unwrap();
    assert_eq!(c.complete(&[ChatMessage::user("hi")]).unwrap(), "hello");
    let r = &server.requests()[0];
    assert_eq!(r.header("authorization"), None, "OPENAI_API_KEY leaked to a local server: {:?}", r.headers);
    assert_eq!(r.header("x-api-key"), None);
    assert!(!format!("{:?}", r.headers).contains(KEY));

    // The same for the local providers' own default ports (vllm:, ollama:, llamacpp:).
    for spec in ["vllm:m", "ollama:m", "llamacpp:m"] {
        assert_eq!(LlmConfig::from_spec(spec, None).unwrap().api_key_env, None, "{spec}");
    }

    // Naming a variable sends its value, and only its value.
    std::env::set_var("LMAC_TEST_LOCAL_KEY", "local-secret-42");
    let server = one_reply_server();
    let cfg = config("openai:m", &server.url).with_api_key_env(Some("LMAC_TEST_LOCAL_KEY"));
    let mut c = HttpLlm::new(cfg).unwrap();
    assert_eq!(c.complete(&[ChatMessage::user("hi")]).unwrap(), "hello");
    let r = &server.requests()[0];
    assert_eq!(r.header("authorization"), Some("Bearer local-secret-42"));

    // Naming OPENAI_API_KEY itself is how a user sends that key to a local server on purpose.
    let server = one_reply_server();
    let mut c = HttpLlm::new(config("openai:m", &server.url).with_api_key_env(Some("OPENAI_API_KEY"))).unwrap();
    c.complete(&[ChatMessage::user("hi")]).unwrap();
    assert_eq!(server.requests()[0].header("authorization"), Some(format!("Bearer {KEY}").as_str()));

    // A named variable that is unset is an error naming it, before any request.
    std::env::remove_var("LMAC_TEST_LOCAL_KEY");
    let server = one_reply_server();
    let e = HttpLlm::new(config("openai:m", &server.url).with_api_key_env(Some("LMAC_TEST_LOCAL_KEY"))).unwrap_err().to_string();
    assert!(e.contains("LMAC_TEST_LOCAL_KEY"), "{e}");
    assert!(server.requests().is_empty());
    std::env::remove_var("OPENAI_API_KEY");
}

#[test]
fn anthropic_reads_its_own_variable_and_sends_it_only_when_named_for_a_custom_url() {
    let _guard = ENV_LOCK.lock().unwrap_or_else(|e| e.into_inner());
    std::env::set_var("OPENAI_API_KEY", "sk-openai-must-not-go-to-anthropic");
    std::env::set_var("ANTHROPIC_API_KEY", "sk-ant-test-77");
    assert_eq!(LlmConfig::from_spec("anthropic:claude", None).unwrap().api_key_env.as_deref(), Some("ANTHROPIC_API_KEY"));
    let server = Server::start(vec![Reply::Anthropic("a".into()), Reply::Anthropic("b".into())]);
    let mut c = HttpLlm::new(config("anthropic:claude", &server.url)).unwrap();
    c.complete(&[ChatMessage::user("hi")]).unwrap();
    let mut c = HttpLlm::new(config("anthropic:claude", &server.url).with_api_key_env(Some("ANTHROPIC_API_KEY"))).unwrap();
    c.complete(&[ChatMessage::user("hi")]).unwrap();
    let r = server.requests();
    assert_eq!((r[0].header("x-api-key"), r[0].header("authorization")), (None, None), "{:?}", r[0].headers);
    assert_eq!((r[1].header("x-api-key"), r[1].header("authorization")), (Some("sk-ant-test-77"), None), "{:?}", r[1].headers);
    std::env::remove_var("OPENAI_API_KEY");
    std::env::remove_var("ANTHROPIC_API_KEY");
}

#[test]
fn a_key_over_plain_http_to_another_host_is_refused_before_connecting() {
    let _guard = ENV_LOCK.lock().unwrap_or_else(|e| e.into_inner());
    std::env::set_var("LMAC_TEST_REMOTE_KEY", "remote-secret");
    // 192.0.2.0/24 is reserved for documentation: nothing answers there, and nothing is tried,
    // because the refusal comes before the HTTP client is even built.
    let cfg = LlmConfig::from_spec("openai:m", Some("http://192.0.2.1:8000/v1")).unwrap().with_api_key_env(Some("LMAC_TEST_REMOTE_KEY"));
    let started = std::time::Instant::now();
    let e = HttpLlm::new(cfg.clone()).unwrap_err();
    assert!(matches!(e, LlmError::InsecureKeyTransport { .. }), "{e}");
    let text = e.to_string();
    assert!(text.contains("https") && text.contains("192.0.2.1") && !text.contains("remote-secret"), "{text}");
    // A key handed in directly is refused the same way.
    assert!(matches!(HttpLlm::with_api_key(cfg, ApiKey::new("k")), Err(LlmError::InsecureKeyTransport { .. })));
    let by_name =
        LlmConfig::from_spec("openai:m", Some("http://llm.example:8000/v1")).unwrap().with_api_key_env(Some("LMAC_TEST_REMOTE_KEY"));
    assert!(matches!(HttpLlm::new(by_name), Err(LlmError::InsecureKeyTransport { .. })));
    assert!(started.elapsed() < Duration::from_secs(1), "it failed fast, without a connection attempt");
    // https to the same host, and http to loopback, are fine (no request is made here).
    let https = LlmConfig::from_spec("openai:m", Some("https://192.0.2.1:8000/v1")).unwrap().with_api_key_env(Some("LMAC_TEST_REMOTE_KEY"));
    assert!(HttpLlm::new(https).is_ok());
    let loopback = LlmConfig::from_spec("openai:m", Some("http://127.0.0.1:9/v1")).unwrap().with_api_key_env(Some("LMAC_TEST_REMOTE_KEY"));
    assert!(HttpLlm::new(loopback).is_ok());
    // Without a key, plain http to another host is not refused by this check (nothing to leak);
    // it needs a named variable or a local URL.
    let keyless = LlmConfig::from_spec("openai:m", Some("http://192.0.2.1:8000/v1")).unwrap();
    assert!(matches!(HttpLlm::new(keyless), Err(LlmError::NoKeyVariable { .. })));
    std::env::remove_var("LMAC_TEST_REMOTE_KEY");
}

/// A server that answers with a redirect to another server: the client must not follow it (it
/// would carry `x-api-key`, which reqwest does not strip, and the whole prompt), for every
/// provider, and must say where the redirect pointed.
#[test]
fn a_redirect_is_never_followed_and_never_carries_the_key_or_the_prompt() {
    const PROMPT: &str = "the secret prompt 4711";
    for spec in ["openai:m", "anthropic:m", "gemini:m", "vllm:m", "ollama:m", "llamacpp:m"] {
        // The second server would answer well, so a followed redirect would succeed.
        let elsewhere = Server::start(vec![Reply::Chat("followed".into()), Reply::Anthropic("followed".into())]);
        let target = format!("{}/stolen", elsewhere.url);
        let first = Server::start(vec![Reply::Redirect(target.clone())]);
        let mut c = HttpLlm::with_api_key(config(spec, &first.url), ApiKey::new(KEY)).unwrap();
        let e = c.complete(&[ChatMessage::user(PROMPT)]).unwrap_err();
        assert!(matches!(e, LlmError::Redirect { status: 307, .. }), "{spec}: {e}");
        let text = e.to_string();
        assert!(text.contains(&target) && text.contains("redirect") && !text.contains(KEY), "{spec}: {text}");
        // The configured server got the key (it is the one configured) and was asked once.
        let asked = first.requests();
        assert_eq!(asked.len(), 1, "{spec}: a redirect is not retried");
        assert!(asked[0].all_text().contains(PROMPT), "{spec}");
        // The other server saw nothing: no connection carried the key or the prompt.
        let seen = elsewhere.requests();
        assert!(seen.is_empty(), "{spec}: the redirect was followed: {:?}", seen.iter().map(|r| &r.headers).collect::<Vec<_>>());
    }
}

#[test]
fn structured_output_follows_the_provider_and_can_be_turned_off() {
    let schema = serde_json::json!({"type": "object", "properties": {"a": {"type": "integer"}}});
    let msgs = [ChatMessage::user("hi")];
    let ask = |spec: &str, structured: Option<StructuredOutput>| {
        let server = Server::start(vec![if spec.starts_with("anthropic") {
            Reply::Anthropic("{\"a\": 1}".into())
        } else {
            Reply::Chat("{\"a\": 1}".into())
        }]);
        let mut c = HttpLlm::with_api_key(config(spec, &server.url), ApiKey::new(KEY)).unwrap();
        if let Some(s) = structured {
            c.set_structured(s);
        }
        assert_eq!(c.complete_with_schema(&msgs, &schema).unwrap(), "{\"a\": 1}");
        server.requests()[0].body.get("response_format").cloned()
    };
    // llama.cpp's servers: a schema turned into a grammar.
    assert_eq!(ask("llamacpp:m", None), Some(serde_json::json!({"type": "json_object", "schema": schema})));
    // OpenAI-compatible (OpenAI, Gemini, vLLM, Ollama): OpenAI's json_schema.
    for spec in ["openai:m", "gemini:m", "vllm:m"] {
        assert_eq!(ask(spec, None).unwrap()["json_schema"]["schema"], schema, "{spec}");
    }
    // Anthropic's messages API takes no response_format; off sends none anywhere.
    assert_eq!(ask("anthropic:m", None), None);
    assert_eq!(ask("llamacpp:m", Some(StructuredOutput::Off)), None);
    // Gemini: Google's OpenAI-compatible endpoint with its own key variable.
    let g = LlmConfig::from_spec("gemini:gemini-2.5-pro", None).unwrap();
    assert_eq!(g.endpoint(), "https://generativelanguage.googleapis.com/v1beta/openai/chat/completions");
    assert_eq!(g.api_key_env.as_deref(), Some("GEMINI_API_KEY"));
}

/// A reply that stopped at the token limit is an error naming the limit and how to raise it (not
/// a malformed protocol to correct, which would be cut again and paid again), for both wire
/// formats; it is recorded, and its replay says the same.
#[test]
fn a_reply_cut_at_the_token_limit_is_an_error_naming_the_limit_and_replays_the_same() {
    let cut = |spec: &str| {
        if spec.starts_with("anthropic") {
            serde_json::json!({"type": "message", "model": "m", "content": [{"type": "text", "text": "{\"messages\": [{\"send"}],
                "stop_reason": "max_tokens"})
        } else {
            serde_json::json!({"model": "m", "choices": [{"message": {"content": "{\"messages\": [{\"send"}, "finish_reason": "length"}]})
        }
        .to_string()
    };
    for spec in ["openai:m", "anthropic:m"] {
        let server = Server::start(vec![Reply::Status(200, None, cut(spec))]);
        let rec = temp_dir("cut");
        let mut cfg = config(spec, &server.url);
        cfg.mode = LlmMode::ReplayOrLive;
        cfg.record_dir = Some(rec.clone());
        let mut c = HttpLlm::new(cfg.clone()).unwrap();
        c.set_max_tokens(7);
        let e = c.complete(&[ChatMessage::user("design")]).unwrap_err();
        assert!(matches!(&e, LlmError::Truncated { limit: Some(7), .. }), "{spec}: {e}");
        let text = e.to_string();
        assert!(text.contains("max_tokens 7") && text.contains("--llm-max-tokens") && text.contains("[{\"send"), "{spec}: {text}");
        assert_eq!(server.requests().len(), 1, "{spec}: a cut reply is not asked again");
        // Recorded (it was paid for), and the replay is the same error, with no server.
        cfg.mode = LlmMode::Replay;
        let mut replay = HttpLlm::new(cfg).unwrap();
        replay.set_max_tokens(7);
        let again = replay.complete(&[ChatMessage::user("design")]).unwrap_err();
        assert!(matches!(again, LlmError::Truncated { .. }), "{spec}: replay gave {again}");
        let _ = std::fs::remove_dir_all(rec);
    }
    // A whole reply ("stop", "end_turn") is not affected: every other test here gets one.
}

/// A 2xx whose body is lost in transit is asked again (one dropped connection should not end a
/// design), and the error says that the lost reply may have been billed.
#[test]
fn a_success_whose_body_is_lost_is_retried_and_says_it_may_have_been_paid() {
    let server = Server::start(vec![Reply::CutBody, Reply::Chat("whole".into())]);
    let mut c = HttpLlm::new(config("openai:m", &server.url)).unwrap();
    assert_eq!(c.complete(&[ChatMessage::user("hi")]).unwrap(), "whole");
    assert_eq!(server.requests().len(), 2);
    let server = Server::start(vec![Reply::CutBody, Reply::CutBody, Reply::CutBody]);
    let mut c = HttpLlm::new(config("openai:m", &server.url)).unwrap();
    let e = c.complete(&[ChatMessage::user("hi")]).unwrap_err();
    let text = e.to_string();
    assert!(matches!(e, LlmError::Transport { attempts: 3, .. }) && text.contains("answered 200") && text.contains("billed"), "{text}");
}
