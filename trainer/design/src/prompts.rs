//! The designer's prompts: templates under `prompts/` (embedded in the binary so it works from
//! any directory; `LMAC_PROMPTS_DIR` points at an edited copy), rendered from the environment
//! schema, the protocol language reference and the meta-information.
//!
//! Placeholders are `{{name}}`. Every template declares its placeholders: a template that lacks
//! one, or uses one that is not declared, is an error (so an edited template cannot silently drop
//! the meta-information or the validator's text). Substitution is one pass, so a value that
//! happens to contain `{{...}}` is left as it is. `prompts/README.md` lists the placeholders.

use super::meta_info::MetaInfo;
use super::Feedback;
use anyhow::{bail, Context, Result};
use lmac_protocol_runner::protocol::{self, ProtocolEnv, ValidatedProtocol};
use lmac_shm_schema::EnvSchema;
use std::collections::BTreeMap;
use std::path::Path;

/// A template: its file name under `prompts/`, its embedded text and its placeholders.
struct Spec {
    name: &'static str,
    text: &'static str,
    placeholders: &'static [&'static str],
}

macro_rules! spec {
    ($name:literal, [$($p:literal),*]) => {
        Spec { name: $name, text: include_str!(concat!("../../../prompts/", $name)), placeholders: &[$($p),*] }
    };
}

const SPECS: &[Spec] = &[
    spec!("system.md", []),
    spec!(
        "task.md",
        [
            "env_name",
            "task_description",
            "reward_description",
            "episode_limit",
            "n_actions",
            "action_list",
            "obs_shape",
            "n_agents",
            "last_agent",
            "obs_dim",
            "obs_dims",
            "state_dim",
            "state_dims"
        ]
    ),
    spec!("critical_dims.md", ["state_dim", "last_state_dim"]),
    spec!("phase0_initialization.md", []),
    spec!("phase1_recognition.md", ["phase"]),
    spec!("phase2_sharing.md", ["phase"]),
    spec!("phase1_goal.md", ["phase"]),
    spec!("phase2_goal.md", ["phase"]),
    spec!(
        "protocol_generation.md",
        ["phase_title", "phase_goal", "obs_shape", "obs_dim", "language_reference", "budget", "previous_phases", "phase"]
    ),
    spec!("additional_context.md", ["feedback"]),
    spec!(
        "feedback.md",
        ["task_prompt", "phase_instruction", "phase_range", "protocol", "meta_information", "alpha", "budget_left", "language_reference"]
    ),
    spec!("correction.md", ["phase", "errors", "budget_left"]),
    spec!("feedback_correction.md", ["problem"]),
];

/// The template names (file names under `prompts/`).
pub fn template_names() -> Vec<&'static str> {
    SPECS.iter().map(|s| s.name).collect()
}

/// The placeholders of every `{{name}}` in a text, in order of appearance.
fn placeholders_in(text: &str) -> Vec<&str> {
    let mut out = Vec::new();
    let mut rest = text;
    while let Some(a) = rest.find("{{") {
        let after = &rest[a + 2..];
        match after.find("}}") {
            Some(b) if is_ident(&after[..b]) => {
                out.push(&after[..b]);
                rest = &after[b + 2..];
            }
            _ => rest = &rest[a + 1..],
        }
    }
    out
}

fn is_ident(s: &str) -> bool {
    !s.is_empty() && s.bytes().all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == b'_') && !s.as_bytes()[0].is_ascii_digit()
}

/// Substitute `{{name}}` in one pass; names not in `vars` stay (checked before).
fn substitute(text: &str, vars: &BTreeMap<&str, &str>) -> String {
    let mut out = String::with_capacity(text.len());
    let mut rest = text;
    while let Some(a) = rest.find("{{") {
        let after = &rest[a + 2..];
        match after.find("}}").filter(|&b| is_ident(&after[..b])) {
            Some(b) => {
                out.push_str(&rest[..a]);
                match vars.get(&after[..b]) {
                    Some(v) => out.push_str(v),
                    None => out.push_str(&rest[a..a + 4 + b]),
                }
                rest = &after[b + 2..];
            }
            None => {
                out.push_str(&rest[..a + 1]);
                rest = &rest[a + 1..];
            }
        }
    }
    out.push_str(rest);
    out
}

/// The prompt templates, checked.
#[derive(Clone, Debug)]
pub struct Templates {
    texts: BTreeMap<&'static str, String>,
    /// Where they came from: `embedded` or a directory.
    pub source: String,
}

impl Templates {
    /// The templates compiled into the binary.
    pub fn embedded() -> Self {
        let t = Templates { texts: SPECS.iter().map(|s| (s.name, s.text.to_string())).collect(), source: "embedded".into() };
        // The embedded set is tested; a failure here is a build of inconsistent files.
        t.check().expect("the embedded prompt templates are consistent");
        t
    }

    /// Every template read from a directory (all files must be there).
    pub fn from_dir(dir: &Path) -> Result<Self> {
        let mut texts = BTreeMap::new();
        for s in SPECS {
            let p = dir.join(s.name);
            let text =
                lmac_shm_schema::safe_fs::read_text_capped(&p, lmac_shm_schema::safe_fs::TEXT_CAP).context("reading a prompt template")?;
            texts.insert(s.name, text);
        }
        let t = Templates { texts, source: dir.display().to_string() };
        t.check()?;
        Ok(t)
    }

    /// `$LMAC_PROMPTS_DIR` when set, else the embedded templates.
    pub fn from_env() -> Result<Self> {
        match std::env::var_os("LMAC_PROMPTS_DIR") {
            Some(d) => Self::from_dir(Path::new(&d)).context("LMAC_PROMPTS_DIR"),
            None => Ok(Self::embedded()),
        }
    }

    /// Every template has exactly its declared placeholders.
    pub fn check(&self) -> Result<()> {
        let mut problems = Vec::new();
        for s in SPECS {
            let text = &self.texts[s.name];
            let used = placeholders_in(text);
            for p in s.placeholders {
                if !used.contains(p) {
                    problems.push(format!("{}: placeholder {{{{{p}}}}} is missing", s.name));
                }
            }
            for u in &used {
                if !s.placeholders.contains(u) {
                    problems.push(format!("{}: unknown placeholder {{{{{u}}}}} (known: {})", s.name, s.placeholders.join(", ")));
                }
            }
        }
        if !problems.is_empty() {
            bail!("prompt templates from {}:\n- {}", self.source, problems.join("\n- "));
        }
        Ok(())
    }

    /// Render a template with values for all its placeholders.
    pub fn render(&self, name: &str, vars: &[(&str, String)]) -> Result<String> {
        let spec = SPECS.iter().find(|s| s.name == name).with_context(|| format!("no prompt template named {name}"))?;
        let map: BTreeMap<&str, &str> = vars.iter().map(|(k, v)| (*k, v.as_str())).collect();
        for p in spec.placeholders {
            if !map.contains_key(p) {
                bail!("rendering {name}: no value for placeholder {{{{{p}}}}}");
            }
        }
        for k in map.keys() {
            if !spec.placeholders.contains(k) {
                bail!("rendering {name}: {{{{{k}}}}} is not a placeholder of this template");
            }
        }
        Ok(substitute(&self.texts[spec.name], &map).trim_end().to_string() + "\n")
    }

    /// The system prompt (the designer's role).
    pub fn system(&self) -> Result<String> {
        self.render("system.md", &[])
    }

    /// I_T: the task, the observation tensor shape, the meaning of every observation and state
    /// dim (`o[batch][agent_id][d]`, `s[d]`) and of every action.
    pub fn task(&self, env_name: &str, schema: &EnvSchema) -> Result<String> {
        let dims = |meanings: &[String], indent: &str| -> Vec<String> {
            meanings.iter().enumerate().map(|(d, m)| format!("{indent}- `o[batch][agent_id][{d}]`: {m}")).collect()
        };
        let obs: Vec<String> = if schema.agents_differ() {
            // Agents that observe different things: each kind's own meanings, under its agents.
            let rest: Vec<usize> = (0..schema.n_agents).filter(|&j| schema.agent_kind(j).is_none()).collect();
            let mut kinds: Vec<(String, Vec<usize>, Vec<String>)> =
                schema.agent_obs.iter().map(|k| (k.name.clone(), k.agents.clone(), schema.obs_meanings_of(k.agents[0]))).collect();
            if !rest.is_empty() {
                kinds.push(("the other agents".into(), rest, schema.obs_meanings()));
            }
            kinds
                .into_iter()
                .flat_map(|(name, agents, meanings)| {
                    let ids: Vec<String> = agents.iter().map(|a| a.to_string()).collect();
                    let mut lines = vec![format!("  - agent_id in {{{}}} ({name}):", ids.join(", "))];
                    lines.extend(dims(&meanings, "    "));
                    lines
                })
                .collect()
        } else {
            dims(&schema.obs_meanings(), "  ")
        };
        let state: Vec<String> = schema.state_meanings().iter().enumerate().map(|(d, m)| format!("  - `s[{d}]`: {m}")).collect();
        let actions: Vec<String> = schema.actions.iter().enumerate().map(|(a, m)| format!("  - {a}: {m}")).collect();
        self.render(
            "task.md",
            &[
                ("env_name", env_name.to_string()),
                ("task_description", schema.task.trim().to_string()),
                ("reward_description", schema.reward.trim().to_string()),
                ("episode_limit", schema.episode_limit.to_string()),
                ("n_actions", schema.n_actions.to_string()),
                ("action_list", actions.join("\n")),
                ("obs_shape", obs_shape(schema.n_agents, schema.obs_dim)),
                ("n_agents", schema.n_agents.to_string()),
                ("last_agent", schema.n_agents.saturating_sub(1).to_string()),
                ("obs_dim", schema.obs_dim.to_string()),
                ("obs_dims", obs.join("\n")),
                ("state_dim", schema.state_dim.to_string()),
                ("state_dims", state.join("\n")),
            ],
        )
    }

    /// The chain-of-thought turn before phase 0: select the task-critical state dims.
    pub fn critical_dims(&self, env: &ProtocolEnv) -> Result<String> {
        self.render(
            "critical_dims.md",
            &[("state_dim", env.state_dim.to_string()), ("last_state_dim", env.state_dim.saturating_sub(1).to_string())],
        )
    }

    /// The feedback prompt's phase instruction (how to read the evaluation, what to suggest):
    /// 1 recognition enhancement, 2 and later sharing enhancement (further phases keep refining
    /// the sharing, as in the paper's more-phases ablation).
    pub fn phase_instruction(&self, phase: usize) -> Result<String> {
        match phase {
            0 => bail!("phase 0 has no feedback: it is written from the task prompt alone"),
            1 => self.render("phase1_recognition.md", &[("phase", phase.to_string())]),
            _ => self.render("phase2_sharing.md", &[("phase", phase.to_string())]),
        }
    }

    /// The generation prompt's statement of the phase's goal.
    pub fn phase_goal(&self, phase: usize) -> Result<String> {
        match phase {
            0 => self.render("phase0_initialization.md", &[]),
            1 => self.render("phase1_goal.md", &[("phase", phase.to_string())]),
            _ => self.render("phase2_goal.md", &[("phase", phase.to_string())]),
        }
    }

    /// I_P: the design principles, the language reference, the budget left after `previous`,
    /// the earlier phases, and what to write for `phase`.
    pub fn protocol_generation(&self, env: &ProtocolEnv, phase: usize, previous: &[ValidatedProtocol]) -> Result<String> {
        self.render(
            "protocol_generation.md",
            &[
                ("phase_title", phase_title(phase)),
                ("phase_goal", self.phase_goal(phase)?.trim_end().to_string()),
                ("obs_shape", obs_shape(env.n_agents, env.obs_dim)),
                ("obs_dim", env.obs_dim.to_string()),
                ("language_reference", protocol::language_reference(Some(env)).trim_end().to_string()),
                ("budget", budget_text(env, previous)),
                ("previous_phases", previous_phases_text(previous, "None: this is the first phase.", PREVIOUS_FIXED)),
                ("phase", phase.to_string()),
            ],
        )
    }

    /// The feedback prompt for `phase` (= k + 1) on the protocol so far (phases 0..=k) and its
    /// meta-information (rendered within `meta_max_chars`).
    #[allow(clippy::too_many_arguments)]
    pub fn feedback(
        &self,
        env_name: &str,
        schema: &EnvSchema,
        env: &ProtocolEnv,
        phase: usize,
        previous: &[ValidatedProtocol],
        meta: &MetaInfo,
        meta_max_chars: usize,
    ) -> Result<String> {
        if previous.is_empty() {
            bail!("feedback for phase {phase}: there is no protocol to analyse yet");
        }
        self.render(
            "feedback.md",
            &[
                ("task_prompt", self.task(env_name, schema)?.trim_end().to_string()),
                ("phase_instruction", self.phase_instruction(phase)?.trim_end().to_string()),
                ("phase_range", if previous.len() == 1 { "phase 0".to_string() } else { format!("phases 0 to {}", previous.len() - 1) }),
                ("protocol", previous_phases_text(previous, "", "")),
                ("meta_information", render_meta(meta, meta_max_chars)),
                ("alpha", schema.alpha.to_string()),
                ("budget_left", budget_left(env, previous).to_string()),
                ("language_reference", reference_for_analysis(env)),
            ],
        )
    }

    /// The feedback appended to the generation prompt of the next phase.
    pub fn additional_context(&self, feedback: &Feedback) -> Result<String> {
        self.render("additional_context.md", &[("feedback", serde_json::to_string_pretty(feedback)?)])
    }

    /// The validator's text handed back for another try.
    pub fn correction(&self, phase: usize, errors: &str, budget_left: usize) -> Result<String> {
        self.render(
            "correction.md",
            &[("phase", phase.to_string()), ("errors", errors.trim_end().to_string()), ("budget_left", budget_left.to_string())],
        )
    }

    /// What was wrong with a feedback reply, handed back for another try.
    pub fn feedback_correction(&self, problem: &str) -> Result<String> {
        self.render("feedback_correction.md", &[("problem", problem.trim_end().to_string())])
    }
}

fn obs_shape(n_agents: usize, obs_dim: usize) -> String {
    format!("(batch, {n_agents}, {obs_dim})")
}

fn phase_title(phase: usize) -> String {
    match phase {
        0 => "phase 0 (initialization)".into(),
        1 => "phase 1 (recognition enhancement)".into(),
        k => format!("phase {k} (sharing enhancement)"),
    }
}

/// Message columns still free per receiving agent after the earlier phases.
pub fn budget_left(env: &ProtocolEnv, previous: &[ValidatedProtocol]) -> usize {
    env.message_budget.saturating_sub(protocol::combined_width(previous))
}

/// The budget in numbers the LLM can plan with: columns left and field columns per sender block.
fn budget_text(env: &ProtocolEnv, previous: &[ValidatedProtocol]) -> String {
    let used = protocol::combined_width(previous);
    let left = budget_left(env, previous);
    let n = env.n_agents;
    let blocks = n.saturating_sub(1).max(1);
    let per_block = left / blocks;
    let mut s = format!("Each receiving agent can take at most {} message columns, all phases together. ", env.message_budget);
    if previous.is_empty() {
        s.push_str(&format!("This phase may use all {left} of them. "));
    } else {
        s.push_str(&format!("The earlier phases use {used}, so this phase may use at most {left}. "));
    }
    s.push_str(&format!(
        "A receiving agent pays, for each other agent that sends it at least one field, {n} sender one-hot columns plus the widths of the fields that agent sends it; the phase's width is the widest receiver's. So if every agent broadcasts every field, the fields may use at most {} columns together ({} if \"sender_one_hot\" is false); fields sent only where they help (peer links) cost less.",
        per_block.saturating_sub(n),
        per_block
    ));
    s
}

const PREVIOUS_FIXED: &str =
    "These phases are fixed; the new phase's fields are appended after theirs, so do not repeat what they already send.\n";

/// The earlier phases as JSON with their widths (the JSON is what the LLM wrote and reads best).
fn previous_phases_text(previous: &[ValidatedProtocol], none: &str, intro: &str) -> String {
    if previous.is_empty() {
        return none.to_string();
    }
    let mut s = String::from(intro);
    for (k, v) in previous.iter().enumerate() {
        s.push_str(&format!(
            "\nPhase {k} ({} message columns per receiving agent):\n```json\n{}\n```\n",
            v.width,
            protocol_json(&v.protocol)
        ));
    }
    s.trim().to_string()
}

/// A protocol as JSON with one line per top-level key and per field: fully pretty-printed
/// expressions take several times the tokens and are harder to scan. Falls back to plain pretty
/// JSON if the layout would not read back as the same protocol (e.g. a key added to the language
/// and not listed here).
pub fn protocol_json(p: &protocol::Protocol) -> String {
    fn line<T: serde::Serialize>(v: &T) -> String {
        serde_json::to_string(v).expect("a protocol part serializes")
    }
    let mut parts: Vec<String> = Vec::new();
    if let Some(n) = &p.name {
        parts.push(format!("  \"name\": {}", line(n)));
    }
    if let Some(k) = &p.phase {
        parts.push(format!("  \"phase\": {}", line(k)));
    }
    parts.push(format!("  \"message_design_instruction\": {}", line(&p.message_design_instruction)));
    parts.push(format!("  \"critical_state_dims\": {}", line(&p.critical_state_dims)));
    if let Some(r) = &p.critical_state_reasoning {
        parts.push(format!("  \"critical_state_reasoning\": {}", line(r)));
    }
    parts.push(format!("  \"sender_one_hot\": {}", line(&p.sender_one_hot)));
    parts.push(format!("  \"history_padding\": {}", line(&p.history_padding)));
    let fields: Vec<String> = p.fields.iter().map(|f| format!("    {}", line(f))).collect();
    parts.push(format!("  \"fields\": [\n{}\n  ]", fields.join(",\n")));
    let text = format!("{{\n{}\n}}", parts.join(",\n"));
    let same = serde_json::from_str::<serde_json::Value>(&text).ok() == serde_json::to_value(p).ok();
    if same {
        text
    } else {
        serde_json::to_string_pretty(p).expect("a protocol serializes")
    }
}

/// The language reference for the feedback prompt, where the answer is feedback, not a protocol:
/// its opening line asks for a protocol object, so it is restated as a description.
fn reference_for_analysis(env: &ProtocolEnv) -> String {
    let r = protocol::language_reference(Some(env));
    let r = r.trim_end();
    match r.split_once('\n') {
        Some((first, rest)) if first.starts_with("Answer with") => {
            format!("A protocol is one JSON object (no code, nothing is executed):\n{rest}")
        }
        _ => r.to_string(),
    }
}

/// The meta-information as JSON within `max_chars`: pretty when it fits, else compact with
/// numbers rounded to 3 decimals, else with the longest lists cut (halving the longest until it
/// fits, with a note of how many entries were left out), else cut at the limit with a note.
pub fn render_meta(meta: &MetaInfo, max_chars: usize) -> String {
    let mut meta = meta.json();
    strip_keys(&mut meta, WALL_CLOCK_KEYS);
    let pretty = serde_json::to_string_pretty(&meta).expect("JSON serializes");
    if pretty.chars().count() <= max_chars {
        return pretty;
    }
    let mut v = round_numbers(&meta);
    let mut s = serde_json::to_string(&v).expect("JSON serializes");
    let mut cuts: BTreeMap<String, usize> = BTreeMap::new();
    while s.chars().count() > max_chars {
        if !halve_longest(&mut v, &mut cuts) {
            break;
        }
        s = serde_json::to_string(&v).expect("JSON serializes");
    }
    if s.chars().count() > max_chars {
        let cut: String = s.chars().take(max_chars).collect();
        return format!("{cut}\n[... cut at {max_chars} characters to fit the prompt]");
    }
    if !cuts.is_empty() {
        let notes: Vec<String> =
            cuts.iter().map(|(p, n)| format!("{} (first entries of {n})", if p.is_empty() { "/" } else { p })).collect();
        s.push_str(&format!("\n[shortened to fit the prompt: lists cut at {}]", notes.join(", ")));
    }
    s
}

/// Wall-clock figures of the meta-information (the discriminator's training time): they differ
/// from run to run, so a prompt carrying them could never be replayed from its recording, and
/// they tell the designer nothing about the protocol. `meta.json` keeps them.
const WALL_CLOCK_KEYS: &[&str] = &["seconds", "ms_per_update"];

fn strip_keys(v: &mut serde_json::Value, keys: &[&str]) {
    match v {
        serde_json::Value::Object(o) => {
            o.retain(|k, _| !keys.contains(&k.as_str()));
            o.values_mut().for_each(|x| strip_keys(x, keys));
        }
        serde_json::Value::Array(a) => a.iter_mut().for_each(|x| strip_keys(x, keys)),
        _ => {}
    }
}

fn round_numbers(v: &serde_json::Value) -> serde_json::Value {
    use serde_json::Value;
    match v {
        Value::Number(n) if n.is_f64() => {
            let x = n.as_f64().unwrap_or(0.0);
            serde_json::Number::from_f64((x * 1000.0).round() / 1000.0).map_or(Value::Null, Value::Number)
        }
        Value::Array(a) => Value::Array(a.iter().map(round_numbers).collect()),
        Value::Object(o) => Value::Object(o.iter().map(|(k, x)| (k.clone(), round_numbers(x))).collect()),
        other => other.clone(),
    }
}

/// Halve the longest array (by element count, at least 2) anywhere in `v`; records its JSON
/// pointer and original length in `cuts`. False when nothing is left to cut.
fn halve_longest(v: &mut serde_json::Value, cuts: &mut BTreeMap<String, usize>) -> bool {
    fn find(v: &serde_json::Value, path: String, best: &mut Option<(usize, String)>) {
        match v {
            serde_json::Value::Array(a) => {
                if a.len() >= 2 && best.as_ref().is_none_or(|(n, _)| a.len() > *n) {
                    *best = Some((a.len(), path.clone()));
                }
                for (i, x) in a.iter().enumerate() {
                    find(x, format!("{path}/{i}"), best);
                }
            }
            serde_json::Value::Object(o) => {
                for (k, x) in o {
                    find(x, format!("{path}/{}", k.replace('~', "~0").replace('/', "~1")), best);
                }
            }
            _ => {}
        }
    }
    let mut best = None;
    find(v, String::new(), &mut best);
    let Some((n, path)) = best else { return false };
    let keep = n.div_ceil(2);
    if let Some(serde_json::Value::Array(a)) = v.pointer_mut(&path) {
        a.truncate(keep);
        // Cuts recorded inside entries that are now gone no longer describe anything shown.
        let prefix = format!("{path}/");
        cuts.retain(|p, _| match p.strip_prefix(&prefix) {
            Some(rest) => rest.split('/').next().and_then(|i| i.parse::<usize>().ok()).is_some_and(|i| i < keep),
            None => true,
        });
        cuts.entry(path).or_insert(n);
        return true;
    }
    false
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn embedded_templates_are_consistent() {
        Templates::embedded().check().unwrap();
        // The README documents every template and its placeholders.
        let readme = include_str!("../../../prompts/README.md");
        for s in SPECS {
            let row = readme
                .lines()
                .find(|l| l.starts_with(&format!("| `{}`", s.name)))
                .unwrap_or_else(|| panic!("prompts/README.md lacks {}", s.name));
            for p in s.placeholders {
                assert!(row.contains(&format!("`{p}`")), "prompts/README.md: {} lacks {p}", s.name);
            }
        }
    }

    /// Agents that observe different things: the task prompt gives each kind's own meanings
    /// under its agents, never one agent's values in another's words.
    #[test]
    fn the_task_prompt_gives_each_kind_of_agent_its_own_meanings() {
        let t = Templates::embedded();
        let mut schema = lmac_shm_schema::schema::load_env("lbf:8x8-2p-2f-s1-coop").unwrap();
        let mut kind = schema.obs_dims.clone();
        kind[0].meaning = format!("as the scout sees it: {}", kind[0].meaning);
        schema.agent_obs = vec![lmac_shm_schema::schema::AgentObs { name: "scout".into(), agents: vec![1], obs_dims: kind }];
        let task = t.task("lbf:8x8-2p-2f-s1-coop", &schema).unwrap();
        assert!(task.contains("agent_id in {1} (scout):") && task.contains("agent_id in {0} (the other agents):"), "{task}");
        let scout = schema.obs_meanings_of(1);
        assert!(task.contains(&format!("    - `o[batch][agent_id][0]`: {}", scout[0])), "{task}");
        assert!(task.contains(&format!("    - `o[batch][agent_id][0]`: {}", schema.obs_meanings()[0])), "{task}");
    }

    /// Appendix B.1's prompts, rendered for one map: every part the paper's templates have.
    #[test]
    fn each_b1_prompt_renders_every_part_for_one_map() {
        let t = Templates::embedded();
        let name = "lbf:8x8-2p-2f-s1-coop-entity";
        let schema = lmac_shm_schema::schema::load_env(name).unwrap();
        let env = lmac_protocol_runner::protocol_env(&schema);
        // Task description I_T: the task, the reward, the actions, the observation tensor and
        // the meaning of every observation and state dim.
        let task = t.task(name, &schema).unwrap();
        assert!(task.contains(schema.task.trim()) && task.contains(schema.reward.trim()), "{task}");
        assert!(schema.actions.iter().all(|a| task.contains(a.as_str())));
        assert!(task.contains("(batch, 2, 29)"));
        for (d, m) in schema.obs_meanings().iter().enumerate() {
            assert!(task.contains(&format!("`o[batch][agent_id][{d}]`")) && task.contains(m.as_str()), "obs dim {d}");
        }
        for (d, m) in schema.state_meanings().iter().enumerate() {
            assert!(task.contains(&format!("`s[{d}]`")) && task.contains(m.as_str()), "state dim {d}");
        }
        // The chain-of-thought step for the task-critical dims.
        assert!(t.critical_dims(&env).unwrap().contains("task-critical state dimensions"));
        // I_P: the seven design principles, the language, the budget, each phase's goal.
        for (phase, goal) in [(0, "initialization"), (1, "recognition enhancement"), (2, "sharing enhancement")] {
            let previous: Vec<ValidatedProtocol> = Vec::new();
            let g = t.protocol_generation(&env, phase, &previous).unwrap();
            for p in [
                "1. Task-oriented communication",
                "2. Unique, sufficient and compact",
                "3. Context- and interaction-aware",
                "4. Explicit and clear",
                "5. Structured output",
                "6. Routing",
                "7. No trainable parts",
            ] {
                assert!(g.contains(p), "phase {phase}: principle {p:?}");
            }
            assert!(g.contains(goal) && g.contains("\"obs_slice\"") && g.contains("at most 64 message columns"), "phase {phase}");
        }
        // The feedback prompt: the phase instruction, the protocol under analysis, the
        // meta-information, alpha, and the three keys the reply must have.
        let p0 = lmac_protocol_runner::protocol::check_str(
            r#"{"name": "ids", "message_design_instruction": "x", "critical_state_dims": [0, 1],
                "fields": [{"name": "pos", "description": "own row and column", "value": {"obs_slice": [27, 29]}}]}"#,
            &env,
        )
        .unwrap();
        let dims: Vec<(usize, String)> = schema.state_meanings().into_iter().enumerate().collect();
        let meta = super::super::meta_info::example(&dims, &[0.7, 0.6], &[0.5, 0.4]);
        for (phase, instruction) in [(1, "recognition enhancement"), (2, "sharing enhancement")] {
            let f = t.feedback(name, &schema, &env, phase, std::slice::from_ref(&p0), &meta, 60_000).unwrap();
            assert!(f.contains(instruction) && f.contains("\"pos\"") && f.contains(&dims[3].1), "phase {phase}: {f}");
            assert!(f.contains(&schema.alpha.to_string()) && f.contains(schema.task.trim()));
            for k in ["Evaluation", "Missing_Information_Hypothesis", "Improvement_Suggestions"] {
                assert!(f.contains(k), "phase {phase}: {k}");
            }
        }
        // The additional context carries the feedback into the next generation prompt.
        let fb = super::super::Feedback {
            evaluation: "phase 0 misses the food".into(),
            missing_information_hypothesis: "teammate position".into(),
            improvement_suggestions: "send the row and column".into(),
        };
        let extra = t.additional_context(&fb).unwrap();
        assert!(
            extra.contains("Additional context")
                && extra.contains("send the row and column")
                && extra.contains("Missing_Information_Hypothesis")
        );
    }

    #[test]
    fn placeholders_and_substitution() {
        assert_eq!(placeholders_in("a {{x}} {\"k\": {{y_1}}} {{ not }} {{{z}}}"), vec!["x", "y_1", "z"]);
        let vars: BTreeMap<&str, &str> = [("x", "{{y}}"), ("y", "Y")].into_iter().collect();
        // One pass: the value of x is not expanded again.
        assert_eq!(substitute("{{x}}-{{y}}-{{q}}-{ {\"a\":1}}", &vars), "{{y}}-Y-{{q}}-{ {\"a\":1}}");
    }

    #[test]
    fn render_errors_name_template_and_placeholder() {
        let t = Templates::embedded();
        let e = t.render("correction.md", &[("phase", "1".into()), ("errors", "x".into())]).unwrap_err().to_string();
        assert!(e.contains("correction.md") && e.contains("budget_left"), "{e}");
        let e = t
            .render("correction.md", &[("phase", "1".into()), ("errors", "x".into()), ("budget_left", "3".into()), ("bogus", "".into())])
            .unwrap_err()
            .to_string();
        assert!(e.contains("bogus"), "{e}");
        let mut broken = t.clone();
        broken.texts.insert("feedback.md", "no placeholders here".into());
        let e = broken.check().unwrap_err().to_string();
        assert!(e.contains("feedback.md") && e.contains("meta_information"), "{e}");
    }

    #[test]
    fn protocol_json_is_compact_and_exact() {
        let text = include_str!("../../../prompts/examples/lbf_8x8_phase2.json");
        let p = protocol::parse_str(text).unwrap();
        let j = protocol_json(&p);
        assert_eq!(protocol::parse_str(&j).unwrap(), p);
        assert_eq!(j.lines().count(), 8 + 2 + p.fields.len(), "{j}");
    }

    #[test]
    fn meta_is_capped() {
        let dims: Vec<(usize, String)> = (0..300).map(|d| (d, format!("s[{d}] - something long enough"))).collect();
        let small = render_meta(&super::super::meta_info::example(&dims[..1], &[0.5, 0.25], &[0.5, 0.25]), 10_000);
        assert!(small.contains("\"dim\": 0,") && small.contains("\"dimension\": \"s[0] - something long enough\""), "{small}");
        // Rates as measured are rounded to 3 decimals; the 5-decimal variances are cut to 3 when shortened.
        let meta = super::super::meta_info::example(&dims, &[0.123, 0.543], &[0.1, 0.2]);
        assert!(render_meta(&meta, 1_000_000).contains("0.0441"));
        let s = render_meta(&meta, 4000);
        assert!(s.chars().count() < 4300, "{}", s.len());
        assert!(s.contains("summary") && s.contains("/dimensions (first entries of 300)"), "{s}");
        assert!(s.contains("0.123") && s.contains("0.044") && !s.contains("0.0441"), "{s}");
    }
}
