//! Message widths: the columns each receiver gets from one phase and from phases together, in
//! either layout (the width rules, once).

use super::ast::{MessageLayout, Protocol};
use super::env::ProtocolEnv;
use super::validate::ValidatedProtocol;

/// Columns each receiver needs before padding for one phase on its own: in the compact layout,
/// per sender that reaches it, the one-hot (if on) and the fields that sender sends it; in the
/// sender-blocks layout, the full [`message_width`] for everyone.
pub fn receiver_widths(p: &Protocol, env: &ProtocolEnv, widths: &[usize], sends: &[Vec<Vec<bool>>]) -> Vec<usize> {
    if p.layout == MessageLayout::SenderBlocks {
        return vec![message_width(p, env, widths); env.n_agents];
    }
    compact_widths(env.n_agents, &[PhaseLinks { onehot: p.sender_one_hot, widths, sends }])
}

/// What the compact layout needs to know of one phase.
pub(super) struct PhaseLinks<'a> {
    pub(super) onehot: bool,
    pub(super) widths: &'a [usize],
    pub(super) sends: &'a [Vec<Vec<bool>>],
}

/// Per receiver, the compact layout of these phases together: for each sender that reaches it in
/// any phase, its one-hot once (if a phase that links them has it on) and every field of every
/// phase it sends there.
pub(super) fn compact_widths(n: usize, phases: &[PhaseLinks]) -> Vec<usize> {
    let sent = |ph: &PhaseLinks, f: usize, j: usize, i: usize| ph.sends.get(f).and_then(|s| s.get(j)).and_then(|s| s.get(i)) == Some(&true);
    (0..n)
        .map(|i| {
            (0..n).filter(|&j| j != i).fold(0usize, |acc, j| {
                let mut linked = false;
                let mut onehot = false;
                let mut w = 0usize;
                for ph in phases {
                    for (f, &fw) in ph.widths.iter().enumerate() {
                        if sent(ph, f, j, i) {
                            linked = true;
                            onehot |= ph.onehot;
                            w = w.saturating_add(fw);
                        }
                    }
                }
                if !linked {
                    return acc;
                }
                acc.saturating_add(if onehot { n } else { 0 }).saturating_add(w)
            })
        })
        .collect()
}

/// Per receiver, the columns the phases compiled together need before padding (the plan's
/// width is the largest). Compact phases share one block per sender across phases (one one-hot
/// per sender); sender-blocks phases are concatenated after them... they cannot be mixed (see
/// [`check_phases`]), so this is either the compact combination or the sum of the blocks.
pub fn combined_receiver_widths(phases: &[ValidatedProtocol]) -> Vec<usize> {
    let n = phases.first().map_or(0, |p| p.env.n_agents);
    let compact: Vec<PhaseLinks> = phases
        .iter()
        .filter(|p| p.protocol.layout == MessageLayout::Compact)
        .map(|p| PhaseLinks { onehot: p.protocol.sender_one_hot, widths: &p.field_widths, sends: &p.sends })
        .collect();
    let blocks: usize =
        phases.iter().filter(|p| p.protocol.layout == MessageLayout::SenderBlocks).fold(0usize, |a, p| a.saturating_add(p.width));
    compact_widths(n, &compact).into_iter().map(|w| w.saturating_add(blocks)).collect()
}

/// The message width of these phases compiled together (what [`check_phases`] returns and the
/// plan's `msg_dim`): the widest receiver's. Not the sum of the phases' own widths in the compact
/// layout, where a sender's one-hot is paid once across phases.
pub fn combined_width(phases: &[ValidatedProtocol]) -> usize {
    combined_receiver_widths(phases).into_iter().max().unwrap_or(0)
}

pub(super) fn block_width(p: &Protocol, env: &ProtocolEnv, widths: &[usize]) -> usize {
    let onehot = if p.sender_one_hot { env.n_agents } else { 0 };
    widths.iter().fold(onehot, |a, &w| a.saturating_add(w))
}

/// Message columns per receiver of a protocol with these field widths in the sender-blocks
/// layout: (n_agents - 1) x (one-hot + all fields), 0 with fewer than 2 agents. It is also the
/// compact layout's width when every agent sends every field to every other (an upper bound).
pub fn message_width(p: &Protocol, env: &ProtocolEnv, widths: &[usize]) -> usize {
    env.n_agents.saturating_sub(1).saturating_mul(block_width(p, env, widths))
}
