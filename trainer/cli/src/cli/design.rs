//! `lmac design`: the three-phase protocol design loop.

use super::parse_steps;
use anyhow::{Context, Result};
use clap::Args;
use lmac_design::offline::OfflineConfig;
use lmac_run::workflow::{interrupt_flag, plot};

/// Env steps of the run that collects a design's dataset, unless told (`lmac design
/// --pretrain-steps`, `lmac experiment --design-steps`).
pub(crate) const DEFAULT_PRETRAIN_STEPS: &str = "100k";

#[derive(Args)]
pub(crate) struct DesignArgs {
    /// Environment, e.g. lbf:8x8-2p-2f-s1-coop.
    #[arg(long, default_value = "lbf:8x8-2p-2f-s1-coop")]
    pub(crate) env: String,
    /// Designer: `offline` (embedded, no network: builds each phase from the meta-information),
    /// or an LLM: `openai:MODEL` (any OpenAI-compatible server: OpenAI, vLLM, llama.cpp,
    /// Ollama; key from OPENAI_API_KEY), `anthropic:MODEL` (key from ANTHROPIC_API_KEY), `gemini:MODEL`
    /// (Google's OpenAI-compatible endpoint; key from GEMINI_API_KEY).
    #[arg(long, default_value = "offline")]
    pub(crate) llm: String,
    /// Base URL of an OpenAI-compatible server, e.g. http://127.0.0.1:8080/v1.
    #[arg(long)]
    pub(crate) base_url: Option<String>,
    /// The environment variable holding the key for a --base-url server. Without it such a
    /// server gets no key (OPENAI_API_KEY goes only to OpenAI's own API); a key is sent only
    /// over https, or over http to this machine.
    #[arg(long, value_name = "VAR")]
    pub(crate) api_key_env: Option<String>,
    /// live: ask the LLM (recording every exchange); replay: answer from the recordings only
    /// (offline, exact); replay-or-live: recordings first, then the LLM.
    #[arg(long, default_value = "live")]
    pub(crate) llm_mode: String,
    /// Where LLM exchanges are recorded and replayed from (default: <out>/llm-recordings).
    #[arg(long)]
    pub(crate) recordings: Option<std::path::PathBuf>,
    /// How the protocol's JSON Schema goes with each generation request, so the reply is valid
    /// JSON of the protocol language by construction: json-schema (OpenAI's response_format;
    /// OpenAI, Gemini, vLLM, Ollama), json-object (llama.cpp's schema-to-grammar), off
    /// (Anthropic, or a server that rejects it). Default: by provider.
    #[arg(long, value_name = "MODE")]
    pub(crate) structured_output: Option<lmac_design::llm::StructuredOutput>,
    /// The most tokens an LLM reply may have (default: the provider's; Anthropic 8192). A reply
    /// cut off at the limit is an error naming it, not a malformed protocol.
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..))]
    pub(crate) llm_max_tokens: Option<u32>,
    /// Corrections the LLM gets per reply (invalid JSON, validation errors) before the design fails.
    #[arg(long, default_value_t = 3)]
    pub(crate) max_retries: usize,
    /// Env steps of the run whose epsilon-greedy policy collects the dataset (paper: 200k of QMIX).
    #[arg(long, default_value = DEFAULT_PRETRAIN_STEPS, value_parser = parse_steps)]
    pub(crate) pretrain_steps: u64,
    /// The method trained to collect the dataset: `qmix-state` (its agents see the global state,
    /// so the dataset's actions and returns show what knowing a thing is worth to a policy that
    /// acts on it; what `--critical-by action` reads), `qmix` (the paper's) or another method
    /// without messages (`lmac train --help` lists them)
    #[arg(long, default_value = "qmix-state", value_name = "ALGO")]
    pub(crate) collect_with: String,
    /// Episodes in the dataset (paper: 5000).
    #[arg(long, default_value_t = 1000)]
    pub(crate) dataset_episodes: usize,
    /// Epsilon while collecting (default: the schedule's value at the end of the QMIX run).
    #[arg(long)]
    pub(crate) dataset_epsilon: Option<f32>,
    /// Reuse a dataset directory (e.g. <design>/collect/dataset) instead of collecting one.
    #[arg(long)]
    pub(crate) dataset: Option<std::path::PathBuf>,
    /// Environments per env server and env servers for the collection run.
    #[arg(long, default_value_t = 16)]
    pub(crate) envs: usize,
    #[arg(long, default_value_t = 2)]
    pub(crate) servers: usize,
    /// Discriminator updates per training (paper: 1000 epochs x 10 iterations).
    #[arg(long)]
    pub(crate) disc_updates: Option<usize>,
    /// Design phases (paper: 3).
    #[arg(long, default_value_t = 3)]
    pub(crate) phases: usize,
    /// Which recovery "without messages" the designer is shown: `retrained` (a second
    /// discriminator trained without messages) or `zeroed` (the paper's: the with-messages
    /// discriminator given zeroed messages). Both are measured and written to recovery.json.
    #[arg(long, default_value = "retrained")]
    pub(crate) without: lmac_design::meta::NoMessages,
    /// Keep every phase in the final protocol, as the paper's does. By default a phase whose
    /// messages add nothing to the kept earlier phases' recovery of the fixed dims (beyond the
    /// held-out noise; phase 0, and a phase with none kept before it, against no messages) is
    /// dropped, and when every phase fails phase 0 is kept (their recoveries are within the
    /// noise, so they cannot rank the phases).
    /// Every phase's verdict is printed and in summary.json either way
    #[arg(long)]
    pub(crate) keep_all_phases: bool,
    /// The default (drop the phases that add nothing); accepted so older commands still run
    #[arg(long, hide = true, conflicts_with = "keep_all_phases")]
    pub(crate) drop_unhelpful_phases: bool,
    /// How the offline designer chooses phase 0's task-critical dims: `relevance` (what the
    /// return depends on, from a value model fitted on the dataset, and agents recover poorly
    /// without messages), `action` (what the dataset's policy's actions depend on, from a
    /// linear model of each agent's action on the state, and agents recover poorly; for a
    /// dataset collected by a policy that sees the state, `--collect-with qmix-state`; ranked as
    /// by `relevance` when those models explain under 25% of the actions) or `recovery` (the
    /// hardest to recover, its first rule)
    #[arg(long, default_value_t = OfflineConfig::default().critical_by)]
    pub(crate) critical_by: lmac_design::offline::CriticalBy,
    /// Most task-critical dims the offline designer's relevance rule lists for phase 0 (the
    /// authors' GPT-4.1 designs name 4-12)
    #[arg(long, default_value_t = OfflineConfig::default().max_relevant_dims, value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..))]
    pub(crate) critical_dims: usize,
    /// Most agents that send one field of the offline designer (0: any). 1 gives each piece of
    /// information one sender (the one whose values explain the most), as the authors' designs do
    #[arg(long, default_value_t = OfflineConfig::default().senders_per_field)]
    pub(crate) senders_per_field: usize,
    /// How the offline designer chooses phase 0's message fields: `least-squares` (the sender
    /// features that best explain the critical dims beyond what receivers see) or
    /// `observation-relevance` (the agent whose whole observation, sent to the others, most
    /// raises their recovery of the critical dims sends the values of it that the team's return
    /// depends on most, by a value model of the joint observation)
    #[arg(long, default_value_t = OfflineConfig::default().fields_by)]
    pub(crate) fields_by: lmac_design::offline::FieldsBy,
    /// Most observation values `--fields-by observation-relevance` sends in phase 0
    #[arg(long, default_value_t = OfflineConfig::default().max_relevant_values, value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..))]
    pub(crate) relevant_values: usize,
    /// Most agents that send in phase 0 with `--fields-by observation-relevance` (those whose
    /// whole observation raises the others' recovery of the critical dims most)
    #[arg(long, default_value_t = OfflineConfig::default().relevant_senders, value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..))]
    pub(crate) relevant_senders: usize,
    /// How `--fields-by observation-relevance` ranks the senders: `recovery` (how much all an
    /// agent sees, sent to the others, raises their recovery of the critical dims), `return`
    /// (how much it raises a value model's prediction of the team's return from another agent's
    /// own observation) or `need` (how much of what the others need of the critical dims it
    /// recovers better than they do; needs `--critical-by action`)
    #[arg(long, default_value_t = OfflineConfig::default().senders_by)]
    pub(crate) senders_by: lmac_design::offline::SendersBy,
    /// Whom `--fields-by observation-relevance`'s senders send to: `everyone` (every other
    /// agent) or `need` (the agents whose own actions depend on critical dims they cannot
    /// recover alone; needs `--critical-by action`)
    #[arg(long, default_value_t = OfflineConfig::default().receivers_by)]
    pub(crate) receivers_by: lmac_design::offline::ReceiversBy,
    /// What of a sender's view `--fields-by observation-relevance` sends: `value` (its values
    /// one by one, most relevant to the return first), `entity` (whole entities of the
    /// schema, e.g. everything the sender sees of the Roach, the entity that matters most to
    /// the receivers' value model first; needs `--senders-by return`) or `recovery` (whole
    /// entities, the one that, sent alone, most raises the receivers' recovery of the critical
    /// dims per value first, unless one entity alone adds more than all that order fits: a
    /// discriminator per entity)
    #[arg(long, default_value_t = OfflineConfig::default().values_by)]
    pub(crate) values_by: lmac_design::offline::ValuesBy,
    /// How the offline designer chooses phase 1's fields: `least-squares` (the sender features
    /// that best explain the state dims phase 0 leaves poorly recovered) or `frame` (the values
    /// of phase 0's sender that place each receiver in its view, found by fitting each
    /// receiver's own view of the entity phase 0 sends, never a copy of what it sees itself;
    /// least squares when none adds enough; needs `--values-by entity` or `recovery`)
    #[arg(long, default_value_t = OfflineConfig::default().phase1_by)]
    pub(crate) phase1_by: lmac_design::offline::Phase1By,
    /// With `--phase1-by frame`: fit each receiver's view on top of the rest of its own
    /// observation too, so nothing it could compute from what it sees is sent. On SMAC-Comm this
    /// sends nothing (sight is symmetric: where the sender sees a receiver is the negative of
    /// where the receiver sees the sender) and LMAC trained worse on 1o_10b
    /// (`docs/results/design.md`); without it, that offset is sent in the sender's frame, as the
    /// authors' phase 1 sends it
    #[arg(long)]
    pub(crate) frame_given_own_view: bool,
    /// With `--values-by recovery`: rank the sender's entities even where a discriminator reads
    /// the critical dims no better than a constant guess with the sender's whole view. By
    /// default the designer then sends every agent's whole view instead (on LBF's grid state),
    /// as the per-entity gains it would rank by are noise there
    #[arg(long)]
    pub(crate) rank_when_blind: bool,
    #[arg(long, default_value_t = 0)]
    pub(crate) seed: u64,
    /// Where design directories go.
    #[arg(long, default_value = "designs")]
    pub(crate) out: std::path::PathBuf,
}

impl DesignArgs {
    /// The command's defaults (the offline designer) for `env`, writing under `out`.
    pub(crate) fn defaults(env: &str, out: std::path::PathBuf) -> DesignArgs {
        use clap::FromArgMatches;
        let cmd = <DesignArgs as clap::Args>::augment_args(clap::Command::new("design"));
        let mut a = DesignArgs::from_arg_matches(&cmd.get_matches_from(["design"])).expect("the defaults parse");
        a.env = env.to_string();
        a.out = out;
        a
    }
}

pub(crate) fn design(a: DesignArgs) -> Result<i32> {
    let dir = design_dir(&a, interrupt_flag())?;
    println!("design written to {}", dir.display());
    println!("final protocol: {}", std::fs::read_to_string(dir.join("final_protocol.txt"))?.trim());
    Ok(0)
}

/// Run the design loop `a` describes; returns its directory.
pub(crate) fn design_dir(a: &DesignArgs, interrupted: std::sync::Arc<std::sync::atomic::AtomicBool>) -> Result<std::path::PathBuf> {
    use lmac_design::llm::LlmMode;
    use lmac_design::llm_designer::{LlmDesigner, LlmDesignerOptions};
    use lmac_design::meta::MetaConfig;
    use lmac_design::offline::OfflineDesigner;
    use lmac_design::run::{run_design, DesignOptions};
    use lmac_design::Designer;
    let opts = DesignOptions {
        env: a.env.clone(),
        out: a.out.clone(),
        seed: a.seed,
        pretrain_steps: a.pretrain_steps,
        collect_algo: a.collect_with.clone(),
        dataset_episodes: a.dataset_episodes,
        dataset_epsilon: a.dataset_epsilon,
        envs: a.envs,
        servers: a.servers,
        dataset: a.dataset.clone(),
        phases: a.phases,
        without: a.without,
        drop_unhelpful_phases: !a.keep_all_phases,
    };
    // One discriminator configuration for the offline designer's phase-0 measurement and for
    // every phase's meta-information.
    let mut meta_cfg = MetaConfig::default();
    if let Some(u) = a.disc_updates {
        meta_cfg.discriminator.updates = u;
    }
    meta_cfg.without = a.without;
    meta_cfg.discriminator.validate()?;
    let mut designer: Box<dyn Designer> = if a.llm == "offline" {
        let cfg = OfflineConfig {
            discriminator: meta_cfg.discriminator.clone(),
            phases: a.phases,
            critical_by: a.critical_by,
            max_relevant_dims: a.critical_dims,
            senders_per_field: a.senders_per_field,
            fields_by: a.fields_by,
            max_relevant_values: a.relevant_values,
            relevant_senders: a.relevant_senders,
            senders_by: a.senders_by,
            receivers_by: a.receivers_by,
            values_by: a.values_by,
            phase1_by: a.phase1_by,
            frame_given_own_view: a.frame_given_own_view,
            whole_view_when_blind: !a.rank_when_blind,
            ..Default::default()
        };
        // Before the dataset is collected, which the offline designer's phase 0 waits for.
        cfg.check()?;
        Box::new(OfflineDesigner::new(cfg))
    } else {
        let mode: LlmMode = a.llm_mode.parse().map_err(anyhow::Error::msg)?;
        let rec = a.recordings.clone().unwrap_or_else(|| a.out.join("llm-recordings"));
        std::fs::create_dir_all(&rec).with_context(|| format!("creating {}", rec.display()))?;
        let options = LlmDesignerOptions {
            max_retries: a.max_retries,
            api_key_env: a.api_key_env.clone(),
            structured: a.structured_output,
            max_tokens: a.llm_max_tokens,
            ..Default::default()
        };
        Box::new(LlmDesigner::from_spec(&a.llm, a.base_url.as_deref(), mode, Some(rec), options)?)
    };
    let dir = run_design(&opts, designer.as_mut(), &meta_cfg, interrupted)?;
    plot("plot_design", &dir);
    Ok(dir)
}
