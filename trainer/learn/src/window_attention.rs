//! The LMAC window encoder's attention over a whole unroll as one burn operation.
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

use super::host_kernel::{exp_approx, host, register, with_simd};

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
        let shape = vec![saved.steps, saved.rows, saved.heads * saved.head_dim];
        let parts = [(node_q, g.q), (node_k, g.k), (node_v, g.v)].map(|(node, values)| (node.map(|n| n.id), values, shape.clone()));
        register::<B>(grads, &device, parts);
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

/// x . y over one head's D values. The products are summed in 8 (or D) independent lanes and
/// the lanes at the end: a single running sum is one long dependency chain the compiler may
/// not reorder (float addition is not associative), which kept this scalar and made the
/// attention 12% of an LMAC update; lanes turn it into vector FMAs.
#[inline(always)]
fn dot<const D: usize>(x: &[f32; D], y: &[f32; D]) -> f32 {
    const L: usize = 8;
    if D % L != 0 {
        let mut acc = 0.0;
        for i in 0..D {
            acc += x[i] * y[i];
        }
        return acc;
    }
    let mut lanes = [0.0f32; L];
    for c in 0..D / L {
        for l in 0..L {
            lanes[l] += x[c * L + l] * y[c * L + l];
        }
    }
    let (lo, hi) = lanes.split_at(4);
    let quad = [lo[0] + hi[0], lo[1] + hi[1], lo[2] + hi[2], lo[3] + hi[3]];
    (quad[0] + quad[2]) + (quad[1] + quad[3])
}

/// dst += s * x over one head's D values.
#[inline(always)]
fn axpy<const D: usize>(dst: &mut [f32; D], s: f32, x: &[f32; D]) {
    for i in 0..D {
        dst[i] += s * x[i];
    }
}

/// Head `h`'s D values of the row starting at `row`.
#[inline(always)]
fn head<const D: usize>(m: &[f32], row: usize, h: usize) -> &[f32; D] {
    m[row + h * D..row + (h + 1) * D].try_into().expect("a head's values")
}

#[inline(always)]
fn head_mut<const D: usize>(m: &mut [f32], row: usize, h: usize) -> &mut [f32; D] {
    (&mut m[row + h * D..row + (h + 1) * D]).try_into().expect("a head's values")
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
        let mut scratch = vec![0.0f32; heads * w];
        let dims = Dims { t, n, a, heads, w, scale: 1.0 / (d as f32).sqrt() };
        by_head_dim!(d, forward_kernel(&q, &k, &v, dims, &mut out, keep.then_some(&mut att[..]), &mut scratch));
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
        let mut scratch = vec![0.0f32; heads * w];
        let dims = Dims { t, n, a: heads * d, heads, w, scale: 1.0 / (d as f32).sqrt() };
        by_head_dim!(d, backward_kernel(self, dims, d_out, &mut g, &mut scratch));
        g
    }
}

/// The kernels for the head widths in use (the default 64 / 4 heads = 16) are compiled with the
/// width as a constant; any other width goes through the 1-wide form (same loops, scalar).
macro_rules! by_head_dim {
    ($d:expr, $f:ident($($arg:expr),* $(,)?)) => {
        match $d {
            4 => with_simd!($f::<4>($($arg),*)),
            8 => with_simd!($f::<8>($($arg),*)),
            16 => with_simd!($f::<16>($($arg),*)),
            32 => with_simd!($f::<32>($($arg),*)),
            64 => with_simd!($f::<64>($($arg),*)),
            _ => with_simd!($f::<1>($($arg),*)),
        }
    };
}
use by_head_dim;

/// Layout of the kernels' loops: [T, N, A] tensors seen as [T, N, heads', D] with
/// heads' = A / D (for the 1-wide fallback every value is its own "head" and a true head spans
/// d of them, so scores are summed over `group` = d / D consecutive chunks).
#[derive(Clone, Copy)]
struct Dims {
    t: usize,
    n: usize,
    a: usize,
    heads: usize,
    w: usize,
    scale: f32,
}

#[inline(always)]
fn forward_kernel<const D: usize>(
    q: &[f32],
    k: &[f32],
    v: &[f32],
    dims: Dims,
    out: &mut [f32],
    mut att: Option<&mut [f32]>,
    scores: &mut [f32],
) {
    let Dims { t, n, a, heads, w, scale } = dims;
    let group = a / heads / D; // chunks of D per head
    for ti in 0..t {
        let valid = w.min(ti + 1);
        for ni in 0..n {
            let row = (ti * n + ni) * a;
            // scores[h * w + o]
            for o in 0..valid {
                let kr = ((ti - o) * n + ni) * a;
                for h in 0..heads {
                    let mut s = 0.0;
                    for c in 0..group {
                        s += dot::<D>(head::<D>(q, row, h * group + c), head::<D>(k, kr, h * group + c));
                    }
                    scores[h * w + o] = s * scale;
                }
            }
            for h in 0..heads {
                let sc = &mut scores[h * w..h * w + valid];
                let max = sc.iter().fold(f32::NEG_INFINITY, |m, &x| m.max(x));
                let mut sum = 0.0;
                for x in sc.iter_mut() {
                    *x = exp_approx(*x - max);
                    sum += *x;
                }
                let inv = 1.0 / sum;
                for x in sc.iter_mut() {
                    *x *= inv;
                }
            }
            for o in 0..valid {
                let vr = ((ti - o) * n + ni) * a;
                for h in 0..heads {
                    let p = scores[h * w + o];
                    for c in 0..group {
                        axpy::<D>(head_mut::<D>(out, row, h * group + c), p, head::<D>(v, vr, h * group + c));
                    }
                }
            }
            if let Some(att) = att.as_deref_mut() {
                let base = (ti * n + ni) * heads * w;
                att[base..base + heads * w].copy_from_slice(&scores[..heads * w]);
            }
        }
    }
}

#[inline(always)]
fn backward_kernel<const D: usize>(s: &Saved, dims: Dims, d_out: &[f32], g: &mut AttentionGrads, d_att: &mut [f32]) {
    let Dims { t, n, a, heads, w, scale } = dims;
    let group = a / heads / D;
    for ti in 0..t {
        let valid = w.min(ti + 1);
        for ni in 0..n {
            let row = (ti * n + ni) * a;
            let base = (ti * n + ni) * heads * w;
            let p = &s.att[base..base + heads * w];
            // d(att) = dy . v_{t-o} per head; d(v_{t-o}) += att dy
            for o in 0..valid {
                let vr = ((ti - o) * n + ni) * a;
                for h in 0..heads {
                    let ph = p[h * w + o];
                    let mut acc = 0.0;
                    for c in 0..group {
                        let j = h * group + c;
                        acc += dot::<D>(head::<D>(d_out, row, j), head::<D>(&s.v, vr, j));
                        axpy::<D>(head_mut::<D>(&mut g.v, vr, j), ph, head::<D>(d_out, row, j));
                    }
                    d_att[h * w + o] = acc;
                }
            }
            // softmax backward: d(score_o) = att_o (d(att_o) - sum_o' att_o' d(att_o'))
            for h in 0..heads {
                let weighted: f32 = (0..valid).map(|o| p[h * w + o] * d_att[h * w + o]).sum();
                for o in 0..valid {
                    d_att[h * w + o] = p[h * w + o] * (d_att[h * w + o] - weighted) * scale;
                }
            }
            for o in 0..valid {
                let kr = ((ti - o) * n + ni) * a;
                for h in 0..heads {
                    let ds = d_att[h * w + o];
                    for c in 0..group {
                        let j = h * group + c;
                        axpy::<D>(head_mut::<D>(&mut g.q, row, j), ds, head::<D>(&s.k, kr, j));
                        axpy::<D>(head_mut::<D>(&mut g.k, kr, j), ds, head::<D>(&s.q, row, j));
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::LearnRng;
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
        // head widths 3 (the generic loop) and 16, 8 (compiled with the width as a constant)
        for (t, window, heads, dh) in [(7, 3, 2, 3), (5, 5, 2, 3), (3, 6, 2, 3), (1, 4, 2, 3), (7, 3, 4, 16), (6, 4, 2, 8)] {
            let n = 4;
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
