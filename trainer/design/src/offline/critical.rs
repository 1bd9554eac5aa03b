//! Phase 0's targets: the task-critical dims, by [`CriticalBy`].

use super::meta_dims::failure;
use super::{worst, CriticalBy, DesignContext, OfflineDesigner, Targets};
use crate::meta::{self, Recovery};
use anyhow::{bail, Context, Result};

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
        let ranking: Vec<String> = rel
            .ranking()
            .into_iter()
            .take(15)
            .map(|d| {
                let verdict = match skill_of(d) {
                    None => "not chosen: constant on B".to_string(),
                    Some(_) if chosen.contains(&d) => "CHOSEN: relevant and poorly recovered without messages".into(),
                    Some(_) if rel.importance[d] < min_rel => format!("not chosen: relevance below {min_rel}"),
                    Some(k) if k >= thr => format!("not chosen: agents recover it without messages (skill {k:.2} >= {thr})"),
                    Some(_) => format!("not chosen: beyond the {} dims kept", self.cfg.max_relevant_dims),
                };
                format!(
                    "{}. {}: relevance {:.4}, skill without messages {}; {verdict}",
                    rel.rank_of(d),
                    meta::dim_label(d, &names),
                    rel.importance[d],
                    skill_of(d).map_or("-".into(), |k| format!("{k:.2}"))
                )
            })
            .collect();
        self.log(
            0,
            "relevance",
            "offline designer: fit a value model of the state on B and rank every state dim by its permutation importance".into(),
            format!("{head}\nMost relevant dims:\n{}", ranking.join("\n")),
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
