//! Candidate features: what a sender could send (observation dims, history aggregates, action
//! histograms), computed on the dataset by a probe protocol through the runner's own plan.

use anyhow::{anyhow, Result};
use lmac_protocol_runner::protocol::{
    self, ActionEncoding, DimSpec, Expr, Field, HistoryPadding, MessageLayout, Protocol, ProtocolEnv, Receivers, Senders,
    ValidatedProtocol, Window, WindowOp,
};

/// What a candidate computes from one sender's observation history.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub(super) enum Kind {
    /// The current value of observation dims.
    Obs,
    /// A window aggregate of observation dims.
    Win(WinOp, usize),
    /// The last action, one-hot.
    LastAction,
    /// The fraction of the last k steps each action was taken.
    ActionHistogram(usize),
}

/// `WindowOp` with an order (for grouping fields deterministically).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub(super) enum WinOp {
    Max,
    Mean,
    LastNonzero,
    Last,
    Delta,
}

impl WinOp {
    pub(super) fn op(self) -> WindowOp {
        match self {
            WinOp::Max => WindowOp::Max,
            WinOp::Mean => WindowOp::Mean,
            WinOp::LastNonzero => WindowOp::LastNonzero,
            WinOp::Last => WindowOp::Last,
            WinOp::Delta => WindowOp::Delta,
        }
    }
}

impl Kind {
    /// Field name stem and description stem.
    pub(super) fn words(self) -> (String, String) {
        match self {
            Kind::Obs => ("obs".into(), "the sender's current observation".into()),
            Kind::Win(WinOp::Max, k) => {
                (format!("max{k}"), format!("the highest value over the sender's last {k} steps of its observation"))
            }
            Kind::Win(WinOp::Mean, k) => (format!("mean{k}"), format!("the mean over the sender's last {k} steps of its observation")),
            Kind::Win(WinOp::LastNonzero, k) => {
                (format!("recent{k}"), format!("the most recent non-zero value within the sender's last {k} steps of its observation"))
            }
            Kind::Win(WinOp::Last, k) => (format!("back{}", k - 1), format!("the sender's observation {} step(s) ago", k - 1)),
            Kind::Win(WinOp::Delta, k) => (format!("delta{k}"), format!("the change over the sender's last {k} steps of its observation")),
            Kind::LastAction => ("last_action".into(), "the sender's previous action (one-hot; zero on the first step)".into()),
            Kind::ActionHistogram(k) => {
                (format!("action_hist{k}"), format!("the fraction of the sender's last {k} steps in which it took each action"))
            }
        }
    }

    /// The expression of this kind over observation `dims` (ignored for action kinds).
    pub(super) fn expr(self, dims: &[usize]) -> Expr {
        match self {
            Kind::Obs => Expr::Obs(dims.to_vec()),
            Kind::Win(op, k) => Expr::Window(Window { op: op.op(), k, of: Box::new(Expr::Obs(dims.to_vec())) }),
            Kind::LastAction => Expr::LastAction(ActionEncoding::OneHot),
            Kind::ActionHistogram(k) => {
                Expr::Window(Window { op: WindowOp::Mean, k, of: Box::new(Expr::LastAction(ActionEncoding::OneHot)) })
            }
        }
    }

    pub(super) fn per_dim(self) -> bool {
        matches!(self, Kind::Obs | Kind::Win(..))
    }
}

/// One candidate: a kind over one observation dim (or an action kind), `width` columns.
#[derive(Clone, Debug)]
pub(super) struct Candidate {
    pub(super) kind: Kind,
    pub(super) dim: Option<usize>,
    pub(super) width: usize,
    /// First column of its values in a sender's probe block.
    pub(super) col: usize,
}

/// The candidate kinds of a phase.
pub(super) fn kinds_for(phase: usize) -> Vec<Kind> {
    match phase {
        0 => vec![Kind::Obs, Kind::LastAction],
        1 => vec![
            Kind::Obs,
            Kind::Win(WinOp::Max, 5),
            Kind::Win(WinOp::Mean, 5),
            Kind::Win(WinOp::LastNonzero, 5),
            Kind::Win(WinOp::Last, 2),
            Kind::Win(WinOp::Delta, 3),
        ],
        _ => vec![Kind::Win(WinOp::Max, 10), Kind::Win(WinOp::Mean, 10), Kind::Win(WinOp::LastNonzero, 10), Kind::ActionHistogram(10)],
    }
}

/// The probe protocol: one field per kind, every sender broadcasting every candidate without
/// one-hot, so each receiver's block for sender j holds j's candidate values.
pub(super) fn probe(kinds: &[Kind], env: &ProtocolEnv) -> Result<(ValidatedProtocol, ProtocolEnv, Vec<Candidate>)> {
    let all: Vec<usize> = (0..env.obs_dim).collect();
    let mut fields = Vec::new();
    let mut cands = Vec::new();
    let mut col = 0;
    for (f, &kind) in kinds.iter().enumerate() {
        fields.push(Field {
            name: format!("probe{f}"),
            description: "candidate".into(),
            senders: Senders::All,
            receivers: Receivers::Broadcast,
            value: kind.expr(&all),
        });
        if kind.per_dim() {
            for d in 0..env.obs_dim {
                cands.push(Candidate { kind, dim: Some(d), width: 1, col: col + d });
            }
            col += env.obs_dim;
        } else {
            cands.push(Candidate { kind, dim: None, width: env.n_actions, col });
            col += env.n_actions;
        }
    }
    let p = Protocol {
        name: Some("offline_probe".into()),
        phase: None,
        message_design_instruction: "offline designer: probe of candidate features (never sent)".into(),
        critical_state_dims: vec![DimSpec::Range(protocol::Slice { start: 0, end: env.state_dim })],
        critical_state_reasoning: None,
        sender_one_hot: false,
        history_padding: HistoryPadding::default(),
        // Every sender broadcasts every candidate, so both layouts agree; `sample` reads the
        // sender blocks at fixed positions, so say so.
        layout: MessageLayout::SenderBlocks,
        fields,
        env: None,
        schema_fingerprint: None,
    };
    let mut penv = env.clone();
    penv.message_budget = usize::MAX / 4;
    let v = protocol::validate(&p, &penv)
        .map_err(|e| anyhow!("offline designer: its probe protocol is invalid (a bug): {}", protocol::errors_to_text(&e)))?;
    Ok((v, penv, cands))
}
