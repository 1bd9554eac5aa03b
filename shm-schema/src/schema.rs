//! Environment schema files: parsing, validation with errors that name the file, the field and
//! the problem, and the natural-language meaning of every dimension (read by the LLM prompts).
//! The format is documented in `shm-schema/SCHEMA.md`.

use serde::{Deserialize, Serialize};
use std::fmt;
use std::path::{Path, PathBuf};

/// A group of consecutive dimensions that share one description template.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct DimGroup {
    pub count: usize,
    /// Optional multi-index shape (product must equal `count`): placeholders {i0}, {i1}, ...
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub shape: Option<Vec<usize>>,
    /// Template with placeholders {k}, {i0}.., {label}.
    pub meaning: String,
    /// Optional per-dimension labels (length `count`): placeholder {label}.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub labels: Option<Vec<String>>,
    /// Optional: the group's `count` dims repeat this many times in a row (per agent, per
    /// entity), `count * repeat` dims in all; placeholder {r} is the repetition (0-based), {k}
    /// and {label} stay the index inside one repetition.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub repeat: Option<usize>,
}

impl DimGroup {
    /// The dimensions the group describes (`count`, times `repeat`); `None` on overflow.
    pub fn dims(&self) -> Option<usize> {
        self.count.checked_mul(self.repeat.unwrap_or(1))
    }
}

/// An environment's declaration: the one contract between env servers, runner and trainer.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct EnvSchema {
    pub name: String,
    pub task: String,
    pub n_agents: usize,
    pub obs_dim: usize,
    pub state_dim: usize,
    pub n_actions: usize,
    pub episode_limit: usize,
    #[serde(default)]
    pub message_columns: usize,
    /// Whether an env server splits its batch into two halves stepped in turn while the other
    /// half's slot travels (double buffering; the default). `false` for environments whose step
    /// costs about the same for half a batch as for a whole one (vectorized numpy, fixed cost
    /// per call): there the split costs more than the wait it hides.
    #[serde(default = "double_buffer_default")]
    pub double_buffer: bool,
    pub alpha: f64,
    pub reward: String,
    pub actions: Vec<String>,
    pub obs_dims: Vec<DimGroup>,
    pub state_dims: Vec<DimGroup>,
    /// Agents that observe different things (a speaker and a listener padded to one width):
    /// per kind of agent, which agents and what each of their observation values means. An
    /// agent listed here reads these meanings in the prompts, `protocol explain` and the
    /// designer's log, and its groups are its entities when the designer ranks what it sends;
    /// an agent not listed reads `obs_dims`.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub agent_obs: Vec<AgentObs>,
}

/// The observation of one kind of agent ([`EnvSchema::agent_obs`]).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct AgentObs {
    /// What these agents are ("speaker").
    pub name: String,
    /// The agents (0-based) that observe so.
    pub agents: Vec<usize>,
    /// Groups covering all `obs_dim` values, padding included.
    pub obs_dims: Vec<DimGroup>,
}

fn double_buffer_default() -> bool {
    true
}

/// A schema problem: which file, which field, what is wrong.
#[derive(Debug, Clone, PartialEq)]
pub struct SchemaError {
    pub file: PathBuf,
    pub field: String,
    pub problem: String,
}

impl fmt::Display for SchemaError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.field.is_empty() {
            write!(f, "{}: {}", self.file.display(), self.problem)
        } else {
            write!(f, "{}: {}: {}", self.file.display(), self.field, self.problem)
        }
    }
}
impl std::error::Error for SchemaError {}

/// All problems found in one schema file (validation reports every problem, not just the first).
#[derive(Debug, Clone)]
pub struct SchemaErrors(pub Vec<SchemaError>);

impl fmt::Display for SchemaErrors {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, e) in self.0.iter().enumerate() {
            if i > 0 {
                writeln!(f)?;
            }
            write!(f, "{e}")?;
        }
        Ok(())
    }
}
impl std::error::Error for SchemaErrors {}

/// Largest schema file read (the biggest real one is a few KiB): a bigger file is refused before
/// it is read into memory.
pub const MAX_FILE_BYTES: u64 = 1 << 20;
/// Largest obs_dim, state_dim and n_actions accepted: every dimension gets a description string
/// and a column in every slot, so a corrupt size must not turn into a huge allocation.
pub const MAX_DIM: usize = 1 << 16;
/// Largest episode_limit accepted (the trainer reserves episode buffers of that many steps).
pub const MAX_EPISODE_LIMIT: usize = 1 << 20;
/// Largest message_columns accepted (reserved after every observation row).
pub const MAX_MESSAGE_COLUMNS: usize = 1 << 20;
/// Most bytes the descriptions of one schema's observation or state dimensions may expand to
/// (every dimension gets its group's meaning, labels and indices filled in; the prompts and
/// the meta-information read them). The real schemas need tens of KiB; a group of 65536
/// dimensions with a 1 MB meaning would need 64 GiB.
pub const MAX_MEANING_BYTES: usize = 64 << 20;

/// How a generated schema marks a text a person must still write (`lmac envs --generate`).
pub const PLACEHOLDER: &str = "EDIT:";

impl EnvSchema {
    /// A short fingerprint of everything the schema says (sizes, limits, every text): the first
    /// 16 hex digits of the SHA-256 of its JSON form. Protocol files lmac writes carry it, so a
    /// protocol used after its environment's schema changed is noticed.
    pub fn fingerprint(&self) -> String {
        use sha2::{Digest, Sha256};
        let digest = Sha256::digest(serde_json::to_vec(self).expect("a schema serializes"));
        digest.iter().take(8).map(|b| format!("{b:02x}")).collect()
    }

    /// Read and validate a schema file.
    pub fn load(path: &Path) -> Result<EnvSchema, SchemaErrors> {
        let err = |field: &str, problem: String| SchemaErrors(vec![SchemaError { file: path.to_path_buf(), field: field.into(), problem }]);
        let size = std::fs::metadata(path).map_err(|e| err("", format!("cannot read the file: {e}")))?.len();
        if size > MAX_FILE_BYTES {
            return Err(err("", format!("the file is {size} bytes; a schema file is at most {MAX_FILE_BYTES}")));
        }
        let bytes = crate::safe_fs::read_capped(path, MAX_FILE_BYTES).map_err(|e| err("", format!("cannot read the file: {e}")))?;
        let text =
            String::from_utf8(bytes).map_err(|e| err("", format!("the file is not UTF-8 text (byte {})", e.utf8_error().valid_up_to())))?;
        Self::parse(&text, path)
    }

    /// Parse and validate schema text; `path` is only used in error messages.
    pub fn parse(text: &str, path: &Path) -> Result<EnvSchema, SchemaErrors> {
        let one = |field: String, problem: String| SchemaErrors(vec![SchemaError { file: path.to_path_buf(), field, problem }]);
        let line = |span: Option<std::ops::Range<usize>>| {
            span.map(|s| format!(" (line {})", text[..s.start.min(text.len())].lines().count().max(1))).unwrap_or_default()
        };
        // Syntax first (a truncated file usually ends inside a string, array or table), then the
        // fields, with the path of the one that does not fit ("obs_dims[1].count").
        let de = toml::Deserializer::parse(text)
            .map_err(|e| one(String::new(), format!("not valid TOML: {}{}", e.message(), line(e.span()))))?;
        let schema: EnvSchema = serde_path_to_error::deserialize(de).map_err(|e| {
            let path_text = e.path().to_string();
            let inner = e.inner();
            let msg = inner.message().to_string();
            // At the top level the path is "." and the message names the key instead
            // ("missing field `n_agents`").
            let field = if path_text.is_empty() || path_text == "." {
                msg.split('`').nth(1).filter(|_| msg.contains("field")).unwrap_or("").to_string()
            } else {
                path_text
            };
            one(field, format!("{msg}{}", line(inner.span())))
        })?;
        schema.validate(path)?;
        Ok(schema)
    }

    /// Every semantic check; all problems are reported together.
    pub fn validate(&self, path: &Path) -> Result<(), SchemaErrors> {
        let mut errs = Vec::new();
        let mut bad = |field: &str, problem: String| errs.push(SchemaError { file: path.to_path_buf(), field: field.into(), problem });
        if self.name.split_once(':').map_or(true, |(f, v)| f.is_empty() || v.is_empty()) {
            bad("name", format!("{:?} must look like FAMILY:VARIANT (e.g. lbf:8x8-2p-2f-s1-coop)", self.name));
        }
        if self.task.trim().is_empty() {
            bad("task", "the task description is empty; the LLM prompt is built from it".into());
        }
        for (field, v) in [
            ("n_agents", self.n_agents),
            ("obs_dim", self.obs_dim),
            ("state_dim", self.state_dim),
            ("n_actions", self.n_actions),
            ("episode_limit", self.episode_limit),
        ] {
            if v == 0 {
                bad(field, "must be at least 1".into());
            }
        }
        if self.n_agents > 64 {
            bad("n_agents", format!("{} agents is more than the supported 64", self.n_agents));
        }
        for (field, v, max) in [
            ("obs_dim", self.obs_dim, MAX_DIM),
            ("state_dim", self.state_dim, MAX_DIM),
            ("n_actions", self.n_actions, MAX_DIM),
            ("episode_limit", self.episode_limit, MAX_EPISODE_LIMIT),
            ("message_columns", self.message_columns, MAX_MESSAGE_COLUMNS),
        ] {
            if v > max {
                bad(field, format!("{v} is more than the supported {max}"));
            }
        }
        if !(self.alpha.is_finite() && self.alpha > 0.0) {
            bad("alpha", format!("must be a positive number, got {}", self.alpha));
        }
        if self.actions.len() != self.n_actions {
            bad("actions", format!("lists {} action names but n_actions = {}", self.actions.len(), self.n_actions));
        }
        check_groups("obs_dims", &self.obs_dims, self.obs_dim, "obs_dim", &mut bad);
        check_groups("state_dims", &self.state_dims, self.state_dim, "state_dim", &mut bad);
        // Which agent_obs entry describes each agent listed (a map: n_agents may be any number
        // in a hostile file, and is only bounded above).
        let mut seen = std::collections::BTreeMap::<usize, usize>::new();
        for (i, a) in self.agent_obs.iter().enumerate() {
            let at = format!("agent_obs[{i}]");
            if a.name.trim().is_empty() {
                bad(&format!("{at}.name"), "is empty: say what these agents are".into());
            }
            if a.agents.is_empty() {
                bad(&format!("{at}.agents"), "lists no agent".into());
            }
            for &j in &a.agents {
                if j >= self.n_agents {
                    bad(&format!("{at}.agents"), format!("agent {j} does not exist (n_agents = {})", self.n_agents));
                } else if let Some(first) = seen.insert(j, i) {
                    bad(&format!("{at}.agents"), format!("agent {j} is already described by agent_obs[{first}]"));
                }
            }
            check_groups(&format!("{at}.obs_dims"), &a.obs_dims, self.obs_dim, "obs_dim", &mut bad);
        }
        if errs.is_empty() {
            Ok(())
        } else {
            Err(SchemaErrors(errs))
        }
    }

    /// The fields still holding a placeholder text that starts with [`PLACEHOLDER`] (what
    /// `lmac envs --generate` writes for a person to replace), by their path in the file. `lmac
    /// envs --check` refuses them; a run does not (the texts only reach the LLM prompts).
    pub fn placeholders(&self) -> Vec<String> {
        let mut at = Vec::new();
        let mut see = |field: String, text: &str| {
            if text.trim_start().starts_with(PLACEHOLDER) {
                at.push(field);
            }
        };
        see("task".into(), &self.task);
        see("reward".into(), &self.reward);
        for (i, a) in self.actions.iter().enumerate() {
            see(format!("actions[{i}]"), a);
        }
        let mut lists: Vec<(String, &Vec<DimGroup>)> = vec![("obs_dims".into(), &self.obs_dims), ("state_dims".into(), &self.state_dims)];
        for (k, a) in self.agent_obs.iter().enumerate() {
            see(format!("agent_obs[{k}].name"), &a.name);
            lists.push((format!("agent_obs[{k}].obs_dims"), &a.obs_dims));
        }
        for (kind, groups) in lists {
            for (i, g) in groups.iter().enumerate() {
                see(format!("{kind}[{i}].meaning"), &g.meaning);
                for (j, l) in g.labels.iter().flatten().enumerate() {
                    see(format!("{kind}[{i}].labels[{j}]"), l);
                }
            }
        }
        at
    }

    /// The meaning of every observation dimension, in order (of the agents `agent_obs` does
    /// not describe).
    pub fn obs_meanings(&self) -> Vec<String> {
        expand(&self.obs_dims)
    }

    /// Whether some agents observe differently from the others ([`EnvSchema::agent_obs`]).
    pub fn agents_differ(&self) -> bool {
        !self.agent_obs.is_empty()
    }

    /// The kind of agent `agent` is (its `agent_obs` entry), if it has one.
    pub fn agent_kind(&self, agent: usize) -> Option<&AgentObs> {
        self.agent_obs.iter().find(|a| a.agents.contains(&agent))
    }

    /// The meaning of every value of agent `agent`'s observation, in order.
    pub fn obs_meanings_of(&self, agent: usize) -> Vec<String> {
        match self.agent_kind(agent) {
            Some(a) => expand(&a.obs_dims),
            None => self.obs_meanings(),
        }
    }

    /// The meaning of every state dimension, in order.
    pub fn state_meanings(&self) -> Vec<String> {
        expand(&self.state_dims)
    }

    /// The observation's entities: runs of consecutive dims the schema describes as one thing
    /// (one unit, one teammate slot, one ball), in order, covering every dim once. A group with a
    /// shape of two or more indices is one entity per row (its last index runs over the row's
    /// values: a `[10, 7]` teammate block is ten teammates of seven values); a repeated group is
    /// one entity per repetition (split into rows likewise); any other group is one entity.
    /// Empty on a schema whose groups do not add up (one that failed validation).
    pub fn obs_entities(&self) -> Vec<std::ops::Range<usize>> {
        entities(&self.obs_dims, self.obs_dim)
    }

    /// Agent `agent`'s entities: those of its own groups ([`EnvSchema::agent_obs`]), else
    /// [`obs_entities`](Self::obs_entities).
    pub fn obs_entities_of(&self, agent: usize) -> Vec<std::ops::Range<usize>> {
        match self.agent_kind(agent) {
            Some(a) => entities(&a.obs_dims, self.obs_dim),
            None => self.obs_entities(),
        }
    }

    /// Message columns the built-in full-communication protocol needs per agent:
    /// every other agent's observation plus its one-hot id. 0 with one agent (no one to talk to),
    /// and 0 rather than an underflow for zero agents (a schema that failed validation).
    pub fn fullcomm_columns(&self) -> usize {
        self.n_agents.saturating_sub(1).saturating_mul(self.obs_dim.saturating_add(self.n_agents))
    }
}

/// The entities of `groups` describing `dim` values (see [`EnvSchema::obs_entities`]).
fn entities(groups: &[DimGroup], dim: usize) -> Vec<std::ops::Range<usize>> {
    let mut out = Vec::new();
    let mut at = 0usize;
    for g in groups {
        let row = match g.shape.as_deref() {
            Some(shape) if shape.len() >= 2 && shape[shape.len() - 1] > 0 => shape[shape.len() - 1],
            _ => g.count,
        };
        if row == 0 || g.count % row != 0 {
            return Vec::new();
        }
        for _ in 0..g.repeat.unwrap_or(1) * (g.count / row) {
            out.push(at..at + row);
            at += row;
        }
    }
    if at != dim {
        return Vec::new();
    }
    out
}

/// The checks of one list of dimension groups describing `dim` dimensions (`dim_field`).
fn check_groups(field: &str, groups: &[DimGroup], dim: usize, dim_field: &str, bad: &mut impl FnMut(&str, String)) {
    let mut total = 0usize;
    // What `expand` will allocate, bounded before anything expands it.
    let mut text_bytes = 0usize;
    for (i, g) in groups.iter().enumerate() {
        let at = format!("{field}[{i}]");
        if g.count == 0 {
            bad(&at, "count must be at least 1".into());
        }
        if g.count > MAX_DIM {
            // Checked before anything expands the group into one description per dim.
            bad(&format!("{at}.count"), format!("{} is more than the supported {MAX_DIM}", g.count));
        }
        match g.repeat {
            Some(0) => bad(&format!("{at}.repeat"), "must be at least 1".into()),
            Some(_) if g.dims().is_none_or(|d| d > MAX_DIM) => {
                bad(&format!("{at}.repeat"), format!("count x repeat is more than the supported {MAX_DIM}"))
            }
            None if g.meaning.contains("{r}") => bad(&at, "meaning uses {r} but the group has no repeat".into()),
            _ => {}
        }
        if g.meaning.trim().is_empty() {
            bad(&at, "meaning is empty: every dimension needs a description".into());
        }
        if let Some(shape) = &g.shape {
            match shape.iter().try_fold(1usize, |a, &d| a.checked_mul(d)) {
                Some(prod) if prod == g.count => {}
                Some(prod) => bad(&at, format!("shape {shape:?} holds {prod} dimensions but count = {}", g.count)),
                None => bad(&at, format!("shape {shape:?} holds more dimensions than fit in memory; count = {}", g.count)),
            }
        }
        if let Some(labels) = &g.labels {
            if labels.len() != g.count {
                bad(&at, format!("{} labels for count = {}", labels.len(), g.count));
            }
        } else if g.meaning.contains("{label}") {
            bad(&at, "meaning uses {label} but the group has no labels".into());
        }
        total = total.saturating_add(g.dims().unwrap_or(usize::MAX));
        // Each dimension's text: the meaning with {k}, {r} and {iN} as numbers (at most 20
        // digits each) and {label} as the longest label.
        let label = g.labels.as_ref().and_then(|l| l.iter().map(String::len).max()).unwrap_or(0);
        let per_dim = g.meaning.len().saturating_add(g.meaning.matches('{').count().saturating_mul(20 + label));
        let group_bytes = per_dim.saturating_mul(g.dims().unwrap_or(usize::MAX));
        let before = text_bytes;
        text_bytes = text_bytes.saturating_add(group_bytes);
        // Named once: at the group that crosses the bound.
        if before <= MAX_MEANING_BYTES && text_bytes > MAX_MEANING_BYTES {
            bad(
                &format!("{at}.meaning"),
                format!(
                    "the descriptions of {field} expand to more than {} MiB ({} dimensions x {per_dim} bytes in this group); \
                             shorten the meaning or describe fewer dimensions",
                    MAX_MEANING_BYTES >> 20,
                    g.dims().unwrap_or(usize::MAX)
                ),
            );
        }
    }
    if total != dim {
        bad(field, format!("the groups describe {total} dimensions but {dim_field} = {dim}"));
    }
}

fn expand(groups: &[DimGroup]) -> Vec<String> {
    let mut out = Vec::new();
    for g in groups {
        for (r, k) in (0..g.repeat.unwrap_or(1)).flat_map(|r| (0..g.count).map(move |k| (r, k))) {
            let mut s = g.meaning.replace("{k}", &k.to_string()).replace("{r}", &r.to_string());
            if let Some(shape) = &g.shape {
                let mut rem = k;
                let mut idx = vec![0; shape.len()];
                for (d, &n) in shape.iter().enumerate().rev() {
                    idx[d] = rem % n.max(1);
                    rem /= n.max(1);
                }
                for (d, v) in idx.iter().enumerate() {
                    s = s.replace(&format!("{{i{d}}}"), &v.to_string());
                }
            }
            if let Some(labels) = &g.labels {
                if let Some(l) = labels.get(k) {
                    s = s.replace("{label}", l);
                }
            }
            out.push(s);
        }
    }
    out
}

/// Where the schema files live: `$LMAC_SCHEMA_DIR`, else `env-server/schemas` found by walking
/// up from the current directory and from the executable's directory.
pub fn schema_dir() -> Option<PathBuf> {
    if let Ok(d) = std::env::var("LMAC_SCHEMA_DIR") {
        return Some(PathBuf::from(d));
    }
    let starts = [std::env::current_dir().ok(), std::env::current_exe().ok()];
    for start in starts.into_iter().flatten() {
        for dir in start.ancestors() {
            let cand = dir.join("env-server").join("schemas");
            if cand.is_dir() {
                return Some(cand);
            }
        }
    }
    None
}

/// Why an environment's schema could not be found or loaded; each says what and where.
#[derive(Debug, thiserror::Error)]
pub enum EnvLookupError {
    #[error("environment name {0:?} must look like FAMILY:VARIANT")]
    BadName(String),
    #[error("cannot find env-server/schemas (set LMAC_SCHEMA_DIR)")]
    NoSchemaDir,
    #[error("unknown environment {name:?}: no schema file {} (see `lmac envs`)", .path.display())]
    Unknown { name: String, path: PathBuf },
    #[error(transparent)]
    Invalid(#[from] SchemaErrors),
    #[error("{}: name: {found:?} does not match the file's place ({expected:?})", .path.display())]
    Misplaced { path: PathBuf, found: String, expected: String },
    #[error("{}: {source}", .dir.display())]
    Io { dir: PathBuf, source: std::io::Error },
}

/// `lbf:8x8-2p-2f-s1-coop` -> `<schema_dir>/lbf/8x8-2p-2f-s1-coop.toml`
pub fn schema_path(env_name: &str) -> Result<PathBuf, EnvLookupError> {
    let (family, variant) = env_name
        .split_once(':')
        .filter(|(f, v)| !f.is_empty() && !v.is_empty() && !v.contains('/') && !f.contains('/'))
        .ok_or_else(|| EnvLookupError::BadName(env_name.to_string()))?;
    let dir = schema_dir().ok_or(EnvLookupError::NoSchemaDir)?;
    let p = dir.join(family).join(format!("{variant}.toml"));
    if !p.is_file() {
        return Err(EnvLookupError::Unknown { name: env_name.to_string(), path: p });
    }
    Ok(p)
}

/// Load an environment's schema by name.
pub fn load_env(env_name: &str) -> Result<EnvSchema, EnvLookupError> {
    let p = schema_path(env_name)?;
    let s = EnvSchema::load(&p)?;
    if s.name != env_name {
        return Err(EnvLookupError::Misplaced { path: p, found: s.name, expected: env_name.to_string() });
    }
    Ok(s)
}

/// Every schema file under the schema directory, sorted by name; parse failures are returned too.
pub fn all_envs() -> Result<Vec<(PathBuf, Result<EnvSchema, SchemaErrors>)>, EnvLookupError> {
    let dir = schema_dir().ok_or(EnvLookupError::NoSchemaDir)?;
    let mut files = Vec::new();
    for fam in std::fs::read_dir(&dir).map_err(|source| EnvLookupError::Io { dir: dir.clone(), source })?.flatten() {
        if fam.path().is_dir() {
            for f in std::fs::read_dir(fam.path()).into_iter().flatten().flatten() {
                if f.path().extension().is_some_and(|e| e == "toml") {
                    files.push(f.path());
                }
            }
        }
    }
    files.sort();
    Ok(files
        .into_iter()
        .map(|p| {
            let r = EnvSchema::load(&p);
            (p, r)
        })
        .collect())
}
