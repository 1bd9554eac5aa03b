//! The interpretable text a person reads: who sends what to whom, and why.

use super::ast::*;
use super::validate::{validate, ValidatedProtocol};
use super::ProtocolEnv;
use std::fmt::Write;

/// Explain a protocol. With an environment, widths, the per-receiver layout and any validation
/// errors are included too.
pub fn explain(p: &Protocol, env: Option<&ProtocolEnv>) -> String {
    let mut s = String::new();
    let title = p.name.as_deref().unwrap_or("(unnamed)");
    match p.phase {
        Some(k) => writeln!(s, "Protocol {title} (phase {k}: {})", phase_name(k)).unwrap(),
        None => writeln!(s, "Protocol {title}").unwrap(),
    }
    let validated = env.map(|e| validate(p, e));
    if let Some(e) = env {
        writeln!(
            s,
            "Environment: {} agents, obs_dim {}, {} actions, state_dim {}, message budget {} columns",
            e.n_agents, e.obs_dim, e.n_actions, e.state_dim, e.message_budget
        )
        .unwrap();
    }

    s.push_str("\nDesign:\n");
    for line in p.message_design_instruction.trim().lines() {
        s.push_str(&wrap(line.trim_end(), "  ", "  "));
    }

    s.push_str("\nTask-critical state dims: ");
    if p.critical_state_dims.is_empty() {
        s.push_str("(none listed)");
    } else {
        let dims: Vec<String> = p
            .critical_state_dims
            .iter()
            .map(|spec| match *spec {
                DimSpec::Dim(d) => match env.and_then(|e| e.state_name(d)) {
                    Some(n) => format!("{d} ({n})"),
                    None => d.to_string(),
                },
                DimSpec::Range(s) => format!("{}..{}", s.start, s.end),
            })
            .collect();
        s.push_str(&dims.join(", "));
    }
    s.push('\n');
    if let Some(r) = &p.critical_state_reasoning {
        s.push_str(&wrap(r.trim(), "Why: ", "     "));
    }

    let ok = match &validated {
        Some(Ok(v)) => Some(v),
        _ => None,
    };
    match ok {
        Some(v) => writeln!(s, "\nMessage fields ({}; each receiving agent gets {} columns):", p.fields.len(), v.width).unwrap(),
        None => writeln!(s, "\nMessage fields ({}):", p.fields.len()).unwrap(),
    }
    for (k, f) in p.fields.iter().enumerate() {
        let w = match ok {
            Some(v) => format!("{} column{}", v.field_widths[k], if v.field_widths[k] == 1 { "" } else { "s" }),
            None => match width(&f.value, env) {
                Some(w) => format!("{w} column{}", if w == 1 { "" } else { "s" }),
                None => "width unknown".into(),
            },
        };
        let head = format!("{}. {} ({w}): ", k + 1, f.name);
        s.push_str(&wrap(&format!("{head}{}", f.description.trim()), "", "   "));
        writeln!(s, "   who:   {}", who(f)).unwrap();
        // Where agents observe different things, each kind of sender's values read in its own
        // meanings: one line per distinct reading.
        let senders: Vec<usize> = match (env, &f.senders) {
            (Some(e), _) if e.agent_obs_names.is_empty() => Vec::new(),
            (Some(e), Senders::All) => (0..e.n_agents).collect(),
            (Some(_), Senders::List(l)) => l.clone(),
            (None, _) => Vec::new(),
        };
        let mut readings: Vec<(String, Vec<usize>)> = Vec::new();
        for &j in &senders {
            let text = explain_expr_of(&f.value, env, Some(j));
            match readings.iter_mut().find(|r| r.0 == text) {
                Some(r) => r.1.push(j),
                None => readings.push((text, vec![j])),
            }
        }
        if readings.len() > 1 {
            for (text, from) in &readings {
                writeln!(s, "   value from {}: {text}", agents_list(from)).unwrap();
            }
        } else {
            let text = readings.pop().map_or_else(|| explain_expr(&f.value, env), |r| r.0);
            writeln!(s, "   value: {text}").unwrap();
        }
    }

    let mut parts = Vec::new();
    if p.sender_one_hot {
        parts.push(match env {
            Some(e) => format!("sender one-hot ({})", e.n_agents),
            None => "sender one-hot (n_agents)".into(),
        });
    }
    let layout = match p.layout {
        MessageLayout::Compact => {
            parts.push("the fields j sends it".into());
            let mut l = format!(
                "Layout (compact): each receiving agent gets, for every other agent j in increasing order that sends it at least one field, [{}] in field order; agents and fields that do not reach it take no columns, and every receiver's message is padded with zeros to the widest receiver's width",
                parts.join(" | ")
            );
            if let Some(v) = ok {
                let w: Vec<usize> = (0..v.env.n_agents).map(|i| v.receiver_width(i)).collect();
                let (lo, hi) = (w.iter().min().copied().unwrap_or(0), w.iter().max().copied().unwrap_or(0));
                let full = super::width::message_width(p, &v.env, &v.field_widths);
                l.push_str(&format!(" ({lo}..{hi} columns used per receiver; the sender-blocks layout would need {full})"));
            }
            l.push('.');
            l
        }
        MessageLayout::SenderBlocks => {
            for (k, f) in p.fields.iter().enumerate() {
                parts.push(match ok {
                    Some(v) => format!("{} ({})", f.name, v.field_widths[k]),
                    None => f.name.clone(),
                });
            }
            format!(
                "Layout (sender_blocks): each receiving agent gets, for every other agent j in increasing order, a block [{}]; columns of fields j does not send to that agent stay zero.",
                parts.join(" | ")
            )
        }
    };
    s.push('\n');
    s.push_str(&wrap(&layout, "", "  "));
    if let Some(v) = ok {
        s.push_str(&receivers_table(v));
    }

    if let Some(k) = max_window(p) {
        let pad = match p.history_padding {
            HistoryPadding::MinusOne => {
                "steps before the episode start read as observation -1 and last action -1 (as the paper's reference code pads)"
            }
            HistoryPadding::Zero => "steps before the episode start read as observation 0 and no last action",
            HistoryPadding::Repeat => "steps before the episode start repeat the episode's first step",
        };
        s.push_str(&wrap(&format!("History: windows reach back up to {k} steps; {pad}."), "", "  "));
    }

    if let Some(Err(errors)) = &validated {
        writeln!(s, "\nNOT VALID for this environment ({} error(s)):", errors.len()).unwrap();
        for e in errors {
            s.push_str(&wrap(&e.to_string(), "- ", "  "));
        }
    }
    s
}

const WRAP: usize = 100;

/// Word-wrap one paragraph at about 100 columns; `first` prefixes the first line, `rest` the others.
fn wrap(text: &str, first: &str, rest: &str) -> String {
    let mut out = String::new();
    let mut line = String::from(first);
    let mut empty = true;
    for word in text.split_whitespace() {
        if !empty && line.chars().count() + 1 + word.chars().count() > WRAP {
            out.push_str(&line);
            out.push('\n');
            line = String::from(rest);
            empty = true;
        }
        if !empty {
            line.push(' ');
        }
        line.push_str(word);
        empty = false;
    }
    out.push_str(&line);
    out.push('\n');
    out
}

/// Explain the final protocol of several phases: where each phase's columns sit in the
/// concatenated message, then each phase.
pub fn explain_phases(phases: &[Protocol], env: Option<&ProtocolEnv>) -> String {
    let mut s = String::new();
    let compact = phases.iter().all(|p| p.layout == MessageLayout::Compact);
    if !compact {
        let widths: Vec<Option<usize>> = phases.iter().map(|p| env.and_then(|e| validate(p, e).ok()).map(|v| v.width)).collect();
        writeln!(s, "Final protocol: {} phase(s), each receiving agent's message is their concatenation", phases.len()).unwrap();
        let mut off = Some(0usize);
        for (k, (p, w)) in phases.iter().zip(&widths).enumerate() {
            let name = p.name.clone().unwrap_or_else(|| format!("phase{k}"));
            match (off, w) {
                (Some(o), Some(w)) => {
                    writeln!(s, "  columns {o}..{}: {name} ({w} columns)", o + w).unwrap();
                    off = Some(o + w);
                }
                _ => {
                    writeln!(s, "  then: {name}").unwrap();
                    off = None;
                }
            }
        }
        if let Some(total) = off {
            writeln!(s, "  total: {total} columns").unwrap();
        }
    } else {
        writeln!(
            s,
            "Final protocol: {} phase(s) in the compact layout: each receiving agent gets, per sender that reaches it in any phase, that sender's one-hot once and then its fields of every phase",
            phases.len()
        )
        .unwrap();
        // Each phase validated after the earlier ones (the budget is shared).
        let mut done: Vec<ValidatedProtocol> = Vec::new();
        if let Some(e) = env {
            for p in phases {
                match super::validate::validate_phase(p, e, &done) {
                    Ok(v) => done.push(v),
                    Err(_) => break,
                }
            }
        }
        if !done.is_empty() && done.len() == phases.len() {
            let per = super::width::combined_receiver_widths(&done);
            let total = per.iter().copied().max().unwrap_or(0);
            let own: Vec<String> = done.iter().map(|v| v.width.to_string()).collect();
            writeln!(
                s,
                "  total: {total} columns per receiving agent (each phase on its own: {}; per receiver before padding: {})",
                own.join(" + "),
                per.iter().map(|w| w.to_string()).collect::<Vec<_>>().join(", ")
            )
            .unwrap();
        }
    }
    for p in phases {
        s.push('\n');
        s.push_str(&explain(p, env));
    }
    s
}

fn phase_name(k: u32) -> &'static str {
    match k {
        0 => "initialization",
        1 => "recognition enhancement",
        2 => "sharing enhancement",
        _ => "refinement",
    }
}

fn agents_list(v: &[usize]) -> String {
    let v: Vec<String> = v.iter().map(|a| a.to_string()).collect();
    match v.len() {
        1 => format!("agent {}", v[0]),
        _ => format!("agents {}", v.join(", ")),
    }
}

fn who(f: &Field) -> String {
    let senders = match &f.senders {
        Senders::All => "every agent".to_string(),
        Senders::List(l) => agents_list(l),
    };
    match &f.receivers {
        Receivers::Broadcast => format!("{senders} -> every other agent (broadcast)"),
        Receivers::Agents(l) => format!("{senders} -> {} (never to itself)", agents_list(l)),
        Receivers::Peer(links) => {
            let l: Vec<String> = links.iter().map(|p| format!("agent {} -> {}", p.from, agents_list(&p.to))).collect();
            format!("peer-to-peer: {}", l.join("; "))
        }
    }
}

fn receivers_table(v: &ValidatedProtocol) -> String {
    let n = v.env.n_agents;
    let mut s = String::new();
    for i in 0..n {
        let mut from = Vec::new();
        for j in (0..n).filter(|&j| j != i) {
            let fields: Vec<&str> =
                v.protocol.fields.iter().enumerate().filter(|(f, _)| v.sends[*f][j][i]).map(|(_, f)| f.name.as_str()).collect();
            if fields.is_empty() {
                from.push(format!("nothing from agent {j}"));
            } else {
                from.push(format!("from agent {j}: {}", fields.join(", ")));
            }
        }
        let cols = match v.protocol.layout {
            MessageLayout::Compact => format!(" ({} of {} columns)", v.receiver_width(i), v.width),
            MessageLayout::SenderBlocks => String::new(),
        };
        s.push_str(&wrap(&format!("agent {i}{cols} receives {}", from.join("; ")), "  ", "    "));
    }
    s
}

fn max_window(p: &Protocol) -> Option<usize> {
    fn walk(e: &Expr, m: &mut Option<usize>) {
        match e {
            Expr::Window(w) => {
                *m = Some(m.unwrap_or(0).max(w.k));
                walk(&w.of, m)
            }
            any_binary!(a, b) => {
                walk(a, m);
                walk(b, m)
            }
            Expr::Neg(a) | Expr::Abs(a) => walk(a, m),
            Expr::Clip(c) => walk(&c.of, m),
            Expr::Reduce(r) => walk(&r.of, m),
            Expr::Concat(v) => v.iter().for_each(|x| walk(x, m)),
            _ => {}
        }
    }
    let mut m = None;
    p.fields.iter().for_each(|f| walk(&f.value, &mut m));
    m
}

/// Width of an expression when it can be known (without validation errors).
fn width(e: &Expr, env: Option<&ProtocolEnv>) -> Option<usize> {
    Some(match e {
        Expr::Obs(d) => d.len(),
        Expr::ObsSlice(s) => s.end.checked_sub(s.start)?,
        Expr::LastAction(ActionEncoding::Index) | Expr::Const(_) | Expr::Reduce(_) => 1,
        Expr::LastAction(ActionEncoding::OneHot) => env?.n_actions,
        Expr::SenderOneHot => env?.n_agents,
        Expr::Window(w) => width(&w.of, env)?,
        any_binary!(a, b) => width(a, env)?.max(width(b, env)?),
        Expr::Neg(a) | Expr::Abs(a) => width(a, env)?,
        Expr::Clip(c) => width(&c.of, env)?,
        Expr::Concat(v) => v.iter().map(|x| width(x, env)).sum::<Option<usize>>()?,
    })
}

fn dims_text(dims: &[usize], env: Option<&ProtocolEnv>, sender: Option<usize>) -> String {
    let names: Vec<&str> = dims.iter().filter_map(|&d| env.and_then(|e| e.obs_name_of(sender, d))).collect();
    if names.len() == dims.len() && !names.is_empty() && names.len() <= 8 {
        format!(" ({})", names.join(", "))
    } else {
        String::new()
    }
}

fn num(x: f64) -> String {
    if x.fract() == 0.0 && x.abs() < 1e9 {
        format!("{}", x as i64)
    } else {
        format!("{x}")
    }
}

/// One expression as a short formula in words.
pub fn explain_expr(e: &Expr, env: Option<&ProtocolEnv>) -> String {
    explain_expr_of(e, env, None)
}

/// [`explain_expr`] as sent by agent `sender`: observation values named in its own meanings
/// where agents observe different things.
pub fn explain_expr_of(e: &Expr, env: Option<&ProtocolEnv>, sender: Option<usize>) -> String {
    let x = |a: &Expr| explain_expr_of(a, env, sender);
    match e {
        Expr::Obs(dims) => {
            let d: Vec<String> = dims.iter().map(|d| d.to_string()).collect();
            format!("obs[{}]{}", d.join(", "), dims_text(dims, env, sender))
        }
        Expr::ObsSlice(s) => {
            let dims: Vec<usize> = (s.start..s.end.min(s.start.saturating_add(9))).collect();
            let names = if s.end.saturating_sub(s.start) <= 8 { dims_text(&dims, env, sender) } else { String::new() };
            format!("obs[{}..{}]{names}", s.start, s.end)
        }
        Expr::LastAction(ActionEncoding::OneHot) => "one-hot of the sender's previous action".into(),
        Expr::LastAction(ActionEncoding::Index) => "index of the sender's previous action (-1 if none)".into(),
        Expr::SenderOneHot => "the sender's one-hot id".into(),
        Expr::Const(c) => num(*c),
        Expr::Window(w) => {
            let k = w.k;
            match w.op {
                WindowOp::Mean => format!("mean over the last {k} steps of {}", x(&w.of)),
                WindowOp::Sum => format!("sum over the last {k} steps of {}", x(&w.of)),
                WindowOp::Min => format!("minimum over the last {k} steps of {}", x(&w.of)),
                WindowOp::Max => format!("maximum over the last {k} steps of {}", x(&w.of)),
                WindowOp::Last => format!("{} as it was {} step{} ago", x(&w.of), k.saturating_sub(1), if k == 2 { "" } else { "s" }),
                WindowOp::LastNonzero => format!("most recent non-zero value within the last {k} steps of {}", x(&w.of)),
                WindowOp::Delta => format!(
                    "change of {} over the last {k} steps (now minus {} step{} ago)",
                    x(&w.of),
                    k.saturating_sub(1),
                    if k == 2 { "" } else { "s" }
                ),
            }
        }
        any_binary!(a, b) => {
            let (pre, mid, post) = infix(e.binary().expect("a binary operator").0);
            format!("{pre}{}{mid}{}{post}", x(a), x(b))
        }
        Expr::Neg(a) => format!("-{}", x(a)),
        Expr::Abs(a) => format!("|{}|", x(a)),
        Expr::Clip(c) => format!("clip({}, {}, {})", x(&c.of), num(c.min), num(c.max)),
        Expr::Reduce(r) => {
            let op = match r.op {
                ReduceOp::Sum => "sum",
                ReduceOp::Mean => "mean",
                ReduceOp::Min => "min",
                ReduceOp::Max => "max",
            };
            format!("{op} of the columns of {}", x(&r.of))
        }
        Expr::Concat(v) => {
            let parts: Vec<String> = v.iter().map(x).collect();
            format!("[{}]", parts.join(" ++ "))
        }
    }
}

/// How an elementwise operator reads between its operands: (before, between, after).
fn infix(op: BinOp) -> (&'static str, &'static str, &'static str) {
    match op {
        BinOp::Add => ("(", " + ", ")"),
        BinOp::Sub => ("(", " - ", ")"),
        BinOp::Mul => ("(", " * ", ")"),
        BinOp::Div => ("(", " / ", ")"),
        BinOp::Min => ("min(", ", ", ")"),
        BinOp::Max => ("max(", ", ", ")"),
        BinOp::Gt => ("[", " > ", "]"),
        BinOp::Lt => ("[", " < ", "]"),
        BinOp::Eq => ("[", " = ", "]"),
    }
}
