//! Dead protocol fields: a (field, sender, receiver) link whose columns carry no information on
//! the dataset B, found before anyone trains on it. A link is dead when every one of its columns
//! is constant over B (always zero is the common case: a feature that never fires) or an exact
//! copy of one of the receiver's own observation columns (it tells the receiver what it
//! already sees). The sender one-hot is constant by design and never counted; columns that are
//! zero by layout (a sender that sends nothing to this receiver) are not links.
//!
//! Reported by `lmac protocol check --dataset`, `lmac protocol explain --dataset` and, in the
//! design loop, in the meta-information the designer reads (`dead_fields`).

use anyhow::{anyhow, Result};
use lmac_protocol_runner::plan::MessagePlan;
use lmac_protocol_runner::protocol::{self, ProtocolEnv, ProtocolPlan, ValidatedProtocol};
use lmac_run::dataset::Dataset;
use serde::{Deserialize, Serialize};

/// Why a column carries nothing.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DeadColumn {
    /// The same value on every step of B.
    Constant(f32),
    /// Equal on every step to the receiver's observation column `o[k]`.
    CopyOfObs(usize),
}

/// One dead link: every column of `field` from `sender` to `receiver` is dead.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DeadField {
    pub phase: usize,
    pub field: String,
    pub sender: usize,
    pub receiver: usize,
    /// Per column of the field, why it is dead.
    pub columns: Vec<DeadColumn>,
}

impl DeadField {
    /// One line for people and the LLM.
    pub fn describe(&self) -> String {
        let why: Vec<String> = self
            .columns
            .iter()
            .enumerate()
            .map(|(q, c)| match c {
                DeadColumn::Constant(v) if *v == 0.0 => format!("[{q}] always 0"),
                DeadColumn::Constant(v) => format!("[{q}] always {v}"),
                DeadColumn::CopyOfObs(k) => format!("[{q}] equals the receiver's own o[{k}]"),
            })
            .collect();
        format!(
            "phase {} field `{}` from agent {} to agent {} carries nothing on the dataset: {}",
            self.phase,
            self.field,
            self.sender,
            self.receiver,
            why.join(", ")
        )
    }
}

/// Tolerance for "constant" and "equal": the runner's messages are f32 copies and sums of
/// observation values, so an exact relation holds to rounding.
const TOL: f32 = 1e-6;

/// The dead links of `phases` (compiled together, as a run would) on `data`.
pub fn find(data: &Dataset, phases: &[ValidatedProtocol], env: &ProtocolEnv) -> Result<Vec<DeadField>> {
    if phases.is_empty() {
        return Ok(Vec::new());
    }
    let (n, od) = (data.header.n_agents, data.header.obs_dim);
    if (n, od) != (env.n_agents, env.obs_dim) {
        return Err(anyhow!(
            "dataset of {} has {n} agents and obs {od}; the protocol's environment has {} and {}",
            data.header.env,
            env.n_agents,
            env.obs_dim
        ));
    }
    let plan = protocol::compile_plan(phases, env).map_err(|e| anyhow!("compiling the protocol: {}", protocol::errors_to_text(&e)))?;
    let messages = data.messages(&mut plan.clone());
    Ok(scan(data, &plan, &messages))
}

/// Which of `sender`'s observation values `dims` are, on every step of B, equal to one of
/// `receiver`'s own: sent, each would be a dead column ([`DeadColumn::CopyOfObs`]). Where
/// sight is symmetric, what the sender sees of the receiver (visible, distance) is what the
/// receiver sees of the sender.
pub fn copies_of_receiver(data: &Dataset, sender: usize, receiver: usize, dims: &[usize]) -> Vec<bool> {
    let (n, od) = (data.header.n_agents, data.header.obs_dim);
    let mut copies: Vec<Vec<usize>> = dims.iter().map(|_| (0..od).collect()).collect();
    for ep in &data.episodes {
        for t in 0..ep.len {
            let oj = &ep.obs[(t * n + sender) * od..(t * n + sender + 1) * od];
            let oi = &ep.obs[(t * n + receiver) * od..(t * n + receiver + 1) * od];
            for (c, &d) in copies.iter_mut().zip(dims) {
                if !c.is_empty() {
                    c.retain(|&k| (oi[k] - oj[d]).abs() <= TOL);
                }
            }
        }
    }
    copies.iter().map(|c| !c.is_empty()).collect()
}

/// The dead links of `plan` on `data`, given the messages the plan writes on it
/// ([`Dataset::messages`]; the design loop has them already).
pub fn scan(data: &Dataset, plan: &ProtocolPlan, messages: &[Vec<f32>]) -> Vec<DeadField> {
    let (n, od) = (data.header.n_agents, data.header.obs_dim);
    let md = plan.msg_dim();
    let mut dead = Vec::new();
    for i in 0..n {
        let cols = plan.columns(i);
        // Per column: still constant (its first value), and the receiver obs columns it still equals.
        let mut first: Vec<Option<f32>> = vec![None; md];
        let mut constant = vec![true; md];
        let mut copies: Vec<Vec<usize>> = (0..md).map(|_| (0..od).collect()).collect();
        for (e, ep) in data.episodes.iter().enumerate() {
            for t in 0..ep.len {
                let m = &messages[e][(t * n + i) * md..(t * n + i + 1) * md];
                let o = &ep.obs[(t * n + i) * od..(t * n + i + 1) * od];
                for c in 0..md {
                    if !cols[c].linked || cols[c].field.is_none() {
                        continue;
                    }
                    let v = m[c];
                    let f = *first[c].get_or_insert(v);
                    if constant[c] && (v - f).abs() > TOL {
                        constant[c] = false;
                    }
                    if !copies[c].is_empty() {
                        copies[c].retain(|&k| (o[k] - v).abs() <= TOL);
                    }
                }
            }
        }
        // Group the linked field columns by (phase, field, sender), in column order.
        let mut c = 0;
        while c < md {
            let col = &cols[c];
            let mut end = c + 1;
            while end < md && cols[end].phase == col.phase && cols[end].field == col.field && cols[end].sender == col.sender {
                end += 1;
            }
            if col.linked && col.field.is_some() {
                let why: Option<Vec<DeadColumn>> = (c..end)
                    .map(|k| {
                        if constant[k] {
                            Some(DeadColumn::Constant(first[k].unwrap_or(0.0)))
                        } else {
                            copies[k].first().map(|&o| DeadColumn::CopyOfObs(o))
                        }
                    })
                    .collect();
                if let Some(columns) = why {
                    dead.push(DeadField { phase: col.phase, field: col.name.clone(), sender: col.sender, receiver: i, columns });
                }
            }
            c = end;
        }
    }
    dead
}
