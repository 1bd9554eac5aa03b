//! The meta-information as data: what [`super::meta::evaluate`] measured on B for phases 0..=k,
//! handed to the designers, written to `phase<k>/meta.json` and shown to the LLM.
//!
//! # The JSON (serde of [`MetaInfo`]; keys sorted, see [`MetaInfo::json`])
//! ```text
//! { "env", "alpha", "phases", "message_columns", "evaluation": {held-out episodes, rows, note},
//!   "discriminators": {"with_communication": TrainReport, "without_communication": TrainReport, "config"},
//!   "target_dims_selection": "how the dims below were chosen",
//!   "dimensions": [ { "dim": 62, "dimension": "s[62] - <meaning>",
//!       "constant_guess_rate": E[chi] of guessing the median,
//!       "with_communication": { "agent_success_rates": [E_t chi per agent],
//!           "variance_across_agents": Var_i,
//!           "early": [per agent], "variance_in_early": Var_i, "mid": .., "late": .. },
//!       "without_communication": { same } }, ... ],
//!   "summary": { "target_dims": [..], "with_communication": {"mean_recovery",
//!       "mean_variance_across_agents"}, "without_communication": {..} } }
//! ```
//! Rates are rounded to 3 decimals and variances to 5 when measured, so what a designer reads
//! is exactly what the file and the prompt show.

use super::discriminator::{DiscriminatorConfig, TrainReport};
use super::meta::GainInterval;
use lmac_learn::stats::{mean, variance};
use serde::{Deserialize, Serialize};

/// Names of the thirds of an episode.
pub const THIRDS: [&str; 3] = ["early", "mid", "late"];

/// Recovery relative to a constant guess: (rate - guess) / (1 - guess), 1 for a dim the guess
/// always gets right (a constant dim). 0 means no better than guessing; negative, worse.
/// Sparse dims (an LBF cell is empty most of the time) reach high raw rates by guessing 0,
/// so rankings of "worst recovered" use this instead of the raw rate.
pub fn skill(rate: f64, guess: f64) -> f64 {
    if guess >= 1.0 - 1e-9 {
        1.0
    } else {
        (rate - guess) / (1.0 - guess)
    }
}

/// The label of a state dim: `s[62] - <meaning>` (or `s[62]` when the meaning is unknown).
pub fn dim_label(d: usize, names: &[String]) -> String {
    match names.get(d).filter(|s| !s.is_empty()) {
        Some(m) => format!("s[{d}] - {m}"),
        None => format!("s[{d}]"),
    }
}

/// The meta-information of phases 0..=k on held-out episodes of B.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MetaInfo {
    /// Environment name, e.g. `lbf:8x8-2p-2f-s1-coop`.
    pub env: String,
    /// The chi threshold on the squared reconstruction error, in the state's own units.
    pub alpha: f64,
    /// Phases evaluated together (k + 1).
    pub phases: usize,
    /// Message columns of those phases (what each agent receives).
    pub message_columns: usize,
    pub evaluation: EvaluationFacts,
    pub discriminators: DiscriminatorReports,
    /// How the target dims were chosen (and cut, when there were too many for the prompt).
    pub target_dims_selection: String,
    /// One entry per target dim, by increasing dim.
    pub dimensions: Vec<DimRecovery>,
    pub summary: MetaSummary,
    /// Links of the protocol that carry nothing on B (constant, or a copy of what the receiver
    /// observes; see `dead_fields`), one line each: candidates to replace.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub dead_fields: Vec<String>,
    /// The design loop's verdicts, said plainly: whether the messages of phases
    /// 0..=k help on the fixed dims at all, and whether the newest phase added anything to the
    /// phases before it (or was dropped). Filled by the design loop, read by every designer.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub verdicts: Vec<String>,
    /// Whether the newest phase added to the phases before it (None for phase 0); the offline
    /// designer raises its bar for the next phase when it did not.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub newest_phase_added: Option<bool>,
}

/// Which data chi was measured on.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EvaluationFacts {
    pub held_out_episodes: usize,
    /// Held-out rows (episode, step, agent).
    pub held_out_rows: u32,
    /// What chi and the two discriminators are, for a reader of the JSON (the LLM).
    pub note: String,
}

/// How the two discriminators trained, and their configuration.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DiscriminatorReports {
    pub with_communication: TrainReport,
    pub without_communication: TrainReport,
    pub config: DiscriminatorConfig,
}

/// Recovery of one state dim, with and without the messages.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DimRecovery {
    /// The state dim's index: what programs use (the label is for people and the LLM).
    pub dim: usize,
    /// `s[62] - <meaning>` ([`dim_label`]).
    pub dimension: String,
    /// E[chi] of always guessing the dim's median: the level a rate must beat.
    pub constant_guess_rate: f64,
    pub with_communication: SideRecovery,
    pub without_communication: SideRecovery,
}

/// One side (with or without communication) of a dim's recovery: per-agent E_t[chi] over whole
/// episodes and per third of each episode ([`THIRDS`]), with population variances across agents.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SideRecovery {
    pub agent_success_rates: Vec<f64>,
    pub variance_across_agents: f64,
    pub early: Vec<f64>,
    pub variance_in_early: f64,
    pub mid: Vec<f64>,
    pub variance_in_mid: f64,
    pub late: Vec<f64>,
    pub variance_in_late: f64,
}

impl SideRecovery {
    /// From unrounded per-agent rates over whole episodes and per third (in [`THIRDS`] order):
    /// rates rounded to 3 decimals, variances (of the unrounded rates) to 5.
    pub fn from_rates(rates: &[f64], thirds: [&[f64]; 3]) -> SideRecovery {
        let r3 = |v: &[f64]| v.iter().map(|&x| round3(x)).collect::<Vec<f64>>();
        let var5 = |v: &[f64]| round5(variance(v));
        let [early, mid, late] = thirds;
        SideRecovery {
            agent_success_rates: r3(rates),
            variance_across_agents: var5(rates),
            early: r3(early),
            variance_in_early: var5(early),
            mid: r3(mid),
            variance_in_mid: var5(mid),
            late: r3(late),
            variance_in_late: var5(late),
        }
    }

    /// Per-agent rates and their variance across agents in third `th` ([`THIRDS`]`[th]`).
    pub fn third(&self, th: usize) -> (&[f64], f64) {
        match th {
            0 => (&self.early, self.variance_in_early),
            1 => (&self.mid, self.variance_in_mid),
            2 => (&self.late, self.variance_in_late),
            _ => panic!("third {th} of an episode: there are {} ({THIRDS:?})", THIRDS.len()),
        }
    }
}

/// Means over the target dims.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MetaSummary {
    /// Every target dim chosen (see [`MetaInfo::target_dims_selection`]).
    pub target_dims: Vec<usize>,
    pub with_communication: RecoverySummary,
    pub without_communication: RecoverySummary,
}

/// Mean recovery and mean variance across agents of one side over the target dims; also one
/// side of a phase in the design directory's `summary.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RecoverySummary {
    pub mean_recovery: f64,
    pub mean_variance_across_agents: f64,
}

/// Every measured state dim of one evaluation, unselected: what the fixed-dim trend and the
/// figures are computed from (`phase<k>/recovery.json`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DimRates {
    pub dim: usize,
    /// E[chi] of always guessing the dim's median.
    pub constant_guess_rate: f64,
    /// Per-agent E_t[chi] with the agent's received messages.
    pub with_messages: Vec<f64>,
    /// Per-agent E_t[chi] of a second discriminator trained and evaluated with the message
    /// columns zeroed (lmac's default "without").
    pub without_retrained: Vec<f64>,
    /// Per-agent E_t[chi] of the with-messages discriminator given zeroed message columns (the
    /// paper's definition: s_hat_0 = D(tau, 0, i)).
    pub without_zeroed: Vec<f64>,
}

/// One side of a [`SetTrend`]: means over a fixed set of dims.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SideTrend {
    /// Mean over dims and agents of E_t[chi].
    pub mean_recovery: f64,
    /// Skill over the constant guess of the set ([`skill`] of `mean_recovery`
    /// against the set's mean constant-guess rate): 0 = no better than guessing each dim's
    /// median, 1 = always within alpha, negative = worse than the guess.
    pub skill: f64,
    /// Mean over dims of each dim's own skill (dominated by dims whose guess is nearly always
    /// right, where one miss costs a lot; per-dim values are in recovery.json).
    pub mean_skill: f64,
    /// Mean over dims of the variance of E_t[chi] across agents.
    pub mean_variance_across_agents: f64,
    /// Per agent: mean over dims of E_t[chi].
    pub per_agent: Vec<f64>,
}

/// Recovery over one fixed set of dims, with and without messages (both definitions).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SetTrend {
    pub dims: usize,
    /// Mean constant-guess rate over the dims: the level `mean_recovery` must beat.
    pub constant_guess_rate: f64,
    pub with_messages: SideTrend,
    pub without_retrained: SideTrend,
    pub without_zeroed: SideTrend,
}

/// Whether a phase's messages help on a set of dims, said plainly: they help when the
/// recovery with messages beats both the no-message baseline (a discriminator retrained without
/// them) and a constant guess of each dim's median.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Verdict {
    pub messages_help: bool,
    /// Skill of the recovery with messages over the no-message baseline:
    /// (with - without) / (1 - without); 0 = no better than without messages.
    pub skill_over_no_messages: f64,
    /// Skill over a constant guess ([`SideTrend::skill`] of the with-messages side).
    pub skill_over_constant_guess: f64,
    /// The sentence the log, `summary.json` and the next phase's designer read.
    pub text: String,
    /// For "does this phase add": the gain's 95% interval over the held-out episodes; the phase
    /// adds only when the whole interval is above zero.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub interval: Option<super::meta::GainInterval>,
}

impl SetTrend {
    /// The verdict on these dims (`what`: how the set is named in the sentence).
    pub fn verdict(&self, what: &str) -> Verdict {
        let (w, o) = (&self.with_messages, &self.without_retrained);
        let over_none = skill(w.mean_recovery, o.mean_recovery);
        let r4 = |x: f64| (x * 1e4).round() / 1e4;
        let helps = w.mean_recovery > o.mean_recovery && w.skill > 0.0;
        let numbers = format!(
            "recovery {:.3} with messages, {:.3} without, constant guess {:.3}: skill {:.3} over no messages, {:.3} over the guess",
            w.mean_recovery, o.mean_recovery, self.constant_guess_rate, over_none, w.skill
        );
        let text = if helps {
            format!("the messages help on {what} ({numbers})")
        } else {
            let worst = if w.skill <= 0.0 && w.mean_recovery <= o.mean_recovery {
                "they beat neither the no-message baseline nor a constant guess"
            } else if w.skill <= 0.0 {
                "a constant guess of each dim does as well"
            } else {
                "agents recover these dims as well without them"
            };
            format!("the messages do NOT help on {what}: {worst} ({numbers}); the next phase should send something else for these dims")
        };
        Verdict {
            messages_help: helps,
            skill_over_no_messages: r4(over_none),
            skill_over_constant_guess: r4(w.skill),
            text,
            interval: None,
        }
    }

    /// Does the newest phase add anything? `self`: phases 0..=k on the fixed dims, `before`:
    /// phases 0..k on the same dims. It helps when recovery with all k + 1 phases' messages is
    /// above recovery with the first k phases' (both discriminators trained on the same B): by
    /// more than the held-out episodes' noise when `interval` ([`super::meta::gain_interval`]
    /// of the two) is given.
    pub fn marginal_verdict(&self, before: &SetTrend, phase: usize, columns: usize, interval: Option<GainInterval>) -> Verdict {
        let with = format!("with phases 0..={phase}");
        let against = format!("with phases 0..{phase}");
        self.adds_to(
            before.with_messages.mean_recovery,
            phase,
            [&with, &against, "the earlier phases", "more message columns", "nothing more"],
            columns,
            interval,
        )
    }

    /// Does phase `phase` add anything when no earlier phase was kept? `self`: that phase's
    /// messages alone on the fixed dims. It helps when recovery with them is above recovery
    /// without messages (a discriminator retrained without them), as
    /// [`marginal_verdict`](Self::marginal_verdict) asks of a later phase against the earlier.
    pub fn adds_over_no_messages(&self, phase: usize, columns: usize, interval: Option<GainInterval>) -> Verdict {
        let with = format!("with phase {phase}'s messages");
        let none = self.without_retrained.mean_recovery;
        self.adds_to(none, phase, [&with, "without messages", "no messages", "message columns", "nothing"], columns, interval)
    }

    /// The verdict of recovery with the phase's messages against `then`, worded by `words`:
    /// [how "now" is named, how "then" is named, what is added to, the columns' noun, what the
    /// messages recover when they do not help].
    fn adds_to(&self, then: f64, phase: usize, words: [&str; 5], columns: usize, interval: Option<GainInterval>) -> Verdict {
        let [with, against, base, noun, recover] = words;
        let now = self.with_messages.mean_recovery;
        let r4 = |x: f64| (x * 1e4).round() / 1e4;
        let over = skill(now, then);
        let mut numbers = format!(
            "recovery on the {} fixed dims {now:.3} {with} against {then:.3} {against}: skill {over:.3} over {base}, for {columns} {noun}",
            self.dims
        );
        if let Some(iv) = &interval {
            numbers.push_str(&format!(
                "; gain {:+.4}, 95% interval [{:+.4}, {:+.4}] over the {} held-out episodes",
                iv.gain, iv.lo, iv.hi, iv.episodes
            ));
        }
        let helps = match &interval {
            Some(iv) => iv.lo > 0.0,
            None => now > then,
        };
        let text = if helps {
            format!("phase {phase} adds to {base} ({numbers})")
        } else if now > then && interval.is_some() {
            format!(
                "phase {phase} does NOT add to {base} beyond the noise of the held-out episodes ({numbers}); its messages cost columns and recover {recover} that this data can tell apart"
            )
        } else {
            format!("phase {phase} does NOT add to {base} ({numbers}); its messages cost columns and recover {recover}")
        };
        Verdict {
            messages_help: helps,
            skill_over_no_messages: r4(over),
            skill_over_constant_guess: r4(self.with_messages.skill),
            text,
            interval,
        }
    }

    /// One line for logs and the CLI.
    pub fn summary_line(&self) -> String {
        let (w, r, z) = (&self.with_messages, &self.without_retrained, &self.without_zeroed);
        format!(
            "on {} dims: recovery {:.3} with messages, {:.3} without (retrained), {:.3} (zeroed); constant guess {:.3}; skill {:.3} / {:.3} / {:.3}",
            self.dims, w.mean_recovery, r.mean_recovery, z.mean_recovery, self.constant_guess_rate, w.skill, r.skill, z.skill
        )
    }

    /// Means over the entries of `table` whose dim is in `dims` (all entries when `dims` is
    /// empty); rates rounded to 4 decimals, variances to 6.
    pub fn over(table: &[DimRates], dims: &[usize]) -> SetTrend {
        let rows: Vec<&DimRates> = table.iter().filter(|r| dims.is_empty() || dims.contains(&r.dim)).collect();
        let r4 = |x: f64| (x * 1e4).round() / 1e4;
        let side = |pick: fn(&DimRates) -> &Vec<f64>| -> SideTrend {
            let n_agents = rows.first().map(|r| pick(r).len()).unwrap_or(0);
            let means: Vec<f64> = rows.iter().map(|r| mean(pick(r))).collect();
            let skills: Vec<f64> = rows.iter().map(|r| skill(mean(pick(r)), r.constant_guess_rate)).collect();
            let vars: Vec<f64> = rows.iter().map(|r| variance(pick(r))).collect();
            let guess = mean(&rows.iter().map(|r| r.constant_guess_rate).collect::<Vec<f64>>());
            SideTrend {
                mean_recovery: r4(mean(&means)),
                skill: r4(skill(mean(&means), guess)),
                mean_skill: r4(mean(&skills)),
                mean_variance_across_agents: (mean(&vars) * 1e6).round() / 1e6,
                per_agent: (0..n_agents).map(|i| r4(mean(&rows.iter().map(|r| pick(r)[i]).collect::<Vec<f64>>()))).collect(),
            }
        };
        SetTrend {
            dims: rows.len(),
            constant_guess_rate: r4(mean(&rows.iter().map(|r| r.constant_guess_rate).collect::<Vec<f64>>())),
            with_messages: side(|r| &r.with_messages),
            without_retrained: side(|r| &r.without_retrained),
            without_zeroed: side(|r| &r.without_zeroed),
        }
    }
}

/// Rounding of rates (3 decimals) in the meta-information.
pub fn round3(x: f64) -> f64 {
    (x * 1000.0).round() / 1000.0
}

/// Rounding of variances (5 decimals) in the meta-information.
pub fn round5(x: f64) -> f64 {
    (x * 100_000.0).round() / 100_000.0
}

impl MetaInfo {
    /// As a JSON value: `meta.json` and the prompt are rendered from this, so their keys come
    /// out sorted (serde_json's map) as they always have, whatever the fields' order here or in
    /// `TrainReport` and `DiscriminatorConfig`.
    pub fn json(&self) -> serde_json::Value {
        // Cannot fail: plain structs, lists, strings and numbers (a non-finite number becomes null).
        serde_json::to_value(self).expect("MetaInfo serializes to JSON")
    }

    /// One line for logs: mean recovery and variance across agents over the target dims.
    pub fn summary_line(&self) -> String {
        let s = &self.summary;
        let (w, o) = (&s.with_communication, &s.without_communication);
        format!(
            "recovery {:.3} with messages, {:.3} without; variance across agents {:.3} with, {:.3} without ({} target dims, {} message columns)",
            w.mean_recovery,
            o.mean_recovery,
            w.mean_variance_across_agents,
            o.mean_variance_across_agents,
            s.target_dims.len(),
            self.message_columns,
        )
    }
}

/// Meta-information with `dims` (index, label), every third of the episodes at the same
/// per-agent rates; for tests of its readers.
#[cfg(test)]
pub(crate) fn example(dims: &[(usize, String)], with: &[f64], without: &[f64]) -> MetaInfo {
    let side = |r: &[f64]| SideRecovery::from_rates(r, [r, r, r]);
    let mean_side = |r: &[f64]| RecoverySummary { mean_recovery: round3(mean(r)), mean_variance_across_agents: round5(variance(r)) };
    MetaInfo {
        env: "lbf:8x8-2p-2f-s1-coop".into(),
        alpha: 0.1,
        phases: 1,
        message_columns: 4,
        evaluation: EvaluationFacts { held_out_episodes: 10, held_out_rows: 400, note: "synthetic".into() },
        discriminators: DiscriminatorReports {
            with_communication: TrainReport::default(),
            without_communication: TrainReport::default(),
            config: DiscriminatorConfig::default(),
        },
        target_dims_selection: "synthetic".into(),
        dimensions: dims
            .iter()
            .map(|(d, label)| DimRecovery {
                dim: *d,
                dimension: label.clone(),
                constant_guess_rate: 0.5,
                with_communication: side(with),
                without_communication: side(without),
            })
            .collect(),
        summary: MetaSummary {
            target_dims: dims.iter().map(|(d, _)| *d).collect(),
            with_communication: mean_side(with),
            without_communication: mean_side(without),
        },
        dead_fields: Vec::new(),
        verdicts: Vec::new(),
        newest_phase_added: None,
    }
}

#[cfg(test)]
mod verdict_tests {
    use super::*;

    fn rates(dim: usize, guess: f64, with: f64, without: f64) -> DimRates {
        DimRates {
            dim,
            constant_guess_rate: guess,
            with_messages: vec![with, with],
            without_retrained: vec![without, without],
            without_zeroed: vec![without, without],
        }
    }

    /// The main job's LBF phase 0 as the issue quotes it: recovery 0.944 with messages, 0.949
    /// without, constant guess 0.958. The verdict says the messages do not help; a phase whose
    /// messages beat both is said to help, with its skill over no messages.
    #[test]
    fn the_verdict_says_when_messages_do_not_help() {
        let bad = SetTrend::over(&[rates(0, 0.958, 0.944, 0.949)], &[]).verdict("the 1 fixed dims");
        assert!(!bad.messages_help);
        assert!(
            bad.text.contains("do NOT help") && bad.text.contains("neither the no-message baseline nor a constant guess"),
            "{}",
            bad.text
        );
        assert!(bad.skill_over_no_messages < 0.0 && bad.skill_over_constant_guess < 0.0, "{bad:?}");
        let good = SetTrend::over(&[rates(0, 0.5, 0.9, 0.6)], &[]).verdict("the 1 fixed dims");
        assert!(good.messages_help, "{good:?}");
        assert!((good.skill_over_no_messages - 0.75).abs() < 1e-9, "(0.9 - 0.6) / (1 - 0.6): {good:?}");
        // better than without messages but not than a constant guess: still not helping
        let guess = SetTrend::over(&[rates(0, 0.95, 0.9, 0.6)], &[]).verdict("x");
        assert!(!guess.messages_help && guess.text.contains("a constant guess of each dim does as well"), "{}", guess.text);
    }

    /// The LBF relevance design's phase 2 (docs/results/design.md): 0.957 with phases 0..=2
    /// against 0.960 with phases 0..2 adds nothing; phase 1's 0.960 against 0.958 adds.
    #[test]
    fn the_marginal_verdict_says_whether_a_phase_adds() {
        let before = SetTrend::over(&[rates(0, 0.92, 0.960, 0.94)], &[]);
        let after = SetTrend::over(&[rates(0, 0.92, 0.957, 0.94)], &[]);
        let v = after.marginal_verdict(&before, 2, 1, None);
        assert!(!v.messages_help && v.text.contains("phase 2 does NOT add"), "{}", v.text);
        assert!(
            v.text.contains("0.957 with phases 0..=2 against 0.960 with phases 0..2") && v.text.contains("1 more message columns"),
            "{}",
            v.text
        );
        let v = before.marginal_verdict(&SetTrend::over(&[rates(0, 0.92, 0.958, 0.94)], &[]), 1, 0, None);
        assert!(v.messages_help && v.text.starts_with("phase 1 adds"), "{}", v.text);
        assert!((v.skill_over_no_messages - 0.0476).abs() < 1e-3, "(0.960 - 0.958) / (1 - 0.958): {v:?}");
    }

    /// The recipe's 1o_10b phase 2 (docs/results/design.md): 0.794 against 0.792 is a gain, but
    /// one the held-out episodes cannot tell from noise, so with its interval the phase does not
    /// add; an interval above zero does.
    #[test]
    fn a_phase_adds_only_beyond_the_held_out_noise() {
        let before = SetTrend::over(&[rates(0, 0.469, 0.792, 0.4)], &[]);
        let after = SetTrend::over(&[rates(0, 0.469, 0.794, 0.4)], &[]);
        let noise = GainInterval { gain: 0.002, lo: -0.003, hi: 0.007, episodes: 200 };
        let v = after.marginal_verdict(&before, 2, 21, Some(noise));
        assert!(!v.messages_help, "{v:?}");
        assert!(v.text.contains("beyond the noise of the held-out episodes") && v.text.contains("[-0.0030, +0.0070]"), "{}", v.text);
        assert_eq!(v.interval, Some(noise));
        let clear = GainInterval { gain: 0.002, lo: 0.001, hi: 0.003, episodes: 200 };
        let v = after.marginal_verdict(&before, 2, 21, Some(clear));
        assert!(v.messages_help && v.text.starts_with("phase 2 adds"), "{}", v.text);
        // a loss stays a loss whatever its interval
        let v = before.marginal_verdict(&after, 2, 21, Some(GainInterval { gain: -0.002, lo: -0.007, hi: 0.003, episodes: 200 }));
        assert!(!v.messages_help && !v.text.contains("beyond the noise"), "{}", v.text);
    }
}
