//! The feedback the designer writes from the meta-information, as text with the numbers.

use super::assemble::short;
use super::meta_dims::{fmt_rates, meta_dims, MetaDim};
use super::{DesignContext, Feedback, OfflineDesigner};
use crate::meta;
use crate::meta_info::MetaInfo;
use anyhow::Result;

impl OfflineDesigner {
    pub(super) fn feedback_text(&mut self, ctx: &DesignContext, phase: usize, meta_v: &MetaInfo) -> Result<Feedback> {
        let dims = meta_dims(meta_v)?;
        let names = ctx.schema.state_meanings();
        let (w, o) = (&meta_v.summary.with_communication, &meta_v.summary.without_communication);
        let (rw, ro, vw, vo) = (w.mean_recovery, o.mean_recovery, w.mean_variance_across_agents, o.mean_variance_across_agents);
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
            meta_v.alpha,
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
            format!("offline designer: feedback from the meta-information of phases 0..={}: {}", phase - 1, meta_v.summary_line()),
            serde_json::to_string_pretty(&fb)?,
        );
        Ok(fb)
    }
}
