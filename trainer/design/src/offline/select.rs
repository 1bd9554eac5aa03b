//! Greedy least-squares selection: covariances on sampled steps, partialling out what a
//! receiver already knows (the sweep operator), and the per-column gain of each candidate.
//!
//! Memory. The selection only ever reads, per receiver i, the covariance of the candidate
//! columns of every sender and the targets (the set Q) conditional on i's own base (its
//! observation and the messages of earlier phases). So nothing p x p is formed (p = n x (base +
//! candidates) + targets, about 33k on `smaclite:2o_20b_vs_2r`, 9 GB a copy): the sampled steps
//! are streamed through the runner's plans again for each pass instead of being held (the probe
//! messages of phase 1 alone would be 30 GB there), Q x Q is computed once, and for one receiver
//! at a time the covariance over its base and Q is built, its base swept out, and only the
//! q x q result kept. A sweep of pivot k changes entry (r, s) from entries (r, s), (r, k),
//! (k, s) and (k, k) alone, so sweeping on the sub-matrix of base(i) and Q gives the very
//! numbers the full matrix gave; base columns constant on the sample are left out (their pivot
//! is always skipped), and every sum runs over the rows in the same order as before, so the
//! picks are those of the dense computation (`dense` in the tests checks it).

use super::candidates::Candidate;
use super::{DesignContext, OfflineConfig};
use anyhow::{anyhow, Result};
use lmac_learn::stats::ColumnSums;
use lmac_protocol_runner::plan::MessagePlan;
use lmac_protocol_runner::protocol::{self, ProtocolEnv, ValidatedProtocol};
use lmac_run::dataset::Dataset;

/// Sweep pivot `k` out of the symmetric matrix `c` (size p): the rest becomes the covariance
/// conditional on variable k (linear partial covariance). Skips near-constant pivots.
pub(super) fn sweep(c: &mut [f64], p: usize, k: usize, orig_var: f64) -> bool {
    let piv = c[k * p + k];
    if piv <= 1e-9 * orig_var.max(1e-12) || piv <= 1e-12 {
        return false;
    }
    let rowk: Vec<f64> = c[k * p..(k + 1) * p].to_vec();
    for r in 0..p {
        let f = rowk[r] / piv;
        if f == 0.0 {
            continue;
        }
        let row = &mut c[r * p..(r + 1) * p];
        for (x, &y) in row.iter_mut().zip(&rowk) {
            *x -= f * y;
        }
    }
    for r in 0..p {
        c[r * p + k] = 0.0;
        c[k * p + r] = 0.0;
    }
    true
}

/// Explained variance of each target (indices `targets` in `c`) by the variables `g`, given
/// what `c` already conditions on: the drop of each target's variance when `g` is swept.
pub(super) fn explained(c: &[f64], p: usize, g: &[usize], targets: &[usize], orig_var: &[f64]) -> Vec<f64> {
    let idx: Vec<usize> = g.iter().chain(targets).copied().collect();
    let q = idx.len();
    let mut m = vec![0f64; q * q];
    for (a, &ia) in idx.iter().enumerate() {
        for (b, &ib) in idx.iter().enumerate() {
            m[a * q + b] = c[ia * p + ib];
        }
    }
    let before: Vec<f64> = (0..targets.len()).map(|t| m[(g.len() + t) * q + g.len() + t]).collect();
    for (a, &ia) in g.iter().enumerate() {
        sweep(&mut m, q, a, orig_var[ia]);
    }
    (0..targets.len()).map(|t| (before[t] - m[(g.len() + t) * q + g.len() + t]).max(0.0)).collect()
}

/// The sampled steps, visited in order as often as the statistics need them: per step every
/// sender's candidate values and the targets, or one agent's base (its observation and the
/// messages of the earlier phases it receives).
pub(super) trait RowSource {
    fn n(&self) -> usize;
    /// Base columns per agent.
    fn base_w(&self) -> usize;
    /// Probe (candidate) columns per sender.
    fn width(&self) -> usize;
    fn rows(&self) -> usize;
    /// Every row in order: the candidates of every sender (n x width, sender by sender) and the
    /// targets.
    fn each_cand(&mut self, f: &mut dyn FnMut(&[f32], &[f32])) -> Result<()>;
    /// Every row in order: agent i's base (base_w values).
    fn each_base(&mut self, i: usize, f: &mut dyn FnMut(&[f32])) -> Result<()>;
}

/// The sampled steps of B: whole episodes spread evenly over B until `max_samples` steps,
/// recomputed through the runner's plans (earlier phases, probe) at every pass.
pub(super) struct Sampled<'a> {
    data: &'a Dataset,
    chosen: Vec<usize>,
    prev: Option<Box<dyn MessagePlan>>,
    probe: Box<dyn MessagePlan>,
    width: usize,
    targets: Vec<usize>,
    rows: usize,
}

/// Choose the sampled episodes and compile the plans that compute their rows.
pub(super) fn sample<'a>(
    ctx: &DesignContext<'a>,
    previous: &[ValidatedProtocol],
    probe_v: &ValidatedProtocol,
    probe_env: &ProtocolEnv,
    width: usize,
    targets: &[usize],
    max_samples: usize,
) -> Result<Sampled<'a>> {
    let data = ctx.dataset.ok_or_else(|| anyhow!("the offline designer needs the dataset B"))?;
    let total: usize = data.steps();
    let stride = total.div_ceil(max_samples.max(1)).max(1);
    // Whole episodes (message history needs them), every stride-th one.
    let chosen: Vec<usize> = (0..data.episodes.len()).step_by(stride).collect();
    let prev = if previous.is_empty() {
        None
    } else {
        Some(protocol::compile(previous, ctx.env).map_err(|e| anyhow!("compiling the earlier phases: {}", protocol::errors_to_text(&e)))?)
    };
    let probe = protocol::compile(std::slice::from_ref(probe_v), probe_env)
        .map_err(|e| anyhow!("offline designer: compiling its probe: {}", protocol::errors_to_text(&e)))?;
    let rows = chosen.iter().map(|&e| data.episodes[e].len).sum();
    Ok(Sampled { data, chosen, prev, probe, width, targets: targets.to_vec(), rows })
}

impl RowSource for Sampled<'_> {
    fn n(&self) -> usize {
        self.data.header.n_agents
    }
    fn base_w(&self) -> usize {
        self.data.header.obs_dim + self.prev.as_ref().map_or(0, |p| p.msg_dim())
    }
    fn width(&self) -> usize {
        self.width
    }
    fn rows(&self) -> usize {
        self.rows
    }
    fn each_cand(&mut self, f: &mut dyn FnMut(&[f32], &[f32])) -> Result<()> {
        let h = &self.data.header;
        let (n, od, sd, width) = (h.n_agents, h.obs_dim, h.state_dim, self.width);
        let pmd = self.probe.msg_dim();
        let mut cand = vec![0f32; n * width];
        let mut y = vec![0f32; self.targets.len()];
        let targets = &self.targets;
        self.data.replay(&self.chosen, self.probe.as_mut(), &mut |e, t, rows| {
            for j in 0..n {
                // Sender j's block as received by agent r = j+1 (mod n).
                let r = (j + 1) % n;
                let pos = if j < r { j } else { j - 1 };
                let at = r * (od + pmd) + od + pos * width;
                cand[j * width..(j + 1) * width].copy_from_slice(&rows[at..at + width]);
            }
            for (v, &d) in y.iter_mut().zip(targets) {
                *v = e.state[t * sd + d];
            }
            f(&cand, &y);
        });
        Ok(())
    }
    fn each_base(&mut self, i: usize, f: &mut dyn FnMut(&[f32])) -> Result<()> {
        let (n, od) = (self.data.header.n_agents, self.data.header.obs_dim);
        match self.prev.as_mut() {
            None => {
                for &k in &self.chosen {
                    let e = &self.data.episodes[k];
                    for t in 0..e.len {
                        f(&e.obs[(t * n + i) * od..(t * n + i + 1) * od]);
                    }
                }
            }
            Some(plan) => {
                let md = plan.msg_dim();
                self.data.replay(&self.chosen, plan.as_mut(), &mut |_, _, rows| f(&rows[i * (od + md)..(i + 1) * (od + md)]));
            }
        }
        Ok(())
    }
}

/// Keep the `keep` candidates with the largest weighted squared marginal correlation between
/// another agent's value and the targets (a cheap filter before the joint least squares).
pub(super) fn prescreen(s: &mut dyn RowSource, cands: &[Candidate], w: &[Vec<f64>], keep: usize) -> Result<Vec<usize>> {
    let (n, width) = (s.n(), s.width());
    let t = w[0].len();
    let cw = n * width;
    let (mut cmo, mut ymo) = (ColumnSums::new(cw), ColumnSums::new(t));
    s.each_cand(&mut |c, y| {
        cmo.add(c);
        ymo.add(y);
    })?;
    let (cmom, ymom) = (cmo.finish(), ymo.finish());
    let (cm, csd, ym, ysd) = (cmom.mean, cmom.sd, ymom.mean, ymom.sd);
    let mut cov = vec![0f64; cw * t];
    s.each_cand(&mut |c, y| {
        for (a, &ca) in c.iter().enumerate() {
            let x = ca as f64 - cm[a];
            if x == 0.0 {
                continue;
            }
            for (d, &yd) in y.iter().enumerate() {
                cov[a * t + d] += x * (yd as f64 - ym[d]);
            }
        }
    })?;
    Ok(keep_most_correlated(&cov, &csd, &ysd, s.rows(), cands, w, (n, width), keep))
}

/// The `keep` candidates whose other-agent values correlate most with the targets: each
/// candidate's squared marginal correlations (from the centred cross sums `cov`, cand-column x
/// target, over `rows` rows, and the columns' SDs) summed over its columns, senders and
/// receivers with the receivers' weights, per column of width. Sorted by index.
#[allow(clippy::too_many_arguments)]
fn keep_most_correlated(
    cov: &[f64],
    csd: &[f64],
    ysd: &[f64],
    rows: usize,
    cands: &[Candidate],
    w: &[Vec<f64>],
    (n, width): (usize, usize),
    keep: usize,
) -> Vec<usize> {
    let t = ysd.len();
    let rows = rows.max(1) as f64;
    let corr2 = |a: usize, d: usize| -> f64 {
        let den = csd[a] * ysd[d];
        if den <= 1e-12 {
            0.0
        } else {
            let r = cov[a * t + d] / rows / den;
            r * r
        }
    };
    let mut scored: Vec<(f64, usize)> = cands
        .iter()
        .enumerate()
        .map(|(k, c)| {
            let mut score = 0.0;
            for j in 0..n {
                for col in c.col..c.col + c.width {
                    for i in (0..n).filter(|&i| i != j) {
                        for d in 0..t {
                            score += w[i][d] * corr2(j * width + col, d);
                        }
                    }
                }
            }
            (score / c.width as f64, k)
        })
        .collect();
    scored.sort_by(|a, b| b.0.partial_cmp(&a.0).unwrap_or(std::cmp::Ordering::Equal).then(a.1.cmp(&b.1)));
    let mut kept: Vec<usize> = scored.iter().take(keep).map(|x| x.1).collect();
    kept.sort_unstable();
    kept
}

/// The selection problem, per receiver, over Q = [sender 0's kept candidate columns | sender 1's
/// | ... | targets]: the covariance conditional on what that receiver already knows.
pub(super) struct Stats {
    pub(super) n: usize,
    /// Candidate columns kept per sender (after the prescreen), as probe-block columns.
    pub(super) cols: Vec<usize>,
    pub(super) t: usize,
    /// Size of Q.
    pub(super) q: usize,
    /// The unconditional variance of each variable of Q.
    pub(super) orig_var: Vec<f64>,
    /// Per receiver, the q x q covariance of Q given its base.
    pub(super) cond: Vec<Vec<f64>>,
}

impl Stats {
    pub(super) fn target(&self, d: usize) -> usize {
        self.n * self.cols.len() + d
    }
}

/// acc[a][b] += x[r][a] * y[r][b] over the rows r of the chunk in order (rows where x[r][a] is
/// 0 add nothing), for a in 0..ma and b in 0..mb, or b <= a when `tri`. Every entry sums its
/// rows in order, so chunking (for the cache) does not change a bit.
fn add_products(acc: &mut [f64], x: &[f64], ma: usize, y: &[f64], mb: usize, rows: usize, tri: bool) {
    for a in 0..ma {
        let len = if tri { a + 1 } else { mb };
        let out = &mut acc[a * mb..a * mb + len];
        for r in 0..rows {
            let xa = x[r * ma + a];
            if xa == 0.0 {
                continue;
            }
            for (c, &yb) in out.iter_mut().zip(&y[r * mb..r * mb + len]) {
                *c += xa * yb;
            }
        }
    }
}

/// Rows per chunk of the product sums.
const CHUNK: usize = 64;

/// The per-receiver conditional covariances of Q (see the module doc), from the kept probe
/// columns `cols`.
pub(super) fn covariance(s: &mut dyn RowSource, cols: Vec<usize>) -> Result<Stats> {
    let (n, base_w, width, rows) = (s.n(), s.base_w(), s.width(), s.rows());
    let nc = cols.len();
    // Q's values per row (f32 as sampled), then its means.
    let mut qv: Vec<f32> = Vec::new();
    let mut t = 0;
    s.each_cand(&mut |c, y| {
        for j in 0..n {
            qv.extend(cols.iter().map(|&col| c[j * width + col]));
        }
        qv.extend_from_slice(y);
        t = y.len();
    })?;
    let q = n * nc + t;
    let rf = rows.max(1) as f64;
    let mut qmean = vec![0f64; q];
    for r in qv.chunks_exact(q.max(1)) {
        for (m, &v) in qmean.iter_mut().zip(r) {
            *m += v as f64;
        }
    }
    qmean.iter_mut().for_each(|m| *m /= rf);
    let centered = |vals: &[f32], mean: &[f64], w: usize, from: usize, k: usize| -> Vec<f64> {
        (from..from + k).flat_map(|r| vals[r * w..(r + 1) * w].iter().zip(mean).map(|(&v, m)| v as f64 - m)).collect()
    };
    // Q x Q, once (lower triangle).
    let mut qq = vec![0f64; q * q];
    for from in (0..rows).step_by(CHUNK) {
        let k = CHUNK.min(rows - from);
        let x = centered(&qv, &qmean, q, from, k);
        add_products(&mut qq, &x, q, &x, q, k, true);
    }
    for a in 0..q {
        for b in 0..=a {
            let v = qq[a * q + b] / rf;
            qq[a * q + b] = v;
            qq[b * q + a] = v;
        }
    }
    let orig_var: Vec<f64> = (0..q).map(|k| qq[k * q + k]).collect();
    // Where Q's variables sit among all agents' variables ([agent 0: base, candidates | agent 1:
    // ... | targets]), to order each receiver's variables as the full matrix did.
    let aw = base_w + nc;
    let global = |u: usize| if u < n * nc { (u / nc) * aw + base_w + u % nc } else { n * aw + (u - n * nc) };
    let mut cond = Vec::with_capacity(n);
    for i in 0..n {
        let mut bv: Vec<f32> = Vec::with_capacity(rows * base_w);
        s.each_base(i, &mut |b| bv.extend_from_slice(&b[..base_w]))?;
        // Base columns with one value on every sampled row never pivot; leave them out.
        let keep: Vec<usize> = (0..base_w).filter(|&c| bv.chunks_exact(base_w).any(|r| r[c] != bv[c] || r[c].is_nan())).collect();
        let nb = keep.len();
        let bsel: Vec<f32> = bv.chunks_exact(base_w.max(1)).flat_map(|r| keep.iter().map(move |&c| r[c])).collect();
        drop(bv);
        let mut bmean = vec![0f64; nb];
        for r in bsel.chunks_exact(nb.max(1)).take(if nb == 0 { 0 } else { rows }) {
            for (m, &v) in bmean.iter_mut().zip(r) {
                *m += v as f64;
            }
        }
        bmean.iter_mut().for_each(|m| *m /= rf);
        // Base x base (lower triangle) and base x Q.
        let mut bb = vec![0f64; nb * nb];
        let mut bq = vec![0f64; nb * q];
        if nb > 0 {
            for from in (0..rows).step_by(CHUNK) {
                let k = CHUNK.min(rows - from);
                let xb = centered(&bsel, &bmean, nb, from, k);
                let xq = centered(&qv, &qmean, q, from, k);
                add_products(&mut bb, &xb, nb, &xb, nb, k, true);
                add_products(&mut bq, &xb, nb, &xq, q, k, false);
            }
        }
        drop(bsel);
        // The local matrix over [base(i) kept | Q] in the full matrix's order of variables.
        let base_at = i * aw;
        let mut order: Vec<(usize, bool, usize)> = keep.iter().enumerate().map(|(k, &c)| (base_at + c, true, k)).collect();
        order.extend((0..q).map(|u| (global(u), false, u)));
        order.sort_unstable();
        let m = order.len();
        let entry = |a: &(usize, bool, usize), b: &(usize, bool, usize)| -> f64 {
            match (a.1, b.1) {
                (true, true) => {
                    let (x, y) = if a.2 >= b.2 { (a.2, b.2) } else { (b.2, a.2) };
                    bb[x * nb + y] / rf
                }
                (true, false) => bq[a.2 * q + b.2] / rf,
                (false, true) => bq[b.2 * q + a.2] / rf,
                (false, false) => qq[a.2 * q + b.2],
            }
        };
        let mut c = vec![0f64; m * m];
        for (x, a) in order.iter().enumerate() {
            for (y, b) in order.iter().enumerate() {
                c[x * m + y] = entry(a, b);
            }
        }
        drop((bb, bq));
        let diag: Vec<f64> = (0..m).map(|x| c[x * m + x]).collect();
        for (x, a) in order.iter().enumerate() {
            if a.1 {
                sweep(&mut c, m, x, diag[x]);
            }
        }
        let at_q: Vec<usize> = {
            let mut v = vec![0usize; q];
            for (x, a) in order.iter().enumerate() {
                if !a.1 {
                    v[a.2] = x;
                }
            }
            v
        };
        let mut cq = vec![0f64; q * q];
        for (u, &xu) in at_q.iter().enumerate() {
            for (v, &xv) in at_q.iter().enumerate() {
                cq[u * q + v] = c[xu * m + xv];
            }
        }
        cond.push(cq);
    }
    Ok(Stats { n, cols, t, q, orig_var, cond })
}

/// One chosen candidate: who sends it to whom, and what it gained.
#[derive(Clone, Debug, PartialEq)]
pub(super) struct Pick {
    pub(super) cand: usize,
    /// links[j][i]: j sends it to i.
    pub(super) links: Vec<Vec<bool>>,
    pub(super) gain: f64,
}

/// The links of a field agent `j` alone sends to every other of the `n` agents.
pub(super) fn to_everyone_from(n: usize, j: usize) -> Vec<Vec<bool>> {
    (0..n).map(|s| (0..n).map(|i| s == j && i != j).collect()).collect()
}

/// Links from `j` to `receivers` (but never to itself), or to every other agent when None or
/// when `receivers` holds no other agent.
pub(super) fn to_receivers_from(n: usize, j: usize, receivers: &Option<Vec<usize>>) -> Vec<Vec<bool>> {
    match receivers {
        Some(r) if r.iter().any(|&i| i != j) => (0..n).map(|s| (0..n).map(|i| s == j && i != j && r.contains(&i)).collect()).collect(),
        _ => to_everyone_from(n, j),
    }
}

/// "every other agent" or "agents 1, 2", for the log.
pub(super) fn receivers_text(j: usize, receivers: &Option<Vec<usize>>) -> String {
    match receivers {
        Some(r) if r.iter().any(|&i| i != j) => {
            let to: Vec<String> = r.iter().filter(|&&i| i != j).map(|i| i.to_string()).collect();
            format!("agent(s) {} (those that need the critical dims)", to.join(", "))
        }
        _ => "every other agent".into(),
    }
}

/// Greedy selection (see the module doc). `w[i][d]`: weight of receiver i and target d.
pub(super) fn select(
    stats: Stats,
    cands: &[Candidate],
    kept: &[usize],
    w: &[Vec<f64>],
    columns: usize,
    cfg: &OfflineConfig,
) -> (Vec<Pick>, Vec<String>) {
    let targets: Vec<usize> = (0..stats.t).map(|d| stats.target(d)).collect();
    let nc = stats.cols.len();
    // Per receiver: the covariance given what it already knows.
    let Stats { n, cols, q: p, orig_var, mut cond, .. } = stats;
    let orig_var = &orig_var;
    let total_w: f64 = w.iter().flatten().sum::<f64>().max(1e-12);
    let vars = |c: &Candidate, j: usize| -> Vec<usize> {
        (c.col..c.col + c.width).filter_map(|col| cols.iter().position(|&x| x == col).map(|k| j * nc + k)).collect()
    };
    let score = |c: &[f64], i: usize, g: &[usize]| -> f64 {
        if g.is_empty() {
            return 0.0;
        }
        let ex = explained(c, p, g, &targets, orig_var);
        ex.iter().enumerate().map(|(d, e)| w[i][d] * e / orig_var[targets[d]].max(1e-12)).sum()
    };
    let mut picks: Vec<Pick> = Vec::new();
    let mut log = Vec::new();
    let mut left = columns;
    // sends[j][i]: j already sends something to i in this phase, so i already has j's one-hot
    // (the compact layout puts each sender's one-hot once per receiver and phase).
    let mut sends = vec![vec![false; n]; n];
    // Message columns per receiver, on average, that a pick's links add.
    let cost_of = |links: &[Vec<bool>], width: usize, sends: &[Vec<bool>]| -> f64 {
        let mut cols = 0usize;
        for j in 0..n {
            for i in (0..n).filter(|&i| links[j][i]) {
                cols += width + if cfg.count_sender_columns && !sends[j][i] { n } else { 0 };
            }
        }
        cols as f64 / n as f64
    };
    loop {
        let mut best: Option<(f64, Pick)> = None;
        for &k in kept {
            let c = &cands[k];
            if c.width > left || picks.iter().any(|p| p.cand == k) {
                continue;
            }
            // Per link gains, then the links worth keeping, then the joint gain over them.
            let mut pair = vec![vec![0f64; n]; n];
            for i in 0..n {
                for j in (0..n).filter(|&j| j != i) {
                    pair[j][i] = score(&cond[i], i, &vars(c, j));
                }
            }
            if cfg.senders_per_field > 0 && cfg.senders_per_field < n {
                // Keep the senders whose links explain the most summed over their receivers.
                let mut by_total: Vec<(f64, usize)> = pair.iter().enumerate().map(|(j, row)| (row.iter().sum::<f64>(), j)).collect();
                by_total.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
                for &(_, j) in &by_total[cfg.senders_per_field..] {
                    pair[j].iter_mut().for_each(|x| *x = 0.0);
                }
            }
            let top = pair.iter().flatten().cloned().fold(0f64, f64::max);
            let mut links: Vec<Vec<bool>> =
                (0..n).map(|j| (0..n).map(|i| i != j && top > 0.0 && pair[j][i] >= cfg.link_fraction * top).collect()).collect();
            if cfg.count_sender_columns {
                // A link must pay for its own columns (its values and, for a new sender, the
                // sender's one-hot): few senders and few columns (the paper's "compact").
                for j in 0..n {
                    for i in 0..n {
                        if links[j][i] {
                            let own = c.width + if sends[j][i] { 0 } else { n };
                            let per_col = pair[j][i] / total_w / (own as f64 / n as f64);
                            links[j][i] = pair[j][i] >= top - 1e-15 || per_col >= cfg.min_gain;
                        }
                    }
                }
            }
            let gain: f64 = (0..n)
                .map(|i| {
                    let g: Vec<usize> = (0..n).filter(|&j| links[j][i]).flat_map(|j| vars(c, j)).collect();
                    score(&cond[i], i, &g)
                })
                .sum::<f64>()
                / total_w;
            // Gain per message column: with count_sender_columns the columns are what the
            // receivers get (values and new senders' one-hots, averaged over receivers), else
            // the candidate's width in one sender block.
            let cost = if cfg.count_sender_columns { cost_of(&links, c.width, &sends).max(1e-12) } else { c.width as f64 };
            let per_col = gain / cost;
            if best.as_ref().is_none_or(|(b, _)| per_col > *b) {
                best = Some((per_col, Pick { cand: k, links, gain }));
            }
        }
        let Some((per_col, pick)) = best else { break };
        if !pick.links.iter().flatten().any(|&l| l) {
            // Not one link explains anything of the targets (e.g. earlier phases already send
            // them): a field with no sender is no field.
            log.push("stopped: no candidate explains any of the targets beyond what the receivers know".into());
            break;
        }
        if per_col < cfg.min_gain && !picks.is_empty() {
            log.push(format!("stopped: the best remaining candidate gains {per_col:.4} per column (< min_gain {})", cfg.min_gain));
            break;
        }
        let c = &cands[pick.cand];
        for (i, ci) in cond.iter_mut().enumerate() {
            for j in (0..n).filter(|&j| pick.links[j][i]) {
                for v in vars(c, j) {
                    sweep(ci, p, v, orig_var[v]);
                }
            }
        }
        left -= c.width;
        for (j, row) in pick.links.iter().enumerate() {
            for (i, &l) in row.iter().enumerate() {
                sends[j][i] |= l;
            }
        }
        log.push(format!("picked {} (gain {:.4}, {:.4} per column, {} columns left)", cand_label(c), pick.gain, per_col, left));
        picks.push(pick);
        if left == 0 {
            break;
        }
    }
    (picks, log)
}

pub(super) fn cand_label(c: &Candidate) -> String {
    let (stem, _) = c.kind.words();
    match c.dim {
        Some(d) => format!("{stem}(o[{d}])"),
        None => stem,
    }
}

#[cfg(test)]
mod tests {
    //! The streamed, per-receiver statistics against the dense p x p computation they replace.
    use super::super::candidates::Kind;
    use super::*;

    /// Sampled rows held in memory: per row n x base_w, n x width, t.
    struct Dense {
        n: usize,
        base_w: usize,
        width: usize,
        base: Vec<f32>,
        cand: Vec<f32>,
        y: Vec<f32>,
        rows: usize,
    }

    impl RowSource for Dense {
        fn n(&self) -> usize {
            self.n
        }
        fn base_w(&self) -> usize {
            self.base_w
        }
        fn width(&self) -> usize {
            self.width
        }
        fn rows(&self) -> usize {
            self.rows
        }
        fn each_cand(&mut self, f: &mut dyn FnMut(&[f32], &[f32])) -> Result<()> {
            let (cw, t) = (self.n * self.width, self.y.len() / self.rows);
            for r in 0..self.rows {
                f(&self.cand[r * cw..(r + 1) * cw], &self.y[r * t..(r + 1) * t]);
            }
            Ok(())
        }
        fn each_base(&mut self, i: usize, f: &mut dyn FnMut(&[f32])) -> Result<()> {
            let (n, bw) = (self.n, self.base_w);
            for r in 0..self.rows {
                f(&self.base[(r * n + i) * bw..(r * n + i + 1) * bw]);
            }
            Ok(())
        }
    }

    // ---- the dense computation as it was (p x p, cloned per receiver) ----

    /// The prescreen's moments and cross sums from the rows held in memory, ranked by the
    /// production ranking: the streamed sums must give the same candidates.
    fn dense_prescreen(s: &Dense, cands: &[Candidate], w: &[Vec<f64>], keep: usize) -> Vec<usize> {
        let (n, width) = (s.n, s.width);
        let t = w[0].len();
        let cw = n * width;
        let cmom = lmac_learn::stats::ColumnMoments::of_flat(&s.cand, cw, s.rows);
        let ymom = lmac_learn::stats::ColumnMoments::of_flat(&s.y, t, s.rows);
        let (cm, csd, ym, ysd) = (cmom.mean, cmom.sd, ymom.mean, ymom.sd);
        let mut cov = vec![0f64; cw * t];
        for r in 0..s.rows {
            let c = &s.cand[r * cw..(r + 1) * cw];
            let y = &s.y[r * t..(r + 1) * t];
            for (a, &ca) in c.iter().enumerate() {
                let x = ca as f64 - cm[a];
                if x == 0.0 {
                    continue;
                }
                for (d, &yd) in y.iter().enumerate() {
                    cov[a * t + d] += x * (yd as f64 - ym[d]);
                }
            }
        }
        keep_most_correlated(&cov, &csd, &ysd, s.rows, cands, w, (n, width), keep)
    }

    /// The full covariance and, per receiver, its base swept out; then the old greedy loop.
    fn dense_select(
        s: &Dense,
        cols: &[usize],
        cands: &[Candidate],
        kept: &[usize],
        w: &[Vec<f64>],
        columns: usize,
        cfg: &OfflineConfig,
    ) -> (Vec<Pick>, Vec<String>) {
        let (n, base_w, width) = (s.n, s.base_w, s.width);
        let t = s.y.len() / s.rows;
        let aw = base_w + cols.len();
        let p = n * aw + t;
        let mut mean = vec![0f64; p];
        let mut x = vec![0f64; p];
        let fill = |r: usize, x: &mut [f64]| {
            for a in 0..n {
                for (c, &v) in s.base[(r * n + a) * base_w..(r * n + a + 1) * base_w].iter().enumerate() {
                    x[a * aw + c] = v as f64;
                }
                let cr = &s.cand[(r * n + a) * width..(r * n + a + 1) * width];
                for (k, &col) in cols.iter().enumerate() {
                    x[a * aw + base_w + k] = cr[col] as f64;
                }
            }
            for d in 0..t {
                x[n * aw + d] = s.y[r * t + d] as f64;
            }
        };
        for r in 0..s.rows {
            fill(r, &mut x);
            for (m, v) in mean.iter_mut().zip(&x) {
                *m += v;
            }
        }
        let rows = s.rows.max(1) as f64;
        mean.iter_mut().for_each(|m| *m /= rows);
        let mut cov = vec![0f64; p * p];
        for r in 0..s.rows {
            fill(r, &mut x);
            for (v, m) in x.iter_mut().zip(&mean) {
                *v -= m;
            }
            for a in 0..p {
                let xa = x[a];
                if xa == 0.0 {
                    continue;
                }
                for (c, &xb) in cov[a * p..a * p + a + 1].iter_mut().zip(&x[..=a]) {
                    *c += xa * xb;
                }
            }
        }
        for a in 0..p {
            for b in 0..=a {
                let v = cov[a * p + b] / rows;
                cov[a * p + b] = v;
                cov[b * p + a] = v;
            }
        }
        let orig_var: Vec<f64> = (0..p).map(|k| cov[k * p + k]).collect();
        // The dense conditional matrices, cut down to Q (what the selection reads), so the
        // greedy loop below is the one under test fed with the dense numbers.
        let qidx: Vec<usize> =
            (0..n).flat_map(|j| (0..cols.len()).map(move |k| j * aw + base_w + k)).chain((0..t).map(|d| n * aw + d)).collect();
        let q = qidx.len();
        let cond: Vec<Vec<f64>> = (0..n)
            .map(|i| {
                let mut c = cov.clone();
                for k in i * aw..i * aw + base_w {
                    sweep(&mut c, p, k, orig_var[k]);
                }
                let mut cq = vec![0f64; q * q];
                for (u, &gu) in qidx.iter().enumerate() {
                    for (v, &gv) in qidx.iter().enumerate() {
                        cq[u * q + v] = c[gu * p + gv];
                    }
                }
                cq
            })
            .collect();
        let stats = Stats { n, cols: cols.to_vec(), t, q, orig_var: qidx.iter().map(|&g| orig_var[g]).collect(), cond };
        select(stats, cands, kept, w, columns, cfg)
    }

    struct Rng(u64);
    impl Rng {
        fn next(&mut self) -> f64 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            (self.0 >> 11) as f64 / (1u64 << 53) as f64
        }
    }

    /// Targets driven by some senders' candidates and by the receivers' own bases, with constant,
    /// sparse (often zero) and duplicated columns.
    fn problem(seed: u64) -> (Dense, Vec<Candidate>, Vec<Vec<f64>>) {
        let (n, base_w, width, t, rows) = (3, 6, 7, 4, 300);
        let mut r = Rng(seed);
        let mut base = Vec::new();
        let mut cand = Vec::new();
        let mut y = Vec::new();
        for _ in 0..rows {
            let hidden: Vec<f64> = (0..4).map(|_| r.next() * 2.0 - 1.0).collect();
            let mut crow = Vec::new();
            for j in 0..n {
                for c in 0..width {
                    let v = match c {
                        0 => hidden[j],
                        1 => hidden[(j + 1) % 4] * 0.5 + 0.1 * r.next(),
                        2 => {
                            if r.next() < 0.7 {
                                0.0
                            } else {
                                hidden[3]
                            }
                        }
                        3 => 1.0,
                        4 => hidden[j] + 0.2 * r.next(),
                        _ => (r.next() < 0.5) as u8 as f64,
                    };
                    crow.push(v as f32);
                }
            }
            for a in 0..n {
                for c in 0..base_w {
                    let v = match c {
                        0 => hidden[a],
                        1 => 0.0,
                        2 => 0.25,
                        3 => crow[((a + 1) % n) * width + 1] as f64,
                        _ => r.next(),
                    };
                    base.push(v as f32);
                }
            }
            cand.extend(crow);
            for d in 0..t {
                y.push((hidden[d % 4] + 0.3 * hidden[(d + 1) % 4] + 0.05 * r.next()) as f32);
            }
        }
        let mut cands: Vec<Candidate> = (0..width - 2).map(|c| Candidate { kind: Kind::Obs, dim: Some(c), width: 1, col: c }).collect();
        cands.push(Candidate { kind: Kind::LastAction, dim: None, width: 2, col: width - 2 });
        let w: Vec<Vec<f64>> = (0..n).map(|i| (0..t).map(|d| 0.2 + ((i * 7 + d * 3) % 5) as f64 / 5.0).collect()).collect();
        (Dense { n, base_w, width, base, cand, y, rows }, cands, w)
    }

    #[test]
    fn streamed_statistics_pick_what_the_dense_matrix_picked() {
        for seed in [1u64, 7, 12345] {
            let (mut s, cands, w) = problem(seed);
            let cfg = OfflineConfig { min_gain: 0.0005, ..OfflineConfig::least_squares_rules() };
            for keep in [3, 6] {
                let kept = prescreen(&mut s, &cands, &w, keep).unwrap();
                assert_eq!(kept, dense_prescreen(&s, &cands, &w, keep), "seed {seed}");
                let mut cols: Vec<usize> = kept.iter().flat_map(|&k| cands[k].col..cands[k].col + cands[k].width).collect();
                cols.sort_unstable();
                let stats = covariance(&mut s, cols.clone()).unwrap();
                let (picks, log) = select(stats, &cands, &kept, &w, 5, &cfg);
                let (dpicks, dlog) = dense_select(&s, &cols, &cands, &kept, &w, 5, &cfg);
                assert!(!picks.is_empty());
                assert_eq!(picks, dpicks, "seed {seed}, keep {keep}");
                assert_eq!(log, dlog);
            }
        }
    }

    /// `senders_per_field = 1`: every pick has one sender (the unique principle), and it is one
    /// of the senders the unrestricted pick used.
    #[test]
    fn one_sender_per_field() {
        let (mut s, cands, w) = problem(7);
        let kept = prescreen(&mut s, &cands, &w, 6).unwrap();
        let mut cols: Vec<usize> = kept.iter().flat_map(|&k| cands[k].col..cands[k].col + cands[k].width).collect();
        cols.sort_unstable();
        let any = OfflineConfig { min_gain: 0.0005, ..OfflineConfig::least_squares_rules() };
        let one = OfflineConfig { senders_per_field: 1, ..any.clone() };
        let (free, _) = select(covariance(&mut s, cols.clone()).unwrap(), &cands, &kept, &w, 5, &any);
        let (picks, _) = select(covariance(&mut s, cols).unwrap(), &cands, &kept, &w, 5, &one);
        assert!(!picks.is_empty());
        let senders = |p: &Pick| (0..p.links.len()).filter(|&j| p.links[j].iter().any(|&l| l)).collect::<Vec<_>>();
        assert!(free.iter().any(|p| senders(p).len() > 1), "the problem has fields with several senders unrestricted: {free:?}");
        for p in &picks {
            assert_eq!(senders(p).len(), 1, "{p:?}");
        }
        let first = free.iter().find(|p| p.cand == picks[0].cand).expect("the first pick is a candidate the free selection took");
        assert!(senders(first).contains(&senders(&picks[0])[0]));
    }

    /// What a receiver already knows changes the picks: with bases that carry nothing (all
    /// constant, so all left out) the selection differs, so the comparison above would notice a
    /// covariance that ignored the bases.
    #[test]
    fn the_base_matters() {
        let (mut s, cands, w) = problem(7);
        let cfg = OfflineConfig { min_gain: 0.0005, ..OfflineConfig::least_squares_rules() };
        let kept = prescreen(&mut s, &cands, &w, 6).unwrap();
        let mut cols: Vec<usize> = kept.iter().flat_map(|&k| cands[k].col..cands[k].col + cands[k].width).collect();
        cols.sort_unstable();
        let (picks, _) = select(covariance(&mut s, cols.clone()).unwrap(), &cands, &kept, &w, 5, &cfg);
        let mut blind = Dense { base: vec![0.0; s.base.len()], ..problem(7).0 };
        let (bpicks, _) = select(covariance(&mut blind, cols).unwrap(), &cands, &kept, &w, 5, &cfg);
        assert_ne!(picks, bpicks);
    }
}
