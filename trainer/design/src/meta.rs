//! The meta-information (paper eq. 3, appendix B.2, Figure B.2): how often each agent recovers
//! each state dim with and without the protocol's messages.
//!
//! chi[l,d,t,i] = 1[(s_hat[l,d,t,i] - s[d,t])^2 <= alpha], where s_hat[1] comes from the
//! discriminator trained with agent i's received messages and s_hat[0] from the one trained with
//! the message columns zeroed, both measured on held-out episodes of B, in the state's own units.
//!
//! [`evaluate`] returns a [`MetaInfo`] ([`super::meta_info`], which also shows its JSON).
//! Early/mid/late are the thirds of each episode's own length (step t of an episode of length
//! L falls in third floor(3t/L)), so short episodes (food collected early) contribute to all
//! three. Variances are population variances across agents.
//!
//! Target dims: the union of the critical state dims of the phases so far (all dims when none
//! are listed). More than [`MetaConfig::max_target_dims`] (prompt size) are cut to the worst
//! recovered with messages relative to a constant guess ([`skill`]; ties: worst without
//! messages, then lower index); [`MetaInfo::target_dims_selection`] says so.

use super::discriminator::{split_episodes, DiscInput, Discriminator, DiscriminatorConfig, TrainReport};
use super::meta_info::{
    round3, round5, DimRates, DimRecovery, DiscriminatorReports, EvaluationFacts, MetaInfo, MetaSummary, RecoverySummary, SideRecovery,
};
use super::DesignContext;
use anyhow::{bail, Result};
use burn::tensor::Device;
use lmac_protocol_runner::plan::MessagePlan;
use lmac_protocol_runner::protocol::{self, ValidatedProtocol};
use lmac_run::dataset::Dataset;
use serde::{Deserialize, Serialize};

/// How the meta-information is measured.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MetaConfig {
    pub discriminator: DiscriminatorConfig,
    /// Most target dims in the meta-information (each costs a few hundred characters of prompt).
    pub max_target_dims: usize,
    /// Which "without messages" the designers are shown (both are always measured and written
    /// to `recovery.json`).
    pub without: NoMessages,
}

impl Default for MetaConfig {
    fn default() -> Self {
        MetaConfig { discriminator: DiscriminatorConfig::default(), max_target_dims: 32, without: NoMessages::Retrained }
    }
}

/// The two definitions of recovery "without messages".
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum NoMessages {
    /// A second discriminator, trained and evaluated with the message columns zeroed: what an
    /// agent can infer without the messages at all.
    #[default]
    Retrained,
    /// The paper's: the with-messages discriminator evaluated with the message columns zeroed
    /// (s_hat_0 = D(tau, 0, i)), which also counts what that discriminator relies on the
    /// messages for even where the agent's own view would have sufficed.
    Zeroed,
}

impl std::str::FromStr for NoMessages {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "retrained" => Ok(NoMessages::Retrained),
            "zeroed" => Ok(NoMessages::Zeroed),
            _ => Err(format!("{s:?}: use \"retrained\" (a second discriminator without messages) or \"zeroed\" (the paper's: the same discriminator, messages zeroed)")),
        }
    }
}

/// Which third of an episode of `len` steps step `t` falls in.
pub fn third(t: usize, len: usize) -> usize {
    (3 * t / len.max(1)).min(2)
}

/// The indicator chi: is the reconstruction within alpha (squared error) of the state?
pub fn chi(s_hat: f32, s: f32, alpha: f64) -> bool {
    let d = (s_hat - s) as f64;
    d * d <= alpha
}

/// chi counted per state dim, agent and third of the episode, over held-out rows.
#[derive(Clone, Debug, PartialEq)]
pub struct Recovery {
    /// The state dims measured.
    pub dims: Vec<usize>,
    pub n_agents: usize,
    /// Successes, indexed [dim position][agent][third].
    hits: Vec<u32>,
    /// Rows, indexed [agent][third] (the same for every dim).
    totals: Vec<u32>,
    /// Successes per held-out episode, indexed [episode position][dim position], summed over
    /// agents and steps: the unit [`gain_interval`] resamples.
    episode_hits: Vec<u32>,
    /// Rows (steps x agents) per held-out episode.
    episode_rows: Vec<u32>,
}

impl Recovery {
    /// Measure `disc` on the rows of `episodes` for `dims`, in chunks (predictions are not kept).
    pub fn measure(disc: &Discriminator, input: &DiscInput, episodes: &[usize], dims: &[usize], alpha: f64) -> Result<Recovery> {
        let data = input.data;
        let (n, sd) = (data.header.n_agents, data.header.state_dim);
        if let Some(&d) = dims.iter().find(|&&d| d >= sd) {
            bail!("state dim {d} is out of range (state_dim {sd})");
        }
        let nd = dims.len();
        let mut r = Recovery {
            dims: dims.to_vec(),
            n_agents: n,
            hits: vec![0; nd * n * 3],
            totals: vec![0; n * 3],
            episode_hits: vec![0; episodes.len() * nd],
            episode_rows: vec![0; episodes.len()],
        };
        // pos: the episode's position in `episodes` (its row of `episode_hits`).
        let mut pos = 0;
        for chunk in episodes.chunks(64) {
            let pred = disc.predict(input, chunk)?;
            let mut row = 0;
            for &e in chunk {
                let ep = &data.episodes[e];
                r.episode_rows[pos] = (ep.len * n) as u32;
                for t in 0..ep.len {
                    let th = third(t, ep.len);
                    let s = &ep.state[t * sd..(t + 1) * sd];
                    for i in 0..n {
                        let p = &pred[row * sd..(row + 1) * sd];
                        r.totals[i * 3 + th] += 1;
                        for (k, &d) in dims.iter().enumerate() {
                            if chi(p[d], s[d], alpha) {
                                r.hits[(k * n + i) * 3 + th] += 1;
                                r.episode_hits[pos * nd + k] += 1;
                            }
                        }
                        row += 1;
                    }
                }
                pos += 1;
            }
        }
        Ok(r)
    }

    /// E_t[chi] of agent i for the k-th measured dim (0 when the agent has no rows).
    pub fn rate(&self, k: usize, i: usize) -> f64 {
        let hits: u32 = (0..3).map(|th| self.hits[(k * self.n_agents + i) * 3 + th]).sum();
        let total: u32 = (0..3).map(|th| self.totals[i * 3 + th]).sum();
        hits as f64 / total.max(1) as f64
    }

    /// E_t[chi] of agent i for the k-th dim over the steps in one third of the episodes.
    pub fn third_rate(&self, k: usize, i: usize, th: usize) -> f64 {
        self.hits[(k * self.n_agents + i) * 3 + th] as f64 / self.totals[i * 3 + th].max(1) as f64
    }

    /// Per-agent rates of the k-th dim.
    pub fn rates(&self, k: usize) -> Vec<f64> {
        (0..self.n_agents).map(|i| self.rate(k, i)).collect()
    }

    /// Mean over agents of the k-th dim's rates.
    pub fn mean_rate(&self, k: usize) -> f64 {
        mean(&self.rates(k))
    }

    /// Variance across agents of the k-th dim's rates.
    pub fn variance_across_agents(&self, k: usize) -> f64 {
        variance(&self.rates(k))
    }

    /// Position of state dim `d` among the measured dims.
    pub fn position(&self, d: usize) -> Option<usize> {
        self.dims.iter().position(|&x| x == d)
    }
}

/// How much recovery of a set of dims changed between two measurements on the same held-out
/// episodes, with a 95% interval from a paired bootstrap over those episodes. It covers which
/// episodes happened to be held out, not how the two discriminators' training happened to go.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GainInterval {
    /// Mean recovery over the dims, "now" minus "then".
    pub gain: f64,
    pub lo: f64,
    pub hi: f64,
    /// Held-out episodes resampled.
    pub episodes: usize,
}

/// Bootstrap resamples behind a [`GainInterval`].
const GAIN_RESAMPLES: usize = 2000;

/// The gain in mean recovery of `dims` (every dim both measured when empty) from `then` to
/// `now`, with its [`GainInterval`]; `None` when the two were not measured on the same
/// episodes or a dim is missing from either.
pub fn gain_interval(now: &Recovery, then: &Recovery, dims: &[usize], seed: u64) -> Option<GainInterval> {
    use rand::{Rng, SeedableRng};
    let dims: Vec<usize> =
        if dims.is_empty() { now.dims.iter().copied().filter(|d| then.dims.contains(d)).collect() } else { dims.to_vec() };
    if dims.is_empty() || now.episode_rows != then.episode_rows || now.episode_rows.is_empty() {
        return None;
    }
    // Per episode: successes over the dims, now and then (each dim shares the episode's rows).
    let per_episode = |r: &Recovery| -> Option<Vec<f64>> {
        let pos: Vec<usize> = dims.iter().map(|&d| r.position(d)).collect::<Option<_>>()?;
        let nd = r.dims.len();
        Some((0..r.episode_rows.len()).map(|e| pos.iter().map(|&k| r.episode_hits[e * nd + k] as f64).sum()).collect())
    };
    let (a, b) = (per_episode(now)?, per_episode(then)?);
    let rows: Vec<f64> = now.episode_rows.iter().map(|&x| x as f64 * dims.len() as f64).collect();
    let diff: Vec<f64> = a.iter().zip(&b).map(|(x, y)| x - y).collect();
    // Mean recovery gain over the episodes `picked` (with repeats in a resample).
    let gain_of = |picked: &mut dyn Iterator<Item = usize>| {
        let (d, n) = picked.fold((0.0, 0.0), |(d, n), e| (d + diff[e], n + rows[e]));
        d / f64::max(n, 1.0)
    };
    let n = diff.len();
    let gain = gain_of(&mut (0..n));
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let gains: Vec<f64> = (0..GAIN_RESAMPLES).map(|_| gain_of(&mut (0..n).map(|_| rng.random_range(0..n)))).collect();
    Some(GainInterval { gain, lo: quantile(&gains, 0.025), hi: quantile(&gains, 0.975), episodes: n })
}

pub use super::meta_info::{dim_label, skill, THIRDS};
pub use lmac_learn::stats::{mean, quantile, variance};

/// Per dim of `dims`: E_t[chi] of the best-known constant guess, the median of the dim over
/// (at most 20 000 evenly spread steps of) the training episodes, on the held-out episodes.
pub fn constant_guess(data: &Dataset, train: &[usize], test: &[usize], dims: &[usize], alpha: f64) -> Vec<f64> {
    let sd = data.header.state_dim;
    let steps: usize = train.iter().map(|&e| data.episodes[e].len).sum();
    let stride = steps.div_ceil(20_000).max(1);
    let mut cols: Vec<Vec<f32>> = vec![Vec::new(); dims.len()];
    let mut k = 0usize;
    for &e in train {
        let ep = &data.episodes[e];
        for t in 0..ep.len {
            if k % stride == 0 {
                for (c, &d) in cols.iter_mut().zip(dims) {
                    c.push(ep.state[t * sd + d]);
                }
            }
            k += 1;
        }
    }
    let guess: Vec<f32> = cols
        .iter_mut()
        .map(|c| {
            c.sort_by(|a, b| a.partial_cmp(b).unwrap_or(std::cmp::Ordering::Equal));
            c.get(c.len() / 2).copied().unwrap_or(0.0)
        })
        .collect();
    let mut hits = vec![0u64; dims.len()];
    let mut total = 0u64;
    for &e in test {
        let ep = &data.episodes[e];
        for t in 0..ep.len {
            total += 1;
            for (h, (&d, &g)) in hits.iter_mut().zip(dims.iter().zip(&guess)) {
                if chi(g, ep.state[t * sd + d], alpha) {
                    *h += 1;
                }
            }
        }
    }
    hits.iter().map(|&h| h as f64 / total.max(1) as f64).collect()
}

/// One side (with or without communication) of the k-th measured dim's entry.
fn side(r: &Recovery, k: usize) -> SideRecovery {
    let [early, mid, late] = [0, 1, 2].map(|th| (0..r.n_agents).map(|i| r.third_rate(k, i, th)).collect::<Vec<f64>>());
    SideRecovery::from_rates(&r.rates(k), [&early, &mid, &late])
}

/// Choose the target dims from the measured ones: `wanted` (all measured when empty), capped
/// to `max` worst recovered with messages relative to the constant guess ([`skill`]; `guess`
/// is aligned with `with.dims`; ties: worst without messages, then lower index). Returns (dims
/// sorted by index, explanation).
pub fn select_targets(with: &Recovery, without: &Recovery, guess: &[f64], wanted: &[usize], max: usize) -> (Vec<usize>, String) {
    let pool: Vec<usize> =
        if wanted.is_empty() { with.dims.clone() } else { wanted.iter().copied().filter(|d| with.position(*d).is_some()).collect() };
    let source = if wanted.is_empty() {
        "all state dims (the protocol lists no critical dims)".to_string()
    } else {
        format!("the {} critical state dims of the protocol phases so far", pool.len())
    };
    if pool.len() <= max {
        return (pool, format!("{source}, all of them"));
    }
    let key = |d: usize| {
        let g = with.position(d).and_then(|k| guess.get(k).copied()).unwrap_or(0.0);
        let kw = with.position(d).map(|k| skill(with.mean_rate(k), g)).unwrap_or(1.0);
        let ko = without.position(d).map(|k| skill(without.mean_rate(k), g)).unwrap_or(1.0);
        (kw, ko, d)
    };
    let mut sorted = pool.clone();
    sorted.sort_by(|&a, &b| key(a).partial_cmp(&key(b)).unwrap_or(std::cmp::Ordering::Equal));
    let mut chosen: Vec<usize> = sorted[..max].to_vec();
    chosen.sort_unstable();
    let note = format!(
        "{source}, cut to the {max} worst recovered with communication to keep the prompt short: lowest mean success rate over agents relative to a constant guess ((rate - constant_guess_rate) / (1 - constant_guess_rate), so sparse dims that are usually 0 do not look well recovered just because 0 is a good guess); the other {} are recovered at least as well",
        pool.len() - max
    );
    (chosen, note)
}

/// What [`meta_info`] needs besides the two recoveries.
pub struct MetaFacts<'a> {
    pub env: &'a str,
    pub alpha: f64,
    pub phases: usize,
    pub message_columns: usize,
    pub state_names: &'a [String],
    pub held_out_episodes: usize,
    pub with_report: &'a TrainReport,
    pub without_report: &'a TrainReport,
    pub config: &'a MetaConfig,
}

/// The meta-information for `targets` (each must be among the measured dims).
/// `guess` is the constant-guess rate of each of `with.dims` ([`constant_guess`]).
pub fn meta_info(facts: &MetaFacts, with: &Recovery, without: &Recovery, guess: &[f64], targets: &[usize], selection: &str) -> MetaInfo {
    let mut dims = Vec::new();
    let (mut mw, mut mo, mut vw, mut vo) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for &d in targets {
        let (Some(kw), Some(ko)) = (with.position(d), without.position(d)) else { continue };
        dims.push(DimRecovery {
            dim: d,
            dimension: dim_label(d, facts.state_names),
            constant_guess_rate: round3(guess.get(kw).copied().unwrap_or(0.0)),
            with_communication: side(with, kw),
            without_communication: side(without, ko),
        });
        mw.push(with.mean_rate(kw));
        mo.push(without.mean_rate(ko));
        vw.push(with.variance_across_agents(kw));
        vo.push(without.variance_across_agents(ko));
    }
    let rows: u32 = with.totals.iter().sum();
    let summary = |m: &[f64], v: &[f64]| RecoverySummary { mean_recovery: round3(mean(m)), mean_variance_across_agents: round5(mean(v)) };
    MetaInfo {
        env: facts.env.to_string(),
        alpha: facts.alpha,
        phases: facts.phases,
        message_columns: facts.message_columns,
        evaluation: EvaluationFacts {
            held_out_episodes: facts.held_out_episodes,
            held_out_rows: rows,
            note: format!(
                "chi = 1[(s_hat - s)^2 <= alpha] in the state's own units, measured on episodes of the dataset that neither discriminator trained on; with_communication: the discriminator given the agent's received messages; without_communication: {}; constant_guess_rate: the success rate of always guessing the dim's median, the level a rate must beat to show any recovery",
                match facts.config.without {
                    NoMessages::Retrained => "the same architecture trained and evaluated with the message columns zeroed",
                    NoMessages::Zeroed => "the with-messages discriminator evaluated with the message columns zeroed",
                }
            ),
        },
        discriminators: DiscriminatorReports {
            with_communication: facts.with_report.clone(),
            without_communication: facts.without_report.clone(),
            config: facts.config.discriminator.clone(),
        },
        target_dims_selection: selection.to_string(),
        dimensions: dims,
        summary: MetaSummary {
            target_dims: targets.to_vec(),
            with_communication: summary(&mw, &vw),
            without_communication: summary(&mo, &vo),
        },
        dead_fields: Vec::new(),
        verdicts: Vec::new(),
        newest_phase_added: None,
    }
}

/// Check that the dataset was collected on the environment the design is for.
pub fn check_dataset(data: &Dataset, ctx: &DesignContext) -> Result<()> {
    let (h, s) = (&data.header, ctx.schema);
    if (h.n_agents, h.obs_dim, h.state_dim, h.n_actions) != (s.n_agents, s.obs_dim, s.state_dim, s.n_actions) {
        bail!(
            "dataset of {} has {} agents, obs {}, state {}, {} actions; the environment {} has {}, {}, {}, {}",
            h.env,
            h.n_agents,
            h.obs_dim,
            h.state_dim,
            h.n_actions,
            ctx.env_name,
            s.n_agents,
            s.obs_dim,
            s.state_dim,
            s.n_actions
        );
    }
    Ok(())
}

/// Both discriminators of one protocol and their recoveries on the held-out episodes.
pub struct Measured {
    pub with: Recovery,
    /// [`NoMessages::Retrained`].
    pub without: Recovery,
    /// [`NoMessages::Zeroed`].
    pub zeroed: Recovery,
    pub with_report: TrainReport,
    pub without_report: TrainReport,
    pub held_out: Vec<usize>,
    pub message_columns: usize,
    /// Constant-guess rate of each measured dim ([`constant_guess`]), aligned with `with.dims`.
    pub guess: Vec<f64>,
    /// The protocol's links that carry nothing on B ([`super::dead_fields`]).
    pub dead_fields: Vec<super::dead_fields::DeadField>,
}

/// Recovery of `dims` on the held-out episodes by a discriminator trained with the messages of
/// `phases` (not the no-message one: [`measure`] for both).
pub fn recovery_with(ctx: &DesignContext, phases: &[ValidatedProtocol], cfg: &DiscriminatorConfig, dims: &[usize]) -> Result<Recovery> {
    let Some(data) = ctx.dataset else { bail!("measuring recovery needs the dataset B, which has not been collected yet") };
    check_dataset(data, ctx)?;
    cfg.validate()?;
    let (train, test) = split_episodes(data.episodes.len(), cfg.holdout_fraction, ctx.seed)?;
    let plan =
        protocol::compile_plan(phases, ctx.env).map_err(|e| anyhow::anyhow!("compiling the protocol: {}", protocol::errors_to_text(&e)))?;
    let messages = data.messages(&mut plan.clone());
    let input = DiscInput::with_messages(data, &messages, plan.msg_dim());
    let (d1, _) = Discriminator::train(&input, &train, cfg, ctx.seed ^ 0x1, &Device::default())?;
    Recovery::measure(&d1, &input, &test, dims, ctx.schema.alpha)
}

/// Recompute the messages of `phases` on B with the runner's compiled plan, train D^(k) with
/// and without them on the training episodes, and count chi on the held-out ones for `dims`
/// (all state dims when empty). With no phases there are no messages and only the
/// no-communication discriminator is trained (`with` is then a copy of `without`).
pub fn measure(ctx: &DesignContext, phases: &[ValidatedProtocol], cfg: &DiscriminatorConfig, dims: &[usize]) -> Result<Measured> {
    let Some(data) = ctx.dataset else { bail!("measuring recovery needs the dataset B, which has not been collected yet") };
    check_dataset(data, ctx)?;
    cfg.validate()?;
    let (train, test) = split_episodes(data.episodes.len(), cfg.holdout_fraction, ctx.seed)?;
    let (messages, msg_dim, dead_fields) = if phases.is_empty() {
        (Vec::new(), 0, Vec::new())
    } else {
        let plan = protocol::compile_plan(phases, ctx.env)
            .map_err(|e| anyhow::anyhow!("compiling the protocol: {}", protocol::errors_to_text(&e)))?;
        let messages = data.messages(&mut plan.clone());
        let dead = super::dead_fields::scan(data, &plan, &messages);
        (messages, plan.msg_dim(), dead)
    };
    let all: Vec<usize> = if dims.is_empty() { (0..data.header.state_dim).collect() } else { dims.to_vec() };
    let device = Device::default();
    let alpha = ctx.schema.alpha;
    let zeroed_input = DiscInput::without_messages(data, msg_dim);
    let (d0, without_report) = Discriminator::train(&zeroed_input, &train, cfg, ctx.seed ^ 0x2, &device)?;
    let without = Recovery::measure(&d0, &zeroed_input, &test, &all, alpha)?;
    let (with, zeroed, with_report) = if phases.is_empty() {
        (without.clone(), without.clone(), without_report.clone())
    } else {
        let input = DiscInput::with_messages(data, &messages, msg_dim);
        let (d1, report) = Discriminator::train(&input, &train, cfg, ctx.seed ^ 0x1, &device)?;
        let with = Recovery::measure(&d1, &input, &test, &all, alpha)?;
        (with, Recovery::measure(&d1, &zeroed_input, &test, &all, alpha)?, report)
    };
    let guess = constant_guess(data, &train, &test, &all, alpha);
    Ok(Measured { with, without, zeroed, with_report, without_report, held_out: test, message_columns: msg_dim, guess, dead_fields })
}

/// The design loop's evaluation of phases 0..=k on B: the meta-information.
pub fn evaluate(ctx: &DesignContext, phases: &[ValidatedProtocol], cfg: &MetaConfig) -> Result<MetaInfo> {
    evaluate_all(ctx, phases, cfg).map(|e| e.meta)
}

/// An evaluation: the meta-information the designers read (target dims only) and every
/// measured dim with both definitions of "without messages" (the figures).
pub struct Evaluation {
    pub meta: MetaInfo,
    pub dims: Vec<DimRates>,
    /// Every measured dim's held-out recovery with the messages and without them (retrained):
    /// what [`gain_interval`] compares across phases.
    pub held_out: HeldOutRecovery,
}

/// Held-out recovery of every state dim with a phase's messages and without them (a
/// discriminator retrained without).
#[derive(Clone, Debug, PartialEq)]
pub struct HeldOutRecovery {
    pub with: Recovery,
    pub without: Recovery,
}

/// [`evaluate`], keeping every measured dim.
pub fn evaluate_all(ctx: &DesignContext, phases: &[ValidatedProtocol], cfg: &MetaConfig) -> Result<Evaluation> {
    if cfg.max_target_dims == 0 {
        bail!("meta.max_target_dims must be at least 1");
    }
    let m = measure(ctx, phases, &cfg.discriminator, &[])?;
    let without = match cfg.without {
        NoMessages::Retrained => &m.without,
        NoMessages::Zeroed => &m.zeroed,
    };
    let mut critical: Vec<usize> = phases.iter().flat_map(|p| p.critical_dims.iter().copied()).collect();
    critical.sort_unstable();
    critical.dedup();
    let (targets, selection) = select_targets(&m.with, without, &m.guess, &critical, cfg.max_target_dims);
    let names = ctx.schema.state_meanings();
    let facts = MetaFacts {
        env: ctx.env_name,
        alpha: ctx.schema.alpha,
        phases: phases.len(),
        message_columns: m.message_columns,
        state_names: &names,
        held_out_episodes: m.held_out.len(),
        with_report: &m.with_report,
        without_report: &m.without_report,
        config: cfg,
    };
    let mut meta = meta_info(&facts, &m.with, without, &m.guess, &targets, &selection);
    meta.dead_fields = m.dead_fields.iter().map(|d| d.describe()).collect();
    let r4 = |v: Vec<f64>| v.into_iter().map(|x| (x * 1e4).round() / 1e4).collect::<Vec<f64>>();
    let dims = (0..m.with.dims.len())
        .map(|k| DimRates {
            dim: m.with.dims[k],
            constant_guess_rate: (m.guess[k] * 1e4).round() / 1e4,
            with_messages: r4(m.with.rates(k)),
            without_retrained: r4(m.without.rates(k)),
            without_zeroed: r4(m.zeroed.rates(k)),
        })
        .collect();
    Ok(Evaluation { meta, dims, held_out: HeldOutRecovery { with: m.with, without: m.without } })
}

#[cfg(test)]
mod gain_tests {
    use super::*;

    /// A recovery of one dim by one agent over `hits.len()` episodes of 10 steps each.
    fn recovery(hits: &[u32]) -> Recovery {
        Recovery {
            dims: vec![3],
            n_agents: 1,
            hits: vec![hits.iter().sum(), 0, 0],
            totals: vec![10 * hits.len() as u32, 0, 0],
            episode_hits: hits.to_vec(),
            episode_rows: vec![10; hits.len()],
        }
    }

    #[test]
    fn the_gain_interval_tells_a_steady_gain_from_noise() {
        // One more hit in every episode: +0.1, and every resample says so.
        let then = recovery(&[5; 40]);
        let steady = recovery(&[6; 40]);
        let iv = gain_interval(&steady, &then, &[3], 7).expect("same episodes");
        assert!((iv.gain - 0.1).abs() < 1e-12 && (iv.lo - 0.1).abs() < 1e-12 && iv.episodes == 40, "{iv:?}");
        // One more hit in half the episodes, one fewer in the other half: +0 on average, and
        // the interval spans zero.
        let mixed: Vec<u32> = (0..40).map(|e| if e % 2 == 0 { 6 } else { 4 }).collect();
        let iv = gain_interval(&recovery(&mixed), &then, &[], 7).expect("same episodes");
        assert!(iv.gain.abs() < 1e-12 && iv.lo < 0.0 && iv.hi > 0.0, "{iv:?}");
        // The same seed gives the same interval.
        assert_eq!(gain_interval(&recovery(&mixed), &then, &[], 7), Some(iv));
        // Different episodes or a dim not measured: no interval.
        assert_eq!(gain_interval(&recovery(&[5; 39]), &then, &[3], 7), None);
        assert_eq!(gain_interval(&steady, &then, &[4], 7), None);
    }
}
