//! The offline designer: the embedded default that needs no network. It is not an LLM and
//! does not pretend to be one; every protocol it writes says "offline designer: ..." and
//! explains its numbers. It designs from the data, deterministically.
//!
//! **By default** ([`OfflineConfig::default`]) it designs for the task:
//! - phase 0's critical dims are the few state dims the dataset's policy's actions depend on
//!   most and agents recover poorly without messages ([`CriticalBy::Action`]; by the return's
//!   value model where the action models explain too little);
//! - one agent sends: the one whose view most helps the others predict the team's return
//!   ([`SendersBy::Return`]); it sends whole entities of its view (a unit, an object), the one
//!   that most raises the others' recovery of the critical dims per value first
//!   ([`ValuesBy::Recovery`]); where a discriminator cannot read even its whole view (the
//!   receivers recover the critical dims with it no better than a constant guess), the
//!   per-entity ranking would measure noise, and every agent sends its whole view instead
//!   ([`OfflineConfig::whole_view_when_blind`]);
//! - phase 1 sends the values of that sender's view that place each receiver in the sender's
//!   frame ([`Phase1By::Frame`]), so the receivers can use phase 0's entity;
//! - phase 2, and any rule the data cannot support, by the greedy least squares below.
//!
//! [`OfflineConfig::least_squares_rules`] designs every phase by least squares:
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

use super::meta::{self, Recovery};
use super::meta_info::MetaInfo;
use super::{DesignContext, Designer, Feedback, PhaseProtocol, TranscriptEntry};
use anyhow::{anyhow, bail, Result};
use lmac_protocol_runner::protocol::{self, DimSpec, HistoryPadding, MessageLayout, Protocol, ValidatedProtocol};

mod assemble;
mod candidates;
mod config;
mod critical;
mod feedback;
mod frame;
mod meta_dims;
mod observation_relevance;
mod probes;
mod select;
use assemble::{fields_from, short};
use candidates::{kinds_for, probe};
pub use config::{CriticalBy, FieldsBy, OfflineConfig, Phase1By, ReceiversBy, SendersBy, ValuesBy};
pub use frame::{frame_fit, FrameFit, FrameFitConfig};
use meta_dims::{failure, meta_dims};
use select::{covariance, prescreen, sample, select, RowSource};

/// The embedded designer (see the module doc).
pub struct OfflineDesigner {
    cfg: OfflineConfig,
    transcript: Vec<TranscriptEntry>,
    /// Phase 0's relevance measurement (None before it, or with [`CriticalBy::Recovery`]) and
    /// what it models: [`CriticalBy::Action`] or [`CriticalBy::Relevance`] (the return).
    relevance: Option<(super::relevance::Relevance, CriticalBy)>,
    /// Phase 0's recovery of every state dim without messages (None before it).
    without: Option<Recovery>,
    /// E_t[chi] of a constant guess of each dim of `without`, in its order.
    guess: Vec<f64>,
    /// Factor on [`OfflineConfig::min_gain`]: doubled each time a phase added nothing to the
    /// phases before it, so the next one sends only what explains more per column.
    gain_scale: f64,
    /// The first entity phase 0 sent whole ([`ValuesBy::Entity`], [`ValuesBy::Recovery`]), for
    /// [`Phase1By::Frame`].
    sent_entity: Option<SentEntity>,
    /// Phase 0's need of each agent for the critical dims (with [`CriticalBy::Action`]).
    needs: Vec<critical::AgentNeed>,
}

/// An entity phase 0 sent: by whom, which of its values, and its name.
#[derive(Clone, Debug)]
struct SentEntity {
    sender: usize,
    values: Vec<usize>,
    name: String,
}

impl OfflineDesigner {
    pub fn new(cfg: OfflineConfig) -> Self {
        OfflineDesigner {
            cfg,
            transcript: Vec::new(),
            relevance: None,
            without: None,
            guess: Vec::new(),
            gain_scale: 1.0,
            sent_entity: None,
            needs: Vec::new(),
        }
    }

    pub fn config(&self) -> &OfflineConfig {
        &self.cfg
    }

    /// Phase 0's relevance measurement, once made.
    pub fn relevance(&self) -> Option<&super::relevance::Relevance> {
        self.relevance.as_ref().map(|r| &r.0)
    }

    /// Whom a sender sends to, by [`OfflineConfig::receivers_by`]: every other agent, or the
    /// agents that need the critical dims (everyone when the needs were not measured or no agent
    /// needs anything).
    fn receivers(&self) -> Option<Vec<usize>> {
        if self.cfg.receivers_by != ReceiversBy::Need {
            return None;
        }
        critical::needy_agents(&self.needs)
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
        let mut s = sample(ctx, &prev, &probe_v, &probe_env, width, &targets.dims, self.cfg.max_samples)?;
        let rows = s.rows();
        if rows < 2 {
            bail!("offline designer: the dataset has {rows} usable steps; it needs at least 2");
        }
        // The fields, and how they were chosen: (in the instruction, in the reasoning).
        let (chosen, chosen_by) = if phase == 0 && self.cfg.fields_by == FieldsBy::ObservationRelevance {
            let by = (
                "by the relevance of what each agent sees to the return",
                "the relevance of each agent's observation to the return, from a value model fitted on the dataset",
            );
            (self.fields_by_observation_relevance(ctx, &cands, per_block, critical)?, by)
        } else if phase == 1 && self.cfg.phase1_by == Phase1By::Frame {
            let by = (
                "by where each receiver is in the sender's view",
                "linear fits on the dataset of each receiver's own view of phase 0's entity on the sender's view",
            );
            // One sender: its block may take this phase's whole share but its one-hot.
            (self.fields_by_frame(ctx, &cands, share.saturating_sub(n))?, by)
        } else {
            (None, ("", ""))
        };
        let chosen_by = if chosen.is_some() {
            chosen_by
        } else {
            ("by greedy least squares", "greedy least-squares feature selection over the dataset")
        };
        let (picks, steps, kept_count, how) = if let Some((picks, steps, how)) = chosen {
            (picks, steps, cands.len(), how)
        } else {
            let kept = prescreen(&mut s, &cands, &targets.weights, self.cfg.prescreen)?;
            let mut cols: Vec<usize> = kept.iter().flat_map(|&k| cands[k].col..cands[k].col + cands[k].width).collect();
            cols.sort_unstable();
            let stats = covariance(&mut s, cols)?;
            let cfg = OfflineConfig { min_gain: self.cfg.min_gain * self.gain_scale, ..self.cfg.clone() };
            let (picks, steps) = select(stats, &cands, &kept, &targets.weights, per_block, &cfg);
            let total_gain: f64 = picks.iter().map(|p| p.gain).sum();
            let how = format!(
                "Together these explain an estimated {:.1}% of the weighted variance of the {} target state dims that receivers could not explain from their own observation{} (linear R^2 on {} sampled steps).",
                100.0 * total_gain,
                targets.dims.len(),
                if prev.is_empty() { "" } else { " and the earlier phases' messages" },
                rows,
            );
            (picks, steps, kept.len(), how)
        };
        drop(s);
        if picks.is_empty() {
            bail!(
                "offline designer: phase {phase} has nothing to send: no candidate feature that fits its {per_block} value columns per sender block explains any of its {} target dims beyond what the receivers already know ({})",
                targets.dims.len(),
                steps.join("; ")
            );
        }
        let fields = fields_from(&picks, &cands, env);
        let names = ctx.schema.state_meanings();
        let target_text: Vec<String> = targets.dims.iter().take(8).map(|&d| meta::dim_label(d, &names)).map(|l| short(&l)).collect();
        let goal = match phase {
            0 => "initialization",
            1 => "recognition enhancement",
            _ => "sharing enhancement",
        };
        let field_text: Vec<String> = fields.iter().map(|f| format!("'{}': {}", f.name, f.description)).collect();
        let instruction = format!(
            "offline designer: phase {phase} ({goal}), chosen {} on the dataset, not by an LLM. {} Each agent sends: {}. {how} Each sender's values reach a receiver after the sender's one-hot id (once per sender in the compact layout).",
            chosen_by.0,
            targets.why,
            field_text.join("; "),
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
            layout: MessageLayout::default(),
            fields,
            env: None,
            schema_fingerprint: None,
        };
        let validated = protocol::validate_phase(&p, env, &prev)
            .map_err(|e| anyhow!("offline designer: its phase {phase} protocol is invalid (a bug): {}", protocol::errors_to_text(&e)))?;
        let reasoning = format!(
            "# Offline designer, phase {phase} ({goal})\n\nThis protocol was built by a deterministic algorithm ({}), not by a language model.\n\n## Targets\n{}\n\n{}\n\n## Budget\n{left} message columns left of {}; this phase's share is {share} ({phases_left} phase(s) left), i.e. {per_block} value columns per sender block after the {n}-column sender one-hot.\n\n## Candidates\n{} candidate features ({}), {} kept by the marginal-correlation prescreen, {} sampled steps.\n\n## Selection\n{}\n\nResulting width: {} columns per receiving agent.\n",
            chosen_by.1,
            targets.dims.iter().map(|&d| format!("- {}", meta::dim_label(d, &names))).collect::<Vec<_>>().join("\n"),
            targets.why,
            env.message_budget,
            cands.len(),
            kinds.iter().map(|k| k.words().0).collect::<Vec<_>>().join(", "),
            kept_count,
            rows,
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
pub(super) fn worst(mut scored: Vec<(usize, f64, Vec<f64>)>, max: usize) -> (Vec<usize>, Vec<Vec<f64>>) {
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
        self.cfg.check()?;
        self.sent_entity = None;
        let (targets, critical) = self.critical_targets(ctx)?;
        self.design(ctx, 0, &[], targets, &critical)
    }

    fn feedback(&mut self, ctx: &DesignContext, phase: usize, _previous: &[PhaseProtocol], meta_v: &MetaInfo) -> Result<Feedback> {
        self.feedback_text(ctx, phase, meta_v)
    }

    fn refine(
        &mut self,
        ctx: &DesignContext,
        phase: usize,
        previous: &[PhaseProtocol],
        _feedback: &Feedback,
        meta_v: &MetaInfo,
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
        // The design loop said the newest phase added nothing: its columns did not pay, so this
        // phase asks twice the gain per column of every candidate.
        let mut targets = targets;
        if meta_v.newest_phase_added == Some(false) {
            self.gain_scale *= 2.0;
            targets.why.push_str(&format!(
                " Phase {} added nothing to the phases before it on the fixed dims, so this phase sends only candidates that explain at least {:.4} of the weighted target variance per column ({}x min_gain).",
                phase - 1,
                self.cfg.min_gain * self.gain_scale,
                self.gain_scale
            ));
        }
        let critical = targets.dims.clone();
        self.design(ctx, phase, previous, targets, &critical)
    }

    fn transcript(&self) -> Vec<TranscriptEntry> {
        self.transcript.clone()
    }

    fn settings(&self) -> Option<serde_json::Value> {
        serde_json::to_value(&self.cfg).ok()
    }

    fn measurements(&self) -> Option<serde_json::Value> {
        let (r, by) = self.relevance.as_ref()?;
        let ranking: Vec<serde_json::Value> = r
            .ranking()
            .into_iter()
            .take(30)
            .map(|d| serde_json::json!({ "dim": d, "rank": r.rank_of(d), "relevance": (r.importance[d] * 1e4).round() / 1e4 }))
            .collect();
        Some(serde_json::json!({
            "relevance": {
                "what": if *by == CriticalBy::Action {
                    "importance of each state dim for a linear model of each agent's action fitted on B: the expected share of the held-out actions' variance lost when the dim is shuffled, averaged over the agents"
                } else {
                    "permutation importance of each state dim for a value model of the return-to-go fitted on B: the share of the held-out return's variance lost when the dim is shuffled"
                },
                "held_out_r2": (r.held_out_r2 * 1e4).round() / 1e4,
                "model": r.model,
                "check_r2": r.check_r2.iter().map(|(k, v)| serde_json::json!({ "model": k, "r2": (v * 1e4).round() / 1e4 })).collect::<Vec<_>>(),
                "gamma": r.gamma,
                "train_episodes": r.train_episodes,
                "held_out_episodes": r.held_out_episodes,
                "eval_rows": r.eval_rows,
                "top": ranking,
                "importance": r.importance.iter().map(|x| (x * 1e4).round() / 1e4).collect::<Vec<f64>>(),
            },
            "needs": self.needs,
        }))
    }
}
