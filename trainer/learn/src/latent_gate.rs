//! The GRU-gate encoder's gate as one burn operation: `z = sigmoid(q . k) * v` per row, from the
//! query q [N, A] and the key and value side by side, kv [N, A + L] (one matmul makes both, since
//! both read the carried state).
//!
//! As burn operations the gate is a product, a row sum, a sigmoid and a broadcast product, each a
//! pass over [N, L] with a fresh buffer, and backward twice as many; over LMAC's 17,600 rows
//! these passes cost about as much as the gate's matmuls. Here forward is one pass and backward
//! one. Tested against the same operations in burn (values and gradients to 1e-5), which stay
//! the reference in the tests.
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

use crate::host_kernel::{host, host_ref, host_values, register, sigmoid, with_simd, HostValues};

/// q [N, A], kv [N, A + L] (k, then v) -> z [N, L] = sigmoid(sum_j q_j k_j) * v.
#[backend_extension(Flex: cfg(feature = "flex"), NdArray: cfg(feature = "ndarray"), Autodiff)]
pub trait LatentGateBackend: Backend {
    fn latent_gate(q: FloatTensor<Self>, kv: FloatTensor<Self>) -> FloatTensor<Self>;
}

/// `sigmoid(q . k) * v` per row, kv = [k | v]; differentiable in q and kv.
pub fn latent_gate(q: Tensor<2>, kv: Tensor<2>) -> Tensor<2> {
    Tensor::from_dispatch(<Dispatch as LatentGateBackend>::latent_gate(q.into_dispatch(), kv.into_dispatch()))
}

#[cfg(feature = "flex")]
impl LatentGateBackend for burn::backend::Flex {
    fn latent_gate(q: FloatTensor<Self>, kv: FloatTensor<Self>) -> FloatTensor<Self> {
        forward_on::<Self>(q, kv, false).0
    }
}

#[cfg(feature = "ndarray")]
impl LatentGateBackend for burn::backend::NdArray {
    fn latent_gate(q: FloatTensor<Self>, kv: FloatTensor<Self>) -> FloatTensor<Self> {
        forward_on::<Self>(q, kv, false).0
    }
}

impl<B: Backend + LatentGateBackend, C: CheckpointStrategy> LatentGateBackend for Autodiff<B, C> {
    fn latent_gate(q: FloatTensor<Self>, kv: FloatTensor<Self>) -> FloatTensor<Self> {
        let nodes = [q.node(), kv.node()];
        let (q, kv) = (q.into_primitive(), kv.into_primitive());
        match LatentGateBackward.prepare::<C>(nodes).compute_bound().stateful() {
            OpsKind::Tracked(prep) => {
                let (z, saved) = forward_on::<B>(q, kv, true);
                prep.finish(saved.expect("saved activations"), z)
            }
            OpsKind::UnTracked(prep) => prep.finish(forward_on::<B>(q, kv, false).0),
        }
    }
}

/// What backward reads: the inputs (shared, not copied) and each row's gate.
#[derive(Debug, Clone)]
struct Saved {
    /// A, the query's and key's width
    width: usize,
    /// L, the value's and output's width
    out: usize,
    q: HostValues,
    kv: HostValues,
    gate: Vec<f32>,
}

fn forward_on<B: Backend>(q: FloatTensor<B>, kv: FloatTensor<B>, save: bool) -> (FloatTensor<B>, Option<Arc<Saved>>) {
    let device = q.device();
    let [rows, width] = q.shape().dims::<2>();
    let [kv_rows, kv_width] = kv.shape().dims::<2>();
    assert!(kv_rows == rows && kv_width >= width, "latent_gate: q [{rows}, {width}] and kv [{kv_rows}, {kv_width}] do not fit");
    let out = kv_width - width;
    let mut z = vec![0.0f32; rows * out];
    let mut gate = vec![0.0f32; rows];
    with_simd!(gate_forward(&host_ref::<B>(&q), &host_ref::<B>(&kv), width, out, &mut z, &mut gate));
    let z = B::float_from_data(TensorData::new(z, [rows, out]), &device);
    if !save {
        return (z, None);
    }
    (z, Some(Arc::new(Saved { width, out, q: host_values::<B>(q), kv: host_values::<B>(kv), gate })))
}

#[inline(always)]
fn gate_forward(q: &[f32], kv: &[f32], width: usize, out: usize, z: &mut [f32], gate: &mut [f32]) {
    for (r, g) in gate.iter_mut().enumerate() {
        let (q, kv) = (&q[r * width..(r + 1) * width], &kv[r * (width + out)..(r + 1) * (width + out)]);
        let (k, v) = kv.split_at(width);
        *g = sigmoid(q.iter().zip(k).map(|(q, k)| q * k).sum());
        z[r * out..(r + 1) * out].iter_mut().zip(v).for_each(|(z, v)| *z = v * *g);
    }
}

/// dq = a k, dk = a q, dv = dz s, with s the row's gate and a = (dz . v) s (1 - s).
#[inline(always)]
fn gate_backward(dz: &[f32], s: &Saved, d_q: &mut [f32], d_kv: &mut [f32]) {
    let (width, out) = (s.width, s.out);
    for r in 0..s.gate.len() {
        let g = s.gate[r];
        let (q, kv, dz) =
            (&s.q[r * width..(r + 1) * width], &s.kv[r * (width + out)..(r + 1) * (width + out)], &dz[r * out..(r + 1) * out]);
        let (k, v) = kv.split_at(width);
        let (d_k, d_v) = d_kv[r * (width + out)..(r + 1) * (width + out)].split_at_mut(width);
        let a = dz.iter().zip(v).map(|(d, v)| d * v).sum::<f32>() * g * (1.0 - g);
        d_q[r * width..(r + 1) * width].iter_mut().zip(k).for_each(|(d, k)| *d = a * k);
        d_k.iter_mut().zip(q).for_each(|(d, q)| *d = a * q);
        d_v.iter_mut().zip(dz).for_each(|(d, dz)| *d = dz * g);
    }
}

#[derive(Debug)]
struct LatentGateBackward;

impl<B: Backend> Backward<B, 2> for LatentGateBackward {
    type State = Arc<Saved>;

    fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, _checkpointer: &mut Checkpointer) {
        let [node_q, node_kv] = ops.parents.map(|n| n.map(|n| n.id));
        let grad = grads.consume::<B>(&ops.node);
        let device = grad.device();
        let s = ops.state;
        let rows = s.gate.len();
        let dz = host::<B>(grad);
        let kv_width = s.width + s.out;
        let (mut d_q, mut d_kv) = (vec![0.0f32; rows * s.width], vec![0.0f32; rows * kv_width]);
        with_simd!(gate_backward(&dz, &s, &mut d_q, &mut d_kv));
        register::<B>(grads, &device, [(node_q, d_q, vec![rows, s.width]), (node_kv, d_kv, vec![rows, kv_width])]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::host_kernel::test_support::{assert_same_grad, max_diff, random};
    use crate::LearnRng;
    use burn::tensor::activation;
    use burn::tensor::Device;

    /// The gate as burn operations, the reference.
    fn gate_reference(q: Tensor<2>, kv: Tensor<2>) -> Tensor<2> {
        let ([n, a], l) = (q.dims(), kv.dims()[1]);
        let k = kv.clone().slice([0..n, 0..a]);
        let v = kv.slice([0..n, a..l]);
        v * activation::sigmoid((q * k).sum_dim(1))
    }

    /// Values and the gradients of q and kv against burn's operations, to 1e-5, with and without
    /// autodiff, with value widths equal to and other than the key's, and zero rows.
    #[test]
    fn matches_burns_operations() {
        for (rows, width, out) in [(41, 8, 8), (29, 6, 10), (0, 5, 5), (3, 1, 2)] {
            let mut rng = LearnRng::seed_from(11);
            let dev = Device::default().autodiff();
            let q = random(&mut rng, [rows, width], &dev);
            let kv = random(&mut rng, [rows, width + out], &dev);
            let weights = random(&mut rng, [rows, out], &dev);
            let (qr, kvr) = (q.clone().require_grad(), kv.clone().require_grad());
            let (qf, kvf) = (q.clone().require_grad(), kv.clone().require_grad());
            let reference = gate_reference(qr.clone(), kvr.clone());
            let fused = latent_gate(qf.clone(), kvf.clone());
            assert!(max_diff(reference.clone(), fused.clone()) < 1e-5, "values, {rows} x {width}");
            if rows == 0 {
                continue; // burn hands no gradient to tensors of no values
            }
            let g_ref = (reference * weights.clone()).sum().backward();
            let g_fused = (fused * weights).sum().backward();
            assert_same_grad("q", qr.grad(&g_ref), qf.grad(&g_fused));
            assert_same_grad("kv", kvr.grad(&g_ref), kvf.grad(&g_fused));
            // untracked inputs: values only
            let plain = Device::default();
            let (q, kv) = (random(&mut rng, [rows, width], &plain), random(&mut rng, [rows, width + out], &plain));
            assert!(max_diff(gate_reference(q.clone(), kv.clone()), latent_gate(q, kv)) < 1e-5, "untracked values");
        }
    }
}
