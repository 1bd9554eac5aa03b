//! The offline designer: the embedded default that needs no network. It is not an LLM and
//! does not pretend to be one; every protocol it writes says "offline designer: ..." and
//! explains its numbers. It designs from the data, deterministically:
//!
//! 1. **Targets and weights.** Phase 0 trains the no-message discriminator on B and takes the
//!    state dims agents recover worst without messages as the task-critical set: mean E_t[chi]
//!    over agents relative to a constant guess ([`meta::skill`]) below
//!    [`OfflineConfig::poor_threshold`] (raw rates mislead on sparse dims: an LBF cell that is
//!    empty 97% of the time is "recovered" 97% of the time by guessing 0). Phase 1
//!    (recognition) takes the dims the meta-information shows still poorly recovered *with* the
//!    messages; phase 2 (sharing) the dims with the largest variance of recovery across agents.
//!    Each (receiving agent i, dim d) gets a weight: its failure rate 1 - E_t[chi] divided by
//!    the constant guess's (phases 0, 1), or in phase 2 its gap to the best agent plus a tenth
//!    of its failure rate, on the same scale (so lagging agents count most).
//! 2. **Candidate features**, each computed by the runner's own compiled plan on B (a probe
//!    protocol, so values match what the runner would send exactly): phase 0 the sender's
//!    current observation dims and its last action; phase 1 also history aggregates of each
//!    observation dim (max, mean and most recent non-zero over 5 steps, the previous step, the
//!    change over 3 steps); phase 2 temporal cues over the last 10 steps (max, mean, most recent
//!    non-zero, and the action histogram), as the paper's reference phase-2 protocol uses.
//! 3. **Greedy least-squares selection.** On a sample of steps, the covariance of every agent's
//!    own observation, the messages it already receives, every sender's candidates and the
//!    target dims is computed once. For each receiver, what it already knows (own observation
//!    and earlier phases' messages) is partialled out (the sweep operator); a candidate's gain
//!    is the weighted fraction of target variance the other agents' values of it explain on
//!    top (linear R^2). The candidate with the best gain per message column is added while it
//!    fits this phase's share of the budget (the budget left divided by the phases left) and
//!    gains at least [`OfflineConfig::min_gain`] per column. A candidate is broadcast when every
//!    sender -> receiver link helps; otherwise only the helping links are kept (peer to peer).
//!
//! Feedback is generated from the meta-information as text with the actual numbers.

use super::discriminator::DiscriminatorConfig;
use super::meta::{self, Recovery};
use super::{DesignContext, Designer, Feedback, PhaseProtocol, TranscriptEntry};
use anyhow::{anyhow, bail, Context, Result};
use lmac_protocol_runner::protocol::{
    self, ActionEncoding, DimSpec, Expr, Field, HistoryPadding, PeerLink, Protocol, ProtocolEnv, Receivers, Senders, ValidatedProtocol,
    Window, WindowOp,
};
use serde::{Deserialize, Serialize};
use serde_json::Value;
use std::collections::BTreeMap;

/// The offline designer's knobs.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OfflineConfig {
    /// The discriminator that measures no-message recovery for phase 0.
    pub discriminator: DiscriminatorConfig,
    /// A dim is poorly recovered when its mean E_t[chi] over agents, relative to a constant
    /// guess ([`meta::skill`]: 0 = no better than guessing, 1 = always right), is below this.
    pub poor_threshold: f64,
    /// Most critical dims phase 0 lists.
    pub max_critical_dims: usize,
    /// Most target dims one phase's feature selection aims at (the worst ones).
    pub max_targets: usize,
    /// Most steps of B the statistics use (a deterministic spread of episodes).
    pub max_samples: usize,
    /// Candidates kept after the marginal-correlation prescreen.
    pub prescreen: usize,
    /// Smallest weighted R^2 gain per message column worth sending (0.004: a column must explain
    /// at least 0.4% of the weighted target variance; below that the picks were artefacts such
    /// as padding-driven "first step" indicators in the synthetic tests).
    pub min_gain: f64,
    /// A sender -> receiver link is kept when it explains at least this fraction of the best
    /// link's gain for the candidate.
    pub link_fraction: f64,
    /// Phases the budget is shared between (the paper's 3).
    pub phases: usize,
}

impl Default for OfflineConfig {
    fn default() -> Self {
        OfflineConfig {
            discriminator: DiscriminatorConfig::default(),
            poor_threshold: 0.8,
            max_critical_dims: 48,
            max_targets: 24,
            max_samples: 20_000,
            prescreen: 48,
            min_gain: 0.004,
            link_fraction: 0.1,
            phases: 3,
        }
    }
}

/// The embedded designer (see the module doc).
pub struct OfflineDesigner {
    cfg: OfflineConfig,
    transcript: Vec<TranscriptEntry>,
}

impl OfflineDesigner {
    pub fn new(cfg: OfflineConfig) -> Self {
        OfflineDesigner { cfg, transcript: Vec::new() }
    }

    pub fn config(&self) -> &OfflineConfig {
        &self.cfg
    }

    fn log(&mut self, phase: usize, kind: &str, prompt: String, reply: String) {
        self.transcript.push(TranscriptEntry { phase, kind: kind.into(), prompt, reply });
    }
}

impl Default for OfflineDesigner {
    fn default() -> Self {
        Self::new(OfflineConfig::default())
    }
}

// ------------------------------------------------------------------------------------------
// Candidates

/// What a candidate computes from one sender's observation history.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
enum Kind {
    /// The current value of observation dims.
    Obs,
    /// A window aggregate of observation dims.
    Win(WinOp, usize),
    /// The last action, one-hot.
    LastAction,
    /// The fraction of the last k steps each action was taken.
    ActionHistogram(usize),
}

/// `WindowOp` with an order (for grouping fields deterministically).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
enum WinOp {
    Max,
    Mean,
    LastNonzero,
    Last,
    Delta,
}

impl WinOp {
    fn op(self) -> WindowOp {
        match self {
            WinOp::Max => WindowOp::Max,
            WinOp::Mean => WindowOp::Mean,
            WinOp::LastNonzero => WindowOp::LastNonzero,
            WinOp::Last => WindowOp::Last,
            WinOp::Delta => WindowOp::Delta,
        }
    }
}

impl Kind {
    /// Field name stem and description stem.
    fn words(self) -> (String, String) {
        match self {
            Kind::Obs => ("obs".into(), "the sender's current observation".into()),
            Kind::Win(WinOp::Max, k) => {
                (format!("max{k}"), format!("the highest value over the sender's last {k} steps of its observation"))
            }
            Kind::Win(WinOp::Mean, k) => (format!("mean{k}"), format!("the mean over the sender's last {k} steps of its observation")),
            Kind::Win(WinOp::LastNonzero, k) => {
                (format!("recent{k}"), format!("the most recent non-zero value within the sender's last {k} steps of its observation"))
            }
            Kind::Win(WinOp::Last, k) => (format!("back{}", k - 1), format!("the sender's observation {} step(s) ago", k - 1)),
            Kind::Win(WinOp::Delta, k) => (format!("delta{k}"), format!("the change over the sender's last {k} steps of its observation")),
            Kind::LastAction => ("last_action".into(), "the sender's previous action (one-hot; zero on the first step)".into()),
            Kind::ActionHistogram(k) => {
                (format!("action_hist{k}"), format!("the fraction of the sender's last {k} steps in which it took each action"))
            }
        }
    }

    /// The expression of this kind over observation `dims` (ignored for action kinds).
    fn expr(self, dims: &[usize]) -> Expr {
        match self {
            Kind::Obs => Expr::Obs(dims.to_vec()),
            Kind::Win(op, k) => Expr::Window(Window { op: op.op(), k, of: Box::new(Expr::Obs(dims.to_vec())) }),
            Kind::LastAction => Expr::LastAction(ActionEncoding::OneHot),
            Kind::ActionHistogram(k) => {
                Expr::Window(Window { op: WindowOp::Mean, k, of: Box::new(Expr::LastAction(ActionEncoding::OneHot)) })
            }
        }
    }

    fn per_dim(self) -> bool {
        matches!(self, Kind::Obs | Kind::Win(..))
    }
}

/// One candidate: a kind over one observation dim (or an action kind), `width` columns.
#[derive(Clone, Debug)]
struct Candidate {
    kind: Kind,
    dim: Option<usize>,
    width: usize,
    /// First column of its values in a sender's probe block.
    col: usize,
}

/// The candidate kinds of a phase.
fn kinds_for(phase: usize) -> Vec<Kind> {
    match phase {
        0 => vec![Kind::Obs, Kind::LastAction],
        1 => vec![
            Kind::Obs,
            Kind::Win(WinOp::Max, 5),
            Kind::Win(WinOp::Mean, 5),
            Kind::Win(WinOp::LastNonzero, 5),
            Kind::Win(WinOp::Last, 2),
            Kind::Win(WinOp::Delta, 3),
        ],
        _ => vec![Kind::Win(WinOp::Max, 10), Kind::Win(WinOp::Mean, 10), Kind::Win(WinOp::LastNonzero, 10), Kind::ActionHistogram(10)],
    }
}

/// The probe protocol: one field per kind, every sender broadcasting every candidate without
/// one-hot, so each receiver's block for sender j holds j's candidate values.
fn probe(kinds: &[Kind], env: &ProtocolEnv) -> Result<(ValidatedProtocol, ProtocolEnv, Vec<Candidate>)> {
    let all: Vec<usize> = (0..env.obs_dim).collect();
    let mut fields = Vec::new();
    let mut cands = Vec::new();
    let mut col = 0;
    for (f, &kind) in kinds.iter().enumerate() {
        fields.push(Field {
            name: format!("probe{f}"),
            description: "candidate".into(),
            senders: Senders::All,
            receivers: Receivers::Broadcast,
            value: kind.expr(&all),
        });
        if kind.per_dim() {
            for d in 0..env.obs_dim {
                cands.push(Candidate { kind, dim: Some(d), width: 1, col: col + d });
            }
            col += env.obs_dim;
        } else {
            cands.push(Candidate { kind, dim: None, width: env.n_actions, col });
            col += env.n_actions;
        }
    }
    let p = Protocol {
        name: Some("offline_probe".into()),
        phase: None,
        message_design_instruction: "offline designer: probe of candidate features (never sent)".into(),
        critical_state_dims: vec![DimSpec::Range(protocol::Slice { start: 0, end: env.state_dim })],
        critical_state_reasoning: None,
        sender_one_hot: false,
        history_padding: HistoryPadding::default(),
        fields,
    };
    let mut penv = env.clone();
    penv.message_budget = usize::MAX / 4;
    let v = protocol::validate(&p, &penv)
        .map_err(|e| anyhow!("offline designer: its probe protocol is invalid (a bug): {}", protocol::errors_to_text(&e)))?;
    Ok((v, penv, cands))
}

// ------------------------------------------------------------------------------------------
// Statistics

/// Sweep pivot `k` out of the symmetric matrix `c` (size p): the rest becomes the covariance
/// conditional on variable k (linear partial covariance). Skips near-constant pivots.
fn sweep(c: &mut [f64], p: usize, k: usize, orig_var: f64) -> bool {
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
fn explained(c: &[f64], p: usize, g: &[usize], targets: &[usize], orig_var: &[f64]) -> Vec<f64> {
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
struct Stats {
    n: usize,
    base_w: usize,
    /// Candidate columns kept per sender (after the prescreen), as probe-block columns.
    cols: Vec<usize>,
    t: usize,
    /// Covariance over [agent 0: base, cand | agent 1: base, cand | ... | targets].
    cov: Vec<f64>,
    p: usize,
}

impl Stats {
    fn agent_w(&self) -> usize {
        self.base_w + self.cols.len()
    }
    fn base(&self, a: usize) -> std::ops::Range<usize> {
        let s = a * self.agent_w();
        s..s + self.base_w
    }
    /// Covariance index of sender j's probe column `col` (None if prescreened out).
    fn cand(&self, j: usize, col: usize) -> Option<usize> {
        self.cols.iter().position(|&c| c == col).map(|k| j * self.agent_w() + self.base_w + k)
    }
    fn target(&self, d: usize) -> usize {
        self.n * self.agent_w() + d
    }
}

/// Rows of sampled steps: (base per agent, candidates per agent, targets), streamed to `f`.
struct Sampled {
    /// per row: n * base_w
    base: Vec<f32>,
    /// per row: n * probe width
    cand: Vec<f32>,
    /// per row: targets
    y: Vec<f32>,
    rows: usize,
}

/// Compute the sampled rows: episodes spread evenly over B until `max_samples` steps.
fn sample(
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
    let sub = super::dataset::Dataset { header: h.clone(), episodes: chosen.iter().map(|&e| data.episodes[e].clone()).collect() };
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

/// Mean and inverse std of columns (for correlations).
fn moments(v: &[f32], w: usize, rows: usize) -> (Vec<f64>, Vec<f64>) {
    let mut m = vec![0f64; w];
    let mut q = vec![0f64; w];
    for r in 0..rows {
        for c in 0..w {
            let x = v[r * w + c] as f64;
            m[c] += x;
            q[c] += x * x;
        }
    }
    let n = rows.max(1) as f64;
    let mut sd = vec![0f64; w];
    for c in 0..w {
        m[c] /= n;
        sd[c] = (q[c] / n - m[c] * m[c]).max(0.0).sqrt();
    }
    (m, sd)
}

/// Keep the `keep` candidates with the largest weighted squared marginal correlation between
/// another agent's value and the targets (a cheap filter before the joint least squares).
fn prescreen(s: &Sampled, n: usize, width: usize, cands: &[Candidate], w: &[Vec<f64>], keep: usize) -> Vec<usize> {
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
fn covariance(s: &Sampled, n: usize, base_w: usize, width: usize, cols: Vec<usize>) -> Stats {
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
struct Pick {
    cand: usize,
    /// links[j][i]: j sends it to i.
    links: Vec<Vec<bool>>,
    gain: f64,
}

/// Greedy selection (see the module doc). `w[i][d]`: weight of receiver i and target d.
fn select(
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

fn cand_label(c: &Candidate) -> String {
    let (stem, _) = c.kind.words();
    match c.dim {
        Some(d) => format!("{stem}(o[{d}])"),
        None => stem,
    }
}

// ------------------------------------------------------------------------------------------
// Protocol assembly

fn short(s: &str) -> String {
    let s = s.trim();
    if s.chars().count() <= 80 {
        s.to_string()
    } else {
        format!("{}...", s.chars().take(77).collect::<String>())
    }
}

fn links_text(links: &[Vec<bool>]) -> String {
    let n = links.len();
    if (0..n).all(|j| (0..n).all(|i| i == j || links[j][i])) {
        return "broadcast by every agent".into();
    }
    let parts: Vec<String> = (0..n)
        .filter_map(|j| {
            let to: Vec<String> = (0..n).filter(|&i| links[j][i]).map(|i| i.to_string()).collect();
            (!to.is_empty()).then(|| format!("{j} -> {}", to.join(",")))
        })
        .collect();
    format!("peer to peer ({})", parts.join("; "))
}

/// Fields from the picks: one per (kind, link pattern), observation dims in increasing order.
fn fields_from(picks: &[Pick], cands: &[Candidate], env: &ProtocolEnv) -> Vec<Field> {
    let n = env.n_agents;
    let mut groups: BTreeMap<(Kind, Vec<Vec<bool>>), Vec<usize>> = BTreeMap::new();
    for p in picks {
        let c = &cands[p.cand];
        groups.entry((c.kind, p.links.clone())).or_default().extend(c.dim);
    }
    let mut fields = Vec::new();
    let mut used: BTreeMap<String, usize> = BTreeMap::new();
    for ((kind, links), mut dims) in groups {
        dims.sort_unstable();
        let (stem, what) = kind.words();
        let k = used.entry(stem.clone()).or_insert(0);
        *k += 1;
        let name = if *k == 1 { stem } else { format!("{stem}_{k}") };
        let broadcast = (0..n).all(|j| (0..n).all(|i| i == j || links[j][i]));
        let senders_list: Vec<usize> = (0..n).filter(|&j| links[j].iter().any(|&x| x)).collect();
        let (senders, receivers) = if broadcast {
            (Senders::All, Receivers::Broadcast)
        } else {
            let peers = senders_list.iter().map(|&j| PeerLink { from: j, to: (0..n).filter(|&i| links[j][i]).collect() }).collect();
            (Senders::List(senders_list), Receivers::Peer(peers))
        };
        let description = if kind.per_dim() {
            let names: Vec<String> = dims
                .iter()
                .map(|&d| format!("o[{d}] ({})", env.obs_names.get(d).map(|s| short(s)).unwrap_or_else(|| "unnamed".into())))
                .collect();
            format!("{what}, dims {}; {}", names.join(", "), links_text(&links))
        } else {
            format!("{what}; {}", links_text(&links))
        };
        fields.push(Field { name, description, senders, receivers, value: kind.expr(&dims) });
    }
    fields
}

// ------------------------------------------------------------------------------------------
// Reading the meta-information

/// Per target dim of a meta JSON: (state dim, per-agent rates, variance across agents, the
/// largest per-third variance with its third), with communication.
struct MetaDim {
    dim: usize,
    /// E[chi] of a constant guess (0 when the JSON does not say).
    guess: f64,
    rates: Vec<f64>,
    rates_without: Vec<f64>,
    variance: f64,
    worst_third: (f64, &'static str),
}

fn parse_dim(label: &str) -> Option<usize> {
    let rest = label.strip_prefix("s[")?;
    rest[..rest.find(']')?].parse().ok()
}

fn floats(v: &Value) -> Vec<f64> {
    v.as_array().map(|a| a.iter().filter_map(|x| x.as_f64()).collect()).unwrap_or_default()
}

fn meta_dims(meta: &Value) -> Result<Vec<MetaDim>> {
    let dims = meta["dimensions"].as_array().ok_or_else(|| anyhow!("the meta-information has no \"dimensions\" list"))?;
    dims.iter()
        .enumerate()
        .map(|(k, d)| {
            let label = d["dimension"].as_str().unwrap_or_default();
            let dim = parse_dim(label)
                .ok_or_else(|| anyhow!("meta-information dimensions[{k}]: \"dimension\" {label:?} does not start with s[<index>]"))?;
            let w = &d["with_communication"];
            let rates = floats(&w["agent_success_rates"]);
            if rates.is_empty() {
                bail!("meta-information dimensions[{k}] ({label}): with_communication.agent_success_rates is missing or empty");
            }
            let worst_third = meta::THIRDS
                .iter()
                .map(|th| (w[format!("variance_in_{th}")].as_f64().unwrap_or(0.0), *th))
                .fold((f64::MIN, "early"), |a, b| if b.0 > a.0 { b } else { a });
            Ok(MetaDim {
                dim,
                guess: d["constant_guess_rate"].as_f64().unwrap_or(0.0),
                variance: meta::variance(&rates),
                rates,
                rates_without: floats(&d["without_communication"]["agent_success_rates"]),
                worst_third,
            })
        })
        .collect()
}

impl MetaDim {
    fn skill(&self) -> f64 {
        meta::skill(meta::mean(&self.rates), self.guess)
    }
}

/// Failure of rate `r` on the scale of the constant guess's failure, in [0, 1] (0 for a dim the
/// guess always gets right: nothing to gain there).
fn failure(r: f64, guess: f64) -> f64 {
    if guess >= 1.0 - 1e-9 {
        0.0
    } else {
        ((1.0 - r) / (1.0 - guess)).clamp(0.0, 1.0)
    }
}

fn fmt_rates(r: &[f64]) -> String {
    format!("[{}]", r.iter().map(|x| format!("{x:.2}")).collect::<Vec<_>>().join(", "))
}

// ------------------------------------------------------------------------------------------
// The designer

/// Targets with their per-agent rates, ordered as chosen.
struct Targets {
    dims: Vec<usize>,
    /// weights[i][k] for receiver i and target k.
    weights: Vec<Vec<f64>>,
    why: String,
}

impl OfflineDesigner {
    /// Build, validate and explain one phase's protocol for `targets`.
    fn design(
        &mut self,
        ctx: &DesignContext,
        phase: usize,
        previous: &[PhaseProtocol],
        targets: Targets,
        critical: &[usize],
    ) -> Result<PhaseProtocol> {
        let env = ctx.env;
        let n = env.n_agents;
        if n < 2 {
            // Every width below is per other agent; with one agent there is no one to talk to.
            bail!("offline designer: {} has {n} agent(s); a communication protocol needs at least 2", ctx.env_name);
        }
        let prev: Vec<ValidatedProtocol> = previous.iter().map(|p| p.validated.clone()).collect();
        let left = super::prompts::budget_left(env, &prev);
        let phases_left = self.cfg.phases.saturating_sub(phase).max(1);
        let share = left / phases_left;
        let per_block = (share / n.saturating_sub(1).max(1)).saturating_sub(n);
        if per_block == 0 {
            bail!(
                "offline designer: no message budget for phase {phase}: {left} of {} columns are left, this phase's share is {share}, and one sender block needs {n} one-hot columns plus at least one value column for each of the {} other agents",
                env.message_budget,
                n - 1
            );
        }
        let kinds = kinds_for(phase);
        let (probe_v, probe_env, cands) = probe(&kinds, env)?;
        let width = probe_v.width / (n - 1);
        let s = sample(ctx, &prev, &probe_v, &probe_env, width, &targets.dims, self.cfg.max_samples)?;
        if s.rows < 2 {
            bail!("offline designer: the dataset has {} usable steps; it needs at least 2", s.rows);
        }
        let kept = prescreen(&s, n, width, &cands, &targets.weights, self.cfg.prescreen);
        let mut cols: Vec<usize> = kept.iter().flat_map(|&k| cands[k].col..cands[k].col + cands[k].width).collect();
        cols.sort_unstable();
        let base_w = s.base.len() / (s.rows * n);
        let stats = covariance(&s, n, base_w, width, cols);
        let (picks, steps) = select(&stats, &cands, &kept, &targets.weights, per_block, &self.cfg);
        if picks.is_empty() {
            bail!("offline designer: no candidate feature fits the {per_block} value columns per sender block of phase {phase}");
        }
        let fields = fields_from(&picks, &cands, env);
        let total_gain: f64 = picks.iter().map(|p| p.gain).sum();
        let names = ctx.schema.state_meanings();
        let target_text: Vec<String> = targets.dims.iter().take(8).map(|&d| meta::dim_label(d, &names)).map(|l| short(&l)).collect();
        let goal = match phase {
            0 => "initialization",
            1 => "recognition enhancement",
            _ => "sharing enhancement",
        };
        let field_text: Vec<String> = fields.iter().map(|f| format!("'{}': {}", f.name, f.description)).collect();
        let instruction = format!(
            "offline designer: phase {phase} ({goal}), chosen by greedy least squares on the dataset, not by an LLM. {} Each agent sends: {}. Together these explain an estimated {:.1}% of the weighted variance of the {} target state dims that receivers could not explain from their own observation{} (linear R^2 on {} sampled steps). Every sender block starts with the sender's one-hot id.",
            targets.why,
            field_text.join("; "),
            100.0 * total_gain,
            targets.dims.len(),
            if prev.is_empty() { "" } else { " and the earlier phases' messages" },
            s.rows,
        );
        let mut crit: Vec<usize> = critical.to_vec();
        crit.sort_unstable();
        crit.dedup();
        let p = Protocol {
            name: Some(format!("offline_phase{phase}")),
            phase: Some(phase as u32),
            message_design_instruction: instruction,
            critical_state_dims: crit.iter().map(|&d| DimSpec::Dim(d)).collect(),
            critical_state_reasoning: Some(format!("offline designer: {} Targets (first 8): {}.", targets.why, target_text.join("; "))),
            sender_one_hot: true,
            history_padding: HistoryPadding::default(),
            fields,
        };
        let validated = protocol::validate_phase(&p, env, &prev)
            .map_err(|e| anyhow!("offline designer: its phase {phase} protocol is invalid (a bug): {}", protocol::errors_to_text(&e)))?;
        let reasoning = format!(
            "# Offline designer, phase {phase} ({goal})\n\nThis protocol was built by a deterministic algorithm (greedy least-squares feature selection over the dataset), not by a language model.\n\n## Targets\n{}\n\n{}\n\n## Budget\n{left} message columns left of {}; this phase's share is {share} ({phases_left} phase(s) left), i.e. {per_block} value columns per sender block after the {n}-column sender one-hot.\n\n## Candidates\n{} candidate features ({}), {} kept by the marginal-correlation prescreen, {} sampled steps.\n\n## Selection\n{}\n\nResulting width: {} columns per receiving agent.\n",
            targets.dims.iter().map(|&d| format!("- {}", meta::dim_label(d, &names))).collect::<Vec<_>>().join("\n"),
            targets.why,
            env.message_budget,
            cands.len(),
            kinds.iter().map(|k| k.words().0).collect::<Vec<_>>().join(", "),
            kept.len(),
            s.rows,
            steps.iter().map(|l| format!("- {l}")).collect::<Vec<_>>().join("\n"),
            validated.width,
        );
        self.log(
            phase,
            "protocol",
            format!(
                "offline designer: select features for phase {phase} ({goal}); targets {:?}; {per_block} value columns per sender block",
                targets.dims
            ),
            serde_json::to_string_pretty(&p)?,
        );
        Ok(PhaseProtocol { protocol: p, validated, reasoning })
    }
}

/// Targets from the worst entries of `scored` (dim, score, per-agent weights), ascending score.
fn worst(mut scored: Vec<(usize, f64, Vec<f64>)>, max: usize) -> (Vec<usize>, Vec<Vec<f64>>) {
    scored.sort_by(|a, b| a.1.partial_cmp(&b.1).unwrap_or(std::cmp::Ordering::Equal).then(a.0.cmp(&b.0)));
    scored.truncate(max);
    let n = scored.first().map(|s| s.2.len()).unwrap_or(0);
    let dims = scored.iter().map(|s| s.0).collect();
    let weights = (0..n).map(|i| scored.iter().map(|s| s.2[i]).collect()).collect();
    (dims, weights)
}

impl Designer for OfflineDesigner {
    fn name(&self) -> String {
        "offline".into()
    }

    fn needs_data_for_initial(&self) -> bool {
        true
    }

    fn initial(&mut self, ctx: &DesignContext) -> Result<PhaseProtocol> {
        let m = meta::measure(ctx, &[], &self.cfg.discriminator, &[]).context("offline designer: measuring recovery without messages")?;
        let r: &Recovery = &m.without;
        let n = r.n_agents;
        let thr = self.cfg.poor_threshold;
        let g = &m.guess;
        // Constant dims (the guess is always right) can never be critical.
        let all: Vec<(usize, f64, Vec<f64>)> = (0..r.dims.len())
            .filter(|&k| g[k] < 1.0 - 1e-9)
            .map(|k| (r.dims[k], meta::skill(r.mean_rate(k), g[k]), r.rates(k).iter().map(|&x| failure(x, g[k])).collect()))
            .collect();
        if all.is_empty() {
            bail!("offline designer: every state dim is constant on the dataset, so there is nothing for messages to recover");
        }
        let poor: Vec<_> = all.iter().filter(|x| x.1 < thr).cloned().collect();
        let (critical, why) = if poor.is_empty() {
            let (d, _) = worst(all.clone(), 8.min(all.len()));
            (d, format!("Without messages every varying state dim is recovered with a skill of at least {thr} over a constant guess (E_t[chi], alpha {}), so the 8 least recovered are targeted.", ctx.schema.alpha))
        } else {
            let (d, _) = worst(poor.clone(), self.cfg.max_critical_dims);
            let why = format!(
                "Without messages, {} of {} varying state dims are recovered with a skill below {thr} (mean E_t[chi] over agents on held-out steps, alpha {}, relative to always guessing the dim's median: 0 = no better than the guess); the {} worst are taken as task-critical.",
                poor.len(), all.len(), ctx.schema.alpha, d.len()
            );
            (d, why)
        };
        let pool: Vec<_> = all.iter().filter(|x| critical.contains(&x.0)).cloned().collect();
        let (dims, weights) = worst(pool, self.cfg.max_targets);
        debug_assert_eq!(weights.len(), n);
        let names = ctx.schema.state_meanings();
        let listing: Vec<String> = critical
            .iter()
            .map(|&d| {
                let k = r.position(d).unwrap_or(0);
                format!("{} (mean E_t[chi] without messages {:.3}, constant guess {:.3})", meta::dim_label(d, &names), r.mean_rate(k), g[k])
            })
            .collect();
        self.log(
            0,
            "critical_dims",
            format!("offline designer: train the no-message discriminator on {} training episodes and measure E_t[chi] on {} held-out episodes for every state dim", m.without_report.train_episodes, m.held_out.len()),
            format!("{why}\n{}", listing.join("\n")),
        );
        self.design(ctx, 0, &[], Targets { dims, weights, why }, &critical)
    }

    fn feedback(&mut self, ctx: &DesignContext, phase: usize, _previous: &[PhaseProtocol], meta_v: &Value) -> Result<Feedback> {
        let dims = meta_dims(meta_v)?;
        let names = ctx.schema.state_meanings();
        let s = &meta_v["summary"];
        let g = |side: &str, key: &str| s[side][key].as_f64().unwrap_or(f64::NAN);
        let (rw, ro, vw, vo) = (
            g("with_communication", "mean_recovery"),
            g("without_communication", "mean_recovery"),
            g("with_communication", "mean_variance_across_agents"),
            g("without_communication", "mean_variance_across_agents"),
        );
        let mut by_rate: Vec<&MetaDim> = dims.iter().collect();
        by_rate.sort_by(|a, b| a.skill().partial_cmp(&b.skill()).unwrap_or(std::cmp::Ordering::Equal));
        let mut by_gain: Vec<&MetaDim> = dims.iter().collect();
        let gain = |d: &MetaDim| meta::mean(&d.rates) - meta::mean(&d.rates_without);
        by_gain.sort_by(|a, b| gain(b).partial_cmp(&gain(a)).unwrap_or(std::cmp::Ordering::Equal));
        let mut by_var: Vec<&MetaDim> = dims.iter().collect();
        by_var.sort_by(|a, b| b.variance.partial_cmp(&a.variance).unwrap_or(std::cmp::Ordering::Equal));
        let label = |d: usize| short(&meta::dim_label(d, &names));
        let worst3: Vec<String> = by_rate
            .iter()
            .take(3)
            .map(|d| {
                format!(
                    "{} with {} / without {} (constant guess {:.2})",
                    label(d.dim),
                    fmt_rates(&d.rates),
                    fmt_rates(&d.rates_without),
                    d.guess
                )
            })
            .collect();
        let best3: Vec<String> =
            by_gain.iter().take(3).filter(|d| gain(d) > 0.0).map(|d| format!("{} (+{:.2})", label(d.dim), gain(d))).collect();
        let evaluation = format!(
            "offline designer: over {} target state dims (alpha {}), agents recover {:.3} of held-out steps with the messages against {:.3} without; the variance of recovery across agents is {:.4} with and {:.4} without. Largest gains from the messages: {}. Worst recovered with messages relative to a constant guess: {}.",
            dims.len(),
            meta_v["alpha"],
            rw,
            ro,
            vw,
            vo,
            if best3.is_empty() { "none (the messages do not raise recovery of any target dim)".into() } else { best3.join("; ") },
            worst3.join("; ")
        );
        let thr = self.cfg.poor_threshold;
        let poor: Vec<&&MetaDim> = by_rate.iter().filter(|d| d.skill() < thr).collect();
        let lagging = |d: &MetaDim| -> String {
            let (i, r) = d.rates.iter().enumerate().fold((0, f64::MAX), |a, (i, &r)| if r < a.1 { (i, r) } else { a });
            format!("agent {i} at {r:.2}")
        };
        let missing = if phase <= 1 {
            if poor.is_empty() {
                format!("Every target dim is recovered with a skill of at least {thr} over a constant guess with the messages; what remains is mostly noise in the reconstruction.")
            } else {
                let list: Vec<String> = poor.iter().take(6).map(|d| format!("{} (worst: {})", label(d.dim), lagging(d))).collect();
                format!(
                    "{} target dims stay below a skill of {} over a constant guess with the messages: {}. The senders' current observation does not carry them; they are likely seen only at some steps (when in view) and need to be remembered, so history aggregates of the observation dims that predict them are missing.",
                    poor.len(),
                    thr,
                    list.join("; ")
                )
            }
        } else {
            let list: Vec<String> = by_var
                .iter()
                .take(6)
                .map(|d| {
                    format!(
                        "{} (variance {:.4}, largest in the {} third at {:.4}; {})",
                        label(d.dim),
                        d.variance,
                        d.worst_third.1,
                        d.worst_third.0,
                        lagging(d)
                    )
                })
                .collect();
            format!("Recovery is uneven across agents on: {}. The lagging agents depend on what their teammates saw earlier, which the current messages do not keep once it leaves the teammate's view.", list.join("; "))
        };
        let suggestions = if phase <= 1 {
            "1. Add, for the still poorly recovered dims, the sender features that best predict them beyond what receivers already know: window aggregates over the last 5 steps (max, mean, most recent non-zero), the previous step and short-term changes. 2. Send each only where it helps (peer to peer when only some senders observe the dim). 3. Keep the message compact: stop adding features once they explain little extra variance.".to_string()
        } else {
            "1. Add temporal cues over the last 10 steps (max, mean, most recent non-zero of the observation dims that predict the uneven dims, and the sender's action histogram) so agents that missed an event can still infer it. 2. Weight the choice towards the agents that lag on each dim. 3. Keep the sender one-hot so the receivers know whose history they read.".to_string()
        };
        let fb = Feedback { evaluation, missing_information_hypothesis: missing, improvement_suggestions: suggestions };
        self.log(
            phase,
            "feedback",
            format!("offline designer: feedback from the meta-information of phases 0..={}: {}", phase - 1, meta::summary_line(meta_v)),
            serde_json::to_string_pretty(&fb)?,
        );
        Ok(fb)
    }

    fn refine(
        &mut self,
        ctx: &DesignContext,
        phase: usize,
        previous: &[PhaseProtocol],
        _feedback: &Feedback,
        meta_v: &Value,
    ) -> Result<PhaseProtocol> {
        if phase == 0 {
            bail!("offline designer: refine is for phases 1 and later (phase 0 is `initial`)");
        }
        let dims = meta_dims(meta_v)?;
        if dims.is_empty() {
            bail!("offline designer: the meta-information lists no target dims to improve");
        }
        let n = ctx.env.n_agents;
        if let Some(d) = dims.iter().find(|d| d.rates.len() != n) {
            bail!(
                "offline designer: the meta-information has {} agent rates for s[{}], the environment has {n} agents",
                d.rates.len(),
                d.dim
            );
        }
        let thr = self.cfg.poor_threshold;
        let targets = if phase == 1 {
            let scored: Vec<_> = dims.iter().map(|d| (d.dim, d.skill(), d.rates.iter().map(|&r| failure(r, d.guess)).collect())).collect();
            let poor = scored.iter().filter(|s| s.1 < thr).count();
            let (t, w) = worst(scored, self.cfg.max_targets);
            let why = if poor > 0 {
                format!("Recognition: {poor} target dim(s) are still recovered with a skill below {thr} over a constant guess (held-out steps) with the messages of the earlier phase(s); the {} worst are targeted, each receiver weighted by its failure rate relative to the guess's.", t.len())
            } else {
                format!("Recognition: every target dim is already recovered with a skill of at least {thr} over a constant guess; the {} least recovered are targeted for the remaining errors.", t.len())
            };
            Targets { dims: t, weights: w, why }
        } else {
            // Sharing: largest variance across agents first (score = -variance), weights put on
            // the agents behind the best one.
            let scored: Vec<_> = dims
                .iter()
                .map(|d| {
                    let best = d.rates.iter().cloned().fold(0f64, f64::max);
                    let weights =
                        d.rates.iter().map(|&r| (failure(r, d.guess) - failure(best, d.guess)) + 0.1 * failure(r, d.guess)).collect();
                    (d.dim, -d.variance.max(d.worst_third.0), weights)
                })
                .collect();
            let uneven = dims.iter().filter(|d| d.variance.max(d.worst_third.0) > 1e-4).count();
            let (t, w) = worst(scored, self.cfg.max_targets);
            let why = format!(
                "Sharing: {uneven} target dim(s) show a variance of recovery across agents above 1e-4 (overall or in one third of the episodes); the {} most uneven are targeted, each receiver weighted by its gap to the best agent plus a tenth of its failure rate, with temporal cues over the last 10 steps as candidates.",
                t.len()
            );
            Targets { dims: t, weights: w, why }
        };
        let critical = targets.dims.clone();
        self.design(ctx, phase, previous, targets, &critical)
    }

    fn transcript(&self) -> Vec<TranscriptEntry> {
        self.transcript.clone()
    }
}
