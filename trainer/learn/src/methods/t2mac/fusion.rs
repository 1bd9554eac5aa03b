//! T2MAC's evidence side, on the host: subjective-logic opinions from Dirichlet evidence, their
//! reduced Dempster-Shafer combination, and per step of a batch the fusion of the opinions each
//! receiver is sent plus the selector's target classes. None of it carries a gradient (the
//! released code runs it under `no_grad`), so it is plain Rust over all steps at once instead
//! of a chain of small tensor operations per sender.

/// The opinion of evidence `e` (non-negative, over A actions) into `belief`: b = e / S, and the
/// returned uncertainty u = A / S, with S = sum(e) + A (Dirichlet strength, alpha = e + 1).
pub fn opinion(e: &[f32], belief: &mut [f64]) -> f64 {
    let a = e.len() as f64;
    let s = e.iter().map(|&x| x as f64).sum::<f64>() + a;
    for (b, &x) in belief.iter_mut().zip(e) {
        *b = x as f64 / s;
    }
    a / s
}

/// Combine opinion (b1, u1) into (b0, u0) with the reduced Dempster-Shafer rule:
/// C = sum_{x != y} b0_x b1_y, b = (b0 b1 + b0 u1 + b1 u0) / (1 - C), u = u0 u1 / (1 - C).
/// With u0, u1 > 0 the conflict C is below (1 - u0)(1 - u1) < 1, so the division is safe.
pub fn combine(b0: &mut [f64], u0: &mut f64, b1: &[f64], u1: f64) {
    let (s0, s1): (f64, f64) = (b0.iter().sum(), b1.iter().sum());
    let same: f64 = b0.iter().zip(b1).map(|(x, y)| x * y).sum();
    let norm = 1.0 - (s0 * s1 - same);
    for (x, &y) in b0.iter_mut().zip(b1) {
        *x = (*x * y + *x * u1 + y * *u0) / norm;
    }
    *u0 = *u0 * u1 / norm;
}

/// Evidence of an opinion (the inverse of [`opinion`]): e = b A / u.
pub fn to_evidence(belief: &[f64], u: f64, out: &mut [f32]) {
    let s = belief.len() as f64 / u;
    for (o, &b) in out.iter_mut().zip(belief) {
        *o = (b * s) as f32;
    }
}

/// One batch's fusion: `g` groups (an environment's step) of `n` agents.
#[derive(Debug, Clone, PartialEq)]
pub struct Fused {
    /// [g, n, A]: the evidence of the fused opinions each receiver was sent (0 when none).
    pub evidence: Vec<f32>,
    /// [g, n]: whether the agent sends its opinion to a teammate.
    pub sends: Vec<bool>,
    /// [g, n]: the selector's target class per sender (a teammate, or the sender itself for
    /// "send to nobody"); empty when no `min_drop` was given (acting, the target network).
    pub targets: Vec<i64>,
    /// [g, n]: the agent's own uncertainty.
    pub uncertainty: Vec<f32>,
    /// [g, n]: how much fusing what it received with its own opinion lowers a receiver's
    /// uncertainty; `None` for a receiver that received nothing.
    pub drop: Vec<Option<f32>>,
}

/// For every group: agent i sends to the teammate j != i with `probs[i, j] > threshold` (at most
/// one when the threshold is at least 0.5); each receiver fuses the opinions sent to it in
/// sender order, starting from the vacuous opinion (b = 0, u = 1), and gets their evidence. The
/// target class of sender i (only with `min_drop`: the n^2 pairwise combinations are the
/// selector's training labels, of no use when acting) is the teammate whose uncertainty the
/// combination of i's opinion with its own lowers most, if by more than `min_drop`, else i.
///
/// `evidence` is [g, n, A] (non-negative), `probs` [g, n, n] (each row the selector's softmax).
pub fn fuse(evidence: &[f32], probs: &[f32], n: usize, a: usize, threshold: f32, min_drop: Option<f32>) -> Fused {
    let g = evidence.len() / (n * a).max(1);
    assert_eq!(evidence.len(), g * n * a, "evidence is [groups, agents, actions]");
    assert_eq!(probs.len(), g * n * n, "probabilities are [groups, agents, agents]");
    let mut out = Fused {
        evidence: vec![0.0; g * n * a],
        sends: vec![false; g * n],
        targets: if min_drop.is_some() { vec![0; g * n] } else { Vec::new() },
        uncertainty: vec![0.0; g * n],
        drop: vec![None; g * n],
    };
    let mut belief = vec![0.0f64; n * a];
    let mut u = vec![0.0f64; n];
    let (mut fb, mut pair) = (vec![0.0f64; a], vec![0.0f64; a]);
    for gi in 0..g {
        for i in 0..n {
            let row = (gi * n + i) * a;
            u[i] = opinion(&evidence[row..row + a], &mut belief[i * a..(i + 1) * a]);
            out.uncertainty[gi * n + i] = u[i] as f32;
        }
        // The receiver of each sender, if any.
        let receiver: Vec<Option<usize>> = (0..n).map(|i| (0..n).find(|&j| j != i && probs[(gi * n + i) * n + j] > threshold)).collect();
        for j in 0..n {
            fb.fill(0.0);
            let mut fu = 1.0f64;
            let mut any = false;
            for i in (0..n).filter(|&i| receiver[i] == Some(j)) {
                combine(&mut fb, &mut fu, &belief[i * a..(i + 1) * a], u[i]);
                any = true;
            }
            if any {
                let row = (gi * n + j) * a;
                to_evidence(&fb, fu, &mut out.evidence[row..row + a]);
                pair.copy_from_slice(&belief[j * a..(j + 1) * a]);
                let mut pu = u[j];
                combine(&mut pair, &mut pu, &fb, fu);
                out.drop[gi * n + j] = Some((u[j] - pu) as f32);
            }
        }
        for i in 0..n {
            out.sends[gi * n + i] = receiver[i].is_some();
        }
        let Some(min_drop) = min_drop else { continue };
        for i in 0..n {
            let mut best = (i, min_drop as f64);
            for j in (0..n).filter(|&j| j != i) {
                pair.copy_from_slice(&belief[j * a..(j + 1) * a]);
                let mut pu = u[j];
                combine(&mut pair, &mut pu, &belief[i * a..(i + 1) * a], u[i]);
                if u[j] - pu > best.1 {
                    best = (j, u[j] - pu);
                }
            }
            out.targets[gi * n + i] = best.0 as i64;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() < 1e-9
    }

    #[test]
    fn an_opinion_and_its_evidence_are_inverse() {
        // e = (2, 0, 1), A = 3: S = 6, b = (1/3, 0, 1/6), u = 1/2.
        let mut b = [0.0; 3];
        let u = opinion(&[2.0, 0.0, 1.0], &mut b);
        assert!(close(u, 0.5) && close(b[0], 1.0 / 3.0) && close(b[1], 0.0) && close(b[2], 1.0 / 6.0), "{b:?} {u}");
        let mut e = [0.0f32; 3];
        to_evidence(&b, u, &mut e);
        assert_eq!(e, [2.0, 0.0, 1.0]);
    }

    #[test]
    fn the_combination_rule_matches_a_hand_computed_case() {
        // b0 = (0.5, 0.2), u0 = 0.3; b1 = (0.1, 0.6), u1 = 0.3.
        // C = 0.5 * 0.6 + 0.2 * 0.1 = 0.32, 1 - C = 0.68.
        // b = (0.05 + 0.15 + 0.03, 0.12 + 0.06 + 0.18) / 0.68 = (0.23, 0.36) / 0.68; u = 0.09 / 0.68.
        let (mut b, mut u) = ([0.5, 0.2], 0.3);
        combine(&mut b, &mut u, &[0.1, 0.6], 0.3);
        assert!(close(b[0], 0.23 / 0.68) && close(b[1], 0.36 / 0.68) && close(u, 0.09 / 0.68), "{b:?} {u}");
        assert!(close(b[0] + b[1] + u, 1.0), "an opinion stays normalised");
        // The vacuous opinion is the identity.
        let (mut v, mut vu) = ([0.0, 0.0], 1.0);
        combine(&mut v, &mut vu, &[0.1, 0.6], 0.3);
        assert!(close(v[0], 0.1) && close(v[1], 0.6) && close(vu, 0.3));
        // Commutative: the order senders are fused in does not matter.
        let (mut x, mut xu) = ([0.1, 0.6], 0.3);
        combine(&mut x, &mut xu, &[0.5, 0.2], 0.3);
        assert!(close(x[0], b[0]) && close(x[1], b[1]) && close(xu, u));
    }

    #[test]
    fn receivers_get_the_fused_opinions_of_their_senders_and_targets_follow_the_drop() {
        // One group of three agents, two actions.
        // Agent 0: e = (8, 0) (confident), agent 1: e = (0, 0) (vacuous: u = 1), agent 2: e = (0, 2).
        let e = [8.0, 0.0, 0.0, 0.0, 0.0, 2.0];
        // Agent 0 sends to 1 (0.8 > 0.75), agent 2 to 1 as well, agent 1 to nobody (0.7 < 0.75).
        let p = [0.1, 0.8, 0.1, 0.2, 0.7, 0.1, 0.05, 0.9, 0.05];
        let f = fuse(&e, &p, 3, 2, 0.75, Some(0.1));
        assert_eq!(f.sends, vec![true, false, true]);
        // Opinions: 0: b = (0.8, 0), u = 0.2; 2: b = (0, 0.5), u = 0.5.
        // Fused at 1: C = 0.8 * 0.5 = 0.4; b = (0.8 * 0.5, 0.5 * 0.2) / 0.6, u = 0.1 / 0.6;
        // evidence = b * 2 / u = (8, 2).
        assert!((f.evidence[2] - 8.0).abs() < 1e-5 && (f.evidence[3] - 2.0).abs() < 1e-5, "{:?}", f.evidence);
        assert_eq!(&f.evidence[..2], &[0.0, 0.0]);
        assert_eq!(&f.evidence[4..], &[0.0, 0.0]);
        assert_eq!(f.drop[0], None);
        // Receiver 1 is vacuous: fusing gives the fused opinion, u from 1 to 1/6.
        assert!((f.drop[1].unwrap() - (1.0 - 1.0 / 6.0) as f32).abs() < 1e-6);
        assert_eq!(f.uncertainty, vec![0.2, 1.0, 0.5]);
        // Targets: agent 0 helps agent 1 most (u 1 -> 0.2) rather than 2 (0.5 -> 0.1 / (1 - 0.4)
        // = 1/6, a drop of 1/3); agent 1 is vacuous and helps nobody (its combination is the
        // identity): target itself; agent 2 helps 1 (1 -> 0.5) more than 0 (0.2 -> 0.1 / 0.6).
        assert_eq!(f.targets, vec![1, 1, 1]);
        // With a threshold above every drop, nobody is worth sending to.
        assert_eq!(fuse(&e, &p, 3, 2, 0.75, Some(0.9)).targets, vec![0, 1, 2]);
    }
}
