//! Greedy least-squares selection: covariances on sampled steps, partialling out what a
//! receiver already knows (the sweep operator), and the per-column gain of each candidate.

#[allow(unused_imports)]
use super::*;

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

/// The selection problem on sampled steps: per agent its base columns (own observation and
/// messages already received) and its candidate columns as a sender, then the target dims.
pub(super) struct Stats {
    pub(super) n: usize,
    pub(super) base_w: usize,
    /// Candidate columns kept per sender (after the prescreen), as probe-block columns.
    pub(super) cols: Vec<usize>,
    pub(super) t: usize,
    /// Covariance over [agent 0: base, cand | agent 1: base, cand | ... | targets].
    pub(super) cov: Vec<f64>,
    pub(super) p: usize,
}

impl Stats {
    pub(super) fn agent_w(&self) -> usize {
        self.base_w + self.cols.len()
    }
    pub(super) fn base(&self, a: usize) -> std::ops::Range<usize> {
        let s = a * self.agent_w();
        s..s + self.base_w
    }
    /// Covariance index of sender j's probe column `col` (None if prescreened out).
    pub(super) fn cand(&self, j: usize, col: usize) -> Option<usize> {
        self.cols.iter().position(|&c| c == col).map(|k| j * self.agent_w() + self.base_w + k)
    }
    pub(super) fn target(&self, d: usize) -> usize {
        self.n * self.agent_w() + d
    }
}

/// Rows of sampled steps: (base per agent, candidates per agent, targets), streamed to `f`.
pub(super) struct Sampled {
    /// per row: n * base_w
    pub(super) base: Vec<f32>,
    /// per row: n * probe width
    pub(super) cand: Vec<f32>,
    /// per row: targets
    pub(super) y: Vec<f32>,
    pub(super) rows: usize,
}

/// Compute the sampled rows: episodes spread evenly over B until `max_samples` steps.
pub(super) fn sample(
    ctx: &DesignContext,
    previous: &[ValidatedProtocol],
    probe_v: &ValidatedProtocol,
    probe_env: &ProtocolEnv,
    width: usize,
    targets: &[usize],
    max_samples: usize,
) -> Result<Sampled> {
    let data = ctx.dataset.ok_or_else(|| anyhow!("the offline designer needs the dataset B"))?;
    let h = &data.header;
    let (n, od, sd) = (h.n_agents, h.obs_dim, h.state_dim);
    let total: usize = data.steps();
    let stride = total.div_ceil(max_samples.max(1)).max(1);
    // Whole episodes (message history needs them), every stride-th one.
    let chosen: Vec<usize> = (0..data.episodes.len()).step_by(stride).collect();
    let sub = crate::dataset::Dataset { header: h.clone(), episodes: chosen.iter().map(|&e| data.episodes[e].clone()).collect() };
    let mut prev_plan = if previous.is_empty() {
        None
    } else {
        Some(protocol::compile(previous, ctx.env).map_err(|e| anyhow!("compiling the earlier phases: {}", protocol::errors_to_text(&e)))?)
    };
    let prev_md = prev_plan.as_ref().map(|p| p.msg_dim()).unwrap_or(0);
    let prev_msgs = prev_plan.as_mut().map(|p| sub.messages(p.as_mut()));
    let mut probe_plan = protocol::compile(std::slice::from_ref(probe_v), probe_env)
        .map_err(|e| anyhow!("offline designer: compiling its probe: {}", protocol::errors_to_text(&e)))?;
    let pmd = probe_plan.msg_dim();
    let probe_msgs = sub.messages(probe_plan.as_mut());
    let base_w = od + prev_md;
    let mut s = Sampled { base: Vec::new(), cand: Vec::new(), y: Vec::new(), rows: 0 };
    for (k, e) in sub.episodes.iter().enumerate() {
        for t in 0..e.len {
            for a in 0..n {
                s.base.extend_from_slice(&e.obs[(t * n + a) * od..(t * n + a + 1) * od]);
                if let Some(m) = &prev_msgs {
                    s.base.extend_from_slice(&m[k][(t * n + a) * prev_md..(t * n + a + 1) * prev_md]);
                }
            }
            for j in 0..n {
                // Sender j's block as received by agent r = j+1 (mod n).
                let r = (j + 1) % n;
                let pos = if j < r { j } else { j - 1 };
                let at = (t * n + r) * pmd + pos * width;
                s.cand.extend_from_slice(&probe_msgs[k][at..at + width]);
            }
            s.y.extend(targets.iter().map(|&d| e.state[t * sd + d]));
            s.rows += 1;
        }
    }
    debug_assert_eq!(s.base.len(), s.rows * n * base_w);
    Ok(s)
}

/// Mean and std of columns (for correlations).
pub(super) fn moments(v: &[f32], w: usize, rows: usize) -> (Vec<f64>, Vec<f64>) {
    let m = crate::stats::ColumnMoments::of_flat(v, w, rows);
    (m.mean, m.sd)
}

/// Keep the `keep` candidates with the largest weighted squared marginal correlation between
/// another agent's value and the targets (a cheap filter before the joint least squares).
pub(super) fn prescreen(s: &Sampled, n: usize, width: usize, cands: &[Candidate], w: &[Vec<f64>], keep: usize) -> Vec<usize> {
    let t = w[0].len();
    let cw = n * width;
    let (cm, csd) = moments(&s.cand, cw, s.rows);
    let (ym, ysd) = moments(&s.y, t, s.rows);
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
    let rows = s.rows.max(1) as f64;
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

/// The joint covariance over every agent's base, its kept candidate columns, and the targets.
pub(super) fn covariance(s: &Sampled, n: usize, base_w: usize, width: usize, cols: Vec<usize>) -> Stats {
    let t = s.y.len() / s.rows.max(1);
    let aw = base_w + cols.len();
    let p = n * aw + t;
    let mut mean = vec![0f64; p];
    let mut x = vec![0f64; p];
    let fill = |r: usize, x: &mut [f64]| {
        for a in 0..n {
            let b = &s.base[(r * n + a) * base_w..(r * n + a + 1) * base_w];
            for (c, &v) in b.iter().enumerate() {
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
            let row = &mut cov[a * p..a * p + a + 1];
            for (c, &xb) in row.iter_mut().zip(&x[..=a]) {
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
    Stats { n, base_w, cols, t, cov, p }
}

/// One chosen candidate: who sends it to whom, and what it gained.
#[derive(Clone, Debug)]
pub(super) struct Pick {
    pub(super) cand: usize,
    /// links[j][i]: j sends it to i.
    pub(super) links: Vec<Vec<bool>>,
    pub(super) gain: f64,
}

/// Greedy selection (see the module doc). `w[i][d]`: weight of receiver i and target d.
pub(super) fn select(
    stats: &Stats,
    cands: &[Candidate],
    kept: &[usize],
    w: &[Vec<f64>],
    columns: usize,
    cfg: &OfflineConfig,
) -> (Vec<Pick>, Vec<String>) {
    let (n, p, t) = (stats.n, stats.p, stats.t);
    let orig_var: Vec<f64> = (0..p).map(|k| stats.cov[k * p + k]).collect();
    let targets: Vec<usize> = (0..t).map(|d| stats.target(d)).collect();
    let total_w: f64 = w.iter().flatten().sum::<f64>().max(1e-12);
    // Per receiver: the covariance given what it already knows.
    let mut cond: Vec<Vec<f64>> = (0..n)
        .map(|i| {
            let mut c = stats.cov.clone();
            for k in stats.base(i) {
                sweep(&mut c, p, k, orig_var[k]);
            }
            c
        })
        .collect();
    let score = |c: &[f64], i: usize, g: &[usize]| -> f64 {
        if g.is_empty() {
            return 0.0;
        }
        let ex = explained(c, p, g, &targets, &orig_var);
        ex.iter().enumerate().map(|(d, e)| w[i][d] * e / orig_var[targets[d]].max(1e-12)).sum()
    };
    let vars = |c: &Candidate, j: usize| -> Vec<usize> { (c.col..c.col + c.width).filter_map(|col| stats.cand(j, col)).collect() };
    let mut picks: Vec<Pick> = Vec::new();
    let mut log = Vec::new();
    let mut left = columns;
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
            let top = pair.iter().flatten().cloned().fold(0f64, f64::max);
            let links: Vec<Vec<bool>> =
                (0..n).map(|j| (0..n).map(|i| i != j && top > 0.0 && pair[j][i] >= cfg.link_fraction * top).collect()).collect();
            let gain: f64 = (0..n)
                .map(|i| {
                    let g: Vec<usize> = (0..n).filter(|&j| links[j][i]).flat_map(|j| vars(c, j)).collect();
                    score(&cond[i], i, &g)
                })
                .sum::<f64>()
                / total_w;
            let per_col = gain / c.width as f64;
            if best.as_ref().is_none_or(|(b, _)| per_col > *b) {
                best = Some((per_col, Pick { cand: k, links, gain }));
            }
        }
        let Some((per_col, pick)) = best else { break };
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
