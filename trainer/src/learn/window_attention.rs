//! The LMAC window encoder's attention over a whole unroll as one burn operation (issue 26).
//!
//! Per step t, row n and head h: scores_o = q_t . k_{t-o} / sqrt(d) for the entries
//! o < min(W, t + 1) (steps before the unroll's first are not there), softmax over o, and the
//! output sum_o att_o v_{t-o}. Written with burn ops this was W shifted copies of the keys and
//! of the values, a [W, T, N, heads] score tensor and a softmax over its first axis: about 60
//! passes over [T, N, A]-sized tensors forward and more backward, most of the LMAC update's
//! time at 1o_10b's shape although the arithmetic is a few tens of MFLOP. Here the projections
//! q, k, v stay ordinary burn matmuls; this operation reads them once, forward and backward
//! (hand-written, registered with burn's autodiff as one node like `gru_sequence.rs`), and
//! keeps only the attention weights [T, N, heads, W] for the backward. Tested against the burn
//! computation to 1e-5 in values and gradients.
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

use super::host_kernel::{exp_approx, host, with_simd};

/// Windowed multi-head attention as a backend operation: q, k, v [T, N, A] (A = heads x d,
/// heads contiguous) -> [T, N, A].
#[backend_extension(Flex: cfg(feature = "flex"), NdArray: cfg(feature = "ndarray"), Autodiff)]
pub trait WindowAttentionBackend: Backend {
    fn window_attention(q: FloatTensor<Self>, k: FloatTensor<Self>, v: FloatTensor<Self>, heads: usize, window: usize)
        -> FloatTensor<Self>;
}

/// Attention of every step's query to the keys and values of its last `window` steps (itself
/// included) within the unroll: q, k, v [T, N, A] time-major, A divisible by `heads` ->
/// [T, N, A]. Differentiable in all three.
pub fn window_attention(q: Tensor<3>, k: Tensor<3>, v: Tensor<3>, heads: usize, window: usize) -> Tensor<3> {
    Tensor::from_dispatch(<Dispatch as WindowAttentionBackend>::window_attention(
        q.into_dispatch(),
        k.into_dispatch(),
        v.into_dispatch(),
        heads,
        window,
    ))
}

#[cfg(feature = "flex")]
impl WindowAttentionBackend for burn::backend::Flex {
    fn window_attention(
        q: FloatTensor<Self>,
        k: FloatTensor<Self>,
        v: FloatTensor<Self>,
        heads: usize,
        window: usize,
    ) -> FloatTensor<Self> {
        forward_on::<Self>(q, k, v, heads, window, false).0
    }
}

#[cfg(feature = "ndarray")]
impl WindowAttentionBackend for burn::backend::NdArray {
    fn window_attention(
        q: FloatTensor<Self>,
        k: FloatTensor<Self>,
        v: FloatTensor<Self>,
        heads: usize,
        window: usize,
    ) -> FloatTensor<Self> {
        forward_on::<Self>(q, k, v, heads, window, false).0
    }
}

impl<B: Backend + WindowAttentionBackend, C: CheckpointStrategy> WindowAttentionBackend for Autodiff<B, C> {
    fn window_attention(
        q: FloatTensor<Self>,
        k: FloatTensor<Self>,
        v: FloatTensor<Self>,
        heads: usize,
        window: usize,
    ) -> FloatTensor<Self> {
        match WindowAttentionBackward.prepare::<C>([q.node(), k.node(), v.node()]).compute_bound().stateful() {
            OpsKind::Tracked(prep) => {
                let (out, saved) = forward_on::<B>(q.into_primitive(), k.into_primitive(), v.into_primitive(), heads, window, true);
                prep.finish(saved.expect("saved activations"), out)
            }
            OpsKind::UnTracked(prep) => {
                prep.finish(forward_on::<B>(q.into_primitive(), k.into_primitive(), v.into_primitive(), heads, window, false).0)
            }
        }
    }
}

#[derive(Debug)]
struct WindowAttentionBackward;

impl<B: Backend> Backward<B, 3> for WindowAttentionBackward {
    type State = Arc<Saved>;

    fn backward(self, ops: Ops<Self::State, 3>, grads: &mut Gradients, _checkpointer: &mut Checkpointer) {
        let [node_q, node_k, node_v] = ops.parents;
        let grad = grads.consume::<B>(&ops.node);
        let device = grad.device();
        let saved = ops.state;
        let g = saved.backward(&host::<B>(grad));
        let shape = [saved.steps, saved.rows, saved.heads * saved.head_dim];
        for (node, values) in [(node_q, g.q), (node_k, g.k), (node_v, g.v)] {
            if let Some(node) = node {
                grads.register::<B>(node.id, B::float_from_data(TensorData::new(values, shape), &device));
            }
        }
    }
}

fn forward_on<B: Backend>(
    q: FloatTensor<B>,
    k: FloatTensor<B>,
    v: FloatTensor<B>,
    heads: usize,
    window: usize,
    save: bool,
) -> (FloatTensor<B>, Option<Arc<Saved>>) {
    let device = q.device();
    let dims = q.shape().dims::<3>();
    let (k_dims, v_dims) = (k.shape().dims::<3>(), v.shape().dims::<3>());
    assert!(
        k_dims == dims && v_dims == dims && heads > 0 && dims[2] % heads == 0 && window > 0,
        "window_attention: q {dims:?}, k {k_dims:?}, v {v_dims:?} must be equal [T, N, A] with A divisible by heads ({heads}), window {window} > 0"
    );
    let [t, n, a] = dims;
    let saved = Saved::forward(host::<B>(q), host::<B>(k), host::<B>(v), t, n, heads, a / heads, window, save);
    let out = B::float_from_data(TensorData::new(saved.out.clone(), dims), &device);
    (out, save.then(|| Arc::new(saved)))
}

/// The forward's output and what its backward reads (all row-major, time-major).
#[derive(Debug, Clone)]
pub struct Saved {
    steps: usize,
    rows: usize,
    heads: usize,
    head_dim: usize,
    /// Entries per step actually attended to: min(window, steps).
    window: usize,
    q: Vec<f32>,
    k: Vec<f32>,
    v: Vec<f32>,
    out: Vec<f32>,
    /// Attention weights [T, N, heads, window]; entries before the first step are 0.
    att: Vec<f32>,
}

/// Gradients of q, k and v, each [T, N, A].
pub struct AttentionGrads {
    pub q: Vec<f32>,
    pub k: Vec<f32>,
    pub v: Vec<f32>,
}

#[inline(always)]
fn dot(x: &[f32], y: &[f32]) -> f32 {
    x.iter().zip(y).map(|(a, b)| a * b).sum()
}

/// dst += s * x
#[inline(always)]
fn axpy(dst: &mut [f32], s: f32, x: &[f32]) {
    for (d, v) in dst.iter_mut().zip(x) {
        *d += s * v;
    }
}

impl Saved {
    /// The forward; without `keep` the attention weights are not stored and the inputs are
    /// dropped (inference, the target network).
    #[allow(clippy::too_many_arguments)]
    pub fn forward(q: Vec<f32>, k: Vec<f32>, v: Vec<f32>, t: usize, n: usize, heads: usize, d: usize, window: usize, keep: bool) -> Saved {
        let a = heads * d;
        assert!(q.len() == t * n * a && k.len() == q.len() && v.len() == q.len(), "window_attention: input lengths");
        let w = window.min(t);
        let mut out = vec![0.0f32; t * n * a];
        let mut att = vec![0.0f32; if keep { t * n * heads * w } else { 0 }];
        let mut scratch = vec![0.0f32; w];
        with_simd!(forward_kernel(&q, &k, &v, (t, n, heads, d, w), &mut out, keep.then_some(&mut att[..]), &mut scratch));
        let (q, k, v) = if keep { (q, k, v) } else { (Vec::new(), Vec::new(), Vec::new()) };
        Saved { steps: t, rows: n, heads, head_dim: d, window: w, q, k, v, out, att }
    }

    /// The gradients of q, k and v from d(out) [T, N, A].
    pub fn backward(&self, d_out: &[f32]) -> AttentionGrads {
        let (t, n, heads, d, w) = (self.steps, self.rows, self.heads, self.head_dim, self.window);
        let len = t * n * heads * d;
        assert_eq!(d_out.len(), len, "window_attention: gradient length");
        assert_eq!(self.att.len(), t * n * heads * w, "window_attention: backward needs a forward run with keep");
        let mut g = AttentionGrads { q: vec![0.0; len], k: vec![0.0; len], v: vec![0.0; len] };
        let mut scratch = vec![0.0f32; w];
        with_simd!(backward_kernel(self, d_out, &mut g, &mut scratch));
        g
    }
}

/// Row offset of step `ti`, row `ni`, head `h` in a [T, N, heads x d] tensor.
#[inline(always)]
fn at(ti: usize, ni: usize, h: usize, (n, heads, d): (usize, usize, usize)) -> usize {
    ((ti * n + ni) * heads + h) * d
}

#[inline(always)]
fn forward_kernel(
    q: &[f32],
    k: &[f32],
    v: &[f32],
    (t, n, heads, d, w): (usize, usize, usize, usize, usize),
    out: &mut [f32],
    mut att: Option<&mut [f32]>,
    scores: &mut [f32],
) {
    let scale = 1.0 / (d as f32).sqrt();
    let shape = (n, heads, d);
    for ti in 0..t {
        let valid = w.min(ti + 1);
        for ni in 0..n {
            for h in 0..heads {
                let row = at(ti, ni, h, shape);
                let qh = &q[row..row + d];
                let mut max = f32::NEG_INFINITY;
                for o in 0..valid {
                    let kr = at(ti - o, ni, h, shape);
                    let s = dot(qh, &k[kr..kr + d]) * scale;
                    scores[o] = s;
                    max = max.max(s);
                }
                let mut sum = 0.0;
                for s in &mut scores[..valid] {
                    *s = exp_approx(*s - max);
                    sum += *s;
                }
                let inv = 1.0 / sum;
                let out_h = &mut out[row..row + d];
                for o in 0..valid {
                    let p = scores[o] * inv;
                    scores[o] = p;
                    let vr = at(ti - o, ni, h, shape);
                    axpy(out_h, p, &v[vr..vr + d]);
                }
                if let Some(att) = att.as_deref_mut() {
                    let base = ((ti * n + ni) * heads + h) * w;
                    att[base..base + valid].copy_from_slice(&scores[..valid]);
                }
            }
        }
    }
}

#[inline(always)]
fn backward_kernel(s: &Saved, d_out: &[f32], g: &mut AttentionGrads, d_att: &mut [f32]) {
    let (t, n, heads, d, w) = (s.steps, s.rows, s.heads, s.head_dim, s.window);
    let scale = 1.0 / (d as f32).sqrt();
    let shape = (n, heads, d);
    for ti in 0..t {
        let valid = w.min(ti + 1);
        for ni in 0..n {
            for h in 0..heads {
                let row = at(ti, ni, h, shape);
                let base = ((ti * n + ni) * heads + h) * w;
                let p = &s.att[base..base + valid];
                let dy = &d_out[row..row + d];
                // d(att_o) = dy . v_{t-o}; d(v_{t-o}) += att_o dy
                let mut weighted = 0.0;
                for o in 0..valid {
                    let vr = at(ti - o, ni, h, shape);
                    d_att[o] = dot(dy, &s.v[vr..vr + d]);
                    weighted += p[o] * d_att[o];
                    axpy(&mut g.v[vr..vr + d], p[o], dy);
                }
                // softmax backward: d(score_o) = att_o (d(att_o) - sum_o' att_o' d(att_o'))
                for o in 0..valid {
                    let ds = p[o] * (d_att[o] - weighted) * scale;
                    let kr = at(ti - o, ni, h, shape);
                    axpy(&mut g.q[row..row + d], ds, &s.k[kr..kr + d]);
                    axpy(&mut g.k[kr..kr + d], ds, &s.q[row..row + d]);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::learn::LearnRng;
    use burn::tensor::activation::softmax;
    use burn::tensor::{Bool, Device};

    fn random(rng: &mut LearnRng, shape: [usize; 3], device: &Device) -> Tensor<3> {
        let v: Vec<f32> = (0..shape.iter().product()).map(|_| rng.uniform() * 4.0 - 2.0).collect();
        Tensor::from_data(TensorData::new(v, shape), device)
    }

    /// The same attention with plain burn ops: W shifted copies of k and v, masked softmax.
    fn reference(q: Tensor<3>, k: Tensor<3>, v: Tensor<3>, heads: usize, window: usize) -> Tensor<3> {
        let [t, n, a] = q.dims();
        let device = q.device();
        let dh = a / heads;
        let w = window.min(t);
        let q = q.reshape([t, n, heads, dh]);
        let (k, v) = (k.reshape([t, n, heads, dh]), v.reshape([t, n, heads, dh]));
        let shift = |m: &Tensor<4>, o: usize| -> Tensor<4> {
            if o == 0 {
                m.clone()
            } else {
                Tensor::cat(vec![Tensor::zeros([o, n, heads, dh], &device), m.clone().narrow(0, 0, t - o)], 0)
            }
        };
        let scores: Vec<Tensor<3>> =
            (0..w).map(|o| (shift(&k, o) * q.clone()).sum_dim(3).reshape([t, n, heads]).div_scalar((dh as f32).sqrt())).collect();
        let scores = Tensor::stack::<4>(scores, 0);
        let invalid: Vec<bool> = (0..w).flat_map(|o| (0..t).map(move |s| o > s)).collect();
        let invalid: Tensor<4, Bool> = Tensor::from_data(TensorData::new(invalid, [w, t, 1, 1]), &device);
        let att = softmax(scores.mask_fill(invalid.expand([w, t, n, heads]), -1e9), 0);
        let out =
            (0..w).map(|o| att.clone().narrow(0, o, 1).reshape([t, n, heads, 1]) * shift(&v, o)).reduce(|x, y| x + y).expect("one entry");
        out.reshape([t, n, a])
    }

    fn max_diff(a: Tensor<3>, b: Tensor<3>) -> f32 {
        (a - b).abs().max().into_scalar::<f32>()
    }

    /// Values and the gradients of q, k and v against the burn computation, to 1e-5, for a
    /// window shorter than, equal to and longer than the unroll, on both devices.
    #[test]
    fn matches_the_burn_computation() {
        for (t, window) in [(7, 3), (5, 5), (3, 6), (1, 4)] {
            let (n, heads, dh) = (4, 2, 3);
            let dev = Device::default().autodiff();
            let mut rng = LearnRng::seed_from(t as u64 * 31 + window as u64);
            let [q, k, v] = [0, 1, 2].map(|_| random(&mut rng, [t, n, heads * dh], &dev).require_grad());
            let weights = random(&mut rng, [t, n, heads * dh], &dev);
            let want = reference(q.clone(), k.clone(), v.clone(), heads, window);
            let got = window_attention(q.clone(), k.clone(), v.clone(), heads, window);
            let d = max_diff(want.clone().inner(), got.clone().inner());
            assert!(d < 1e-5, "T {t}, W {window}: values differ by {d}");
            let g_want = (want * weights.clone()).sum().backward();
            let g_got = (got.clone() * weights).sum().backward();
            for (name, x) in [("q", &q), ("k", &k), ("v", &v)] {
                let d = max_diff(x.grad(&g_want).expect("reference gradient"), x.grad(&g_got).expect("kernel gradient"));
                assert!(d < 1e-5, "T {t}, W {window}: d{name} differs by {d}");
            }
            // no autodiff: the same values
            let plain = window_attention(q.inner(), k.inner(), v.inner(), heads, window);
            assert!(max_diff(plain, got.inner()) < 1e-5);
        }
    }
}
