//! Execution of a compiled plan: the straight-line program run over the whole batch, window
//! aggregates over the plan's history rings, and the scatter into each receiver's message.

use super::ast::*;
use super::compile::{Channel, Column, Inst, ProtocolPlan, Seg, Un};
use super::validate::MAX_WINDOW;
use crate::plan::{MessagePlan, StepView};

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
    pub(super) fn compute_pads(&mut self) {
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

    fn fresh(&self) -> Box<dyn MessagePlan> {
        // The program and tables as compiled; the run state as before the first step (`ensure`
        // sizes it then).
        let mut p = self.clone();
        p.regs = Vec::new();
        p.count = Vec::new();
        p.step = 0;
        p.num_envs = 0;
        for c in &mut p.channels {
            c.ring = Vec::new();
        }
        Box::new(p)
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
