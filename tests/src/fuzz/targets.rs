//! The parsers under test, each with its valid seeds and its mutations.
//! - `schema`: environment schema TOML (`EnvSchema::parse`), seeded with every shipped schema.
//! - `config`: a run config file plus `key=value` overrides (`TrainConfig::resolve`).
//! - `protocol`: protocol JSON or an LLM answer holding it (parse, explain, validate, compile,
//!   and run the compiled plan), seeded with `prompts/examples`.
//! - `llm_reply`: a chat-completion / Messages response body (`parse_response`), then the reply
//!   text as feedback (`parse_feedback`) and as a protocol.
//! - `dataset`: a trajectory dataset directory (`Dataset::load`, then `messages`), mutated from
//!   a valid two-episode dataset.
//! - `checkpoint`: a learner checkpoint (`Learner::load_checkpoint`, then a training step),
//!   mutated from a valid small checkpoint with its replay buffer.
//!
//! The ring's 24-byte slot message has no decoder to fuzz: iceoryx2 hands the `#[repr(C)]`
//! struct over as it is (every bit pattern is a valid `SlotMsg`, and its receivers match on
//! `kind`), so there is no parser there.

use super::mutate::*;
use super::{scratch_dir, Case, Rng, Target};
use lmac_design::llm::{parse_response, Provider};
use lmac_design::llm_designer::parse_feedback;
use lmac_protocol_runner::plan::{MessagePlan, StepView};
use lmac_protocol_runner::protocol::{self, ProtocolEnv};
use lmac_run::dataset::{Dataset, DatasetHeader, Trajectory};
use lmac_run::episode::{Episode, EpisodeDims};
use lmac_run::learn::{Device, LearnConfig, LearnRng, Learner};
use lmac_run::train::TrainConfig;
use lmac_shm_schema::EnvSchema;
use serde_json::{json, Value};
use std::path::{Path, PathBuf};

pub const PARSERS: &[&str] = &["schema", "config", "protocol", "llm_reply", "dataset", "checkpoint", "ring_message"];

pub fn make(name: &str) -> Result<Box<dyn Target>, String> {
    Ok(match name {
        "schema" => Box::new(SchemaTarget::new()?),
        "config" => Box::new(ConfigTarget::new()?),
        "protocol" => Box::new(ProtocolTarget::new()?),
        "llm_reply" => Box::new(LlmReplyTarget::new()?),
        "dataset" => Box::new(DatasetTarget::new()?),
        "checkpoint" => Box::new(CheckpointTarget::new()?),
        "ring_message" => Box::new(RingMessageTarget),
        other => return Err(format!("unknown parser {other:?}: use one of {} or all", PARSERS.join(", "))),
    })
}

/// The workspace root (for the shipped schemas and example protocols).
fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn leak_keys(keys: impl IntoIterator<Item = String>) -> Vec<&'static str> {
    let mut v: Vec<String> = keys.into_iter().collect();
    v.sort();
    v.dedup();
    v.into_iter().map(|k| &*Box::leak(k.into_boxed_str())).collect()
}

fn json_keys(v: &Value, out: &mut Vec<String>) {
    match v {
        Value::Object(m) => {
            for (k, x) in m {
                out.push(k.clone());
                json_keys(x, out);
            }
        }
        Value::Array(a) => a.iter().for_each(|x| json_keys(x, out)),
        Value::String(s) if s.len() < 40 => out.push(s.clone()),
        _ => {}
    }
}

fn toml_keys(v: &toml::Value, out: &mut Vec<String>) {
    match v {
        toml::Value::Table(t) => {
            for (k, x) in t {
                out.push(k.clone());
                toml_keys(x, out);
            }
        }
        toml::Value::Array(a) => a.iter().for_each(|x| toml_keys(x, out)),
        toml::Value::String(s) if s.len() < 40 => out.push(s.clone()),
        _ => {}
    }
}

/// Mutated TOML text from a seed: tree edits (re-serialized), byte damage, or random bytes.
fn mutate_toml_text(r: &mut Rng, seed: &str, keys: &[&'static str]) -> (Vec<u8>, String) {
    match r.below(10) {
        0..=4 => {
            let mut v: toml::Value = toml::from_str::<toml::Table>(seed).map(toml::Value::Table).expect("seed TOML parses");
            let n = 1 + r.index(3);
            for _ in 0..n {
                mutate_toml(r, &mut v, keys);
            }
            match toml::to_string(&v) {
                Ok(t) => (t.into_bytes(), format!("{n} tree edit(s)")),
                Err(_) => (seed.as_bytes().to_vec(), "tree edit not serializable: the seed".into()),
            }
        }
        5..=8 => {
            let mut b = seed.as_bytes().to_vec();
            let kinds: Vec<&str> = (0..1 + r.index(3)).map(|_| mutate_bytes(r, &mut b)).collect();
            (b, kinds.join(", "))
        }
        _ => ((0..r.index(2048)).map(|_| r.next() as u8).collect(), "random bytes".into()),
    }
}

// ------------------------------------------------------------------------------------------

pub struct SchemaTarget {
    seeds: Vec<String>,
    keys: Vec<&'static str>,
}

impl SchemaTarget {
    fn new() -> Result<Self, String> {
        let envs = lmac_shm_schema::schema::all_envs().map_err(|e| e.to_string())?;
        let seeds: Vec<String> = envs.iter().filter_map(|(p, _)| std::fs::read_to_string(p).ok()).collect();
        if seeds.is_empty() {
            return Err("no schema files found (set LMAC_SCHEMA_DIR)".into());
        }
        let mut keys = Vec::new();
        for s in &seeds {
            toml_keys(&toml::Value::Table(toml::from_str(s).map_err(|e| e.to_string())?), &mut keys);
        }
        Ok(SchemaTarget { seeds, keys: leak_keys(keys) })
    }
}

impl Target for SchemaTarget {
    fn name(&self) -> &'static str {
        "schema"
    }
    fn generate(&mut self, r: &mut Rng) -> Case {
        let seed = r.pick(&self.seeds).clone();
        let (b, note) = mutate_toml_text(r, &seed, &self.keys);
        Case::text("schema.toml", b, note)
    }
    fn run(&mut self, case: &Case) -> Result<(), String> {
        let text = String::from_utf8_lossy(&case.files[0].1);
        let s = EnvSchema::parse(&text, Path::new("fuzzed-schema.toml")).map_err(|e| e.to_string())?;
        // What the rest of lmac computes from an accepted schema.
        let _ = (s.obs_meanings(), s.state_meanings(), s.fullcomm_columns());
        let env = lmac_protocol_runner::protocol_env(&s);
        let _ = lmac_protocol_runner::plan_for(&lmac_protocol_runner::ProtocolSpec::FullComm, &s).map(|p| p.msg_dim());
        let _ = env;
        Ok(())
    }
    fn error_must_name(&self) -> &'static [&'static str] {
        &["fuzzed-schema.toml"]
    }
}

// ------------------------------------------------------------------------------------------

pub struct ConfigTarget {
    seeds: Vec<String>,
    keys: Vec<&'static str>,
    dir: PathBuf,
}

impl ConfigTarget {
    fn new() -> Result<Self, String> {
        let base = TrainConfig::default();
        let mut seeds = vec![toml::to_string(&base).map_err(|e| e.to_string())?];
        let mut envs: Vec<String> = lmac_shm_schema::schema::all_envs()
            .map_err(|e| e.to_string())?
            .into_iter()
            .filter_map(|(_, s)| s.ok().map(|s| s.name))
            .collect();
        envs.sort();
        for (k, algo) in ["vdn", "qplex", "fullcomm", "qmix-state"].iter().enumerate() {
            let mut c = base.clone();
            c.run.algo = algo.to_string();
            if let Some(e) = envs.get(k) {
                c.run.env = e.clone();
            }
            seeds.push(toml::to_string(&c).map_err(|e| e.to_string())?);
        }
        let mut c = base.clone();
        c.run.protocol = root().join("prompts/examples/lbf_8x8_phase0.json").display().to_string();
        seeds.push(toml::to_string(&c).map_err(|e| e.to_string())?);
        let mut keys = envs.clone();
        for s in &seeds {
            toml_keys(&toml::Value::Table(toml::from_str(s).map_err(|e| e.to_string())?), &mut keys);
        }
        Ok(ConfigTarget { seeds, keys: leak_keys(keys), dir: scratch_dir("config") })
    }
}

impl Target for ConfigTarget {
    fn name(&self) -> &'static str {
        "config"
    }
    fn generate(&mut self, r: &mut Rng) -> Case {
        let seed = r.pick(&self.seeds).clone();
        let (b, note) = if r.chance(0.2) { (seed.into_bytes(), "the seed".to_string()) } else { mutate_toml_text(r, &seed, &self.keys) };
        // Overrides as the CLI passes them: section.key=value, the value TOML or bare text.
        let mut overrides = Vec::new();
        for _ in 0..r.below(3) {
            let section = *r.pick(&["run", "learn", "", "run.steps", "x"]);
            let key = *r.pick(&self.keys);
            let val = match r.below(5) {
                0 => random_string(r),
                1 => (*r.pick(&["0", "-1", "1e400", "nan", "\"\"", "[1,", "{a=1}", "1\nrun.envs = 0", "18446744073709551616"])).to_string(),
                _ => r.below(100).to_string(),
            };
            overrides.push(if section.is_empty() { format!("{key}={val}") } else { format!("{section}.{key}={val}") });
        }
        if r.chance(0.03) {
            overrides.push("no equals sign".into());
        }
        let mut case = Case::text("config.toml", b, note);
        case.files.push(("overrides.txt".into(), serde_json::to_vec(&overrides).unwrap()));
        case
    }
    fn run(&mut self, case: &Case) -> Result<(), String> {
        let path = self.dir.join("config.toml");
        std::fs::write(&path, &case.files[0].1).map_err(|e| format!("fuzz harness: {e}"))?;
        let overrides: Vec<String> = serde_json::from_slice(&case.files[1].1).unwrap_or_default();
        let cfg = TrainConfig::resolve(Some(&path), &overrides).map_err(|e| format!("{e:#}"))?;
        let _ = (cfg.protocol(), cfg.effective_learn());
        Ok(())
    }
}

// ------------------------------------------------------------------------------------------

/// Runs a compiled plan over a few steps of hostile observations (NaN, huge values, bad actions).
fn run_plan(r: &mut Rng, plan: &mut dyn MessagePlan, n: usize, od: usize, n_actions: usize) {
    let md = plan.msg_dim();
    let ne = 1 + r.index(2);
    let mut rows = vec![0.0f32; ne * n * (od + md)];
    for _ in 0..3 {
        for x in rows.iter_mut() {
            *x = match r.below(16) {
                0 => f32::NAN,
                1 => 1e30,
                2 => f32::NEG_INFINITY,
                _ => r.below(5) as f32 - 1.0,
            };
        }
        let first: Vec<bool> = (0..ne).map(|_| r.chance(0.3)).collect();
        let la: Vec<i32> = (0..ne * n).map(|_| r.below(n_actions as u64 + 3) as i32 - 2).collect();
        plan.apply(&mut StepView {
            num_envs: ne,
            n_agents: n,
            obs_dim: od,
            msg_dim: md,
            rows: &mut rows,
            first: &first,
            last_actions: &la,
        });
    }
}

pub struct ProtocolTarget {
    seeds: Vec<Value>,
    envs: Vec<ProtocolEnv>,
    keys: Vec<&'static str>,
}

/// Protocol language words: keys and string values the mutations draw from.
const PROTOCOL_WORDS: &[&str] = &[
    "name",
    "phase",
    "message_design_instruction",
    "critical_state_dims",
    "sender_one_hot",
    "history_padding",
    "fields",
    "description",
    "senders",
    "receivers",
    "value",
    "all",
    "broadcast",
    "agents",
    "peer",
    "from",
    "to",
    "obs",
    "obs_slice",
    "start",
    "end",
    "last_action",
    "one_hot",
    "index",
    "const",
    "window",
    "op",
    "k",
    "of",
    "add",
    "sub",
    "mul",
    "div",
    "min",
    "max",
    "gt",
    "lt",
    "eq",
    "neg",
    "abs",
    "clip",
    "reduce",
    "concat",
    "mean",
    "sum",
    "last",
    "delta",
    "last_nonzero",
    "minus_one",
    "zero",
    "repeat",
];

impl ProtocolTarget {
    fn new() -> Result<Self, String> {
        let dir = root().join("prompts/examples");
        let mut seeds = Vec::new();
        for e in std::fs::read_dir(&dir).map_err(|e| format!("{}: {e}", dir.display()))? {
            let p = e.map_err(|e| e.to_string())?.path();
            if p.extension().is_some_and(|x| x == "json") {
                let text = std::fs::read_to_string(&p).map_err(|e| e.to_string())?;
                seeds.push(serde_json::from_str(&text).map_err(|e| format!("{}: {e}", p.display()))?);
            }
        }
        if seeds.is_empty() {
            return Err(format!("no example protocols in {}", dir.display()));
        }
        let mut envs: Vec<ProtocolEnv> = Vec::new();
        for name in ["lbf:8x8-2p-2f-s1-coop", "lbf:11x11-6p-4f-s1-coop", "smaclite:5z_vs_1ul"] {
            if let Ok(s) = lmac_shm_schema::schema::load_env(name) {
                envs.push(lmac_protocol_runner::protocol_env(&s));
            }
        }
        envs.extend([ProtocolEnv::new(3, 5, 4, 10, 120), ProtocolEnv::new(1, 4, 2, 3, 50), ProtocolEnv::new(4, 3, 0, 0, 400)]);
        let mut keys: Vec<String> = PROTOCOL_WORDS.iter().map(|s| s.to_string()).collect();
        seeds.iter().for_each(|s| json_keys(s, &mut keys));
        Ok(ProtocolTarget { seeds, envs, keys: leak_keys(keys) })
    }
}

/// Protocol-ish text: a mutated example, wrapped the ways LLMs answer, or damaged bytes.
fn protocol_text(r: &mut Rng, seeds: &[Value], keys: &[&'static str]) -> (Vec<u8>, String) {
    let mut v = r.pick(seeds).clone();
    let mut note = Vec::new();
    if r.chance(0.8) {
        let n = 1 + r.index(4);
        for _ in 0..n {
            mutate_json(r, &mut v, keys);
        }
        note.push(format!("{n} tree edit(s)"));
    }
    if r.chance(0.05) {
        v = nest_json(r, v);
        note.push("nested".into());
    }
    if r.chance(0.05) {
        v = random_json(r, 5, keys);
        note.push("random JSON".into());
    }
    let nested = note.iter().any(|n| n == "nested");
    // Pretty-printing deep nesting is quadratic in the depth: compact text for those.
    let text = if nested || r.chance(0.5) { v.to_string() } else { serde_json::to_string_pretty(&v).unwrap() };
    let text = match r.below(6) {
        0 => format!("Here is the protocol:\n```json\n{text}\n```\nDone."),
        1 => format!("I reasoned {{a}} about it. {text} That is all {{b}}."),
        _ => text,
    };
    let mut b = text.into_bytes();
    if r.chance(0.3) {
        note.push(mutate_bytes(r, &mut b).into());
    }
    (b, note.join(", "))
}

impl Target for ProtocolTarget {
    fn name(&self) -> &'static str {
        "protocol"
    }
    fn generate(&mut self, r: &mut Rng) -> Case {
        let (b, note) = protocol_text(r, &self.seeds, &self.keys);
        let mut case = Case::text("protocol.json", b, note);
        case.files.push(("env_index".into(), r.index(self.envs.len()).to_string().into_bytes()));
        case
    }
    fn run(&mut self, case: &Case) -> Result<(), String> {
        let text = String::from_utf8_lossy(&case.files[0].1);
        let k: usize = std::str::from_utf8(&case.files[1].1).ok().and_then(|s| s.parse().ok()).unwrap_or(0);
        let env = &self.envs[k % self.envs.len()];
        let p = protocol::parse_llm_text(&text).map_err(|e| protocol::errors_to_text(&e))?;
        let _ = protocol::explain(&p, Some(env));
        let _ = protocol::explain(&p, None);
        let v = protocol::validate(&p, env).map_err(|e| protocol::errors_to_text(&e))?;
        let mut plan = protocol::compile_plan(std::slice::from_ref(&v), env).map_err(|e| protocol::errors_to_text(&e))?;
        if plan.msg_dim() != v.width {
            panic!("compiled width {} differs from the validated width {}", plan.msg_dim(), v.width);
        }
        let mut r = Rng(text.len() as u64 ^ 0x5eed);
        run_plan(&mut r, &mut plan, env.n_agents, env.obs_dim, env.n_actions);
        Ok(())
    }
}

// ------------------------------------------------------------------------------------------

pub struct LlmReplyTarget {
    protocols: Vec<Value>,
    keys: Vec<&'static str>,
    env: ProtocolEnv,
}

impl LlmReplyTarget {
    fn new() -> Result<Self, String> {
        let p = ProtocolTarget::new()?;
        let mut keys: Vec<String> = p.keys.iter().map(|s| s.to_string()).collect();
        keys.extend(
            [
                "choices",
                "message",
                "content",
                "role",
                "assistant",
                "finish_reason",
                "stop",
                "refusal",
                "error",
                "model",
                "usage",
                "type",
                "text",
                "stop_reason",
                "Evaluation",
                "Missing_Information_Hypothesis",
                "Improvement_Suggestions",
                "evaluation",
            ]
            .map(String::from),
        );
        Ok(LlmReplyTarget { protocols: p.seeds, keys: leak_keys(keys), env: p.envs[0].clone() })
    }
}

impl Target for LlmReplyTarget {
    fn name(&self) -> &'static str {
        "llm_reply"
    }
    fn generate(&mut self, r: &mut Rng) -> Case {
        // The reply text: a protocol, feedback, or prose, each possibly damaged.
        let (text, mut note) = match r.below(3) {
            0 => {
                let (b, n) = protocol_text(r, &self.protocols, &self.keys);
                (String::from_utf8_lossy(&b).into_owned(), format!("protocol reply ({n})"))
            }
            1 => {
                let mut fb = json!({"Evaluation": "e", "Missing_Information_Hypothesis": ["a", "b"], "Improvement_Suggestions": "i"});
                for _ in 0..r.below(3) {
                    mutate_json(r, &mut fb, &self.keys);
                }
                let t = match r.below(3) {
                    0 => format!("Analysis {{x}}:\n```json\n{fb}\n```"),
                    1 => format!("{} {fb} {}", "{".repeat(r.index(50)), "}".repeat(r.index(50))),
                    _ => fb.to_string(),
                };
                (t, "feedback reply".into())
            }
            _ => (random_string(r), "random text".into()),
        };
        let anthropic = r.chance(0.3);
        let mut body = if anthropic {
            json!({"id": "m", "type": "message", "content": [{"type": "text", "text": text}], "stop_reason": "end_turn", "model": "x"})
        } else {
            json!({"id": "c", "choices": [{"index": 0, "message": {"role": "assistant", "content": text}, "finish_reason": "stop"}], "usage": {}})
        };
        if r.chance(0.5) {
            let n = 1 + r.index(3);
            for _ in 0..n {
                mutate_json(r, &mut body, &self.keys);
            }
            note.push_str(&format!(", {n} body edit(s)"));
        }
        let mut b = body.to_string().into_bytes();
        if r.chance(0.2) {
            note.push_str(&format!(", body {}", mutate_bytes(r, &mut b)));
        }
        // The client reads at most MAX_BODY_BYTES of a response; it never parses more.
        if b.len() as u64 > lmac_design::llm::MAX_BODY_BYTES {
            b.truncate(lmac_design::llm::MAX_BODY_BYTES as usize);
            note.push_str(", cut to the body limit");
        }
        let mut case = Case::text("body.json", b, note);
        case.files.push(("provider".into(), if anthropic { b"anthropic".to_vec() } else { b"openai".to_vec() }));
        case
    }
    fn run(&mut self, case: &Case) -> Result<(), String> {
        let raw = String::from_utf8_lossy(&case.files[0].1);
        let provider = if case.files[1].1 == b"anthropic" { Provider::Anthropic } else { Provider::OpenAi };
        let reply = parse_response(provider, &raw)?;
        let _ = parse_feedback(&reply.text);
        if let Ok(p) = protocol::parse_llm_text(&reply.text) {
            let _ = protocol::validate(&p, &self.env);
        }
        Ok(())
    }
}

// ------------------------------------------------------------------------------------------

pub struct DatasetTarget {
    header: Vec<u8>,
    episodes: Vec<u8>,
    /// Offsets of the episode records' headers in episodes.bin.
    records: Vec<usize>,
    keys: Vec<&'static str>,
    dir: PathBuf,
}

impl DatasetTarget {
    fn new() -> Result<Self, String> {
        let header = DatasetHeader {
            env: "fuzz:tiny".into(),
            n_agents: 2,
            obs_dim: 3,
            state_dim: 2,
            n_actions: 4,
            episode_limit: 6,
            protocol: "none".into(),
            policy: "fuzz".into(),
            seed: 5,
        };
        let ep = |len: usize, x: f32| Trajectory {
            len,
            obs: (0..len * 6).map(|i| i as f32 * x).collect(),
            state: vec![x; len * 2],
            actions: (0..len * 2).map(|i| (i % 4) as i32).collect(),
            reward: vec![1.0; len],
            terminated: true,
            truncated: false,
        };
        let data = Dataset { header, episodes: vec![ep(3, 0.5), ep(1, -1.0), ep(2, 2.0)] };
        let base = scratch_dir("dataset-seed").join("data");
        data.save(&base).map_err(|e| format!("{e:#}"))?;
        let header = std::fs::read(base.join("header.json")).map_err(|e| e.to_string())?;
        let episodes = std::fs::read(base.join("episodes.bin")).map_err(|e| e.to_string())?;
        let mut records = Vec::new();
        let mut at = 8;
        for e in &data.episodes {
            records.push(at);
            at += 8 + 4 * e.len * (6 + 2 + 2 + 1);
        }
        let mut keys = Vec::new();
        json_keys(&serde_json::from_slice(&header).map_err(|e| e.to_string())?, &mut keys);
        Ok(DatasetTarget { header, episodes, records, keys: leak_keys(keys), dir: scratch_dir("dataset").join("data") })
    }
}

impl Target for DatasetTarget {
    fn name(&self) -> &'static str {
        "dataset"
    }
    fn generate(&mut self, r: &mut Rng) -> Case {
        let (mut header, mut episodes) = (self.header.clone(), self.episodes.clone());
        let mut note = Vec::new();
        let what = r.below(10);
        if what < 4 {
            let mut v: Value = serde_json::from_slice(&header).unwrap();
            if r.chance(0.7) {
                // The numbers that size the payload.
                let key = *r.pick(&["episodes", "steps", "n_agents", "obs_dim", "state_dim", "n_actions", "episode_limit", "version"]);
                v[key] = edge_number(r);
                note.push(format!("header {key} = {}", v[key]));
            } else {
                mutate_json(r, &mut v, &self.keys);
                note.push("header tree edit".into());
            }
            header = v.to_string().into_bytes();
        }
        if what >= 3 {
            if r.chance(0.5) {
                let at = *r.pick(&self.records);
                let field = r.below(3);
                match field {
                    0 => poke_le(r, &mut episodes, at, 4),
                    1 => episodes[at + 4] = r.next() as u8,
                    _ => {
                        let off = at + 8 + 4 * r.index(8);
                        poke_le(r, &mut episodes, off, 4)
                    }
                }
                note.push(format!("record at {at} field {field} poked"));
            } else {
                note.push(format!("episodes.bin {}", mutate_bytes(r, &mut episodes)));
            }
        }
        if r.chance(0.05) {
            header = b"".to_vec();
            note.push("empty header".into());
        }
        Case { files: vec![("header.json".into(), header), ("episodes.bin".into(), episodes)], note: note.join(", ") }
    }
    fn run(&mut self, case: &Case) -> Result<(), String> {
        case.write_to(&self.dir).map_err(|e| format!("fuzz harness: {e}"))?;
        let d = Dataset::load(&self.dir).map_err(|e| format!("{e:#}"))?;
        // What the design loop does next with a dataset: recompute messages with a plan.
        let mut plan = Box::new(lmac_protocol_runner::builtin::NoMessages);
        let msgs = d.messages(plan.as_mut());
        if msgs.len() != d.episodes.len() {
            panic!("messages for {} episodes out of {}", msgs.len(), d.episodes.len());
        }
        Ok(())
    }
    fn error_must_name(&self) -> &'static [&'static str] {
        &["header.json", "episodes.bin"]
    }
}

// ------------------------------------------------------------------------------------------

const CK_DIMS: EpisodeDims = EpisodeDims { n_agents: 2, obs_width: 3, state_dim: 4, n_actions: 3 };
const CK_FILES: [&str; 5] = ["state.json", "buffer.bin", "net.bpk", "target.bpk", "optim.bpk"];

pub struct CheckpointTarget {
    files: Vec<(String, Vec<u8>)>,
    keys: Vec<&'static str>,
    dir: PathBuf,
}

fn ck_episode(rng: &mut LearnRng, len: usize) -> Episode {
    let d = CK_DIMS;
    let mut ep = Episode::with_capacity(&d, len);
    for _ in 0..len {
        (0..d.n_agents * d.obs_width).for_each(|_| ep.obs.push(rng.uniform()));
        (0..d.state_dim).for_each(|_| ep.state.push(rng.uniform()));
        for _ in 0..d.n_agents {
            ep.avail.extend_from_slice(&[1, 1, 1]);
            ep.actions.push(rng.below(3) as i32);
        }
        ep.reward.push(rng.uniform());
        ep.len += 1;
    }
    ep.terminated = true;
    ep
}

impl CheckpointTarget {
    fn new() -> Result<Self, String> {
        let cfg = LearnConfig {
            batch_size: 2,
            buffer_size: 4,
            rnn_hidden_dim: 8,
            mixing_embed_dim: 4,
            hypernet_embed: 8,
            seed: 9,
            ..LearnConfig::default()
        };
        let mut l = Learner::new(CK_DIMS, cfg, Device::default()).map_err(|e| e.to_string())?;
        let mut rng = LearnRng::seed_from(3);
        for i in 0..3 {
            l.add_episode(ck_episode(&mut rng, 2 + i)).map_err(|e| e.to_string())?;
        }
        l.train_step().map_err(|e| e.to_string())?;
        let base = scratch_dir("checkpoint-seed").join("ck");
        l.save_checkpoint(&base, true).map_err(|e| e.to_string())?;
        let mut files = Vec::new();
        for f in CK_FILES {
            files.push((f.to_string(), std::fs::read(base.join(f)).map_err(|e| format!("{f}: {e}"))?));
        }
        let mut keys = Vec::new();
        json_keys(&serde_json::from_slice(&files[0].1).map_err(|e| e.to_string())?, &mut keys);
        Ok(CheckpointTarget { files, keys: leak_keys(keys), dir: scratch_dir("checkpoint").join("ck") })
    }
}

impl Target for CheckpointTarget {
    fn name(&self) -> &'static str {
        "checkpoint"
    }
    fn generate(&mut self, r: &mut Rng) -> Case {
        let k = *r.pick(&[0, 0, 0, 1, 1, 1, 2, 3, 4]);
        let (name, mut b) = self.files[k].clone();
        let note = match (k, r.below(3)) {
            (0, 0 | 1) => {
                let mut v: Value = serde_json::from_slice(&b).unwrap();
                if r.chance(0.6) {
                    let path = *r.pick(&[
                        "/dims/n_agents",
                        "/dims/obs_width",
                        "/dims/state_dim",
                        "/dims/n_actions",
                        "/config/rnn_hidden_dim",
                        "/config/buffer_size",
                        "/config/batch_size",
                        "/config/mixing_embed_dim",
                        "/counters/episodes",
                        "/has_buffer",
                        "/format_version",
                        "/epsilon",
                    ]);
                    let new = edge_number(r);
                    if let Some(x) = v.pointer_mut(path) {
                        *x = new.clone();
                    }
                    b = v.to_string().into_bytes();
                    format!("state.json {path} = {new}")
                } else {
                    mutate_json(r, &mut v, &self.keys);
                    b = v.to_string().into_bytes();
                    "state.json tree edit".into()
                }
            }
            (1, 0 | 1) => {
                // count, next, then the first episode's len.
                let at = *r.pick(&[8usize, 16, 24]);
                poke_le(r, &mut b, at, 8);
                format!("buffer.bin u64 at {at} poked")
            }
            _ => format!("{name} {}", mutate_bytes(r, &mut b)),
        };
        Case { files: vec![(name, b)], note }
    }
    fn run(&mut self, case: &Case) -> Result<(), String> {
        for (name, bytes) in &self.files {
            std::fs::create_dir_all(&self.dir).map_err(|e| format!("fuzz harness: {e}"))?;
            std::fs::write(self.dir.join(name), bytes).map_err(|e| format!("fuzz harness: {e}"))?;
        }
        case.write_to(&self.dir).map_err(|e| format!("fuzz harness: {e}"))?;
        let mut l = Learner::load_checkpoint(&self.dir, Device::default()).map_err(|e| e.to_string())?;
        // A resumed run trains next: a loaded buffer must be usable.
        if l.can_train() {
            l.train_step().map_err(|e| format!("after loading {}: train_step: {e}", self.dir.display()))?;
        }
        Ok(())
    }
    fn error_must_name(&self) -> &'static [&'static str] {
        &["lmac-fuzz-checkpoint"]
    }
}

/// The 24-byte slot messages a ring member receives from its peers: any bytes, checked by
/// `ring::check_slot_msg` against a ring of random sizes seen from a random member. A message it
/// accepts must be safe to index with: its member and slot inside the ring.
pub struct RingMessageTarget;

fn ring_case(bytes: &[u8]) -> Option<(lmac_shm_schema::ring::RingSpec, usize, lmac_shm_schema::SlotMsg)> {
    use lmac_shm_schema::{ring::RingSpec, SlotMsg, Stage};
    if bytes.len() != 32 {
        return None;
    }
    let u32_at = |i: usize| u32::from_le_bytes(bytes[i..i + 4].try_into().expect("4 bytes"));
    let (n_members, n_slots) = (1 + (bytes[24] as usize % 8), 1 + (bytes[25] as usize % 8));
    let role = [Stage::Env, Stage::Runner, Stage::Trainer][bytes[26] as usize % 3];
    let (member, inbox) = (bytes[27] as usize % n_members, bytes[28] as usize % n_members);
    let spec = RingSpec { run: "fuzz".into(), n_members, n_slots, role, member };
    let msg = SlotMsg {
        kind: u32_at(0),
        member: u32_at(4),
        slot: u32_at(8),
        _pad: u32_at(12),
        seq: u64::from_le_bytes(bytes[16..24].try_into().ok()?),
    };
    Some((spec, inbox, msg))
}

impl Target for RingMessageTarget {
    fn name(&self) -> &'static str {
        "ring_message"
    }
    fn generate(&mut self, r: &mut Rng) -> Case {
        // 24 message bytes + 8 bytes choosing the ring; fields are often near the edges.
        let mut b: Vec<u8> = (0..32).map(|_| r.below(256) as u8).collect();
        for field in [0usize, 4, 8] {
            if r.chance(0.6) {
                let v = *r.pick(&[0u32, 1, 2, 3, 7, 8, u32::MAX, u32::MAX - 1]);
                b[field..field + 4].copy_from_slice(&v.to_le_bytes());
            }
        }
        Case { files: vec![("message.bin".into(), b)], note: "slot message and ring sizes".into() }
    }
    fn run(&mut self, case: &Case) -> Result<(), String> {
        let (spec, inbox, msg) = ring_case(&case.files[0].1).ok_or("not 32 bytes")?;
        match lmac_shm_schema::ring::check_slot_msg(&spec, inbox, &msg) {
            Ok(()) if msg.member as usize >= spec.n_members || msg.slot as usize >= spec.n_slots => {
                panic!("accepted a message outside the ring: {msg:?} for {spec:?}")
            }
            Ok(()) => Ok(()),
            Err((field, value, problem)) => Err(format!("{field} {value} {problem}")),
        }
    }
}
