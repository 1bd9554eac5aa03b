//! Phase 0's targets: the task-critical dims, by [`CriticalBy`].

use super::meta_dims::failure;
use super::{worst, CriticalBy, DesignContext, OfflineDesigner, Targets};
use crate::meta::{self, Recovery};
use anyhow::{bail, Context, Result};
use serde::Serialize;

/// What one agent needs of the task-critical dims, and who can supply each: read from what its
/// own actions depend on ([`crate::relevance::Relevance::per_agent`]) and how poorly it
/// recovers each dim from its own observation.
#[derive(Clone, Debug, Serialize)]
pub struct AgentNeed {
    pub agent: usize,
    /// The critical dims, most needed first.
    pub dims: Vec<DimNeed>,
}

/// One agent's need of one critical dim.
#[derive(Clone, Debug, Serialize)]
pub struct DimNeed {
    pub dim: usize,
    /// How much the agent's own actions depend on the dim: the share of their held-out variance
    /// lost when the dim is shuffled.
    pub action_dependence: f64,
    /// How often the agent fails to recover the dim without messages, relative to a constant
    /// guess (0: always recovers it, 1: no better than the guess).
    pub failure: f64,
    /// `action_dependence x failure`: what a message of the dim is worth to this agent.
    pub need: f64,
    /// The other agent that recovers the dim best from its own observation.
    pub supplier: Option<usize>,
    /// Every agent's E_t[chi] of the dim without messages.
    pub recovery: Vec<f64>,
}

/// Share of the neediest agent's total need an agent must have to receive, with
/// [`super::ReceiversBy::Need`]: a tenth keeps the agents whose actions visibly depend on what
/// they miss and drops those whose need is estimation noise.
const NEEDY_SHARE: f64 = 0.1;

/// The agents that need the critical dims ([`super::ReceiversBy::Need`]); None when no agent
/// needs anything (then everyone receives).
pub(super) fn needy_agents(needs: &[AgentNeed]) -> Option<Vec<usize>> {
    let totals: Vec<f64> = needs.iter().map(|a| a.dims.iter().map(|x| x.need).sum()).collect();
    let max = totals.iter().copied().fold(0.0, f64::max);
    (max > 0.0).then(|| (0..totals.len()).filter(|&i| totals[i] >= NEEDY_SHARE * max).collect())
}

/// What agent `j` can supply of what the others need ([`super::SendersBy::Need`]): for each
/// other agent and critical dim, its need times how much better `j` recovers the dim than it.
pub(super) fn supply(needs: &[AgentNeed], j: usize) -> f64 {
    needs
        .iter()
        .filter(|a| a.agent != j)
        .flat_map(|a| a.dims.iter().map(move |x| x.need * (x.recovery[j] - x.recovery[a.agent]).max(0.0)))
        .sum()
}

/// Each agent's need of the `critical` dims and their best supplier. `per_agent` is the
/// agents' own action dependence ([agent][dim], empty for an agent that could not be fitted);
/// `r` the recovery without messages, `guess` a constant guess's E_t[chi] in `r`'s order.
pub(super) fn agent_needs(per_agent: &[Vec<f64>], r: &Recovery, guess: &[f64], critical: &[usize]) -> Vec<AgentNeed> {
    (0..r.n_agents)
        .map(|i| {
            let mut dims: Vec<DimNeed> = critical
                .iter()
                .filter_map(|&d| {
                    let k = r.position(d)?;
                    let rates = r.rates(k);
                    let action_dependence = per_agent.get(i).and_then(|v| v.get(d)).copied().unwrap_or(0.0);
                    let failure = failure(rates[i], guess[k]);
                    let supplier = (0..r.n_agents).filter(|&j| j != i).max_by(|&a, &b| rates[a].total_cmp(&rates[b]).then(b.cmp(&a)));
                    Some(DimNeed { dim: d, action_dependence, failure, need: action_dependence * failure, supplier, recovery: rates })
                })
                .collect();
            dims.sort_by(|a, b| b.need.total_cmp(&a.need).then(a.dim.cmp(&b.dim)));
            AgentNeed { agent: i, dims }
        })
        .collect()
}

impl OfflineDesigner {
    /// Phase 0's targets and critical dims: the no-message discriminator measures every state
    /// dim's recovery, and the dims are ranked by [`OfflineConfig::critical_by`], falling back
    /// (saying so) where the data cannot support the ranking.
    pub(super) fn critical_targets(&mut self, ctx: &DesignContext) -> Result<(Targets, Vec<usize>)> {
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
        let max_critical = self.cfg.max_critical_dims;
        let by_recovery = || -> (Vec<usize>, String) {
            if poor.is_empty() {
                let (d, _) = worst(all.clone(), 8.min(all.len()));
                (d, format!("Without messages every varying state dim is recovered with a skill of at least {thr} over a constant guess (E_t[chi], alpha {}), so the 8 least recovered are targeted.", ctx.schema.alpha))
            } else {
                let (d, _) = worst(poor.clone(), max_critical);
                let why = format!(
                    "Without messages, {} of {} varying state dims are recovered with a skill below {thr} (mean E_t[chi] over agents on held-out steps, alpha {}, relative to always guessing the dim's median: 0 = no better than the guess); the {} worst are taken as task-critical.",
                    poor.len(), all.len(), ctx.schema.alpha, d.len()
                );
                (d, why)
            }
        };
        // (dims, why, per-dim factor on the receivers' weights)
        let (critical, why, importance) = match self.cfg.critical_by {
            CriticalBy::Recovery => {
                let (d, why) = by_recovery();
                (d, why, None)
            }
            CriticalBy::Relevance | CriticalBy::Action => {
                let data = ctx.dataset.context("offline designer: ranking dims by relevance needs the dataset B")?;
                // By the policy's actions first when asked; when their models explain too
                // little of the policy, by the return; when that explains too little, by recovery.
                let mut fell_back = String::new();
                let mut by = self.cfg.critical_by;
                let (rel, choice) = loop {
                    let rel = if by == CriticalBy::Action {
                        crate::relevance::measure_actions(data, &self.cfg.relevance, ctx.seed)
                            .context("offline designer: measuring what each agent's actions depend on")?
                    } else {
                        crate::relevance::measure(data, &self.cfg.relevance, ctx.seed)
                            .context("offline designer: measuring each state dim's relevance to the return")?
                    };
                    match self.by_relevance(ctx, &rel, by, &all) {
                        Err(reason) if by == CriticalBy::Action => {
                            eprintln!("lmac: offline designer: ranking by the return instead: {reason}");
                            fell_back = format!("By the policy's actions: {reason} So the dims are ranked by the return instead. ");
                            by = CriticalBy::Relevance;
                        }
                        choice => break (rel, choice),
                    }
                };
                self.relevance = Some((rel.clone(), by));
                match choice {
                    Ok((d, why)) => (d, format!("{fell_back}{why}"), Some(rel.importance)),
                    Err(reason) => {
                        let (d, why) = by_recovery();
                        (d, format!("{fell_back}{reason} So phase 0 falls back to the hardest dims to recover: {why}"), None)
                    }
                }
            }
        };
        let pool: Vec<_> = all
            .iter()
            .filter(|x| critical.contains(&x.0))
            .map(|x| {
                let f = importance.as_ref().map_or(1.0, |imp| imp[x.0]);
                // Relevance mode ranks by relevance x failure; the weights carry both.
                let score = if importance.is_some() { -f * (1.0 - x.1.clamp(0.0, 1.0)) } else { x.1 };
                (x.0, score, x.2.iter().map(|w| w * f).collect::<Vec<f64>>())
            })
            .collect();
        let (dims, weights) = worst(pool, self.cfg.max_targets);
        debug_assert_eq!(weights.len(), n);
        let names = ctx.schema.state_meanings();
        let listing: Vec<String> = critical
            .iter()
            .map(|&d| {
                let k = r.position(d).unwrap_or(0);
                let rel = self.relevance.as_ref().map(|r| &r.0).filter(|_| importance.is_some());
                let rel = rel.map_or(String::new(), |x| format!("relevance {:.4} (rank {}), ", x.importance[d], x.rank_of(d)));
                format!(
                    "{} ({rel}mean E_t[chi] without messages {:.3}, constant guess {:.3})",
                    meta::dim_label(d, &names),
                    r.mean_rate(k),
                    g[k]
                )
            })
            .collect();
        let needs = self
            .relevance
            .as_ref()
            .filter(|(rel, _)| !rel.per_agent.is_empty())
            .map(|(rel, _)| agent_needs(&rel.per_agent, r, g, &critical));
        if let Some(needs) = needs {
            let names = &names;
            let lines: Vec<String> = needs
                .iter()
                .flat_map(|a| {
                    a.dims.iter().map(move |x| {
                        format!(
                            "agent {}: {} - its actions' dependence {:.4} x its failure without messages {:.2} = need {:.4}; {}",
                            a.agent,
                            meta::dim_label(x.dim, &names),
                            x.action_dependence,
                            x.failure,
                            x.need,
                            x.supplier.map_or("no other agent".into(), |j| format!(
                                "best recovered by agent {j} (E_t[chi] {:.3})",
                                x.recovery[j]
                            ))
                        )
                    })
                })
                .collect();
            self.log(
                0,
                "needs",
                "offline designer: what each agent's own actions depend on among the critical dims, how poorly it recovers each without messages, and who recovers it best".into(),
                lines.join("\n"),
            );
            self.needs = needs;
        }
        self.log(
            0,
            "critical_dims",
            format!("offline designer: train the no-message discriminator on {} training episodes and measure E_t[chi] on {} held-out episodes for every state dim", m.without_report.train_episodes, m.held_out.len()),
            format!("{why}\n{}", listing.join("\n")),
        );
        self.without = Some(m.without);
        self.guess = m.guess;
        Ok((Targets { dims, weights, why }, critical))
    }

    /// [`CriticalBy::Relevance`]: the dims that are relevant to the return and poorly recovered
    /// without messages, most relevant x worst recovered first, with the reason (Err: why the
    /// ranking cannot be used). `all` is (dim, skill without messages, per-agent failures).
    /// The ranking with the reason for each of its top dims goes to the transcript and the log.
    fn by_relevance(
        &mut self,
        ctx: &DesignContext,
        rel: &crate::relevance::Relevance,
        by: CriticalBy,
        all: &[(usize, f64, Vec<f64>)],
    ) -> std::result::Result<(Vec<usize>, String), String> {
        let (thr, min_rel) = (self.cfg.poor_threshold, self.cfg.min_relevance);
        let names = ctx.schema.state_meanings();
        let skill_of = |d: usize| all.iter().find(|x| x.0 == d).map(|x| x.1);
        let priority = |d: usize| rel.importance[d] * (1.0 - skill_of(d).unwrap_or(1.0).clamp(0.0, 1.0));
        let mut chosen: Vec<usize> = all.iter().filter(|x| rel.importance[x.0] >= min_rel && x.1 < thr).map(|x| x.0).collect();
        chosen.sort_by(|&a, &b| priority(b).total_cmp(&priority(a)).then(a.cmp(&b)));
        chosen.truncate(self.cfg.max_relevant_dims);
        let relevant = rel.importance.iter().filter(|&&x| x >= min_rel).count();
        let head = if by == CriticalBy::Action {
            format!(
                "A linear model of each agent's action (one-hot) on the state, fitted at the steps where the agent observes anything, explains {:.1}% of the held-out actions' variance on average over the agents ({} training, {} held-out episodes of B); a dim's relevance is the expected share of that variance lost when the dim is shuffled ({} held-out agent-steps), averaged over the agents. {relevant} dim(s) have a relevance of at least {min_rel}.",
                100.0 * rel.held_out_r2,
                rel.train_episodes,
                rel.held_out_episodes,
                rel.eval_rows
            )
        } else {
            format!(
                "A value model of the state ({} predicting the return-to-go, gamma {}) explains {:.1}% of the held-out return's variance ({} training, {} held-out episodes of B); a dim's relevance is the share of that variance lost when the dim is shuffled across {} held-out steps.{} {relevant} dim(s) have a relevance of at least {min_rel}.",
                rel.model.describe(),
                rel.gamma,
                100.0 * rel.held_out_r2,
                rel.train_episodes,
                rel.held_out_episodes,
                rel.eval_rows,
                rel.model_choice()
            )
        };
        // Listed by the quantity the choice is made by, relevance x (1 - skill), so the list
        // reads top-down as the designer chose; constant dims (no skill) last, by relevance.
        let mut listed = rel.ranking();
        listed.sort_by(|&a, &b| {
            let key = |d: usize| skill_of(d).map(|_| priority(d));
            key(b)
                .partial_cmp(&key(a))
                .unwrap_or(std::cmp::Ordering::Equal)
                .then(rel.importance[b].total_cmp(&rel.importance[a]))
                .then(a.cmp(&b))
        });
        let ranking: Vec<String> = listed
            .into_iter()
            .take(15)
            .enumerate()
            .map(|(k, d)| {
                let verdict = match skill_of(d) {
                    None => "not chosen: constant on B".to_string(),
                    Some(_) if chosen.contains(&d) => "CHOSEN: relevant and poorly recovered without messages".into(),
                    Some(_) if rel.importance[d] < min_rel => format!("not chosen: relevance below {min_rel}"),
                    Some(k) if k >= thr => format!("not chosen: agents recover it without messages (skill {k:.2} >= {thr})"),
                    Some(_) => format!("not chosen: beyond the {} dims kept", self.cfg.max_relevant_dims),
                };
                format!(
                    "{}. {}: relevance x (1 - skill) {}, relevance {:.4} (rank {}), skill without messages {}; {verdict}",
                    k + 1,
                    meta::dim_label(d, &names),
                    skill_of(d).map_or("-".into(), |_| format!("{:.4}", priority(d))),
                    rel.importance[d],
                    rel.rank_of(d),
                    skill_of(d).map_or("-".into(), |k| format!("{k:.2}"))
                )
            })
            .collect();
        self.log(
            0,
            "relevance",
            "offline designer: fit a value model of the state on B and rank every state dim by its permutation importance".into(),
            format!("{head}\nDims by relevance x (1 - skill), the order the choice is made in:\n{}", ranking.join("\n")),
        );
        eprintln!("lmac: offline designer: {head}");
        for line in ranking.iter().take(8) {
            eprintln!("lmac:   {line}");
        }
        let floor = if by == CriticalBy::Action { self.cfg.min_action_r2 } else { self.cfg.min_value_r2 };
        if rel.held_out_r2 < floor {
            return Err(format!(
                "The model explains only {:.1}% of the held-out {} variance (below {:.1}%), too little to rank dims by.",
                100.0 * rel.held_out_r2,
                if by == CriticalBy::Action { "actions'" } else { "return's" },
                100.0 * floor
            ));
        }
        if chosen.is_empty() {
            return Err(format!(
                "No dim is both relevant (at least {min_rel}) and poorly recovered without messages (skill below {thr}): agents already see what the return depends on."
            ));
        }
        let why = format!(
            "{head} The task-critical dims are the {} that are relevant and recovered with a skill below {thr} over a constant guess without messages, ordered by relevance x (1 - skill); each receiver's weight on a dim is its failure rate relative to the guess's times the dim's relevance.",
            chosen.len()
        );
        Ok((chosen, why))
    }
}
