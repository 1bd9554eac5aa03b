//! `lmac design`: runs the three phases end to end and writes the design directory.
//!
//! ```text
//! <out>/<env>/<time>-<designer>/
//!   options.json            what was asked (env, designer, seeds, budgets)
//!   collect/                the short QMIX run that collects the dataset B (config, metrics,
//!                           checkpoint) and collect/dataset/ (see `dataset`)
//!   phase<k>/protocol.json  the phase's protocol (validated), protocol.txt its explanation,
//!                           reasoning.md the designer's reasoning, feedback.json (k >= 1) the
//!                           feedback that led to it, meta.json the meta-information of
//!                           phases 0..=k on B (its target dims), recovery.json every state
//!                           dim's per-agent recovery with messages and without (both
//!                           definitions) and its constant-guess rate
//!   final.txt               the final protocol (all phases) explained; final_protocol.txt the
//!                           `--protocol` / `run.protocol` value that trains with it
//!   transcript.json         every prompt and reply (or the offline designer's account)
//!   summary.json            per phase: recovery, skill over a constant guess and variance
//!                           across agents, with and without messages, on fixed dims (phase 0's
//!                           critical dims, and all dims) and on the phase's target dims;
//!                           recovery.png plots the fixed-dim trend (the paper's Figure 3)
//! ```

use super::meta::{evaluate_all, gain_interval, Evaluation, HeldOutRecovery, MetaConfig};
use super::meta_info::{RecoverySummary, SetTrend, Verdict};
use super::{DesignContext, Designer, PhaseProtocol};
use anyhow::{bail, Context, Result};
use lmac_protocol_runner::protocol::{self, ValidatedProtocol};
use lmac_run::dataset::Dataset;
use serde::Serialize;
use std::path::{Path, PathBuf};

/// What to design and with how much data.
#[derive(Clone, Debug, Serialize)]
pub struct DesignOptions {
    pub env: String,
    /// Parent of the design directory.
    pub out: PathBuf,
    pub seed: u64,
    /// Env steps of the run whose epsilon-greedy policy collects B (the paper: 200k).
    pub pretrain_steps: u64,
    /// The method that run trains: `qmix` (the paper's) or another message-free method, e.g.
    /// `qmix-state`, whose agents see the global state: B's returns then show what knowing
    /// something is worth to a policy that acts on it, where a QMIX policy that cannot see the
    /// Roach on 1o_10b makes its position matter little to the return.
    pub collect_algo: String,
    /// Episodes in B (the paper: 5000).
    pub dataset_episodes: usize,
    /// Epsilon while collecting (None: the schedule's value at the end of the QMIX run).
    pub dataset_epsilon: Option<f32>,
    /// Environments per env server and env servers of the collection run.
    pub envs: usize,
    pub servers: usize,
    /// Use this dataset directory instead of collecting one.
    pub dataset: Option<PathBuf>,
    /// Number of phases: 3 in the paper (initialization, recognition, sharing).
    pub phases: usize,
    /// Which "without messages" the designer is shown (both are measured).
    pub without: super::meta::NoMessages,
    /// Drop a phase whose messages add nothing to the kept earlier phases' on the fixed dims
    /// (phase 0, or any phase when none before it was kept: nothing to recovery without
    /// messages); its verdict says so either way. A phase is not dropped where the
    /// discriminator recovers the fixed dims no better than a constant guess on both sides of
    /// the verdict (the gain measures nothing there). When every phase goes, phase 0 is kept.
    /// `summary.json` says why a phase that does not add is kept. Off keeps the paper's three
    /// phases.
    pub drop_unhelpful_phases: bool,
}

/// One phase's line of `summary.json` (read by `lmac_report.plot_design`). The target dims change from
/// phase to phase (they steer the designer); the trend is read on `fixed_dims` and `all_dims`.
#[derive(Clone, Debug, Serialize)]
pub struct PhaseEvaluation {
    pub phase: usize,
    pub message_columns: usize,
    /// On the fixed dims ([`fixed_dims`]), the same for every phase.
    pub fixed_dims: SetTrend,
    /// On every state dim.
    pub all_dims: SetTrend,
    /// On this phase's target dims (what the designer was shown).
    pub with_messages: RecoverySummary,
    pub without_messages: RecoverySummary,
    pub target_dims: Vec<usize>,
    /// Do the messages of phases 0..=k help on the fixed dims (against the no-message baseline
    /// and a constant guess)?
    pub verdict: Verdict,
    /// Does it add to the phases kept before it on the fixed dims (to no messages when none
    /// was kept)? Phase 0 is judged so only with [`DesignOptions::drop_unhelpful_phases`].
    #[serde(skip_serializing_if = "Option::is_none")]
    pub adds: Option<Verdict>,
    /// Dropped from the final protocol (see [`DesignOptions::drop_unhelpful_phases`]).
    pub dropped: bool,
    /// Why a phase that does not add is in the final protocol anyway: the discriminator reads
    /// the fixed dims no better than a constant guess on either side of the verdict, so it
    /// cannot be measured; or every phase failed, and a design sends something (phase 0, the
    /// designer's first).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub kept_because: Option<String>,
    /// Every dim's held-out recovery, which the next phase's "adds" is measured against.
    #[serde(skip)]
    pub held_out: HeldOutRecovery,
}

/// The dims the trend is read on, fixed at phase 0: its task-critical dims (all dims when it
/// names none), so "k = 0 -> 1 -> 2" compares the same set. Returns (dims, where they come from).
pub fn fixed_dims(phase0: &ValidatedProtocol) -> (Vec<usize>, &'static str) {
    let mut fixed = phase0.critical_dims.clone();
    fixed.sort_unstable();
    fixed.dedup();
    let source = if fixed.is_empty() { "all state dims (phase 0 names no critical dims)" } else { "phase 0's critical state dims" };
    (fixed, source)
}

/// Evaluate design phase k with the phases kept before it (`phases`, k's last) on B and write `meta.json` and `recovery.json` into
/// `phase_dir`; log the result. Returns the meta-information (for the designer) and the phase's
/// `summary.json` line.
pub fn evaluate_phase(
    ctx: &DesignContext,
    phases: &[ValidatedProtocol],
    k: usize,
    fixed: &[usize],
    meta_cfg: &MetaConfig,
    phase_dir: &Path,
) -> Result<(super::meta_info::MetaInfo, PhaseEvaluation)> {
    // `k` names the design phase: after a dropped phase, `phases` (the ones kept, this one
    // last) is shorter than k + 1.
    let Evaluation { meta, dims, held_out } = evaluate_all(ctx, phases, meta_cfg)
        .with_context(|| format!("evaluating phase {k} with the {} phase(s) kept on the dataset", phases.len()))?;
    std::fs::create_dir_all(phase_dir).with_context(|| format!("creating {}", phase_dir.display()))?;
    write(&phase_dir.join("meta.json"), &serde_json::to_string_pretty(&meta.json())?)?;
    let recovery = serde_json::json!({ "alpha": ctx.schema.alpha, "dims": dims });
    write(&phase_dir.join("recovery.json"), &serde_json::to_string_pretty(&recovery)?)?;
    let fixed_trend = SetTrend::over(&dims, fixed);
    let verdict = fixed_trend.verdict(&format!("the {} fixed dims", fixed_trend.dims));
    let ev = PhaseEvaluation {
        phase: k,
        message_columns: lmac_protocol_runner::protocol::combined_width(phases),
        fixed_dims: fixed_trend,
        all_dims: SetTrend::over(&dims, &[]),
        with_messages: meta.summary.with_communication.clone(),
        without_messages: meta.summary.without_communication.clone(),
        target_dims: meta.summary.target_dims.clone(),
        verdict,
        adds: None,
        dropped: false,
        kept_because: None,
        held_out,
    };
    eprintln!("lmac: phase {k}: {}", meta.summary_line());
    for d in &meta.dead_fields {
        eprintln!("lmac: phase {k}: warning: {d}");
    }
    eprintln!("lmac: phase {k}: fixed dims {}", ev.fixed_dims.summary_line());
    eprintln!("lmac: phase {k}: {}", ev.verdict.text);
    Ok((meta, ev))
}

fn write(path: &Path, text: &str) -> Result<()> {
    std::fs::write(path, text).with_context(|| format!("writing {}", path.display()))
}

fn save_phase(dir: &Path, k: usize, p: &PhaseProtocol, ctx: &DesignContext) -> Result<PathBuf> {
    let pd = dir.join(format!("phase{k}"));
    std::fs::create_dir_all(&pd)?;
    let file = pd.join("protocol.json");
    // The file says which environment (and schema) it was designed for; the in-memory protocol,
    // which prompts and recordings read, stays as the designer wrote it.
    let saved = protocol::Protocol {
        env: Some(ctx.env_name.to_string()),
        schema_fingerprint: Some(ctx.schema.fingerprint()),
        ..p.protocol.clone()
    };
    write(&file, &serde_json::to_string_pretty(&saved)?)?;
    write(&pd.join("protocol.txt"), &protocol::explain(&p.protocol, Some(ctx.env)))?;
    write(&pd.join("reasoning.md"), &p.reasoning)?;
    Ok(file)
}

/// Run the design: phases, dataset (collected through the pipeline's real processes unless
/// given), discriminators with `meta_cfg`, feedback. Returns the design directory. Ctrl-C
/// (`interrupted`) stops the collection run cleanly.
pub fn run_design(
    opts: &DesignOptions,
    designer: &mut dyn Designer,
    meta_cfg: &MetaConfig,
    interrupted: std::sync::Arc<std::sync::atomic::AtomicBool>,
) -> Result<PathBuf> {
    if opts.phases == 0 {
        bail!("--phases: at least 1");
    }
    let schema = lmac_shm_schema::schema::load_env(&opts.env)?;
    let penv = lmac_protocol_runner::protocol_env(&schema);
    // A directory of this design's own, even when another starts in the same second.
    let dir = lmac_run::run_dir::create_unique_dir(
        &opts.out.join(lmac_run::run_dir::env_dir_name(&opts.env)),
        &format!("{}-{}", lmac_run::run_dir::stamp(), designer.name().replace([':', '/'], "_")),
    )?;
    write(&dir.join("options.json"), &serde_json::to_string_pretty(opts)?)?;
    eprintln!("lmac: design of {} with the {} designer in {}", opts.env, designer.name(), dir.display());
    let ctx0 = DesignContext { env_name: &opts.env, schema: &schema, env: &penv, dataset: None, seed: opts.seed };

    let mut phases: Vec<PhaseProtocol> = Vec::new();
    let mut files: Vec<PathBuf> = Vec::new();
    let persist_transcript =
        |d: &dyn Designer| -> Result<()> { write(&dir.join("transcript.json"), &serde_json::to_string_pretty(&d.transcript())?) };
    // Phase 0 before the data when the designer works from the task prompt alone (an LLM).
    if !designer.needs_data_for_initial() {
        let p0 = designer.initial(&ctx0).inspect_err(|_| {
            let _ = persist_transcript(designer);
        })?;
        files.push(save_phase(&dir, 0, &p0, &ctx0)?);
        eprintln!("lmac: phase 0: {}", protocol::check_summary(&p0.validated));
        phases.push(p0);
    }

    // The dataset B: collected by a short run (QMIX unless told) with phase 0's protocol fixed (no messages
    // when the designer needs data for phase 0), or reused.
    let data_dir = match &opts.dataset {
        Some(d) => d.clone(),
        None => {
            let run_dir = dir.join("collect");
            std::fs::create_dir_all(&run_dir)?;
            // No phase yet (the offline designer designs phase 0 from B): QMIX's own, no messages.
            let protocol = match files.is_empty() {
                true => String::new(),
                false => lmac_protocol_runner::ProtocolSpec::Files(files.iter().map(|f| f.display().to_string()).collect()).to_string(),
            };
            let cfg = lmac_run::train::TrainConfig {
                run: lmac_run::train::RunSection {
                    env: opts.env.clone(),
                    algo: opts.collect_algo.clone(),
                    protocol,
                    steps: opts.pretrain_steps.max(1),
                    envs: opts.envs,
                    servers: opts.servers,
                    dataset_episodes: opts.dataset_episodes,
                    dataset_epsilon: opts.dataset_epsilon,
                    // Only its dataset is kept: no final evaluation of the collecting policy.
                    final_eval_episodes: Some(0),
                    ..Default::default()
                },
                learn: lmac_learn::LearnConfig { seed: opts.seed, ..Default::default() },
                ..Default::default()
            };
            cfg.check()?;
            write(&run_dir.join("config.toml"), &toml::to_string_pretty(&cfg)?)?;
            eprintln!(
                "lmac: collecting the dataset: {} for {} env steps, then {} episodes",
                opts.collect_algo, opts.pretrain_steps, opts.dataset_episodes
            );
            lmac_run::workflow::train_dirs(std::slice::from_ref(&run_dir), interrupted).context("collecting the dataset")?;
            lmac_run::train::dataset_dir(&run_dir)
        }
    };
    let data = Dataset::load(&data_dir).with_context(|| format!("loading the dataset {}", data_dir.display()))?;
    if data.header.env != opts.env {
        bail!("dataset {} was collected on {}, not {}", data_dir.display(), data.header.env, opts.env);
    }
    eprintln!(
        "lmac: dataset: {} episodes, {} steps ({})",
        data.episodes.len(),
        data.episodes.iter().map(|e| e.len).sum::<usize>(),
        data.header.policy
    );
    let ctx = DesignContext { dataset: Some(&data), ..ctx0 };

    if phases.is_empty() {
        let p0 = designer.initial(&ctx).inspect_err(|_| {
            let _ = persist_transcript(designer);
        })?;
        files.push(save_phase(&dir, 0, &p0, &ctx)?);
        eprintln!("lmac: phase 0: {}", protocol::check_summary(&p0.validated));
        phases.push(p0);
    }

    let mut evaluations: Vec<PhaseEvaluation> = Vec::new();
    let (fixed, fixed_source) = fixed_dims(&phases[0].validated);
    // The evaluation of the phases kept so far, with its meta-information (what a dropped
    // phase's successor is designed from).
    let mut kept: Option<(super::meta_info::MetaInfo, PhaseEvaluation)> = None;
    // The dropped phases (design phase, protocol, file), in case every phase goes.
    let mut set_aside: Vec<(usize, PhaseProtocol, PathBuf)> = Vec::new();
    for k in 0..opts.phases {
        let validated: Vec<ValidatedProtocol> = phases.iter().map(|p| p.validated.clone()).collect();
        let (mut meta, mut ev) = evaluate_phase(&ctx, &validated, k, &fixed, meta_cfg, &dir.join(format!("phase{k}")))?;
        meta.verdicts.push(format!("phases 0..={k}: {}", ev.verdict.text));
        // Phase k against the phases kept before it (against no messages when none was kept).
        let adds = match &kept {
            Some((_, kept_ev)) => {
                let added = ev.message_columns.saturating_sub(kept_ev.message_columns);
                let interval = gain_interval(&ev.held_out.with, &kept_ev.held_out.with, &fixed, ctx.seed);
                Some(ev.fixed_dims.marginal_verdict(&kept_ev.fixed_dims, k, added, interval))
            }
            None if k > 0 || opts.drop_unhelpful_phases => {
                let interval = gain_interval(&ev.held_out.with, &ev.held_out.without, &fixed, ctx.seed);
                Some(ev.fixed_dims.adds_over_no_messages(k, ev.message_columns, interval))
            }
            None => None,
        };
        // Both sides of the verdict no better than a constant guess of each fixed dim: the
        // discriminator reads this map's state neither with the phase's messages nor with what
        // it is compared against, so the gain between them measures nothing (LBF's grid, where
        // even the partner's whole view recovers the cells worse than the guess).
        let baseline_skill = kept.as_ref().map_or(ev.fixed_dims.without_retrained.skill, |(_, e)| e.fixed_dims.with_messages.skill);
        let unmeasurable = ev.fixed_dims.with_messages.skill <= 0.0 && baseline_skill <= 0.0;
        if let Some(adds) = adds {
            eprintln!("lmac: phase {k}: {}", adds.text);
            if !adds.messages_help && opts.drop_unhelpful_phases && unmeasurable {
                let why = format!(
                    "the discriminator recovers the fixed dims no better than a constant guess of each, with this phase's messages (skill {:.3} over the guess) and with what it is compared against ({baseline_skill:.3}: {base}), so what the phase adds cannot be measured on this data; it is kept as the designer made it",
                    ev.fixed_dims.with_messages.skill,
                    base = if kept.is_some() { "the phases kept before it" } else { "no messages" }
                );
                eprintln!("lmac: phase {k}: kept: {why}");
                ev.kept_because = Some(why);
                meta.verdicts.push(adds.text.clone());
            } else if !adds.messages_help && opts.drop_unhelpful_phases {
                eprintln!("lmac: phase {k}: dropped from the final protocol (--keep-all-phases keeps every phase)");
                let phase = phases.pop().context("a phase to drop")?;
                let file = files.pop().context("a phase file to drop")?;
                set_aside.push((k, phase, file));
                ev.dropped = true;
                // The next phase is designed on the phases kept, told why this one went.
                if let Some((kept_meta, _)) = &kept {
                    meta = kept_meta.clone();
                }
                let base = if kept.is_some() { "the phases before it" } else { "no earlier phase" };
                meta.verdicts.push(format!("{}; it was dropped, so the next phase builds on {base}", adds.text));
            } else {
                meta.verdicts.push(adds.text.clone());
            }
            if k > 0 {
                meta.newest_phase_added = Some(adds.messages_help);
            }
            ev.adds = Some(adds);
        }
        if !ev.dropped {
            kept = Some((meta.clone(), ev.clone()));
        }
        evaluations.push(ev);
        persist_transcript(designer)?;
        if k + 1 == opts.phases {
            break;
        }
        let fb = designer.feedback(&ctx, k + 1, &phases, &meta).inspect_err(|_| {
            let _ = persist_transcript(designer);
        })?;
        let pd = dir.join(format!("phase{}", k + 1));
        std::fs::create_dir_all(&pd)?;
        write(&pd.join("feedback.json"), &serde_json::to_string_pretty(&fb)?)?;
        let next = designer.refine(&ctx, k + 1, &phases, &fb, &meta).inspect_err(|_| {
            let _ = persist_transcript(designer);
        })?;
        files.push(save_phase(&dir, k + 1, &next, &ctx)?);
        eprintln!("lmac: phase {}: {}", k + 1, protocol::check_summary(&next.validated));
        phases.push(next);
    }
    persist_transcript(designer)?;
    if phases.is_empty() {
        // Every phase was dropped. LMAC is a method that communicates, so the design keeps one
        // and says that none helped. Their recoveries are all within the held-out noise of no
        // messages, so they cannot rank the phases: the designer's first, phase 0, is kept (a
        // best-by-recovery pick chose, on LBF, a phase of one value over phase 0's whole views
        // by 0.948 against 0.948).
        anyhow::ensure!(!set_aside.is_empty(), "design: no phase was made, so none can be kept");
        let (k, phase, file) = set_aside.remove(0);
        let why = format!(
            "no phase's messages add to recovery without messages on the fixed dims beyond the held-out noise, and a design must send something: phase {k}, the first the designer made, is kept (recovery {:.3}; the others {}); its messages should not be expected to help recover these dims",
            evaluations[k].fixed_dims.with_messages.mean_recovery,
            set_aside
                .iter()
                .map(|(j, _, _)| format!("phase {j} {:.3}", evaluations[*j].fixed_dims.with_messages.mean_recovery))
                .collect::<Vec<_>>()
                .join(", ")
        );
        eprintln!("lmac: phase {k}: kept in the final protocol after all: {why}");
        evaluations[k].dropped = false;
        evaluations[k].kept_because = Some(why);
        phases.push(phase);
        files.push(file);
    }

    let all: Vec<_> = phases.iter().map(|p| p.protocol.clone()).collect();
    write(&dir.join("final.txt"), &protocol::explain_phases(&all, Some(ctx.env)))?;
    let measurements = designer.measurements();
    let received = received_per_agent(&phases);
    for line in agent_lines(&received, measurements.as_ref().and_then(|m| m.get("needs"))) {
        eprintln!("lmac: {line}");
    }
    let spec = files.iter().map(|f| f.display().to_string()).collect::<Vec<_>>().join("+");
    write(&dir.join("final_protocol.txt"), &format!("{spec}\n"))?;
    let summary = serde_json::json!({
        "env": opts.env,
        "designer": designer.name(),
        "alpha": schema.alpha,
        "dataset": data_dir.display().to_string(),
        "dataset_episodes": data.episodes.len(),
        "target_dims": evaluations.last().map(|e| e.target_dims.clone()).unwrap_or_default(),
        "fixed_dims": fixed,
        "fixed_dims_source": fixed_source,
        "evaluations": evaluations,
        "final_protocol": spec,
        "designer_measurements": measurements,
        "received": received,
        "designer_settings": designer.settings(),
    });
    write(&dir.join("summary.json"), &serde_json::to_string_pretty(&summary)?)?;
    Ok(dir)
}

/// What each agent receives in the final protocol, phase by phase: from which sender, which
/// field and its value (the `received` entry of `summary.json`).
fn received_per_agent(phases: &[PhaseProtocol]) -> Vec<serde_json::Value> {
    let n = phases.first().map_or(0, |p| p.validated.env.n_agents);
    (0..n)
        .map(|i| {
            let mut from = Vec::new();
            for p in phases {
                for (f, sends) in p.validated.sends.iter().enumerate() {
                    for (j, to) in sends.iter().enumerate() {
                        if to[i] {
                            let field = &p.protocol.fields[f];
                            from.push(
                                serde_json::json!({"phase": p.protocol.phase, "sender": j, "field": field.name, "value": field.value}),
                            );
                        }
                    }
                }
            }
            serde_json::json!({"agent": i, "receives": from})
        })
        .collect()
}

/// One log line per agent: what it needs of the critical dims and who supplies each best (when
/// the designer measured needs), then what it receives.
fn agent_lines(received: &[serde_json::Value], needs: Option<&serde_json::Value>) -> Vec<String> {
    let needs = needs.and_then(|n| n.as_array()).cloned().unwrap_or_default();
    received
        .iter()
        .enumerate()
        .map(|(i, r)| {
            let need = needs.iter().find(|n| n["agent"] == i).map(|n| {
                let dims: Vec<String> = n["dims"]
                    .as_array()
                    .map(|d| d.as_slice())
                    .unwrap_or_default()
                    .iter()
                    .map(|d| {
                        let supplier = d["supplier"].as_u64().map(|s| format!(", best from agent {s}")).unwrap_or_default();
                        format!("s[{}] {:.3}{supplier}", d["dim"], d["need"].as_f64().unwrap_or(0.0))
                    })
                    .collect();
                format!("needs {}; ", dims.join(", "))
            });
            let got: Vec<String> = r["receives"]
                .as_array()
                .map(|a| a.as_slice())
                .unwrap_or_default()
                .iter()
                .map(|x| format!("phase {} '{}' {} from agent {}", x["phase"], x["field"].as_str().unwrap_or(""), x["value"], x["sender"]))
                .collect();
            let got = if got.is_empty() { "receives nothing".to_string() } else { format!("receives {}", got.join(", ")) };
            format!("agent {i}: {}{got}", need.unwrap_or_default())
        })
        .collect()
}
