//! Validation against an environment. Every error carries the JSON path of the offending
//! element and a message written to be handed back verbatim to the LLM that wrote the protocol.

use super::ast::*;
use super::env::ProtocolEnv;
use super::error::{ErrorKind, ValidationError};
use super::parse::{parse_str, read_protocol_file};
use super::width::{block_width, combined_width, compact_widths, receiver_widths, PhaseLinks};
use std::collections::BTreeSet;

/// Longest window (k) an aggregate may use.
pub const MAX_WINDOW: usize = 64;
/// Deepest expression nesting accepted.
pub const MAX_DEPTH: usize = 24;
/// Most expression nodes in one protocol.
pub const MAX_NODES: usize = 4096;
/// Most fields in one protocol.
pub const MAX_FIELDS: usize = 256;

/// A protocol that passed validation against one environment, with its derived facts.
#[derive(Debug, Clone, PartialEq)]
pub struct ValidatedProtocol {
    pub protocol: Protocol,
    pub env: ProtocolEnv,
    /// Width of each field's value, in field order.
    pub field_widths: Vec<usize>,
    /// `sends[f][j][i]`: sender j sends field f to receiver i.
    pub sends: Vec<Vec<Vec<bool>>>,
    /// Message columns each receiving agent gets from this protocol (phase): in the compact
    /// layout the widest receiver's (the others are padded with zeros to it).
    pub width: usize,
    /// The critical state dims, expanded and sorted.
    pub critical_dims: Vec<usize>,
    /// What is valid but suspicious: the protocol was saved for another environment, or before
    /// its environment's schema changed.
    pub warnings: Vec<String>,
}

impl ValidatedProtocol {
    /// Columns of one sender block: one-hot (if on) + all field widths.
    pub fn block_width(&self) -> usize {
        block_width(&self.protocol, &self.env, &self.field_widths)
    }
    /// Does sender j send anything to receiver i in this phase?
    pub fn links(&self, j: usize, i: usize) -> bool {
        self.sends.iter().any(|s| s[j][i])
    }
    /// Columns receiver i's message needs in this phase before padding (in the sender-blocks
    /// layout every receiver needs `width`).
    pub fn receiver_width(&self, i: usize) -> usize {
        receiver_widths(&self.protocol, &self.env, &self.field_widths, &self.sends).get(i).copied().unwrap_or(0)
    }
}

// ------------------------------------------------------------------------------------------
// Validation

/// Validate a parsed protocol against an environment, with the whole budget available.
pub fn validate(p: &Protocol, env: &ProtocolEnv) -> Result<ValidatedProtocol, Vec<ValidationError>> {
    validate_phase(p, env, &[])
}

/// Parse and validate JSON text.
pub fn check_str(text: &str, env: &ProtocolEnv) -> Result<ValidatedProtocol, Vec<ValidationError>> {
    validate(&parse_str(text)?, env)
}

/// Read, parse and validate a protocol file.
pub fn check_file(path: impl AsRef<std::path::Path>, env: &ProtocolEnv) -> Result<ValidatedProtocol, Vec<ValidationError>> {
    let text = read_protocol_file(path.as_ref()).map_err(|e| vec![ValidationError::new(ErrorKind::Io, "", e.to_string())])?;
    check_str(&text, env)
}

/// Validate a later phase: `previous` phases already use part of the message budget.
pub fn validate_phase(p: &Protocol, env: &ProtocolEnv, previous: &[ValidatedProtocol]) -> Result<ValidatedProtocol, Vec<ValidationError>> {
    let mut v = Validator { env, errors: Vec::new(), nodes: 0, nodes_reported: false };
    let n = env.n_agents;
    if n < 2 {
        v.err(
            ErrorKind::Env,
            "",
            None,
            format!("the environment has {n} agent(s): messages need at least 2 agents (a sender never receives its own message)"),
        );
        return Err(v.errors);
    }

    if let Some(name) = &p.name {
        if !valid_ident(name) {
            v.err(ErrorKind::Name, "name", None, format!("protocol name {name:?} must be 1-64 characters of letters, digits, '_' or '-'"));
        }
    }
    if p.message_design_instruction.trim().is_empty() {
        v.err(
            ErrorKind::Empty,
            "message_design_instruction",
            None,
            "the design description is empty: explain what each agent shares, with whom, and why".to_string(),
        );
    }
    v.critical_dims(p);

    if p.fields.is_empty() {
        v.err(ErrorKind::Empty, "fields", None, "the protocol has no fields: define at least one message field".to_string());
    }
    if p.fields.len() > MAX_FIELDS {
        v.err(ErrorKind::Size, "fields", None, format!("{} fields is more than the limit of {MAX_FIELDS}", p.fields.len()));
        return Err(v.errors);
    }

    let mut names = BTreeSet::new();
    let mut widths = Vec::with_capacity(p.fields.len());
    let mut sends = Vec::with_capacity(p.fields.len());
    for (fi, f) in p.fields.iter().enumerate() {
        let fp = format!("fields[{fi}]");
        let fname = Some(f.name.as_str());
        if !valid_ident(&f.name) {
            v.err(
                ErrorKind::Name,
                &format!("{fp}.name"),
                None,
                format!("field name {:?} must be 1-64 characters of letters, digits, '_' or '-'", f.name),
            );
        } else if !names.insert(f.name.as_str()) {
            v.err(
                ErrorKind::Name,
                &format!("{fp}.name"),
                None,
                format!("field name {:?} is used by an earlier field: field names must be unique", f.name),
            );
        }
        if f.description.trim().is_empty() {
            v.err(ErrorKind::Empty, &format!("{fp}.description"), fname, "the description is empty: say what the value means".to_string());
        }
        let senders = v.senders(f, &fp);
        sends.push(v.receivers(f, &fp, &senders));
        let w = v.expr(&f.value, &format!("{fp}.value"), fname, 0, false);
        widths.push(w.unwrap_or(0));
    }
    if !v.errors.is_empty() {
        return Err(v.errors);
    }

    // Budget.
    let per_receiver = receiver_widths(p, env, &widths, &sends);
    let width = per_receiver.iter().copied().max().unwrap_or(0);
    if let Some(q) = previous.iter().find(|q| q.protocol.layout != p.layout) {
        v.err(
            ErrorKind::Phases,
            "layout",
            None,
            format!(
                "this phase uses the {} layout but an earlier phase ({}) uses {}: all phases of one protocol use the same layout",
                layout_name(p.layout),
                q.protocol.name.as_deref().unwrap_or("unnamed"),
                layout_name(q.protocol.layout)
            ),
        );
        return Err(v.errors);
    }
    let used = combined_width(previous);
    let available = env.message_budget.saturating_sub(used);
    // What this phase adds to the plan's width (in the compact layout a sender that already
    // reaches a receiver does not pay its one-hot again).
    let added = match p.layout {
        MessageLayout::SenderBlocks => width,
        MessageLayout::Compact => {
            let mut links: Vec<PhaseLinks> = previous
                .iter()
                .map(|q| PhaseLinks { onehot: q.protocol.sender_one_hot, widths: &q.field_widths, sends: &q.sends })
                .collect();
            links.push(PhaseLinks { onehot: p.sender_one_hot, widths: &widths, sends: &sends });
            compact_widths(n, &links).into_iter().max().unwrap_or(0).saturating_sub(used)
        }
    };
    if added > available {
        let onehot = if p.sender_one_hot { n } else { 0 };
        let prev = if previous.is_empty() {
            String::new()
        } else {
            format!(" (the budget is {} columns and earlier phases already use {used})", env.message_budget)
        };
        let msg = match p.layout {
            MessageLayout::SenderBlocks => {
                // A width above zero means at least one other agent (message_width is 0 with one),
                // but keep the arithmetic safe on its own.
                let senders = n.saturating_sub(1);
                let parts: Vec<String> = p.fields.iter().zip(&widths).map(|(f, w)| format!("{}={w}", f.name)).collect();
                format!(
                    "the message is {width} columns per receiving agent but only {available} are available{prev}: \
                     width = (n_agents - 1 = {}) sender blocks x ({onehot} sender one-hot + {} field columns: {}) (layout sender_blocks). \
                     Remove or narrow fields (e.g. aggregate with reduce, or pick fewer obs dims) by at least {} columns per block, \
                     or use the default compact layout",
                    senders,
                    block_width(p, env, &widths) - onehot,
                    parts.join(", "),
                    (width - available).div_ceil(senders.max(1))
                )
            }
            MessageLayout::Compact => {
                let i = per_receiver.iter().position(|&w| w == width).unwrap_or(0);
                let total = if previous.is_empty() {
                    String::new()
                } else {
                    format!(" (with the earlier phases the message would be {} columns, {added} more than they use)", used + added)
                };
                let from: Vec<String> = (0..n)
                    .filter(|&j| j != i && sends.iter().any(|s| s[j][i]))
                    .map(|j| {
                        let fw: usize = (0..widths.len()).filter(|&f| sends[f][j][i]).map(|f| widths[f]).sum();
                        format!("{j}: {}", onehot + fw)
                    })
                    .collect();
                let parts: Vec<String> = p.fields.iter().zip(&widths).map(|(f, w)| format!("{}={w}", f.name)).collect();
                format!(
                    "the message is {width} columns per receiving agent{total} but only {available} are available{prev}: \
                     the widest receiver, agent {i}, is reached by {} sender(s), each costing {onehot} sender one-hot columns plus the \
                     fields it sends there (columns per sender {}; field widths {}). \
                     Remove at least {} columns there: send fewer fields to that agent (receivers/peer links), narrow fields \
                     (e.g. aggregate with reduce, or pick fewer obs dims), or have fewer agents send to it",
                    from.len(),
                    from.join(", "),
                    parts.join(", "),
                    added - available
                )
            }
        };
        v.err(ErrorKind::Budget, "fields", None, msg);
        return Err(v.errors);
    }
    let critical_dims: BTreeSet<usize> = p.critical_state_dims.iter().flat_map(|s| s.dims()).collect();
    Ok(ValidatedProtocol {
        protocol: p.clone(),
        env: env.clone(),
        field_widths: widths,
        sends,
        width,
        critical_dims: critical_dims.into_iter().collect(),
        warnings: identity_warnings(p, env),
    })
}

/// The protocol's recorded environment against the one it is used on.
fn identity_warnings(p: &Protocol, env: &ProtocolEnv) -> Vec<String> {
    match (&p.env, &p.schema_fingerprint) {
        (Some(written), _) if !env.env_name.is_empty() && *written != env.env_name => vec![format!(
            "this protocol was designed for {written}, not {}: its dims fit, but what they mean may not",
            env.env_name
        )],
        (_, Some(fp)) if !env.schema_fingerprint.is_empty() && *fp != env.schema_fingerprint => vec![format!(
            "the schema of {} changed since this protocol was saved (fingerprint {fp}, now {}): check that the dims it reads still mean the same",
            if env.env_name.is_empty() { "the environment" } else { &env.env_name },
            env.schema_fingerprint
        )],
        _ => Vec::new(),
    }
}

fn valid_ident(s: &str) -> bool {
    !s.is_empty() && s.len() <= 64 && s.chars().all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
}

struct Validator<'a> {
    env: &'a ProtocolEnv,
    errors: Vec<ValidationError>,
    nodes: usize,
    nodes_reported: bool,
}

impl Validator<'_> {
    fn err(&mut self, kind: ErrorKind, path: &str, field: Option<&str>, message: String) {
        self.errors.push(ValidationError { kind, path: path.to_string(), field: field.map(str::to_string), message });
    }

    fn agent_range(&self) -> String {
        match self.env.n_agents {
            0 => "n_agents is 0, so there are no agents".to_string(),
            n => format!("n_agents is {n}, so agents are 0..={}", n - 1),
        }
    }

    fn critical_dims(&mut self, p: &Protocol) {
        let sd = self.env.state_dim;
        if p.critical_state_dims.is_empty() && sd > 0 {
            self.err(
                ErrorKind::Empty,
                "critical_state_dims",
                None,
                format!("list the task-critical state dims the protocol targets (indices in 0..{sd})"),
            );
        }
        let mut seen = BTreeSet::new();
        for (k, spec) in p.critical_state_dims.iter().enumerate() {
            let path = format!("critical_state_dims[{k}]");
            match *spec {
                DimSpec::Dim(d) => {
                    if d >= sd {
                        self.err(
                            ErrorKind::StateDim,
                            &path,
                            None,
                            format!("state dim {d} is out of range: state_dim is {sd}, valid dims are 0..={}", sd.saturating_sub(1)),
                        );
                    } else if !seen.insert(d) {
                        self.err(ErrorKind::StateDim, &path, None, format!("state dim {d} is listed twice"));
                    }
                }
                DimSpec::Range(Slice { start, end }) => {
                    if start >= end {
                        self.err(
                            ErrorKind::StateDim,
                            &path,
                            None,
                            format!("empty range: start {start} must be below end {end} (end is exclusive)"),
                        );
                    } else if end > sd {
                        self.err(
                            ErrorKind::StateDim,
                            &path,
                            None,
                            format!("range {start}..{end} is out of range: end is exclusive and at most state_dim = {sd}"),
                        );
                    } else {
                        let dup = (start..end).filter(|d| !seen.insert(*d)).count();
                        if dup > 0 {
                            self.err(ErrorKind::StateDim, &path, None, format!("range {start}..{end} repeats {dup} dim(s) listed earlier"));
                        }
                    }
                }
            }
        }
    }

    /// Checked sender set (in range, unique, non-empty); falls back to the valid part.
    fn senders(&mut self, f: &Field, fp: &str) -> Vec<usize> {
        let n = self.env.n_agents;
        let fname = Some(f.name.as_str());
        match &f.senders {
            Senders::All => (0..n).collect(),
            Senders::List(list) => {
                if list.is_empty() {
                    self.err(
                        ErrorKind::Empty,
                        &format!("{fp}.senders"),
                        fname,
                        "the sender list is empty: use \"all\" or list agent indices".into(),
                    );
                }
                let mut out = BTreeSet::new();
                for (k, &j) in list.iter().enumerate() {
                    let path = format!("{fp}.senders[{k}]");
                    if j >= n {
                        let r = self.agent_range();
                        self.err(ErrorKind::Agent, &path, fname, format!("sender agent {j} is out of range: {r}"));
                    } else if !out.insert(j) {
                        self.err(ErrorKind::Agent, &path, fname, format!("sender agent {j} is listed twice"));
                    }
                }
                out.into_iter().collect()
            }
        }
    }

    /// `sends[j][i]` for this field.
    fn receivers(&mut self, f: &Field, fp: &str, senders: &[usize]) -> Vec<Vec<bool>> {
        let n = self.env.n_agents;
        let fname = Some(f.name.as_str());
        let mut m = vec![vec![false; n]; n];
        match &f.receivers {
            Receivers::Broadcast => {
                for &j in senders {
                    for i in (0..n).filter(|&i| i != j) {
                        m[j][i] = true;
                    }
                }
            }
            Receivers::Agents(list) => {
                let path = format!("{fp}.receivers.agents");
                if list.is_empty() {
                    self.err(ErrorKind::Empty, &path, fname, "the receiver list is empty: list agent indices or use \"broadcast\"".into());
                }
                let mut set = BTreeSet::new();
                for (k, &i) in list.iter().enumerate() {
                    if i >= n {
                        let r = self.agent_range();
                        self.err(ErrorKind::Agent, &format!("{path}[{k}]"), fname, format!("receiver agent {i} is out of range: {r}"));
                    } else if !set.insert(i) {
                        self.err(ErrorKind::Agent, &format!("{path}[{k}]"), fname, format!("receiver agent {i} is listed twice"));
                    }
                }
                if !set.is_empty() {
                    for &j in senders {
                        let to: Vec<usize> = set.iter().copied().filter(|&i| i != j).collect();
                        if to.is_empty() {
                            self.err(ErrorKind::Agent, &path, fname, format!("sender agent {j} would send only to itself: messages go to other agents; add other receivers or remove agent {j} from the senders"));
                        }
                        for i in to {
                            m[j][i] = true;
                        }
                    }
                }
            }
            Receivers::Peer(links) => {
                let path = format!("{fp}.receivers.peer");
                if links.is_empty() {
                    self.err(
                        ErrorKind::Empty,
                        &path,
                        fname,
                        "the peer list is empty: give each sender its receivers, e.g. [{\"from\": 0, \"to\": [1]}]".into(),
                    );
                }
                let mut froms = BTreeSet::new();
                for (k, l) in links.iter().enumerate() {
                    let lp = format!("{path}[{k}]");
                    if l.from >= n {
                        let r = self.agent_range();
                        self.err(ErrorKind::Agent, &format!("{lp}.from"), fname, format!("agent {} is out of range: {r}", l.from));
                        continue;
                    }
                    if !froms.insert(l.from) {
                        self.err(
                            ErrorKind::Agent,
                            &format!("{lp}.from"),
                            fname,
                            format!("agent {} has more than one peer entry: merge them into one", l.from),
                        );
                        continue;
                    }
                    if !senders.contains(&l.from) {
                        self.err(
                            ErrorKind::Agent,
                            &format!("{lp}.from"),
                            fname,
                            format!("agent {} has a peer entry but is not a sender of this field (senders: {:?})", l.from, senders),
                        );
                        continue;
                    }
                    if l.to.is_empty() {
                        self.err(
                            ErrorKind::Empty,
                            &format!("{lp}.to"),
                            fname,
                            format!("agent {} sends to nobody: list at least one other agent", l.from),
                        );
                    }
                    let mut tos = BTreeSet::new();
                    for (q, &i) in l.to.iter().enumerate() {
                        let tp = format!("{lp}.to[{q}]");
                        if i >= n {
                            let r = self.agent_range();
                            self.err(ErrorKind::Agent, &tp, fname, format!("receiver agent {i} is out of range: {r}"));
                        } else if i == l.from {
                            self.err(ErrorKind::Agent, &tp, fname, format!("agent {i} cannot send to itself: messages go to other agents"));
                        } else if !tos.insert(i) {
                            self.err(ErrorKind::Agent, &tp, fname, format!("receiver agent {i} is listed twice"));
                        } else {
                            m[l.from][i] = true;
                        }
                    }
                }
                for &j in senders {
                    if !froms.contains(&j) && !links.is_empty() {
                        self.err(ErrorKind::Agent, &path, fname, format!("agent {j} is a sender of this field but has no peer entry: add {{\"from\": {j}, \"to\": [...]}} or restrict \"senders\""));
                    }
                }
            }
        }
        m
    }

    /// Width of an expression, or None if it (or a part) is invalid (errors recorded).
    fn expr(&mut self, e: &Expr, path: &str, field: Option<&str>, depth: usize, in_window: bool) -> Option<usize> {
        if depth > MAX_DEPTH {
            self.err(ErrorKind::Size, path, field, format!("expression nested deeper than {MAX_DEPTH} levels: simplify it"));
            return None;
        }
        self.nodes += 1;
        if self.nodes > MAX_NODES {
            if !self.nodes_reported {
                self.nodes_reported = true;
                self.err(ErrorKind::Size, path, field, format!("the protocol has more than {MAX_NODES} expression nodes: simplify it"));
            }
            return None;
        }
        let env = self.env;
        let od = env.obs_dim;
        match e {
            Expr::Obs(dims) => {
                if dims.is_empty() {
                    self.err(
                        ErrorKind::Empty,
                        &format!("{path}.obs"),
                        field,
                        "the dim list is empty: list at least one observation dim".into(),
                    );
                    return None;
                }
                let mut ok = true;
                for (k, &d) in dims.iter().enumerate() {
                    if d >= od {
                        ok = false;
                        self.err(
                            ErrorKind::ObsDim,
                            &format!("{path}.obs[{k}]"),
                            field,
                            format!("observation dim {d} is out of range: obs_dim is {od}, valid dims are 0..={}", od.saturating_sub(1)),
                        );
                    }
                }
                ok.then_some(dims.len())
            }
            Expr::ObsSlice(s) => {
                let sp = format!("{path}.obs_slice");
                if s.start >= s.end {
                    self.err(
                        ErrorKind::ObsDim,
                        &sp,
                        field,
                        format!("empty slice: start {} must be below end {} (end is exclusive)", s.start, s.end),
                    );
                    None
                } else if s.end > od {
                    self.err(
                        ErrorKind::ObsDim,
                        &sp,
                        field,
                        format!(
                            "slice {}..{} is out of range: end is exclusive and at most obs_dim = {od} (valid dims are 0..={})",
                            s.start,
                            s.end,
                            od.saturating_sub(1)
                        ),
                    );
                    None
                } else {
                    Some(s.end - s.start)
                }
            }
            Expr::LastAction(enc) => {
                if env.n_actions == 0 {
                    self.err(ErrorKind::Env, &format!("{path}.last_action"), field, "the environment has no discrete actions".into());
                    return None;
                }
                Some(match enc {
                    ActionEncoding::OneHot => env.n_actions,
                    ActionEncoding::Index => 1,
                })
            }
            Expr::SenderOneHot => Some(env.n_agents),
            Expr::Const(c) => {
                if !c.is_finite() || c.abs() > f32::MAX as f64 {
                    self.err(ErrorKind::Number, &format!("{path}.const"), field, format!("constant {c} is not a finite 32-bit float"));
                    None
                } else {
                    Some(1)
                }
            }
            Expr::Window(w) => {
                let wp = format!("{path}.window");
                let mut ok = true;
                if in_window {
                    ok = false;
                    self.err(
                        ErrorKind::Window,
                        &wp,
                        field,
                        "a window cannot contain another window: aggregate a per-step expression".into(),
                    );
                }
                if w.k == 0 || w.k > MAX_WINDOW {
                    ok = false;
                    self.err(
                        ErrorKind::Window,
                        &format!("{wp}.k"),
                        field,
                        format!("window length k = {} is out of range: k must be in 1..={MAX_WINDOW}", w.k),
                    );
                }
                let inner = self.expr(&w.of, &format!("{wp}.of"), field, depth + 1, true);
                if ok {
                    inner
                } else {
                    None
                }
            }
            any_binary!(a, b) => {
                let op = e.binary().expect("a binary operator").0.name();
                let wa = self.expr(a, &format!("{path}.{op}[0]"), field, depth + 1, in_window);
                let wb = self.expr(b, &format!("{path}.{op}[1]"), field, depth + 1, in_window);
                let (wa, wb) = (wa?, wb?);
                if wa == wb || wa == 1 || wb == 1 {
                    Some(wa.max(wb))
                } else {
                    self.err(ErrorKind::Width, &format!("{path}.{op}"), field, format!("width mismatch: {op}[0] has width {wa} and {op}[1] has width {wb}; elementwise operators need equal widths or one side of width 1"));
                    None
                }
            }
            Expr::Neg(a) => self.expr(a, &format!("{path}.neg"), field, depth + 1, in_window),
            Expr::Abs(a) => self.expr(a, &format!("{path}.abs"), field, depth + 1, in_window),
            Expr::Clip(c) => {
                let cp = format!("{path}.clip");
                let mut ok = true;
                for (name, x) in [("min", c.min), ("max", c.max)] {
                    if !x.is_finite() || x.abs() > f32::MAX as f64 {
                        ok = false;
                        self.err(
                            ErrorKind::Number,
                            &format!("{cp}.{name}"),
                            field,
                            format!("clip {name} {x} is not a finite 32-bit float"),
                        );
                    }
                }
                if ok && c.min > c.max {
                    ok = false;
                    self.err(ErrorKind::Number, &cp, field, format!("clip range is empty: min {} is above max {}", c.min, c.max));
                }
                let w = self.expr(&c.of, &format!("{cp}.of"), field, depth + 1, in_window);
                if ok {
                    w
                } else {
                    None
                }
            }
            Expr::Reduce(r) => self.expr(&r.of, &format!("{path}.reduce.of"), field, depth + 1, in_window).map(|_| 1),
            Expr::Concat(parts) => {
                if parts.is_empty() {
                    self.err(ErrorKind::Empty, &format!("{path}.concat"), field, "concat of nothing: list at least one expression".into());
                    return None;
                }
                let mut total = Some(0usize);
                for (k, x) in parts.iter().enumerate() {
                    let w = self.expr(x, &format!("{path}.concat[{k}]"), field, depth + 1, in_window);
                    total = match (total, w) {
                        (Some(t), Some(w)) => Some(t.saturating_add(w)),
                        _ => None,
                    };
                }
                total
            }
        }
    }
}

/// Check that validated phases fit together (same environment, one layout, the combined width
/// within the budget); returns the combined width ([`combined_width`]), the plan's `msg_dim`.
pub fn check_phases(phases: &[ValidatedProtocol], env: &ProtocolEnv) -> Result<usize, Vec<ValidationError>> {
    let mut errors = Vec::new();
    for (k, p) in phases.iter().enumerate() {
        let (a, b) = (&p.env, env);
        if (a.n_agents, a.obs_dim, a.n_actions, a.state_dim) != (b.n_agents, b.obs_dim, b.n_actions, b.state_dim) {
            errors.push(ValidationError::new(
                ErrorKind::Phases,
                format!("phases[{k}]"),
                format!(
                    "phase was validated for n_agents={} obs_dim={} n_actions={} state_dim={}, not for this environment (n_agents={} obs_dim={} n_actions={} state_dim={})",
                    a.n_agents, a.obs_dim, a.n_actions, a.state_dim, b.n_agents, b.obs_dim, b.n_actions, b.state_dim
                ),
            ));
        }
        if p.protocol.layout != phases[0].protocol.layout {
            errors.push(ValidationError::new(
                ErrorKind::Phases,
                format!("phases[{k}].layout"),
                format!(
                    "phase {k} uses the {} layout and phase 0 the {} layout: all phases of one protocol use the same layout",
                    layout_name(p.protocol.layout),
                    layout_name(phases[0].protocol.layout)
                ),
            ));
        }
    }
    if !errors.is_empty() {
        return Err(errors);
    }
    let total = combined_width(phases);
    if total > env.message_budget {
        let parts: Vec<String> =
            phases.iter().enumerate().map(|(k, p)| format!("phase {}: {}", p.protocol.phase.map_or(k, |x| x as usize), p.width)).collect();
        errors.push(ValidationError::new(
            ErrorKind::Budget,
            "",
            format!(
                "the phases together need {total} message columns per receiving agent (on their own: {}) but the budget is {}",
                parts.join(", "),
                env.message_budget
            ),
        ));
    }
    if errors.is_empty() {
        Ok(total)
    } else {
        Err(errors)
    }
}

fn layout_name(l: MessageLayout) -> &'static str {
    match l {
        MessageLayout::Compact => "compact",
        MessageLayout::SenderBlocks => "sender_blocks",
    }
}

/// One line for `lmac protocol check`: what passed and how much of the budget it uses.
pub fn check_summary(v: &ValidatedProtocol) -> String {
    let p = &v.protocol;
    let widths: Vec<String> = p.fields.iter().zip(&v.field_widths).map(|(f, w)| format!("{}={w}", f.name)).collect();
    format!(
        "OK: {} ({} field(s): {}): {} message columns per receiving agent of a budget of {} ({} agents, {} critical state dims)",
        p.name.as_deref().unwrap_or("protocol"),
        p.fields.len(),
        widths.join(", "),
        v.width,
        v.env.message_budget,
        v.env.n_agents,
        v.critical_dims.len()
    )
}
