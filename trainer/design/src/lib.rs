//! Protocol design (paper section 4.1, appendix B.1-B.2): the three LLM-guided phases that write,
//! check against data and refine a communication protocol.
//!
//! The data flow, one direction:
//! 1. a designer writes phase 0 (`Designer::initial`);
//! 2. a trajectory dataset B is collected through the real pipeline ([`dataset`]);
//! 3. for each phase k, the messages of the protocol so far are recomputed on B by the runner's
//!    own compiled plan, a discriminator D^(k) learns to reconstruct the state with and without
//!    them ([`discriminator`]), and the meta-information chi says per agent and state dim how
//!    often reconstruction succeeds ([`meta`], handed on as a [`meta_info::MetaInfo`]);
//! 4. the designer turns the meta-information into feedback and the next phase's protocol
//!    (`Designer::feedback`, `Designer::refine`); the final protocol is phase 0 + 1 + 2.
//!
//! Designers: an LLM over HTTP ([`llm`], [`llm_designer`], prompts rendered by [`prompts`]) or
//! the embedded offline designer ([`offline`]), a deterministic algorithm over the
//! meta-information that needs no network and is labelled as what it is.

pub mod dead_fields;
pub mod discriminator;
pub mod llm;
pub mod llm_designer;
pub mod meta;
pub mod meta_info;
pub mod offline;
pub mod prompts;
pub mod relevance;
pub mod run;

use lmac_protocol_runner::protocol::{Protocol, ProtocolEnv, ValidatedProtocol};
use lmac_shm_schema::EnvSchema;
use meta_info::MetaInfo;
use serde::{Deserialize, Serialize};

/// What every designer may read: the environment (its schema with the meaning of every
/// dimension, and the protocol view of it with the message budget) and, when it exists, the
/// trajectory dataset.
pub struct DesignContext<'a> {
    /// Environment name, e.g. `lbf:8x8-2p-2f-s1-coop`.
    pub env_name: &'a str,
    pub schema: &'a EnvSchema,
    pub env: &'a ProtocolEnv,
    /// The dataset B (None before it is collected).
    pub dataset: Option<&'a lmac_run::dataset::Dataset>,
    /// Seed for everything random in the design (discriminator init, batches).
    pub seed: u64,
}

/// The paper's feedback c^(k+1): JSON with these three keys.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Feedback {
    #[serde(rename = "Evaluation")]
    pub evaluation: String,
    #[serde(rename = "Missing_Information_Hypothesis")]
    pub missing_information_hypothesis: String,
    #[serde(rename = "Improvement_Suggestions")]
    pub improvement_suggestions: String,
}

/// One exchange with a designer, kept for the design directory's transcript.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct TranscriptEntry {
    pub phase: usize,
    /// `critical_dims`, `protocol`, `feedback`, `correction` ...
    pub kind: String,
    pub prompt: String,
    pub reply: String,
}

/// A designer's protocol for one phase: already validated against the environment and the
/// budget left by the earlier phases.
#[derive(Clone, Debug)]
pub struct PhaseProtocol {
    pub protocol: Protocol,
    pub validated: ValidatedProtocol,
    /// Reasoning the designer gave (chain of thought about critical dims, or the offline
    /// designer's account of its choice).
    pub reasoning: String,
}

/// Writes protocols and feedback. Implemented by the LLM designer and the offline designer.
pub trait Designer {
    /// For logs and the design directory: `offline`, `openai:gpt-4.1`, ...
    fn name(&self) -> String;
    /// Whether `initial` needs the dataset (the offline designer does: it designs from data;
    /// an LLM designs phase 0 from the task prompt alone, as in the paper).
    fn needs_data_for_initial(&self) -> bool;
    /// Phase 0 (initialization): select the task-critical state dims, then write f_C^(0).
    fn initial(&mut self, ctx: &DesignContext) -> anyhow::Result<PhaseProtocol>;
    /// Feedback c^(k+1) on the protocol so far (`previous`, phases 0..k) from the
    /// meta-information of phases 0..=k ([`meta::evaluate`]). `phase` is k + 1.
    fn feedback(&mut self, ctx: &DesignContext, phase: usize, previous: &[PhaseProtocol], meta: &MetaInfo) -> anyhow::Result<Feedback>;
    /// Phase k + 1's protocol (recognition enhancement for 1, sharing enhancement for 2),
    /// using the feedback; it must fit the budget left by `previous`.
    fn refine(
        &mut self,
        ctx: &DesignContext,
        phase: usize,
        previous: &[PhaseProtocol],
        feedback: &Feedback,
        meta: &MetaInfo,
    ) -> anyhow::Result<PhaseProtocol>;
    /// Everything said so far (prompts and replies), for the transcript file.
    fn transcript(&self) -> Vec<TranscriptEntry>;

    /// What the designer measured itself, for the design's `summary.json` (the offline
    /// designer: each state dim's relevance to the return).
    fn measurements(&self) -> Option<serde_json::Value> {
        None
    }

    /// The designer's own settings, for the design's `summary.json`, so a design says how it
    /// was made (the offline designer: every knob of its configuration).
    fn settings(&self) -> Option<serde_json::Value> {
        None
    }
}
