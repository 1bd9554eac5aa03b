//! Compilation of validated protocol phases into a gather/compute plan (run by `execute`).
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
//! plan's `msg_dim`, [`combined_width`](super::width::combined_width)). A sender's one-hot is
//! paid once, not once per phase. It is kept (rather than replaced by a fixed position per
//! sender) because agents share one network and, in the compact layout, the sender behind a
//! column differs between receivers: the one-hot says whose values follow. The `sender_blocks`
//! layout (the earlier one, kept to reproduce old runs) gives every receiver, per phase, a full
//! block [one-hot | every field] per other agent, phases concatenated.
//! The design loop's D^(k) compiles phases 0..k on their own, so it never needs phase k's columns
//! at a fixed place in the final plan.

use super::ast::*;
use super::error::ValidationError;
use super::validate::{check_phases, validate, ValidatedProtocol};
use super::ProtocolEnv;
use crate::plan::MessagePlan;

#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) enum Un {
    Neg,
    Abs,
}

#[derive(Debug, Clone)]
pub(super) enum Inst {
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
pub(super) struct Channel {
    pub(super) expr: Expr,
    /// How the steps before the episode read (from the phase that declared the window).
    pub(super) padding: HistoryPadding,
    pub(super) src: usize,
    pub(super) w: usize,
    /// Ring depth (the longest window over this channel).
    pub(super) depth: usize,
    /// Per agent, the value of the channel's expression on a padding step (unused for `repeat`).
    pub(super) pad: Vec<f32>,
    /// rows x (depth + 1) x w; slot `depth` of a row holds its padding value.
    pub(super) ring: Vec<f32>,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) enum Seg {
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
    pub(super) name: String,
    pub(super) n_agents: usize,
    pub(super) obs_dim: usize,
    pub(super) n_actions: usize,
    pub(super) msg_dim: usize,
    pub(super) prog: Vec<Inst>,
    pub(super) n_regs: usize,
    pub(super) channels: Vec<Channel>,
    /// Scatter table per receiving agent.
    pub(super) segs: Vec<Vec<Seg>>,
    /// Column labels per receiving agent.
    pub(super) labels: Vec<Vec<String>>,
    /// Column sources per receiving agent.
    pub(super) columns: Vec<Vec<Column>>,
    // --- run state ---
    pub(super) regs: Vec<f32>,
    /// Per env: steps of the current episode seen (saturating at the deepest ring).
    pub(super) count: Vec<usize>,
    pub(super) max_depth: usize,
    pub(super) step: u64,
    pub(super) num_envs: usize,
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
            any_binary!(a, b) => {
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
