//! Phase 1 by the sender's frame (`--phase1-by frame`, after a whole-entity phase 0).
//!
//! What an agent sees of a unit it sees in its own frame: an offset from itself. Phase 0 sends
//! the sender's view of the entity the return needs (on `smaclite:1o_10b_vs_1r` the Overseer's
//! offset to the Roach); a receiver can act on it only when it also knows where it is itself in
//! the sender's view. So phase 1 finds, from B, which further values of the sender's view turn
//! phase 0's message into each receiver's own view of that entity: on the steps where the
//! receiver sees the entity too (its view is the target), a linear fit of the receiver's view on
//! phase 0's values, then greedily on each other value the sender sees, keeps the values that
//! explain a share of the receiver's view on top; a value equal to one of the receiver's own on
//! every step is never taken. On 1o_10b the fit names each Baneling's offset in the Overseer's
//! view (the authors' phase 1). The receiver could work that offset out itself (SMAC-Comm's
//! sight is symmetric: it is the negative of its own offset to the Overseer), and
//! [`FrameFitConfig::given_own_view`] leaves out everything it could compute linearly, but LMAC
//! trained far worse without it (`docs/results/design.md`), so the default sends it.

use super::assemble::short;
use super::candidates::{Candidate, Kind};
use super::observation_relevance::varies_for;
use super::select::{self, receivers_text, to_receivers_from, Pick};
use super::{DesignContext, OfflineDesigner};
use anyhow::{Context, Result};
use lmac_run::dataset::Dataset;
use std::collections::BTreeMap;

/// Fewest steps a receiver must share with the sender (both seeing the entity) to be fitted.
const MIN_ROWS: usize = 20;

/// What one receiver needs of the sender's view to read phase 0's message in its own frame.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameFit {
    pub receiver: usize,
    /// Steps where the receiver and the sender both see the entity (some of its values non-zero).
    pub rows: usize,
    /// Share of the variance of the receiver's own view of the entity that the rest of its own
    /// observation explains (linear R^2 on those steps; 0 unless [`FrameFitConfig::given_own_view`]).
    pub r2_own: f64,
    /// Share phase 0's values (the sender's view of the entity) add to that.
    pub r2_sent: f64,
    /// The sender's further values, in the order chosen, with the share each adds.
    pub picks: Vec<(usize, f64)>,
    /// Candidates left out because the receiver has them already: on every step of B equal to
    /// one of its own values (sent, they would be dead columns).
    pub copies: Vec<usize>,
}

/// How [`frame_fit`] fits.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameFitConfig {
    /// About this many steps of B, whole episodes spread evenly over it.
    pub max_rows: usize,
    /// Most values one receiver's fit takes.
    pub max_picks: usize,
    /// Smallest share of the target's variance a value must add to be taken.
    pub min_gain: f64,
    /// Fit on top of the rest of the receiver's own observation too, so that nothing it could
    /// compute from its own view linearly is sent. On SMAC-Comm that leaves nothing: sight is
    /// symmetric, so where the Overseer sees a Baneling is the negative of where the Baneling
    /// sees the Overseer. Without it, values the receiver has in another form (the offset in
    /// the sender's frame) are sent, as the authors' phase 1 sends them, and LMAC trains far
    /// better with them (`docs/results/design.md`); exact copies are left out either way.
    pub given_own_view: bool,
}

impl FrameFit {
    pub fn r2(&self) -> f64 {
        self.r2_own + self.r2_sent + self.picks.iter().map(|p| p.1).sum::<f64>()
    }
}

/// For each receiver (every agent but `sender`): which of `candidates` (the sender's o[d])
/// explain the receiver's own view of the entity (its o[d] for d in `sent`) on top of the
/// sender's view of it (the sender's o[sent]) and, with [`FrameFitConfig::given_own_view`], the
/// rest of the receiver's own observation, greedily, each adding at least `min_gain` of the
/// target's variance, at most `max_picks`; never a value the receiver has already (equal to one
/// of its own on every step of B). Fewer than [`MIN_ROWS`] shared steps: no picks.
pub fn frame_fit(data: &Dataset, sender: usize, sent: &[usize], candidates: &[usize], cfg: &FrameFitConfig) -> Vec<FrameFit> {
    let (n, od) = (data.header.n_agents, data.header.obs_dim);
    let own: Vec<usize> = if cfg.given_own_view { (0..od).filter(|d| !sent.contains(d)).collect() } else { Vec::new() };
    let (q, b, k) = (own.len(), sent.len(), candidates.len());
    // Columns: [receiver's own o[own], sender's o[sent], sender's o[candidates], receiver's o[sent]].
    let p = q + 2 * b + k;
    let total: usize = data.steps();
    let stride = total.div_ceil(cfg.max_rows.max(1)).max(1);
    let mut fits = Vec::new();
    for i in (0..n).filter(|&i| i != sender) {
        let (mut sum, mut cross, mut rows) = (vec![0f64; p], vec![0f64; p * p], 0usize);
        let mut row = vec![0f64; p];
        for ep in data.episodes.iter().step_by(stride) {
            for t in 0..ep.len {
                let oj = &ep.obs[(t * n + sender) * od..(t * n + sender + 1) * od];
                let oi = &ep.obs[(t * n + i) * od..(t * n + i + 1) * od];
                if !sent.iter().any(|&d| oj[d] != 0.0) || !sent.iter().any(|&d| oi[d] != 0.0) {
                    continue;
                }
                let values =
                    own.iter().map(|&d| oi[d]).chain(sent.iter().chain(candidates).map(|&d| oj[d])).chain(sent.iter().map(|&d| oi[d]));
                for (x, v) in row.iter_mut().zip(values) {
                    *x = v as f64;
                }
                for r in 0..p {
                    sum[r] += row[r];
                    let xr = row[r];
                    for (c, &xc) in cross[r * p..(r + 1) * p].iter_mut().zip(&row) {
                        *c += xr * xc;
                    }
                }
                rows += 1;
            }
        }
        let is_copy = crate::dead_fields::copies_of_receiver(data, sender, i, candidates);
        let copies = candidates.iter().zip(&is_copy).filter(|x| *x.1).map(|x| *x.0).collect();
        let mut fit = FrameFit { receiver: i, rows, r2_own: 0.0, r2_sent: 0.0, picks: Vec::new(), copies };
        if rows < MIN_ROWS {
            fits.push(fit);
            continue;
        }
        let m = rows as f64;
        let mut cov: Vec<f64> = (0..p * p).map(|x| cross[x] / m - sum[x / p] * sum[x % p] / (m * m)).collect();
        let orig: Vec<f64> = (0..p).map(|r| cov[r * p + r]).collect();
        let targets: Vec<usize> = (q + b + k..p).collect();
        let target_var: f64 = targets.iter().map(|&t| orig[t]).sum();
        if target_var <= 1e-12 {
            fits.push(fit);
            continue;
        }
        let explained = |cov: &[f64]| 1.0 - targets.iter().map(|&t| cov[t * p + t].max(0.0)).sum::<f64>() / target_var;
        for c in 0..q {
            select::sweep(&mut cov, p, c, orig[c]);
        }
        fit.r2_own = explained(&cov);
        for c in q..q + b {
            select::sweep(&mut cov, p, c, orig[c]);
        }
        fit.r2_sent = explained(&cov) - fit.r2_own;
        while fit.picks.len() < cfg.max_picks {
            // A candidate the receiver's own values and the earlier picks determine (left with
            // rounding-level variance) cannot add anything.
            let best = (q + b..q + b + k)
                .filter(|&c| !is_copy[c - q - b] && !fit.picks.iter().any(|x| x.0 == candidates[c - q - b]))
                .filter(|&c| cov[c * p + c] > 1e-6 * orig[c].max(1e-12))
                .map(|c| (c, targets.iter().map(|&t| cov[c * p + t].powi(2)).sum::<f64>() / cov[c * p + c] / target_var))
                .max_by(|x, y| x.1.total_cmp(&y.1).then(y.0.cmp(&x.0)));
            match best {
                Some((c, gain)) if gain >= cfg.min_gain => {
                    select::sweep(&mut cov, p, c, orig[c]);
                    fit.picks.push((candidates[c - q - b], gain));
                }
                _ => break,
            }
        }
        fits.push(fit);
    }
    fits
}

impl OfflineDesigner {
    /// [`Phase1By::Frame`]: phase 1's picks (the sender's values that place each receiver in
    /// its view, to every other agent), the log and how they were chosen; None (said in the log
    /// and the transcript) when phase 0 sent no entity or no value places any receiver, and
    /// least squares chooses instead.
    #[allow(clippy::type_complexity)]
    pub(super) fn fields_by_frame(
        &mut self,
        ctx: &DesignContext,
        cands: &[Candidate],
        room: usize,
    ) -> Result<Option<(Vec<Pick>, Vec<String>, String)>> {
        let data = ctx.dataset.context("offline designer: placing the receivers in the sender's view needs the dataset B")?;
        let n = data.header.n_agents;
        let obs_cand = |d: usize| cands.iter().position(|c| c.kind == Kind::Obs && c.dim == Some(d));
        let label = |d: usize| {
            let sender = self.sent_entity.as_ref().map(|e| e.sender);
            ctx.env.obs_name_of(sender, d).map(short).unwrap_or_else(|| "unnamed".into())
        };
        let Some(sent) = self.sent_entity.clone() else {
            let reason = "phase 0 sent no single entity to place the receivers by (it sent every agent's whole view, or chose its fields by least squares)";
            eprintln!("lmac: offline designer: phase 1's fields by least squares instead: {reason}");
            self.log(1, "fields_by", "offline designer: choose phase 1's fields".into(), format!("By least squares instead: {reason}."));
            return Ok(None);
        };
        let j = sent.sender;
        let candidates: Vec<usize> =
            (0..data.header.obs_dim).filter(|d| !sent.values.contains(d) && obs_cand(*d).is_some() && varies_for(data, j, *d)).collect();
        let given_own_view = self.cfg.frame_given_own_view;
        let fit_cfg = FrameFitConfig {
            max_rows: self.cfg.max_samples,
            max_picks: self.cfg.frame_values_per_receiver,
            min_gain: self.cfg.frame_min_gain,
            given_own_view,
        };
        let receivers = self.receivers();
        let links = to_receivers_from(n, j, &receivers);
        // Only the receivers the sender's values go to are placed.
        let fits: Vec<FrameFit> =
            frame_fit(data, j, &sent.values, &candidates, &fit_cfg).into_iter().filter(|f| links[j][f.receiver]).collect();
        // Each value by the share it adds, summed over the receivers it places.
        let mut by_value: BTreeMap<usize, (f64, Vec<usize>)> = BTreeMap::new();
        for f in &fits {
            for &(d, g) in &f.picks {
                let e = by_value.entry(d).or_default();
                e.0 += g;
                e.1.push(f.receiver);
            }
        }
        let mut ranked: Vec<(usize, f64)> = by_value.iter().map(|(&d, x)| (d, x.0)).collect();
        ranked.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
        let kept: Vec<usize> = {
            let mut k: Vec<usize> = ranked.iter().take(room).map(|x| x.0).collect();
            k.sort_unstable();
            k
        };
        let mut lines: Vec<String> = fits
            .iter()
            .map(|f| {
                if f.rows < MIN_ROWS {
                    return format!("agent {}: sees it together with agent {j} on {} steps of B, too few to fit", f.receiver, f.rows);
                }
                let picks: Vec<String> = f.picks.iter().map(|&(d, g)| format!("o[{d}] ({}) {g:+.3}", label(d))).collect();
                let own = if given_own_view {
                    format!("the rest of its own view explains {:.3} of its view of it, ", f.r2_own)
                } else {
                    String::new()
                };
                let copies = if f.copies.is_empty() {
                    String::new()
                } else {
                    let d: Vec<String> = f.copies.iter().map(|d| d.to_string()).collect();
                    format!(" (left out: agent {j}'s o[{}], equal to values it sees itself on every step)", d.join(", "))
                };
                format!(
                    "agent {}: on {} steps where it sees it too, {own}agent {j}'s o[{}] explain {:.3}; {}; R^2 {:.3}{copies}",
                    f.receiver,
                    f.rows,
                    sent.values.iter().map(|d| d.to_string()).collect::<Vec<_>>().join(", "),
                    f.r2_sent,
                    if picks.is_empty() { "no further value adds".to_string() } else { format!("then {}", picks.join(", ")) },
                    f.r2()
                )
            })
            .collect();
        for (d, g) in &ranked {
            let verdict = if kept.contains(d) { "CHOSEN" } else { "not chosen: beyond this phase's share of the budget" };
            lines.push(format!("agent {j}'s o[{d}] ({}): places agent(s) {:?}, {g:.3} summed; {verdict}", label(*d), by_value[d].1));
        }
        let head = format!(
            "Phase 0 sends agent {j}'s view of {}, in agent {j}'s frame. On the steps of B where a receiver sees it too, a linear fit of the receiver's own view of it on {}phase 0's values, then greedily on each other value agent {j} sees that the receiver does not see itself (each adding at least {:.2} of the variance, at most {} per receiver), finds what turns agent {j}'s view into the receiver's: where the receiver is in agent {j}'s view.",
            sent.name,
            if given_own_view { "the rest of its own observation and " } else { "" },
            self.cfg.frame_min_gain,
            self.cfg.frame_values_per_receiver
        );
        self.log(
            1,
            "frame",
            format!("offline designer: find which of agent {j}'s values place each receiver in its view (linear fits on B)"),
            format!("{head}\n{}", lines.join("\n")),
        );
        eprintln!("lmac: offline designer: {head}");
        for line in lines.iter().take(n + 8) {
            eprintln!("lmac:   {line}");
        }
        if kept.is_empty() {
            let reason =
                format!("no value of agent {j}'s view adds {:.2} to any receiver's view of {}", self.cfg.frame_min_gain, sent.name);
            eprintln!("lmac: offline designer: phase 1's fields by least squares instead: {reason}");
            self.log(1, "fields_by", "offline designer: choose phase 1's fields".into(), format!("By least squares instead: {reason}."));
            return Ok(None);
        }
        let mut picks = Vec::new();
        for &d in &kept {
            let cand = obs_cand(d).context("offline designer: a frame value has no candidate (a bug)")?;
            picks.push(Pick { cand, links: links.clone(), gain: by_value[&d].0 / (n - 1) as f64 });
        }
        let how = format!(
            "{head} Phase 1 sends the {} value(s) that place some receiver, from agent {j} to {}.",
            picks.len(),
            receivers_text(j, &receivers)
        );
        Ok(Some((picks, lines, how)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use lmac_learn::LearnRng;
    use lmac_run::dataset::{DatasetHeader, Trajectory};

    /// Three agents on a line; agent 2 sees the target's offset (o[0]) and each teammate's
    /// offset (o[1] agent 0, o[2] agent 1) plus noise (o[3]); an agent sees the target when it
    /// is within 1. The receiver's view of the target is the sender's minus the receiver's
    /// offset: the fit must name each receiver's own slot, and only it.
    #[test]
    fn the_fit_names_where_each_receiver_is_in_the_senders_view() {
        let (n, od, len) = (3, 4, 10);
        let mut rng = LearnRng::seed_from(5);
        let episodes: Vec<Trajectory> = (0..200)
            .map(|_| {
                let mut obs = Vec::new();
                for _ in 0..len {
                    let target = rng.uniform() * 2.0 - 1.0;
                    let x = [rng.uniform() * 2.0 - 1.0, rng.uniform() * 2.0 - 1.0, rng.uniform() * 0.4 - 0.2];
                    let seen = |a: usize| if (target - x[a]).abs() < 1.0 { target - x[a] } else { 0.0 };
                    obs.extend([seen(0), 0.0, 0.0, 0.0]);
                    obs.extend([seen(1), 0.0, 0.0, 0.0]);
                    obs.extend([seen(2), x[0] - x[2], x[1] - x[2], rng.uniform()]);
                }
                Trajectory {
                    len,
                    obs,
                    state: vec![0.0; len],
                    actions: vec![0; len * n],
                    reward: vec![0.0; len],
                    terminated: true,
                    truncated: false,
                }
            })
            .collect();
        let header = DatasetHeader {
            env: "synthetic".into(),
            n_agents: n,
            obs_dim: od,
            state_dim: 1,
            n_actions: 2,
            episode_limit: len,
            protocol: String::new(),
            policy: "random".into(),
            seed: 0,
        };
        let data = Dataset { header, episodes };
        let plain = FrameFitConfig { max_rows: 10_000, max_picks: 4, min_gain: 0.05, given_own_view: false };
        let fits = frame_fit(&data, 2, &[0], &[1, 2, 3], &plain);
        assert_eq!(fits.iter().map(|f| f.receiver).collect::<Vec<_>>(), vec![0, 1]);
        for f in &fits {
            assert!(f.rows > 500, "{f:?}");
            assert_eq!(f.picks.iter().map(|p| p.0).collect::<Vec<_>>(), vec![1 + f.receiver], "{f:?}");
            assert!(f.r2() > 0.99 && f.r2_own + f.r2_sent < 0.9, "{f:?}");
        }
        // A receiver that sees its own offset to the sender (agent 0's o[1], the negative of the
        // sender's offset to it, as with symmetric sight): nothing of the sender's is picked for
        // it, its own view and phase 0's explain its view of the target; agent 1's fit is as before.
        let mut mirrored = data.clone();
        for ep in &mut mirrored.episodes {
            for t in 0..ep.len {
                ep.obs[t * n * od + 1] = -ep.obs[(t * n + 2) * od + 1];
            }
        }
        let given = FrameFitConfig { given_own_view: true, ..plain };
        let fits = frame_fit(&mirrored, 2, &[0], &[1, 2, 3], &given);
        assert!(fits[0].picks.is_empty() && fits[0].r2_own + fits[0].r2_sent > 0.99, "{:?}", fits[0]);
        assert_eq!(fits[1].picks.iter().map(|p| p.0).collect::<Vec<_>>(), vec![2], "{:?}", fits[1]);
        // Without the receiver's view in the fit, the negated offset is sent (a form the
        // receiver does not have); an exact copy of one of its own values never is.
        let fits = frame_fit(&mirrored, 2, &[0], &[1, 2, 3], &plain);
        assert_eq!(fits[0].picks.iter().map(|p| p.0).collect::<Vec<_>>(), vec![1], "{:?}", fits[0]);
        let mut copied = data.clone();
        for ep in &mut copied.episodes {
            for t in 0..ep.len {
                ep.obs[t * n * od + 1] = ep.obs[(t * n + 2) * od + 1];
            }
        }
        let fits = frame_fit(&copied, 2, &[0], &[1, 2, 3], &plain);
        assert_eq!((fits[0].copies.clone(), fits[0].picks.len()), (vec![1], 0), "{:?}", fits[0]);
        // Fewer shared steps than the fit needs: no picks.
        let few = Dataset { episodes: data.episodes[..1].to_vec(), ..data.clone() };
        assert!(frame_fit(&few, 2, &[0], &[1, 2, 3], &plain).iter().all(|f| f.picks.is_empty()));
    }
}
