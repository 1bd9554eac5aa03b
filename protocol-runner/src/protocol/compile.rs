//! Compilation of validated protocol phases into a gather/compute plan, and its execution.
//!
//! The plan is a straight-line program over a per-row register file (one row per env and
//! agent), executed instruction by instruction over the whole batch. Every field value is a
//! register range; window aggregates read per-channel history ring buffers that the plan owns
//! (one per distinct per-step expression, as deep as the longest window over it). A scatter
//! table per receiving agent then copies sender registers into the receiver's message columns.
//!
//! Layout: in the default compact layout receiver i gets, for each sender j that sends it at
//! least one field in any phase, [one-hot(j) | the fields of phase 0 j sends i | those of phase 1
//! | ...], then zeros up to the widest receiver's width, so every receiver has one width (the
//! plan's `msg_dim`, [`combined_width`](super::validate::combined_width)). A sender's one-hot is
//! paid once, not once per phase. It is kept (rather than replaced by a fixed position per
//! sender) because agents share one network and, in the compact layout, the sender behind a
//! column differs between receivers: the one-hot says whose values follow. The `sender_blocks`
//! layout (the earlier one, kept to reproduce old runs) gives every receiver, per phase, a full
//! block [one-hot | every field] per other agent, phases concatenated.
//! The design loop's D^(k) compiles phases 0..k on their own, so it never needs phase k's columns
//! at a fixed place in the final plan.

use super::ast::*;
use super::validate::{check_phases, validate, ValidatedProtocol, ValidationError, MAX_WINDOW};
use super::ProtocolEnv;
use crate::plan::{MessagePlan, StepView};

#[derive(Debug, Clone, Copy, PartialEq)]
enum Un {
    Neg,
    Abs,
}

#[derive(Debug, Clone)]
enum Inst {
    /// regs[dst + c] = obs[dims[c]]
    Gather {
        dst: usize,
        dims: Vec<usize>,
    },
    /// regs[dst .. dst+len] = obs[start .. start+len]
    Slice {
        dst: usize,
        start: usize,
        len: usize,
    },
    ActOneHot {
        dst: usize,
    },
    ActIndex {
        dst: usize,
    },
    SenderOneHot {
        dst: usize,
    },
    Const {
        dst: usize,
        v: f32,
    },
    Bin {
        op: BinOp,
        dst: usize,
        a: usize,
        wa: usize,
        b: usize,
        wb: usize,
        w: usize,
    },
    Un {
        op: Un,
        dst: usize,
        a: usize,
        w: usize,
    },
    Clip {
        dst: usize,
        a: usize,
        w: usize,
        lo: f32,
        hi: f32,
    },
    Reduce {
        op: ReduceOp,
        dst: usize,
        a: usize,
        w: usize,
    },
    Copy {
        dst: usize,
        src: usize,
        w: usize,
    },
    /// Record channel `ch`'s current value (its `src` registers) in its history ring.
    Push {
        ch: usize,
    },
    /// regs[dst..dst+w] = aggregate over the last k values of channel `ch`.
    Agg {
        op: WindowOp,
        ch: usize,
        k: usize,
        dst: usize,
    },
}

#[derive(Debug, Clone)]
struct Channel {
    expr: Expr,
    /// How the steps before the episode read (from the phase that declared the window).
    padding: HistoryPadding,
    src: usize,
    w: usize,
    /// Ring depth (the longest window over this channel).
    depth: usize,
    /// Per agent, the value of the channel's expression on a padding step (unused for `repeat`).
    pad: Vec<f32>,
    /// rows x (depth + 1) x w; slot `depth` of a row holds its padding value.
    ring: Vec<f32>,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Seg {
    /// msg[dst .. dst+len] = regs[row(sender)][src .. src+len]
    Copy {
        dst: usize,
        sender: usize,
        src: usize,
        len: usize,
    },
    Zero {
        dst: usize,
        len: usize,
    },
}

/// Where one column of a receiver's message comes from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Column {
    /// The phase (0-based) and its name (`phase<k>` when it has none).
    pub phase: usize,
    pub phase_name: String,
    /// The agent whose value the column holds (for padding: the receiver itself; nobody sends it).
    pub sender: usize,
    /// The field's index in its phase; None for the sender one-hot and for padding.
    pub field: Option<usize>,
    /// Field name (`sender_one_hot` for the one-hot, `padding` for padding).
    pub name: String,
    /// Position inside the field (or the one-hot, or the phase's padding run).
    pub q: usize,
    /// The sender sends this to the receiver; false: the column is zero by layout (an unsent
    /// block part in the sender-blocks layout, or padding).
    pub linked: bool,
    /// Zero padding after this receiver's columns, up to the phase's width (compact layout).
    pub padding: bool,
}

impl Column {
    /// `phase/fromJ/field[q]`, or `phase/padding[q]`.
    pub fn label(&self) -> String {
        if self.padding {
            format!("{}/padding[{}]", self.phase_name, self.q)
        } else {
            format!("{}/from{}/{}[{}]", self.phase_name, self.sender, self.name, self.q)
        }
    }
}

/// A compiled protocol (one or more phases), ready to run.
#[derive(Debug, Clone)]
pub struct ProtocolPlan {
    name: String,
    n_agents: usize,
    obs_dim: usize,
    n_actions: usize,
    msg_dim: usize,
    prog: Vec<Inst>,
    n_regs: usize,
    channels: Vec<Channel>,
    /// Scatter table per receiving agent.
    segs: Vec<Vec<Seg>>,
    /// Column labels per receiving agent.
    labels: Vec<Vec<String>>,
    /// Column sources per receiving agent.
    columns: Vec<Vec<Column>>,
    // --- run state ---
    regs: Vec<f32>,
    /// Per env: steps of the current episode seen (saturating at the deepest ring).
    count: Vec<usize>,
    max_depth: usize,
    step: u64,
    num_envs: usize,
}

/// Compile validated phases (phase 0 first) into one plan: each receiver's message is the
/// concatenation of the phases' messages.
pub fn compile(phases: &[ValidatedProtocol], env: &ProtocolEnv) -> Result<Box<dyn MessagePlan>, Vec<ValidationError>> {
    Ok(Box::new(compile_plan(phases, env)?))
}

/// As [`compile`], returning the concrete plan (column labels, direct use in tests/benches).
pub fn compile_plan(phases: &[ValidatedProtocol], env: &ProtocolEnv) -> Result<ProtocolPlan, Vec<ValidationError>> {
    if phases.is_empty() {
        return Err(vec![ValidationError::new(super::ErrorKind::Phases, "", "no protocol phases to compile")]);
    }
    // Re-derive every phase's facts against this environment (the inputs' fields are public, so
    // the plan never trusts widths it did not compute itself).
    let mut fresh = Vec::with_capacity(phases.len());
    let mut errors = Vec::new();
    for (k, p) in phases.iter().enumerate() {
        match validate(&p.protocol, env) {
            Ok(v) => fresh.push(v),
            Err(es) => errors.extend(es.into_iter().map(|mut e| {
                e.path = if e.path.is_empty() { format!("phases[{k}]") } else { format!("phases[{k}].{}", e.path) };
                e
            })),
        }
    }
    if !errors.is_empty() {
        return Err(errors);
    }
    let phases = &fresh[..];
    let msg_dim = check_phases(phases, env)?;
    let n = env.n_agents;
    let mut c = Compiler {
        prog: Vec::new(),
        n_regs: 0,
        channels: Vec::new(),
        n_actions: env.n_actions,
        n_agents: n,
        padding: HistoryPadding::default(),
        into: None,
    };
    let mut segs = vec![Vec::new(); n];
    let mut columns: Vec<Vec<Column>> = vec![Vec::new(); n];
    // check_phases refused mixed layouts.
    let blocks = phases[0].protocol.layout == MessageLayout::SenderBlocks;
    let pnames: Vec<String> =
        phases.iter().enumerate().map(|(k, p)| p.protocol.name.clone().unwrap_or_else(|| format!("phase{k}"))).collect();
    // Compact: one sender one-hot, shared by every phase.
    let onehot_reg = if !blocks && phases.iter().any(|p| p.protocol.sender_one_hot) {
        let r = c.alloc(n);
        c.prog.push(Inst::SenderOneHot { dst: r });
        Some(r)
    } else {
        None
    };
    // Per phase, the first register of each field's value.
    let mut field_at: Vec<Vec<usize>> = Vec::with_capacity(phases.len());
    let mut block_at = Vec::with_capacity(phases.len());
    for ph in phases {
        let p = &ph.protocol;
        c.padding = p.history_padding;
        // Sender blocks: [one-hot | field 1 | field 2 | ...] contiguous in the registers, so a
        // receiver's whole block from one sender is a single copy. Compact: the fields alone.
        let onehot = if blocks && p.sender_one_hot { n } else { 0 };
        let blk = c.alloc(onehot + ph.field_widths.iter().sum::<usize>());
        if onehot > 0 {
            c.prog.push(Inst::SenderOneHot { dst: blk });
        }
        let mut at = Vec::with_capacity(p.fields.len());
        let mut off = blk + onehot;
        for f in &p.fields {
            at.push(off);
            off += c.expr_into(&f.value, off);
        }
        field_at.push(at);
        block_at.push(blk);
    }
    for i in 0..n {
        let mut col = 0usize;
        let mut push = |src: Option<usize>, w: usize, k: usize, j: usize, field: Option<usize>, name: &str, linked: bool| {
            // A copy of sender j's registers src.., or zeros.
            segs[i].push(match src {
                Some(src) => Seg::Copy { dst: col, sender: j, src, len: w },
                None => Seg::Zero { dst: col, len: w },
            });
            for q in 0..w {
                columns[i].push(Column {
                    phase: k,
                    phase_name: pnames[k].clone(),
                    sender: j,
                    field,
                    name: name.to_string(),
                    q,
                    linked,
                    padding: false,
                });
            }
            col += w;
        };
        if blocks {
            for (k, ph) in phases.iter().enumerate() {
                for j in (0..n).filter(|&j| j != i) {
                    if ph.protocol.sender_one_hot {
                        let linked = ph.links(j, i);
                        push(linked.then_some(block_at[k]), n, k, j, None, "sender_one_hot", linked);
                    }
                    for (f, fld) in ph.protocol.fields.iter().enumerate() {
                        let w = ph.field_widths[f];
                        let linked = ph.sends[f][j][i];
                        push(linked.then_some(field_at[k][f]), w, k, j, Some(f), &fld.name, linked);
                    }
                }
            }
        } else {
            // For each sender that reaches i in any phase: its one-hot once, then every field of
            // every phase it sends i; senders and fields that do not reach i take no columns.
            for j in (0..n).filter(|&j| j != i) {
                let Some(first) = phases.iter().position(|ph| ph.links(j, i)) else { continue };
                if let Some(r) = onehot_reg {
                    if phases.iter().any(|ph| ph.protocol.sender_one_hot && ph.links(j, i)) {
                        push(Some(r), n, first, j, None, "sender_one_hot", true);
                    }
                }
                for (k, ph) in phases.iter().enumerate() {
                    for (f, fld) in ph.protocol.fields.iter().enumerate() {
                        if ph.sends[f][j][i] {
                            let w = ph.field_widths[f];
                            push(Some(field_at[k][f]), w, k, j, Some(f), &fld.name, true);
                        }
                    }
                }
            }
            // Zero padding up to the widest receiver.
            debug_assert!(col <= msg_dim, "receiver {i} needs {col} columns, the plan is {msg_dim} wide");
            let pad = msg_dim.saturating_sub(col);
            if pad > 0 {
                segs[i].push(Seg::Zero { dst: col, len: pad });
                let k = phases.len() - 1;
                for q in 0..pad {
                    columns[i].push(Column {
                        phase: k,
                        phase_name: pnames[k].clone(),
                        sender: i,
                        field: None,
                        name: "padding".into(),
                        q,
                        linked: false,
                        padding: true,
                    });
                }
            }
        }
        debug_assert_eq!(columns[i].len(), msg_dim);
    }
    for s in &mut segs {
        *s = merge_segs(std::mem::take(s));
    }
    let name = phases
        .iter()
        .enumerate()
        .map(|(k, p)| p.protocol.name.clone().unwrap_or_else(|| format!("phase{k}")))
        .collect::<Vec<_>>()
        .join("+");
    let max_depth = c.channels.iter().map(|ch| ch.depth).max().unwrap_or(1);
    let mut plan = ProtocolPlan {
        name,
        n_agents: n,
        obs_dim: env.obs_dim,
        n_actions: env.n_actions,
        msg_dim,
        prog: c.prog,
        n_regs: c.n_regs,
        channels: c.channels,
        segs,
        labels: columns.iter().map(|c| c.iter().map(Column::label).collect()).collect(),
        columns,
        regs: Vec::new(),
        count: Vec::new(),
        max_depth,
        step: 0,
        num_envs: 0,
    };
    plan.compute_pads();
    Ok(plan)
}

/// Merge adjacent zero runs, and adjacent copies from contiguous registers of one sender.
fn merge_segs(segs: Vec<Seg>) -> Vec<Seg> {
    let mut out: Vec<Seg> = Vec::with_capacity(segs.len());
    for s in segs {
        match (out.last_mut(), s) {
            (Some(Seg::Zero { dst, len }), Seg::Zero { dst: d2, len: l2 }) if *dst + *len == d2 => *len += l2,
            (Some(Seg::Copy { dst, sender, src, len }), Seg::Copy { dst: d2, sender: s2, src: r2, len: l2 })
                if *sender == s2 && *dst + *len == d2 && *src + *len == r2 =>
            {
                *len += l2
            }
            (_, s) => out.push(s),
        }
    }
    out.retain(|s| !matches!(s, Seg::Zero { len: 0, .. } | Seg::Copy { len: 0, .. }));
    out
}

struct Compiler {
    prog: Vec<Inst>,
    n_regs: usize,
    channels: Vec<Channel>,
    n_actions: usize,
    n_agents: usize,
    /// The padding of the phase being compiled.
    padding: HistoryPadding,
    /// Output registers requested for the next node compiled.
    into: Option<usize>,
}

impl Compiler {
    /// The caller's requested output registers, or fresh ones.
    fn place(&mut self, into: Option<usize>, w: usize) -> usize {
        match into {
            Some(d) => d,
            None => self.alloc(w),
        }
    }

    /// Emit code for `e` writing its value at registers `dst..`.
    fn expr_into(&mut self, e: &Expr, dst: usize) -> usize {
        self.into = Some(dst);
        let (at, w) = self.expr(e);
        debug_assert_eq!(at, dst);
        w
    }

    fn alloc(&mut self, w: usize) -> usize {
        let r = self.n_regs;
        self.n_regs += w;
        r
    }

    /// Emit code for `e`; returns (first register, width).
    fn expr(&mut self, e: &Expr) -> (usize, usize) {
        // The output place asked for by the caller applies to this node only, not its children.
        let into = self.into.take();
        match e {
            Expr::Obs(dims) => {
                let dst = self.place(into, dims.len());
                // A run of consecutive dims is a slice copy.
                if dims.windows(2).all(|p| p[1] == p[0] + 1) {
                    self.prog.push(Inst::Slice { dst, start: dims[0], len: dims.len() });
                } else {
                    self.prog.push(Inst::Gather { dst, dims: dims.clone() });
                }
                (dst, dims.len())
            }
            Expr::ObsSlice(s) => {
                let len = s.end - s.start;
                let dst = self.place(into, len);
                self.prog.push(Inst::Slice { dst, start: s.start, len });
                (dst, len)
            }
            Expr::LastAction(ActionEncoding::OneHot) => {
                let w = self.n_actions;
                let dst = self.place(into, w);
                self.prog.push(Inst::ActOneHot { dst });
                (dst, w)
            }
            Expr::LastAction(ActionEncoding::Index) => {
                let dst = self.place(into, 1);
                self.prog.push(Inst::ActIndex { dst });
                (dst, 1)
            }
            Expr::SenderOneHot => {
                let w = self.n_agents;
                let dst = self.place(into, w);
                self.prog.push(Inst::SenderOneHot { dst });
                (dst, w)
            }
            Expr::Const(v) => {
                let dst = self.place(into, 1);
                self.prog.push(Inst::Const { dst, v: *v as f32 });
                (dst, 1)
            }
            Expr::Window(win) => {
                let pad = self.padding;
                let ch = match self.channels.iter().position(|c| c.expr == *win.of && c.padding == pad) {
                    Some(ch) => {
                        self.channels[ch].depth = self.channels[ch].depth.max(win.k);
                        ch
                    }
                    None => {
                        let (src, w) = self.expr(&win.of);
                        let ch = self.channels.len();
                        self.channels.push(Channel {
                            expr: (*win.of).clone(),
                            padding: pad,
                            src,
                            w,
                            depth: win.k,
                            pad: Vec::new(),
                            ring: Vec::new(),
                        });
                        self.prog.push(Inst::Push { ch });
                        ch
                    }
                };
                let w = self.channels[ch].w;
                let dst = self.place(into, w);
                self.prog.push(Inst::Agg { op: win.op, ch, k: win.k, dst });
                (dst, w)
            }
            Expr::Add(a, b)
            | Expr::Sub(a, b)
            | Expr::Mul(a, b)
            | Expr::Div(a, b)
            | Expr::Min(a, b)
            | Expr::Max(a, b)
            | Expr::Gt(a, b)
            | Expr::Lt(a, b)
            | Expr::Eq(a, b) => {
                let op = e.binary().expect("a binary operator").0;
                let (a, wa) = self.expr(a);
                let (b, wb) = self.expr(b);
                let w = wa.max(wb);
                let dst = self.place(into, w);
                self.prog.push(Inst::Bin { op, dst, a, wa, b, wb, w });
                (dst, w)
            }
            Expr::Neg(a) | Expr::Abs(a) => {
                let op = if matches!(e, Expr::Neg(_)) { Un::Neg } else { Un::Abs };
                let (a, w) = self.expr(a);
                let dst = self.place(into, w);
                self.prog.push(Inst::Un { op, dst, a, w });
                (dst, w)
            }
            Expr::Clip(c) => {
                let (a, w) = self.expr(&c.of);
                let dst = self.place(into, w);
                self.prog.push(Inst::Clip { dst, a, w, lo: c.min as f32, hi: c.max as f32 });
                (dst, w)
            }
            Expr::Reduce(r) => {
                let (a, w) = self.expr(&r.of);
                let dst = self.place(into, 1);
                self.prog.push(Inst::Reduce { op: r.op, dst, a, w });
                (dst, 1)
            }
            Expr::Concat(parts) => {
                let compiled: Vec<(usize, usize)> = parts.iter().map(|p| self.expr(p)).collect();
                let w: usize = compiled.iter().map(|c| c.1).sum();
                let dst = self.place(into, w);
                let mut off = dst;
                for (src, pw) in compiled {
                    self.prog.push(Inst::Copy { dst: off, src, w: pw });
                    off += pw;
                }
                (dst, w)
            }
        }
    }
}

/// Where instructions read their inputs from.
struct Input<'a> {
    rows: &'a [f32],
    rw: usize,
    last_actions: &'a [i32],
    /// Padding run: the last-action one-hot is filled with this value.
    act_pad: Option<f32>,
}

const EPS: f32 = 1e-6;

impl ProtocolPlan {
    /// Column labels of receiver `i`'s message (`phase/fromJ/field[q]`).
    pub fn column_labels(&self, receiver: usize) -> &[String] {
        &self.labels[receiver]
    }
    /// Where each column of receiver `i`'s message comes from.
    pub fn columns(&self, receiver: usize) -> &[Column] {
        &self.columns[receiver]
    }
    /// Number of distinct history channels and the deepest window.
    pub fn history_shape(&self) -> (usize, usize) {
        (self.channels.len(), self.max_depth)
    }
    /// Forget all history (every env restarts).
    pub fn reset(&mut self) {
        self.count.iter_mut().for_each(|c| *c = 0);
    }

    /// Evaluate every channel's expression on a padding step (per agent), once per padding mode.
    fn compute_pads(&mut self) {
        let n = self.n_agents;
        let nr = self.n_regs;
        for c in &mut self.channels {
            c.pad = vec![0.0; n * c.w];
        }
        for (mode, obs_v, act_v) in [(HistoryPadding::MinusOne, -1.0f32, -1.0f32), (HistoryPadding::Zero, 0.0, 0.0)] {
            if !self.channels.iter().any(|c| c.padding == mode) {
                continue;
            }
            let rows = vec![obs_v; n * self.obs_dim];
            let la = vec![-1i32; n];
            let mut regs = vec![0.0f32; n * nr];
            let input = Input { rows: &rows, rw: self.obs_dim, last_actions: &la, act_pad: Some(act_v) };
            for inst in &self.prog {
                match inst {
                    Inst::Push { ch } => {
                        let c = &mut self.channels[*ch];
                        if c.padding == mode {
                            for r in 0..n {
                                c.pad[r * c.w..(r + 1) * c.w].copy_from_slice(&regs[r * nr + c.src..r * nr + c.src + c.w]);
                            }
                        }
                    }
                    Inst::Agg { dst, ch, .. } => {
                        // Never inside a channel expression; keep the registers defined anyway.
                        let w = self.channels[*ch].w;
                        for r in 0..n {
                            regs[r * nr + dst..r * nr + dst + w].fill(0.0);
                        }
                    }
                    _ => exec_pure(inst, &mut regs, nr, n, n, &input, self.n_actions),
                }
            }
        }
    }

    fn ensure(&mut self, num_envs: usize) {
        if self.num_envs == num_envs && !self.regs.is_empty() {
            return;
        }
        let rows = num_envs * self.n_agents;
        self.num_envs = num_envs;
        self.regs = vec![0.0; rows * self.n_regs.max(1)];
        self.count = vec![0; num_envs];
        let n = self.n_agents;
        for c in &mut self.channels {
            let (d, w) = (c.depth, c.w);
            c.ring = vec![0.0; rows * (d + 1) * w];
            if c.padding != HistoryPadding::Repeat {
                for r in 0..rows {
                    let a = r % n;
                    c.ring[(r * (d + 1) + d) * w..(r * (d + 1) + d + 1) * w].copy_from_slice(&c.pad[a * w..(a + 1) * w]);
                }
            }
        }
    }
}

/// Execute one instruction that does not touch history, over rows 0..n_rows.
#[inline]
fn exec_pure(inst: &Inst, regs: &mut [f32], nr: usize, n_rows: usize, n_agents: usize, inp: &Input, n_actions: usize) {
    match *inst {
        Inst::Gather { dst, ref dims } => {
            for r in 0..n_rows {
                let o = &inp.rows[r * inp.rw..];
                let g = &mut regs[r * nr + dst..r * nr + dst + dims.len()];
                for (x, &d) in g.iter_mut().zip(dims) {
                    *x = o[d];
                }
            }
        }
        Inst::Slice { dst, start, len } => {
            for r in 0..n_rows {
                regs[r * nr + dst..r * nr + dst + len].copy_from_slice(&inp.rows[r * inp.rw + start..r * inp.rw + start + len]);
            }
        }
        Inst::ActOneHot { dst } => {
            for r in 0..n_rows {
                let g = &mut regs[r * nr + dst..r * nr + dst + n_actions];
                // Elementwise writes (not fill + set): no library call per row.
                match inp.act_pad {
                    Some(v) => g.iter_mut().for_each(|x| *x = v),
                    None => {
                        let a = inp.last_actions[r] as i64;
                        for (q, x) in g.iter_mut().enumerate() {
                            *x = (q as i64 == a) as u8 as f32;
                        }
                    }
                }
            }
        }
        Inst::ActIndex { dst } => {
            for r in 0..n_rows {
                regs[r * nr + dst] = if inp.act_pad.is_some() { -1.0 } else { inp.last_actions[r].max(-1) as f32 };
            }
        }
        Inst::SenderOneHot { dst } => {
            for r in 0..n_rows {
                let g = &mut regs[r * nr + dst..r * nr + dst + n_agents];
                let me = r % n_agents;
                for (q, x) in g.iter_mut().enumerate() {
                    *x = (q == me) as u8 as f32;
                }
            }
        }
        Inst::Const { dst, v } => {
            for r in 0..n_rows {
                regs[r * nr + dst] = v;
            }
        }
        Inst::Bin { op, dst, a, wa, b, wb, w } => {
            let (sa, sb) = ((wa > 1) as usize, (wb > 1) as usize);
            // One monomorphic loop per operator (no call per element).
            macro_rules! each {
                ($f:expr) => {{
                    let f = $f;
                    for r in 0..n_rows {
                        let o = r * nr;
                        for c in 0..w {
                            regs[o + dst + c] = f(regs[o + a + c * sa], regs[o + b + c * sb]);
                        }
                    }
                }};
            }
            match op {
                BinOp::Add => each!(|x: f32, y: f32| x + y),
                BinOp::Sub => each!(|x: f32, y: f32| x - y),
                BinOp::Mul => each!(|x: f32, y: f32| x * y),
                BinOp::Div => each!(|x: f32, y: f32| if y.abs() < EPS { 0.0 } else { x / y }),
                BinOp::Min => each!(f32::min),
                BinOp::Max => each!(f32::max),
                BinOp::Gt => each!(|x: f32, y: f32| (x > y) as u8 as f32),
                BinOp::Lt => each!(|x: f32, y: f32| (x < y) as u8 as f32),
                BinOp::Eq => each!(|x: f32, y: f32| ((x - y).abs() < EPS) as u8 as f32),
            }
        }
        Inst::Un { op, dst, a, w } => {
            for r in 0..n_rows {
                let o = r * nr;
                for c in 0..w {
                    let x = regs[o + a + c];
                    regs[o + dst + c] = match op {
                        Un::Neg => -x,
                        Un::Abs => x.abs(),
                    };
                }
            }
        }
        Inst::Clip { dst, a, w, lo, hi } => {
            for r in 0..n_rows {
                let o = r * nr;
                for c in 0..w {
                    // max/min (not clamp) so a NaN observation cannot panic.
                    regs[o + dst + c] = regs[o + a + c].max(lo).min(hi);
                }
            }
        }
        Inst::Reduce { op, dst, a, w } => {
            for r in 0..n_rows {
                let o = r * nr;
                let xs = &regs[o + a..o + a + w];
                let v = match op {
                    ReduceOp::Sum => xs.iter().sum(),
                    ReduceOp::Mean => xs.iter().sum::<f32>() / w as f32,
                    ReduceOp::Min => xs.iter().copied().fold(f32::INFINITY, f32::min),
                    ReduceOp::Max => xs.iter().copied().fold(f32::NEG_INFINITY, f32::max),
                };
                regs[o + dst] = v;
            }
        }
        Inst::Copy { dst, src, w } => {
            for r in 0..n_rows {
                let o = r * nr;
                regs.copy_within(o + src..o + src + w, o + dst);
            }
        }
        Inst::Push { .. } | Inst::Agg { .. } => unreachable!("history instructions are executed by the plan"),
    }
}

impl MessagePlan for ProtocolPlan {
    fn msg_dim(&self) -> usize {
        self.msg_dim
    }

    fn name(&self) -> String {
        self.name.clone()
    }

    fn apply(&mut self, step: &mut StepView<'_>) {
        let n = self.n_agents;
        assert_eq!(step.n_agents, n, "protocol plan {} was compiled for {n} agents, the step has {}", self.name, step.n_agents);
        assert_eq!(
            step.obs_dim, self.obs_dim,
            "protocol plan {} was compiled for obs_dim {}, the step has {}",
            self.name, self.obs_dim, step.obs_dim
        );
        assert!(
            self.msg_dim <= step.msg_dim,
            "protocol plan {} writes {} message columns, the slab reserves {}",
            self.name,
            self.msg_dim,
            step.msg_dim
        );
        let ne = step.num_envs;
        self.ensure(ne);
        let rows_n = ne * n;
        let rw = step.row_width();
        let od = self.obs_dim;
        let nr = self.n_regs;

        // Episode bookkeeping: count[e] = steps of the current episode seen, this one included.
        let max_depth = self.max_depth;
        for (e, c) in self.count.iter_mut().enumerate() {
            *c = if step.first[e] { 1 } else { (*c + 1).min(max_depth) };
        }
        let t = self.step;
        self.step += 1;

        // 1. Compute every field value of every (env, sender) row.
        {
            let inp = Input { rows: &*step.rows, rw, last_actions: step.last_actions, act_pad: None };
            let regs = &mut self.regs;
            for inst in &self.prog {
                match *inst {
                    Inst::Push { ch } => {
                        let c = &mut self.channels[ch];
                        let (d, w) = (c.depth, c.w);
                        let slot = (t % d as u64) as usize;
                        for r in 0..rows_n {
                            let at = (r * (d + 1) + slot) * w;
                            c.ring[at..at + w].copy_from_slice(&regs[r * nr + c.src..r * nr + c.src + w]);
                        }
                    }
                    Inst::Agg { op, ch, k, dst } => {
                        let c = &self.channels[ch];
                        agg(op, c, k, dst, t, regs, nr, rows_n, n, &self.count);
                    }
                    ref i => exec_pure(i, regs, nr, rows_n, n, &inp, self.n_actions),
                }
            }
        }

        // 2. Scatter into every receiver's message columns.
        let regs = &self.regs;
        for e in 0..ne {
            for i in 0..n {
                let row = &mut step.rows[(e * n + i) * rw + od..(e * n + i + 1) * rw];
                for s in &self.segs[i] {
                    match *s {
                        Seg::Copy { dst, sender, src, len } => {
                            let o = (e * n + sender) * nr + src;
                            row[dst..dst + len].copy_from_slice(&regs[o..o + len]);
                        }
                        Seg::Zero { dst, len } => row[dst..dst + len].fill(0.0),
                    }
                }
                if self.msg_dim < row.len() {
                    row[self.msg_dim..].fill(0.0);
                }
            }
        }
    }
}

/// Window aggregate of channel `c` over the last k steps for every row.
#[allow(clippy::too_many_arguments)]
fn agg(op: WindowOp, c: &Channel, k: usize, dst: usize, t: u64, regs: &mut [f32], nr: usize, rows_n: usize, n: usize, count: &[usize]) {
    let (d, w) = (c.depth, c.w);
    let repeat = c.padding == HistoryPadding::Repeat;
    // Ring slot of the value s steps back (s < k <= d) in a full window, the same for every row.
    let cur = (t % d as u64) as usize;
    let mut full = [0usize; MAX_WINDOW];
    for (s, slot) in full[..k].iter_mut().enumerate() {
        *slot = (cur + d - s) % d;
    }
    let mut part = [0usize; MAX_WINDOW];
    let stride = (d + 1) * w;
    for r in 0..rows_n {
        let cnt = count[r / n];
        // Slots of this row's window: before the episode start, the padding slot `d` (or the
        // episode's first step when repeating).
        let slots: &[usize] = if cnt >= k {
            &full[..k]
        } else {
            for s in 0..k {
                part[s] = if s < cnt {
                    full[s]
                } else if repeat {
                    full[cnt - 1]
                } else {
                    d
                };
            }
            &part[..k]
        };
        let ring = &c.ring[r * stride..(r + 1) * stride];
        let at = |s: usize| &ring[slots[s] * w..slots[s] * w + w];
        let o = r * nr + dst;
        let out = &mut regs[o..o + w];
        match op {
            WindowOp::Last => out.copy_from_slice(at(k - 1)),
            WindowOp::Delta => {
                for ((x, a), b) in out.iter_mut().zip(at(0)).zip(at(k - 1)) {
                    *x = a - b;
                }
            }
            WindowOp::Sum => fold(out, ring, slots, w, |x, y| x + y),
            WindowOp::Mean => {
                fold(out, ring, slots, w, |x, y| x + y);
                let inv = 1.0 / k as f32;
                out.iter_mut().for_each(|x| *x *= inv);
            }
            WindowOp::LastNonzero => {
                for (q, x) in out.iter_mut().enumerate() {
                    *x = slots.iter().map(|&sl| ring[sl * w + q]).find(|v| *v != 0.0).unwrap_or(0.0);
                }
            }
            WindowOp::Min => fold(out, ring, slots, w, f32::min),
            WindowOp::Max => fold(out, ring, slots, w, f32::max),
        }
    }
}

/// out[q] = f(...f(f(x_0[q], x_1[q]), x_2[q])..., x_{k-1}[q]) over the ring slots, with the
/// accumulators kept in registers (eight columns at a time).
#[inline(always)]
fn fold(out: &mut [f32], ring: &[f32], slots: &[usize], w: usize, f: impl Fn(f32, f32) -> f32) {
    const L: usize = 8;
    let mut q = 0;
    while q + L <= w {
        let mut acc: [f32; L] = ring[slots[0] * w + q..slots[0] * w + q + L].try_into().unwrap();
        for &sl in &slots[1..] {
            let src: &[f32; L] = ring[sl * w + q..sl * w + q + L].try_into().unwrap();
            for j in 0..L {
                acc[j] = f(acc[j], src[j]);
            }
        }
        out[q..q + L].copy_from_slice(&acc);
        q += L;
    }
    while q < w {
        let mut acc = ring[slots[0] * w + q];
        for &sl in &slots[1..] {
            acc = f(acc, ring[sl * w + q]);
        }
        out[q] = acc;
        q += 1;
    }
}
