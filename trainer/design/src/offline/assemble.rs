//! Protocol assembly: picked candidates become protocol fields with their prose.

use super::candidates::{Candidate, Kind};
use super::select::Pick;
use lmac_protocol_runner::protocol::{Field, PeerLink, ProtocolEnv, Receivers, Senders};
use std::collections::BTreeMap;

pub(super) fn short(s: &str) -> String {
    let s = s.trim();
    if s.chars().count() <= 80 {
        s.to_string()
    } else {
        format!("{}...", s.chars().take(77).collect::<String>())
    }
}

pub(super) fn links_text(links: &[Vec<bool>]) -> String {
    let n = links.len();
    if (0..n).all(|j| (0..n).all(|i| i == j || links[j][i])) {
        return "broadcast by every agent".into();
    }
    let parts: Vec<String> = (0..n)
        .filter_map(|j| {
            let to: Vec<String> = (0..n).filter(|&i| links[j][i]).map(|i| i.to_string()).collect();
            (!to.is_empty()).then(|| format!("{j} -> {}", to.join(",")))
        })
        .collect();
    format!("peer to peer ({})", parts.join("; "))
}

/// Fields from the picks: one per (kind, link pattern), observation dims in increasing order.
pub(super) fn fields_from(picks: &[Pick], cands: &[Candidate], env: &ProtocolEnv) -> Vec<Field> {
    let n = env.n_agents;
    let mut groups: BTreeMap<(Kind, Vec<Vec<bool>>), Vec<usize>> = BTreeMap::new();
    for p in picks {
        let c = &cands[p.cand];
        groups.entry((c.kind, p.links.clone())).or_default().extend(c.dim);
    }
    let mut fields = Vec::new();
    let mut used: BTreeMap<String, usize> = BTreeMap::new();
    for ((kind, links), mut dims) in groups {
        dims.sort_unstable();
        let (stem, what) = kind.words();
        let k = used.entry(stem.clone()).or_insert(0);
        *k += 1;
        let name = if *k == 1 { stem } else { format!("{stem}_{k}") };
        let broadcast = (0..n).all(|j| (0..n).all(|i| i == j || links[j][i]));
        let senders_list: Vec<usize> = (0..n).filter(|&j| links[j].iter().any(|&x| x)).collect();
        // Named in the one sender's own meanings where agents observe different things.
        let one_sender = (senders_list.len() == 1).then(|| senders_list[0]);
        let (senders, receivers) = if broadcast {
            (Senders::All, Receivers::Broadcast)
        } else {
            let peers = senders_list.iter().map(|&j| PeerLink { from: j, to: (0..n).filter(|&i| links[j][i]).collect() }).collect();
            (Senders::List(senders_list), Receivers::Peer(peers))
        };
        let description = if kind.per_dim() {
            let names: Vec<String> = dims
                .iter()
                .map(|&d| format!("o[{d}] ({})", env.obs_name_of(one_sender, d).map(short).unwrap_or_else(|| "unnamed".into())))
                .collect();
            format!("{what}, dims {}; {}", names.join(", "), links_text(&links))
        } else {
            format!("{what}; {}", links_text(&links))
        };
        fields.push(Field { name, description, senders, receivers, value: kind.expr(&dims) });
    }
    fields
}
