//! LMAC's agent-network input as one burn operation: each row of the batch's inputs u [N, W]
//! without its message columns [from, to), then the latent z [N, L] -> [N, W - (to - from) + L].
//!
//! As burn operations this is two column slices of u (strided views, each copied) and a
//! concatenation, three passes over the rows; here it is one. Backward hands z (and u, where it
//! is tracked) its columns of the gradient. Tested against the same operations in burn.
// burn marks its ndarray backend deprecated; the `ndarray` feature still selects it.
#![cfg_attr(feature = "ndarray", allow(deprecated))]

use std::ops::Range;

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::autodiff::Autodiff;
use burn::backend::tensor::FloatTensor;
use burn::backend::{backend_extension, Backend, Dispatch, TensorMetadata};
use burn::tensor::{Tensor, TensorData};

use crate::host_kernel::{host, host_ref, register};

/// u [N, W] without columns [from, to), then z [N, L].
#[backend_extension(Flex: cfg(feature = "flex"), NdArray: cfg(feature = "ndarray"), Autodiff)]
pub trait AgentInputBackend: Backend {
    fn agent_input(u: FloatTensor<Self>, from: usize, to: usize, z: FloatTensor<Self>) -> FloatTensor<Self>;
}

/// Each row of `u` without its columns `drop`, then the row of `z`; differentiable in both.
pub fn agent_input(u: Tensor<2>, drop: Range<usize>, z: Tensor<2>) -> Tensor<2> {
    Tensor::from_dispatch(<Dispatch as AgentInputBackend>::agent_input(u.into_dispatch(), drop.start, drop.end, z.into_dispatch()))
}

#[cfg(feature = "flex")]
impl AgentInputBackend for burn::backend::Flex {
    fn agent_input(u: FloatTensor<Self>, from: usize, to: usize, z: FloatTensor<Self>) -> FloatTensor<Self> {
        forward_on::<Self>(&u, from..to, &z)
    }
}

#[cfg(feature = "ndarray")]
impl AgentInputBackend for burn::backend::NdArray {
    fn agent_input(u: FloatTensor<Self>, from: usize, to: usize, z: FloatTensor<Self>) -> FloatTensor<Self> {
        forward_on::<Self>(&u, from..to, &z)
    }
}

impl<B: Backend + AgentInputBackend, C: CheckpointStrategy> AgentInputBackend for Autodiff<B, C> {
    fn agent_input(u: FloatTensor<Self>, from: usize, to: usize, z: FloatTensor<Self>) -> FloatTensor<Self> {
        let nodes = [u.node(), z.node()];
        let (u, z) = (u.into_primitive(), z.into_primitive());
        let width = u.shape().dims::<2>()[1];
        let y = forward_on::<B>(&u, from..to, &z);
        match AgentInputBackward.prepare::<C>(nodes).compute_bound().stateful() {
            OpsKind::Tracked(prep) => prep.finish(Columns { width, from, to }, y),
            OpsKind::UnTracked(prep) => prep.finish(y),
        }
    }
}

fn forward_on<B: Backend>(u: &FloatTensor<B>, drop: Range<usize>, z: &FloatTensor<B>) -> FloatTensor<B> {
    let [rows, width] = u.shape().dims::<2>();
    let [z_rows, latent] = z.shape().dims::<2>();
    assert!(
        z_rows == rows && drop.start <= drop.end && drop.end <= width,
        "agent_input: u [{rows}, {width}] without columns {drop:?}, then z [{z_rows}, {latent}], do not fit"
    );
    let out = width - drop.len() + latent;
    let (u_host, z_host) = (host_ref::<B>(u), host_ref::<B>(z));
    let mut y = Vec::with_capacity(rows * out);
    for r in 0..rows {
        let row = &u_host[r * width..(r + 1) * width];
        y.extend_from_slice(&row[..drop.start]);
        y.extend_from_slice(&row[drop.end..]);
        y.extend_from_slice(&z_host[r * latent..(r + 1) * latent]);
    }
    B::float_from_data(TensorData::new(y, [rows, out]), &u.device())
}

/// The columns u had and the ones it lost: all backward needs.
#[derive(Debug, Clone)]
struct Columns {
    width: usize,
    from: usize,
    to: usize,
}

#[derive(Debug)]
struct AgentInputBackward;

impl<B: Backend> Backward<B, 2> for AgentInputBackward {
    type State = Columns;

    fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, _checkpointer: &mut Checkpointer) {
        let [node_u, node_z] = ops.parents.map(|n| n.map(|n| n.id));
        let grad = grads.consume::<B>(&ops.node);
        let device = grad.device();
        let Columns { width, from, to } = ops.state;
        let [rows, out] = grad.shape().dims::<2>();
        let kept = width - (to - from);
        let g = host::<B>(grad);
        let (mut d_u, mut d_z) = (Vec::new(), Vec::new());
        if node_u.is_some() {
            d_u = vec![0.0f32; rows * width];
            for (d, g) in d_u.chunks_exact_mut(width.max(1)).zip(g.chunks_exact(out.max(1))) {
                d[..from].copy_from_slice(&g[..from]);
                d[to..].copy_from_slice(&g[from..kept]);
            }
        }
        if node_z.is_some() {
            d_z.reserve(rows * (out - kept));
            for g in g.chunks_exact(out.max(1)) {
                d_z.extend_from_slice(&g[kept..]);
            }
        }
        register::<B>(grads, &device, [(node_u, d_u, vec![rows, width]), (node_z, d_z, vec![rows, out - kept])]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::host_kernel::test_support::{assert_same_grad, max_diff, random};
    use crate::LearnRng;
    use burn::tensor::Device;

    /// The same as burn operations, the reference.
    fn reference(u: Tensor<2>, drop: Range<usize>, z: Tensor<2>) -> Tensor<2> {
        let [n, w] = u.dims();
        Tensor::cat(vec![u.clone().slice([0..n, 0..drop.start]), u.slice([0..n, drop.end..w]), z], 1)
    }

    /// Values and the gradients of u and z against burn's operations, with message columns in
    /// the middle, at either end, none, and zero rows.
    #[test]
    fn matches_burns_operations() {
        for (rows, width, drop, latent) in [(23, 10, 3..7, 4), (5, 6, 0..2, 3), (5, 6, 4..6, 2), (7, 5, 2..2, 3), (0, 4, 1..3, 2)] {
            let what = format!("{rows} rows, {width} columns without {drop:?}, latent {latent}");
            let mut rng = LearnRng::seed_from(9);
            let dev = Device::default().autodiff();
            let u = random(&mut rng, [rows, width], &dev);
            let z = random(&mut rng, [rows, latent], &dev);
            let weights = random(&mut rng, [rows, width - drop.len() + latent], &dev);
            let (ur, zr, uf, zf) = (u.clone().require_grad(), z.clone().require_grad(), u.clone().require_grad(), z.require_grad());
            let r = reference(ur.clone(), drop.clone(), zr.clone());
            let f = agent_input(uf.clone(), drop.clone(), zf.clone());
            assert_eq!(max_diff(r.clone(), f.clone()), 0.0, "{what}");
            if rows == 0 {
                continue; // burn hands no gradient to tensors of no values
            }
            let (g_r, g_f) = ((r * weights.clone()).sum().backward(), (f * weights).sum().backward());
            assert_same_grad("u", ur.grad(&g_r), uf.grad(&g_f));
            assert_same_grad("z", zr.grad(&g_r), zf.grad(&g_f));
            // z alone tracked (LMAC's TD into the encoder)
            let (zr, zf) = (zr.detach().require_grad(), zf.detach().require_grad());
            let weights = random(&mut rng, [rows, width - drop.len() + latent], &dev);
            let g_r = (reference(u.clone(), drop.clone(), zr.clone()) * weights.clone()).sum().backward();
            let g_f = (agent_input(u, drop.clone(), zf.clone()) * weights).sum().backward();
            assert_same_grad("z alone", zr.grad(&g_r), zf.grad(&g_f));
            // nothing tracked
            let plain = Device::default();
            let (u, z) = (random(&mut rng, [rows, width], &plain), random(&mut rng, [rows, latent], &plain));
            assert_eq!(max_diff(reference(u.clone(), drop.clone(), z.clone()), agent_input(u, drop.clone(), z)), 0.0, "{what}");
        }
    }
}
