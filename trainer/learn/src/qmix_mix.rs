//! QMIX's mixing of the agents' utilities as one burn operation, from what its hypernetworks
//! output per row: `Q_tot = elu(q . |W1| + b1) . |w_final| + V`, with q [N, n] the chosen
//! utilities, W1 [N, n * E] (row-major [n, E] per row), b1 and w_final [N, E], V [N, 1].
//!
//! As burn operations the mixing is two absolute values, a broadcast product and row sum over
//! [N, n, E], a sum, an ELU, a product and row sum and a sum, each a pass with a fresh buffer
//! (and backward about twice as many). Here forward is one pass over the rows and backward one.
//! Tested against the same operations in burn (values and gradients to 1e-5), which stay the
//! reference in the tests.
// burn marks its ndarray backend deprecated; the `ndarray` feature still selects it.
#![cfg_attr(feature = "ndarray", allow(deprecated))]

use std::sync::Arc;

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::autodiff::Autodiff;
use burn::backend::tensor::FloatTensor;
use burn::backend::{backend_extension, Backend, Dispatch, TensorMetadata};
use burn::tensor::{Tensor, TensorData};

use crate::host_kernel::{host, host_ref, host_values, register, with_simd, HostValues};

/// qs [N, n], w1 [N, n * E], b1 [N, E], w_final [N, E], v [N, 1] -> Q_tot [N].
#[backend_extension(Flex: cfg(feature = "flex"), NdArray: cfg(feature = "ndarray"), Autodiff)]
pub trait QmixMixBackend: Backend {
    fn qmix_mix(
        qs: FloatTensor<Self>,
        w1: FloatTensor<Self>,
        b1: FloatTensor<Self>,
        w_final: FloatTensor<Self>,
        v: FloatTensor<Self>,
    ) -> FloatTensor<Self>;
}

/// `elu(q . |W1| + b1) . |w_final| + V` per row (see the file's header); differentiable in
/// every input.
pub fn qmix_mix(qs: Tensor<2>, w1: Tensor<2>, b1: Tensor<2>, w_final: Tensor<2>, v: Tensor<2>) -> Tensor<1> {
    Tensor::from_dispatch(<Dispatch as QmixMixBackend>::qmix_mix(
        qs.into_dispatch(),
        w1.into_dispatch(),
        b1.into_dispatch(),
        w_final.into_dispatch(),
        v.into_dispatch(),
    ))
}

#[cfg(feature = "flex")]
impl QmixMixBackend for burn::backend::Flex {
    fn qmix_mix(
        qs: FloatTensor<Self>,
        w1: FloatTensor<Self>,
        b1: FloatTensor<Self>,
        w_final: FloatTensor<Self>,
        v: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        forward_on::<Self>(Inputs { qs, w1, b1, w_final, v }, false).0
    }
}

#[cfg(feature = "ndarray")]
impl QmixMixBackend for burn::backend::NdArray {
    fn qmix_mix(
        qs: FloatTensor<Self>,
        w1: FloatTensor<Self>,
        b1: FloatTensor<Self>,
        w_final: FloatTensor<Self>,
        v: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        forward_on::<Self>(Inputs { qs, w1, b1, w_final, v }, false).0
    }
}

impl<B: Backend + QmixMixBackend, C: CheckpointStrategy> QmixMixBackend for Autodiff<B, C> {
    fn qmix_mix(
        qs: FloatTensor<Self>,
        w1: FloatTensor<Self>,
        b1: FloatTensor<Self>,
        w_final: FloatTensor<Self>,
        v: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let nodes = [qs.node(), w1.node(), b1.node(), w_final.node(), v.node()];
        let inputs = Inputs {
            qs: qs.into_primitive(),
            w1: w1.into_primitive(),
            b1: b1.into_primitive(),
            w_final: w_final.into_primitive(),
            v: v.into_primitive(),
        };
        match QmixMixBackward.prepare::<C>(nodes).compute_bound().stateful() {
            OpsKind::Tracked(prep) => {
                let (y, saved) = forward_on::<B>(inputs, true);
                prep.finish(saved.expect("saved activations"), y)
            }
            OpsKind::UnTracked(prep) => prep.finish(forward_on::<B>(inputs, false).0),
        }
    }
}

struct Inputs<B: Backend> {
    qs: FloatTensor<B>,
    w1: FloatTensor<B>,
    b1: FloatTensor<B>,
    w_final: FloatTensor<B>,
    v: FloatTensor<B>,
}

/// What backward reads: the inputs it needs (shared, not copied) and the hidden layer.
#[derive(Debug, Clone)]
struct Saved {
    agents: usize,
    embed: usize,
    qs: HostValues,
    w1: HostValues,
    w_final: HostValues,
    /// elu(q . |W1| + b1) [N, E]
    hidden: Vec<f32>,
}

fn forward_on<B: Backend>(inputs: Inputs<B>, save: bool) -> (FloatTensor<B>, Option<Arc<Saved>>) {
    let Inputs { qs, w1, b1, w_final, v } = inputs;
    let device = qs.device();
    let [rows, agents] = qs.shape().dims::<2>();
    let [_, embed] = b1.shape().dims::<2>();
    let fits = |t: &FloatTensor<B>, w: usize| t.shape().dims::<2>() == [rows, w];
    assert!(
        fits(&w1, agents * embed) && fits(&b1, embed) && fits(&w_final, embed) && fits(&v, 1),
        "qmix_mix: qs {:?}, w1 {:?}, b1 {:?}, w_final {:?}, v {:?} do not fit",
        qs.shape().dims::<2>(),
        w1.shape().dims::<2>(),
        b1.shape().dims::<2>(),
        w_final.shape().dims::<2>(),
        v.shape().dims::<2>()
    );
    let mut hidden = host_ref::<B>(&b1).into_owned();
    let mut q_tot = host_ref::<B>(&v).into_owned();
    with_simd!(mix_forward(&host_ref::<B>(&qs), &host_ref::<B>(&w1), &host_ref::<B>(&w_final), agents, embed, &mut hidden, &mut q_tot));
    let y = B::float_from_data(TensorData::new(q_tot, [rows]), &device);
    if !save {
        return (y, None);
    }
    let saved = Saved { agents, embed, qs: host_values::<B>(qs), w1: host_values::<B>(w1), w_final: host_values::<B>(w_final), hidden };
    (y, Some(Arc::new(saved)))
}

/// hidden (holding b1) becomes elu(q . |W1| + b1); q_tot (holding V) gains hidden . |w_final|.
#[inline(always)]
fn mix_forward(qs: &[f32], w1: &[f32], w_final: &[f32], agents: usize, embed: usize, hidden: &mut [f32], q_tot: &mut [f32]) {
    for (r, q_tot) in q_tot.iter_mut().enumerate() {
        let h = &mut hidden[r * embed..(r + 1) * embed];
        for (i, q) in qs[r * agents..(r + 1) * agents].iter().enumerate() {
            let w = &w1[(r * agents + i) * embed..(r * agents + i + 1) * embed];
            h.iter_mut().zip(w).for_each(|(h, w)| *h += q * w.abs());
        }
        h.iter_mut().for_each(|h| *h = if *h > 0.0 { *h } else { h.exp() - 1.0 });
        *q_tot += h.iter().zip(&w_final[r * embed..(r + 1) * embed]).map(|(h, w)| h * w.abs()).sum::<f32>();
    }
}

/// The derivative of |x| as burn takes it: the sign, 0 at 0.
#[inline(always)]
fn sign(x: f32) -> f32 {
    if x > 0.0 {
        1.0
    } else if x < 0.0 {
        -1.0
    } else {
        0.0
    }
}

/// Gradients of every input from d(Q_tot) (see [`Saved`]); `d_b1` receives d(pre-activation).
#[inline(always)]
fn mix_backward(g: &[f32], s: &Saved, d_qs: &mut [f32], d_w1: &mut [f32], d_b1: &mut [f32], d_w_final: &mut [f32]) {
    let (agents, embed) = (s.agents, s.embed);
    for (r, g) in g.iter().enumerate() {
        let span = r * embed..(r + 1) * embed;
        let (h, wf) = (&s.hidden[span.clone()], &s.w_final[span.clone()]);
        d_w_final[span.clone()].iter_mut().zip(h).zip(wf).for_each(|((d, h), w)| *d = g * h * sign(*w));
        // elu'(a) = 1 for a > 0, else exp(a) = elu(a) + 1
        let d_a = &mut d_b1[span];
        d_a.iter_mut().zip(h).zip(wf).for_each(|((d, h), w)| *d = g * w.abs() * if *h > 0.0 { 1.0 } else { h + 1.0 });
        for i in 0..agents {
            let at = (r * agents + i) * embed..(r * agents + i + 1) * embed;
            let (w, q) = (&s.w1[at.clone()], s.qs[r * agents + i]);
            d_qs[r * agents + i] = d_a.iter().zip(w).map(|(d, w)| d * w.abs()).sum();
            d_w1[at].iter_mut().zip(d_a.iter()).zip(w).for_each(|((d, d_a), w)| *d = d_a * q * sign(*w));
        }
    }
}

#[derive(Debug)]
struct QmixMixBackward;

impl<B: Backend> Backward<B, 5> for QmixMixBackward {
    type State = Arc<Saved>;

    fn backward(self, ops: Ops<Self::State, 5>, grads: &mut Gradients, _checkpointer: &mut Checkpointer) {
        let [node_qs, node_w1, node_b1, node_w_final, node_v] = ops.parents.map(|n| n.map(|n| n.id));
        let grad = grads.consume::<B>(&ops.node);
        let device = grad.device();
        let s = ops.state;
        let g = host::<B>(grad);
        let (rows, agents, embed) = (g.len(), s.agents, s.embed);
        let (mut d_qs, mut d_w1) = (vec![0.0f32; rows * agents], vec![0.0f32; rows * agents * embed]);
        let (mut d_b1, mut d_w_final) = (vec![0.0f32; rows * embed], vec![0.0f32; rows * embed]);
        with_simd!(mix_backward(&g, &s, &mut d_qs, &mut d_w1, &mut d_b1, &mut d_w_final));
        register::<B>(
            grads,
            &device,
            [
                (node_qs, d_qs, vec![rows, agents]),
                (node_w1, d_w1, vec![rows, agents * embed]),
                (node_b1, d_b1, vec![rows, embed]),
                (node_w_final, d_w_final, vec![rows, embed]),
                (node_v, g, vec![rows, 1]),
            ],
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::host_kernel::test_support::{assert_same_grad, max_diff, random};
    use crate::LearnRng;
    use burn::tensor::activation::elu;
    use burn::tensor::Device;

    /// The mixing as burn operations (`QmixMixer::forward` before this operation), the reference.
    fn mix_reference(qs: Tensor<2>, w1: Tensor<2>, b1: Tensor<2>, w_final: Tensor<2>, v: Tensor<2>) -> Tensor<1> {
        let [n, na] = qs.dims();
        let e = b1.dims()[1];
        let w1 = w1.abs().reshape([n, na, e]);
        let hidden = elu((qs.reshape([n, na, 1]) * w1).sum_dim(1).reshape([n, e]) + b1, 1.0);
        ((hidden * w_final.abs()).sum_dim(1) + v).reshape([n])
    }

    /// Values and the gradients of every input against burn's operations, to 1e-5, with and
    /// without autodiff, including zero rows and one agent.
    #[test]
    fn matches_burns_operations() {
        for (rows, agents, embed) in [(37, 5, 8), (0, 3, 4), (4, 1, 3)] {
            let mut rng = LearnRng::seed_from(3);
            let dev = Device::default().autodiff();
            let shapes = [[rows, agents], [rows, agents * embed], [rows, embed], [rows, embed], [rows, 1]];
            let inputs: Vec<Tensor<2>> = shapes.iter().map(|s| random(&mut rng, *s, &dev)).collect();
            let weights: Tensor<1> = random(&mut rng, [rows, 1], &dev).reshape([rows]);
            let tracked = |i: &[Tensor<2>]| i.iter().map(|t| t.clone().require_grad()).collect::<Vec<_>>();
            let (r, f) = (tracked(&inputs), tracked(&inputs));
            let reference = mix_reference(r[0].clone(), r[1].clone(), r[2].clone(), r[3].clone(), r[4].clone());
            let fused = qmix_mix(f[0].clone(), f[1].clone(), f[2].clone(), f[3].clone(), f[4].clone());
            assert!(max_diff(reference.clone(), fused.clone()) < 1e-5, "values, {rows} x {agents} x {embed}");
            if rows == 0 {
                continue; // burn hands no gradient to tensors of no values
            }
            let g_ref = (reference * weights.clone()).sum().backward();
            let g_fused = (fused * weights).sum().backward();
            for (i, what) in ["qs", "w1", "b1", "w_final", "v"].iter().enumerate() {
                assert_same_grad(what, r[i].grad(&g_ref), f[i].grad(&g_fused));
            }
            // untracked inputs: values only
            let plain = Device::default();
            let i: Vec<Tensor<2>> = shapes.iter().map(|s| random(&mut rng, *s, &plain)).collect();
            let reference = mix_reference(i[0].clone(), i[1].clone(), i[2].clone(), i[3].clone(), i[4].clone());
            assert!(max_diff(reference, qmix_mix(i[0].clone(), i[1].clone(), i[2].clone(), i[3].clone(), i[4].clone())) < 1e-5);
        }
    }
}
