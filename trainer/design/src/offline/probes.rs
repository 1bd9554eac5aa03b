//! Probe messages: what one agent sending some of its view adds to the others' recovery of the
//! critical dims, measured by a discriminator trained per probe.

use super::{DesignContext, OfflineDesigner};
use crate::meta;
use anyhow::{anyhow, Context, Result};
use lmac_protocol_runner::protocol::{self, DimSpec, Expr, Field, HistoryPadding, MessageLayout, PeerLink, Protocol, Receivers, Senders};

/// What one probe message measured: how much it raises the receivers' recovery of the critical
/// dims over no messages, and that recovery (mean E_t[chi] over the dims and the receivers).
#[derive(Clone, Copy, Debug)]
pub(super) struct Probe {
    pub(super) gain: f64,
    pub(super) recovery: f64,
}

impl OfflineDesigner {
    /// Per agent j: how much sending all of j's observation to every other agent raises their
    /// recovery of `dims` ([`Self::probe_gains`] with one probe per agent).
    pub(super) fn whole_view_probes(&self, ctx: &DesignContext, dims: &[usize]) -> Result<Vec<Probe>> {
        let od = ctx.env.obs_dim;
        let probes: Vec<(usize, Vec<usize>)> = (0..ctx.env.n_agents).map(|j| (j, (0..od).collect())).collect();
        self.probe_gains(ctx, dims, &probes)
    }

    /// Mean E_t[chi] of a constant guess of each of `dims` (phase 0's measurement).
    pub(super) fn guess_rate(&self, dims: &[usize]) -> Result<f64> {
        let without = self.without.as_ref().context("offline designer: phase 0's recovery without messages is not measured yet")?;
        let rates = dims
            .iter()
            .map(|&d| without.position(d).and_then(|k| self.guess.get(k).copied()))
            .collect::<Option<Vec<f64>>>()
            .context("offline designer: a critical dim has no constant-guess rate (a bug)")?;
        Ok(meta::mean(&rates))
    }

    /// Per probe (j, values): how much agent j sending its o[values] to every other agent
    /// raises their recovery of `dims` (mean E_t[chi] over the dims and the receivers, with
    /// against without messages; a discriminator trained per probe on B's training episodes,
    /// measured on the held-out ones; "without" is phase 0's own measurement), and the
    /// receivers' recovery with the probe. 0 for a probe with no values.
    pub(super) fn probe_gains(&self, ctx: &DesignContext, dims: &[usize], probes: &[(usize, Vec<usize>)]) -> Result<Vec<Probe>> {
        let env = ctx.env;
        let n = env.n_agents;
        let disc = &self.cfg.discriminator;
        let without = self.without.as_ref().context("offline designer: phase 0's recovery without messages is not measured yet")?;
        let mut gains = Vec::with_capacity(probes.len());
        for (j, values) in probes.iter().map(|(j, v)| (*j, v)) {
            if values.is_empty() {
                gains.push(Probe { gain: 0.0, recovery: 0.0 });
                continue;
            }
            let what = if values.len() == env.obs_dim {
                "its whole observation".to_string()
            } else {
                format!("its o[{}]", values.iter().map(|d| d.to_string()).collect::<Vec<_>>().join(", "))
            };
            let p = Protocol {
                name: Some(format!("offline_probe_{j}")),
                phase: Some(0),
                message_design_instruction: format!("probe: agent {j} sends {what}"),
                critical_state_dims: dims.iter().map(|&d| DimSpec::Dim(d)).collect(),
                critical_state_reasoning: None,
                sender_one_hot: true,
                history_padding: HistoryPadding::default(),
                layout: MessageLayout::default(),
                fields: vec![Field {
                    name: "probe".into(),
                    description: "probe".into(),
                    senders: Senders::List(vec![j]),
                    receivers: Receivers::Peer(vec![PeerLink { from: j, to: (0..n).filter(|&i| i != j).collect() }]),
                    value: Expr::Obs(values.clone()),
                }],
                env: None,
                schema_fingerprint: None,
            };
            let v = protocol::validate_phase(&p, env, &[])
                .map_err(|e| anyhow!("offline designer: its probe is invalid (a bug): {}", protocol::errors_to_text(&e)))?;
            let with = meta::recovery_with(ctx, &[v], disc, dims)
                .with_context(|| format!("offline designer: recovery with agent {j} sending {what}"))?;
            let (mut sum, mut recovered) = (0.0, 0.0);
            for (k, &d) in dims.iter().enumerate() {
                let kw = without.position(d).with_context(|| format!("offline designer: s[{d}] has no recovery without messages"))?;
                for i in (0..n).filter(|&i| i != j) {
                    sum += with.rate(k, i) - without.rate(kw, i);
                    recovered += with.rate(k, i);
                }
            }
            let cells = (dims.len() * (n - 1)).max(1) as f64;
            let gain = sum / cells;
            gains.push(Probe { gain, recovery: recovered / cells });
            eprintln!("lmac: offline designer: agent {j} sending {what} to the others: recovery of the critical dims {gain:+.4}");
        }
        Ok(gains)
    }
}
