//! Phase 0's fields by [`FieldsBy::ObservationRelevance`]: which agents send, and which values
//! or whole entities of their view.

use super::assemble::short;
use super::candidates::{Candidate, Kind};
use super::probes::Probe;
use super::select::{receivers_text, to_receivers_from, Pick};
use super::{DesignContext, OfflineDesigner, SendersBy, SentEntity, ValuesBy};
use anyhow::{Context, Result};

/// Whether agent `j`'s o[d] takes more than one value on B (a value constant for the sender
/// would be a dead message field).
pub(super) fn varies_for(data: &lmac_run::dataset::Dataset, j: usize, d: usize) -> bool {
    let (n, od) = (data.header.n_agents, data.header.obs_dim);
    let mut first = None;
    data.episodes.iter().flat_map(|ep| (0..ep.len).map(move |t| ep.obs[(t * n + j) * od + d])).any(|v| *first.get_or_insert(v) != v)
}

/// An entity's name: what its values' meanings share at the start, up to the labels ("enemy 0
/// (Roach) as seen by this agent"), or its one value's meaning.
fn entity_name(meanings: &[String]) -> String {
    let Some(first) = meanings.first() else { return "unnamed".into() };
    let mut len = first.len();
    for m in &meanings[1..] {
        len = first
            .char_indices()
            .zip(m.chars())
            .take_while(|((_, a), b)| a == b)
            .map(|((i, a), _)| i + a.len_utf8())
            .last()
            .unwrap_or(0)
            .min(len);
    }
    // Up to the last ": " of the shared start (the labels follow it), else all of it.
    let shared = &first[..len];
    let name = shared.rfind(": ").map_or(shared, |i| &shared[..i]).trim_end_matches(|c: char| c.is_whitespace() || c == ',' || c == '(');
    if name.is_empty() || meanings.len() == 1 {
        first.clone()
    } else {
        name.to_string()
    }
}

impl OfflineDesigner {
    /// [`FieldsBy::ObservationRelevance`]: phase 0's picks (one sender per value, to every other
    /// agent), the selection's log and the sentence saying how they were chosen; None (said in
    /// the log and the transcript) when the value model explains too little of the return or
    /// no observation value is relevant, and least squares chooses instead.
    #[allow(clippy::type_complexity)]
    pub(super) fn fields_by_observation_relevance(
        &mut self,
        ctx: &DesignContext,
        cands: &[Candidate],
        per_block: usize,
        critical: &[usize],
    ) -> Result<Option<(Vec<Pick>, Vec<String>, String)>> {
        let data = ctx.dataset.context("offline designer: ranking observation values by relevance needs the dataset B")?;
        let (n, od) = (data.header.n_agents, data.header.obs_dim);
        let receivers = self.receivers();
        // Senders by need only where the needs were measured (the actions' models were used).
        let senders_by = if self.cfg.senders_by == SendersBy::Need && self.needs.is_empty() {
            eprintln!("lmac: offline designer: senders by the return instead of by need: the needs were not measured (the dims were not ranked by the actions)");
            SendersBy::Return
        } else {
            self.cfg.senders_by
        };
        // Each agent's own entities (agents may observe different things).
        let entities: Vec<Vec<std::ops::Range<usize>>> = (0..n).map(|j| ctx.schema.obs_entities_of(j)).collect();
        let rel = crate::relevance::measure_joint_observation(data, &self.cfg.relevance, ctx.seed ^ 0x0B5E_0000_0000_0001)
            .context("offline designer: measuring each agent's observation values' relevance to the return")?;
        let obs_cand = |d: usize| cands.iter().position(|c| c.kind == Kind::Obs && c.dim == Some(d));
        let label = |col: usize| {
            let (j, d) = (col / od, col % od);
            format!("agent {j}'s o[{d}] ({})", ctx.env.obs_name_of(Some(j), d).map(short).unwrap_or_else(|| "unnamed".into()))
        };
        let mut per_sender = vec![0usize; n];
        let mut picks: Vec<Pick> = Vec::new();
        let mut lines = Vec::new();
        let usable = rel.held_out_r2 >= self.cfg.min_value_r2;
        // The senders, by `--senders-by`: `recovery`, the agents whose whole observation, sent
        // to the others, makes the critical dims most recoverable (a discriminator trained per
        // candidate sender: what an agent sees counts in whatever frame it sees it, where least
        // squares on the state's frame cannot use an offset), their values ranked by the joint
        // observation's value model; `return`, the agents whose whole observation most helps
        // the others predict the team's return, their values ranked by what that receivers'
        // model uses of them (importance per sender and observation dim).
        let mut value_importance: Option<Vec<Vec<f64>>> = None;
        // Per sender and entity (SendersBy::Return only).
        let mut entity_importance: Vec<Vec<f64>> = Vec::new();
        // Per agent, its whole view sent to the others (SendersBy::Recovery only; the check
        // below reuses it).
        let mut whole_views: Option<Vec<Probe>> = None;
        let (gains, gain_text): (Vec<f64>, Vec<String>) = match senders_by {
            SendersBy::Need => {
                let g: Vec<f64> = (0..n).map(|j| super::critical::supply(&self.needs, j)).collect();
                let text = g
                    .iter()
                    .map(|x| {
                        format!("it can supply {x:.4} of what the others need (their need x how much better it recovers each critical dim)")
                    })
                    .collect();
                (g, text)
            }
            SendersBy::Recovery => {
                let probes = self.whole_view_probes(ctx, critical)?;
                let g: Vec<f64> = probes.iter().map(|p| p.gain).collect();
                whole_views = Some(probes);
                let text = g
                    .iter()
                    .map(|x| format!("all it sees, sent to the others, raises their recovery of the critical dims by {x:+.3}"))
                    .collect();
                (g, text)
            }
            SendersBy::Return => {
                let g = crate::relevance::receiver_return_gains(
                    data,
                    |j| entities[j].clone(),
                    &self.cfg.relevance,
                    ctx.seed ^ 0x0B5E_0000_0000_0002,
                )
                .context("offline designer: measuring what each agent's observation adds to the others' prediction of the return")?;
                let text = g
                    .iter()
                    .map(|x| {
                        format!(
                            "all it sees, beside another agent's own observation, raises a value model's held-out R^2 of the return by {:+.3} ({:.3} -> {:.3})",
                            x.gain(),
                            x.r2_without,
                            x.r2_with
                        )
                    })
                    .collect();
                value_importance = Some(g.iter().map(|x| x.sender_importance.clone()).collect());
                entity_importance = g.iter().map(|x| x.entity_importance.clone()).collect();
                (g.iter().map(|x| x.gain()).collect(), text)
            }
        };
        // Importance of column j * od + d (agent j's o[d]) by the measure in use.
        let importance = |col: usize| match &value_importance {
            Some(v) => v[col / od][col % od],
            None => rel.importance[col],
        };
        let rank_of = |col: usize| {
            let x = importance(col);
            1 + (0..n * od).filter(|&c| importance(c) > x || (importance(c) == x && c < col)).count()
        };
        let mut agents: Vec<usize> = (0..n).collect();
        agents.sort_by(|&a, &b| gains[b].total_cmp(&gains[a]).then(a.cmp(&b)));
        let senders: Vec<usize> = agents.iter().copied().filter(|&j| gains[j] > 0.0).take(self.cfg.relevant_senders.max(1)).collect();
        let mut agent_lines: Vec<String> = agents
            .iter()
            .map(|&j| {
                let verdict = if senders.contains(&j) { "a SENDER".to_string() } else { "not a sender".to_string() };
                format!("agent {j}: {}; relevance of all it sees to the return {:.4}; {verdict}", gain_text[j], rel.groups[j])
            })
            .collect();
        lines.append(&mut agent_lines);
        // Can the discriminator see a message here at all? The most one agent can send is all it
        // sees; when the receivers recover the critical dims with it no better than a constant
        // guess, every entity's probe below would measure noise, and a compact pick would follow
        // the cost per value rather than the task. Then every agent sends its whole view.
        let mut blind: Option<String> = None;
        if self.cfg.whole_view_when_blind && self.cfg.values_by == ValuesBy::Recovery {
            let best = agents[0];
            let whole = match &whole_views {
                Some(probes) => probes[best],
                None => self.probe_gains(ctx, critical, &[(best, (0..od).collect())])?[0],
            };
            let guess = self.guess_rate(critical)?;
            let measured = format!(
                "with all agent {best} sees (the agent ranked first as a sender), the others recover the critical dims at {:.3} ({:+.4} over no messages) against {guess:.3} for a constant guess of each dim",
                whole.recovery, whole.gain
            );
            if whole.recovery <= guess {
                blind = Some(measured);
            } else {
                lines.push(format!("the discriminator can read a message here: {measured}; the entities are ranked"));
            }
        }
        // Entities ranked and shown: every probe's with `recovery` (each cost a discriminator).
        let shown_entities = if self.cfg.values_by == ValuesBy::Recovery { 12 } else { 8 };
        if let Some(measured) = &blind {
            // FullComm's message, each agent's block cut to what the whole budget gives one
            // sender (its values the return's model uses most kept first).
            let block = (ctx.env.message_budget / (n - 1)).saturating_sub(n);
            lines.push(format!(
                "the discriminator cannot read a message here: {measured}, so its gains per entity would be noise; every agent sends all of its view that varies on B, to every other agent"
            ));
            for &j in &agents {
                let mut varying: Vec<usize> = (0..od).filter(|&d| varies_for(data, j, d) && obs_cand(d).is_some()).collect();
                let cut = varying.len().saturating_sub(block);
                varying.sort_by(|&a, &b| importance(j * od + b).total_cmp(&importance(j * od + a)).then(a.cmp(&b)));
                varying.truncate(block);
                varying.sort_unstable();
                for &d in &varying {
                    let cand = obs_cand(d).context("offline designer: a varying value has no candidate (a bug)")?;
                    per_sender[j] += 1;
                    picks.push(Pick { cand, links: to_receivers_from(n, j, &receivers), gain: importance(j * od + d) });
                }
                let left_out = if cut > 0 {
                    format!(" ({cut} least relevant left out: a sender's block holds {block} values)")
                } else {
                    String::new()
                };
                lines.push(format!(
                    "agent {j}: CHOSEN: o[{}] sent to every other agent{left_out}",
                    varying.iter().map(|d| d.to_string()).collect::<Vec<_>>().join(", ")
                ));
            }
        } else if self.cfg.values_by != ValuesBy::Value {
            // The senders' entities, best first: by `entity`, the costliest to shuffle in the
            // receivers' value model; by `recovery`, the most added to the receivers' recovery
            // of the critical dims per value sent. Each sends every value of it that varies for
            // its sender on B, whole, while the budget has room for it (the first entity chosen
            // fills what room there is with its most relevant values).
            // Each sender's own meanings (agents may observe different things).
            let meanings: Vec<Vec<String>> = (0..n).map(|j| ctx.schema.obs_meanings_of(j)).collect();
            // varying_by[j][k]: the values of entity k that vary for sender j on B (each a scan of B,
            // so once per sender).
            let mut varying_by: Vec<Vec<Vec<usize>>> = vec![Vec::new(); n];
            for &j in &senders {
                varying_by[j] =
                    entities[j].iter().map(|e| e.clone().filter(|&d| varies_for(data, j, d) && obs_cand(d).is_some()).collect()).collect();
            }
            let by_recovery = self.cfg.values_by == ValuesBy::Recovery;
            // score[j][k] and what it measured, per sender j (others stay empty).
            let mut score = vec![Vec::new(); n];
            let mut score_text = vec![Vec::new(); n];
            // probe_gain[j][k]: with `recovery`, what entity k of sender j adds in all.
            let mut probe_gain = vec![Vec::new(); n];
            for &j in &senders {
                if by_recovery {
                    let probes: Vec<(usize, Vec<usize>)> = varying_by[j].iter().map(|v| (j, v.clone())).collect();
                    probe_gain[j] = self.probe_gains(ctx, critical, &probes)?.into_iter().map(|p| p.gain).collect();
                    for (g, (_, sent)) in probe_gain[j].iter().zip(&probes) {
                        let per_value = if sent.is_empty() { 0.0 } else { g / sent.len() as f64 };
                        score[j].push(per_value);
                        score_text[j].push(format!(
                            "sent alone to the others, it raises their recovery of the critical dims by {g:+.4} ({per_value:+.4} per value sent)"
                        ));
                    }
                } else {
                    for k in 0..entities[j].len() {
                        let imp = entity_importance[j][k];
                        score[j].push(imp);
                        let e = entities[j][k].clone();
                        score_text[j].push(format!(
                            "relevance {imp:.4} (its values one by one: {})",
                            e.map(|d| format!("{:.3}", importance(j * od + d))).collect::<Vec<_>>().join(", ")
                        ));
                    }
                }
            }
            let mut ranked: Vec<(usize, usize)> =
                senders.iter().flat_map(|&j| (0..entities[j].len()).map(|k| (j, k)).collect::<Vec<_>>()).collect();
            ranked.sort_by(|&(a, x), &(b, y)| score[b][y].total_cmp(&score[a][x]).then((a, x).cmp(&(b, y))));
            if by_recovery {
                let budget = self.cfg.max_relevant_values;
                let useful: Vec<(usize, usize)> =
                    ranked.iter().copied().filter(|&(j, k)| score[j][k] > 0.0 && !varying_by[j][k].is_empty()).collect();
                let items: Vec<(f64, usize)> = useful.iter().map(|&(j, k)| (probe_gain[j][k], varying_by[j][k].len())).collect();
                if let Some((i, greedy)) = worth_more_alone(&items, budget) {
                    let best = useful[i];
                    ranked.retain(|p| *p != best);
                    ranked.insert(0, best);
                    score_text[best.0][best.1].push_str(&format!(
                        "; first: alone it adds more ({:+.4}) than the entities that fit the {budget} values by gain per value together ({greedy:+.4})",
                        items[i].0
                    ));
                }
            }
            for &(j, k) in ranked.iter().take(shown_entities) {
                let e = entities[j][k].clone();
                let x = score[j][k];
                let mut varying = varying_by[j][k].clone();
                let room = self.cfg.max_relevant_values.saturating_sub(picks.len()).min(per_block.saturating_sub(per_sender[j]));
                let verdict = if !usable && !by_recovery {
                    "not chosen: the value model explains too little".to_string()
                } else if by_recovery && x <= 0.0 {
                    "not chosen: it adds nothing to the receivers' recovery".to_string()
                } else if !by_recovery && x < self.cfg.min_relevance {
                    format!("not chosen: shuffling it costs less than {}", self.cfg.min_relevance)
                } else if varying.is_empty() {
                    format!("not chosen: none of its values varies for agent {j} on B")
                } else if room == 0 {
                    format!("not chosen: the {} values kept are chosen", picks.len())
                } else if varying.len() > room && !picks.is_empty() {
                    format!("not chosen: its {} varying values do not fit the {room} left", varying.len())
                } else {
                    varying.sort_by(|&a, &b| importance(j * od + b).total_cmp(&importance(j * od + a)).then(a.cmp(&b)));
                    varying.truncate(room);
                    varying.sort_unstable();
                    if self.sent_entity.is_none() {
                        let name = short(&entity_name(meanings[j].get(e.clone()).unwrap_or(&[])));
                        self.sent_entity = Some(SentEntity { sender: j, values: varying.clone(), name });
                    }
                    for &d in &varying {
                        let cand = obs_cand(d).context("offline designer: a varying value has no candidate (a bug)")?;
                        per_sender[j] += 1;
                        picks.push(Pick {
                            cand,
                            links: to_receivers_from(n, j, &receivers),
                            gain: if by_recovery { x } else { importance(j * od + d) },
                        });
                    }
                    format!(
                        "CHOSEN: o[{}] sent by this agent to {}",
                        varying.iter().map(|d| d.to_string()).collect::<Vec<_>>().join(", "),
                        receivers_text(j, &receivers)
                    )
                };
                lines.push(format!(
                    "agent {j}'s {} (o[{}..{}]): {}; {verdict}",
                    short(&entity_name(meanings[j].get(e.clone()).unwrap_or(&[]))),
                    e.start,
                    e.end,
                    score_text[j][k]
                ));
            }
        } else {
            let mut ranked: Vec<usize> = (0..n * od).filter(|c| senders.contains(&(c / od))).collect();
            ranked.sort_by(|&a, &b| importance(b).total_cmp(&importance(a)).then(a.cmp(&b)));
            for col in ranked.into_iter().take(3 * self.cfg.max_relevant_values) {
                let (j, d) = (col / od, col % od);
                let imp = importance(col);
                let verdict = if !usable {
                    "not chosen: the value model explains too little".to_string()
                } else if picks.len() >= self.cfg.max_relevant_values {
                    format!("not chosen: beyond the {} values kept", self.cfg.max_relevant_values)
                } else if imp <= 0.0 {
                    "not chosen: shuffling it costs nothing".to_string()
                } else if per_sender[j] >= per_block {
                    format!("not chosen: agent {j}'s block is full ({per_block} values)")
                } else if let Some(k) = obs_cand(d) {
                    per_sender[j] += 1;
                    picks.push(Pick { cand: k, links: to_receivers_from(n, j, &receivers), gain: imp });
                    format!("CHOSEN: sent by this agent to {}", receivers_text(j, &receivers))
                } else {
                    "not chosen: constant on the dataset".into()
                };
                lines.push(format!("{}. {}: relevance {imp:.4}; {verdict}", rank_of(col), label(col)));
            }
        }
        let head = format!(
            "A value model of the team's joint observation (every agent's observation side by side; {} predicting the return-to-go, gamma {}) explains {:.1}% of the held-out return's variance ({} training, {} held-out episodes of B); an observation value's relevance is the share of that variance lost when it is shuffled across {} held-out steps, an agent's when all it sees is shuffled at once.{} The senders are the {} agent(s) whose whole observation {}.",
            rel.model.describe(),
            rel.gamma,
            100.0 * rel.held_out_r2,
            rel.train_episodes,
            rel.held_out_episodes,
            rel.eval_rows,
            rel.model_choice(),
            senders.len(),
            match senders_by {
                SendersBy::Need => "supplies most of what the others need of the critical dims; each sends its values most relevant to the joint observation's value model",
                SendersBy::Recovery => "sent to the others most raises their recovery of the critical dims; each sends its values most relevant to the joint observation's value model",
                SendersBy::Return => "most helps the others predict the team's return (a value model on a receiver's observation with and without it); each sends the values of its view that model uses most (their relevance below is in that model)",
            }
        );
        self.log(
            0,
            "observation_relevance",
            "offline designer: fit a value model of the joint observation on B and rank every agent's observation values by permutation importance".into(),
            format!("{head}\nMost relevant observation values:\n{}", lines.join("\n")),
        );
        eprintln!("lmac: offline designer: {head}");
        for line in lines.iter().take(n + 9) {
            eprintln!("lmac:   {line}");
        }
        if picks.is_empty() {
            let reason = if usable && senders.is_empty() {
                match senders_by {
                    SendersBy::Need => "no agent can supply what the others need of the critical dims".to_string(),
                    SendersBy::Recovery => {
                        "no agent's observation, sent to the others, raises their recovery of the critical dims".to_string()
                    }
                    SendersBy::Return => "no agent's observation helps the others predict the return".to_string(),
                }
            } else if self.cfg.values_by == ValuesBy::Recovery {
                "no entity of the senders' view, sent alone, adds to the others' recovery of the critical dims".to_string()
            } else if usable {
                "no value of the senders' observation costs the value model anything when shuffled".to_string()
            } else {
                format!("the value model explains less than {:.1}%", 100.0 * self.cfg.min_value_r2)
            };
            eprintln!("lmac: offline designer: phase 0's fields by least squares instead: {reason}");
            self.log(0, "fields_by", "offline designer: choose phase 0's fields".into(), format!("By least squares instead: {reason}."));
            return Ok(None);
        }
        let total: f64 = picks.iter().map(|p| p.gain).sum();
        let how = match (&blind, self.cfg.values_by) {
            (Some(measured), _) => format!(
                "{head} Phase 0 sends every agent's whole view ({} values in all, each from the agent that sees it to every other agent): a discriminator could not read even the best sender's whole view ({measured}), so no finer choice could be measured on this map.",
                picks.len()
            ),
            (None, ValuesBy::Value) => format!(
                "{head} Phase 0 sends the {} most relevant values of agent(s) {} (relevance {total:.3} summed), each from the agent that sees it to every other agent.",
                picks.len(),
                senders.iter().map(|j| j.to_string()).collect::<Vec<_>>().join(", ")
            ),
            (None, ValuesBy::Entity) => format!(
                "{head} Phase 0 sends whole entities (the schema's units and objects as the sender sees them), the one whose values shuffled together cost that model most first: {} value(s) of agent(s) {}, from the agent that sees them to every other agent.",
                picks.len(),
                senders.iter().map(|j| j.to_string()).collect::<Vec<_>>().join(", ")
            ),
            (None, ValuesBy::Recovery) => format!(
                "{head} Phase 0 sends whole entities (the schema's units and objects as the sender sees them), the one that, sent alone to the others, most raises their recovery of the critical dims per value sent first (a discriminator trained per sender and entity on B, measured on held-out episodes): {} value(s) of agent(s) {}, from the agent that sees them to every other agent.",
                picks.len(),
                senders.iter().map(|j| j.to_string()).collect::<Vec<_>>().join(", ")
            ),
        };
        let steps = lines.into_iter().take(n + picks.len().max(shown_entities)).collect();
        Ok(Some((picks, steps, how)))
    }
}

/// Gain per value is the greedy order of a knapsack, which can pass over one item worth more
/// than everything that order fits: on 1o_10b the Overseer's move feature (+0.33 of recovery
/// for 4 values) fills the 6 values before the Roach (+0.37 for 5). The usual guard: when one
/// item that fits alone gains more than the greedy selection in total, it goes first. `items`:
/// (total gain, values) in gain-per-value order. Returns (that item's index, the greedy total).
fn worth_more_alone(items: &[(f64, usize)], budget: usize) -> Option<(usize, f64)> {
    let (mut used, mut greedy) = (0, 0.0);
    for &(gain, size) in items {
        if used + size <= budget {
            used += size;
            greedy += gain;
        }
    }
    let best = (0..items.len()).filter(|&i| items[i].1 <= budget).max_by(|&a, &b| items[a].0.total_cmp(&items[b].0).then(b.cmp(&a)))?;
    (items[best].0 > greedy).then_some((best, greedy))
}

#[cfg(test)]
mod knapsack_tests {
    use super::worth_more_alone;

    /// The probes the designer measured on 1o_10b (the Overseer's move feature, the Roach, a
    /// Baneling's slot) and on LBF 8x8 (the partner's column, row and view rows).
    #[test]
    fn one_entity_worth_more_than_the_greedy_fill_goes_first() {
        let one_o_ten_b = [(0.3300, 4), (0.3667, 5), (0.0348, 6), (0.0308, 6)];
        assert_eq!(worth_more_alone(&one_o_ten_b, 6), Some((1, 0.33)));
        // With room for both, the greedy order takes both and stays.
        assert_eq!(worth_more_alone(&one_o_ten_b, 9), None);
        let lbf = [(0.0027, 1), (0.0026, 1), (0.0026, 2), (0.0025, 2), (0.0036, 3)];
        assert_eq!(worth_more_alone(&lbf, 6), None);
        // An item too big for the budget is never put first.
        assert_eq!(worth_more_alone(&[(0.1, 2), (0.5, 7)], 6), None);
        assert_eq!(worth_more_alone(&[], 6), None);
    }
}
