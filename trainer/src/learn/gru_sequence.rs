//! A GRU unrolled over a whole sequence as one burn operation (issue 16).
//!
//! The agent's update is small matrices over sequential steps, so its cost was per-operation
//! overhead, not arithmetic: a plain burn unroll makes about fifteen tensor operations per
//! step forward and as many backward, each allocating. Here the time-independent parts (the
//! first layer and the GRU's input projection) run once over all steps as ordinary burn ops,
//! and only the recurrence is this one custom operation: forward and its backward through time
//! are plain loops over host slices with one `gemm` call per step, registered with burn's
//! autodiff as a single node (`#[backend_extension]`, hand-written `Backward`).
//!
//! Conventions are torch's `GRUCell` with burn's row layout (weights [in, out], gates r, z, n):
//! `gh = h W_hh + b_hh`, `r = sigmoid(gi_r + gh_r)`, `z = sigmoid(gi_z + gh_z)`,
//! `n = tanh(gi_n + r * gh_n)`, `h' = n + z (h - n)`, from `h_0 = 0`. `gi = x W_ih + b_ih` is
//! the caller's. Tested against the step-by-step burn cell (values and gradients to 1e-5).
// burn marks its ndarray backend deprecated; the `ndarray` feature still selects it.
#![cfg_attr(feature = "ndarray", allow(deprecated))]

use std::future::Future;
use std::pin::pin;
use std::sync::Arc;
use std::task::{Context, Poll, Waker};

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::autodiff::Autodiff;
use burn::backend::tensor::FloatTensor;
use burn::backend::{backend_extension, Backend, Dispatch, TensorMetadata};
use burn::tensor::{Tensor, TensorData};

/// The recurrence as a backend operation: gi [T, N, 3H], w_hh [H, 3H], b_hh [3H] -> h [T, N, H].
#[backend_extension(Flex: cfg(feature = "flex"), NdArray: cfg(feature = "ndarray"), Autodiff)]
pub trait GruSequenceBackend: Backend {
    fn gru_sequence(gi: FloatTensor<Self>, w_hh: FloatTensor<Self>, b_hh: FloatTensor<Self>) -> FloatTensor<Self>;
}

/// The hidden states of the GRU over time: `gi` [T, N, 3H] (input projections of all steps,
/// bias included), `w_hh` [H, 3H], `b_hh` [3H] -> [T, N, H]. Differentiable in all three.
pub fn gru_sequence(gi: Tensor<3>, w_hh: Tensor<2>, b_hh: Tensor<1>) -> Tensor<3> {
    Tensor::from_dispatch(<Dispatch as GruSequenceBackend>::gru_sequence(gi.into_dispatch(), w_hh.into_dispatch(), b_hh.into_dispatch()))
}

#[cfg(feature = "flex")]
impl GruSequenceBackend for burn::backend::Flex {
    fn gru_sequence(gi: FloatTensor<Self>, w_hh: FloatTensor<Self>, b_hh: FloatTensor<Self>) -> FloatTensor<Self> {
        forward_on::<Self>(gi, w_hh, b_hh, false).0
    }
}

#[cfg(feature = "ndarray")]
impl GruSequenceBackend for burn::backend::NdArray {
    fn gru_sequence(gi: FloatTensor<Self>, w_hh: FloatTensor<Self>, b_hh: FloatTensor<Self>) -> FloatTensor<Self> {
        forward_on::<Self>(gi, w_hh, b_hh, false).0
    }
}

impl<B: Backend + GruSequenceBackend, C: CheckpointStrategy> GruSequenceBackend for Autodiff<B, C> {
    fn gru_sequence(gi: FloatTensor<Self>, w_hh: FloatTensor<Self>, b_hh: FloatTensor<Self>) -> FloatTensor<Self> {
        match GruSequenceBackward.prepare::<C>([gi.node(), w_hh.node(), b_hh.node()]).compute_bound().stateful() {
            OpsKind::Tracked(prep) => {
                let (out, saved) = forward_on::<B>(gi.into_primitive(), w_hh.into_primitive(), b_hh.into_primitive(), true);
                prep.finish(saved.expect("saved activations"), out)
            }
            OpsKind::UnTracked(prep) => {
                prep.finish(forward_on::<B>(gi.into_primitive(), w_hh.into_primitive(), b_hh.into_primitive(), false).0)
            }
        }
    }
}

#[derive(Debug)]
struct GruSequenceBackward;

impl<B: Backend> Backward<B, 3> for GruSequenceBackward {
    type State = Arc<Saved>;

    fn backward(self, ops: Ops<Self::State, 3>, grads: &mut Gradients, _checkpointer: &mut Checkpointer) {
        let [node_gi, node_w, node_b] = ops.parents;
        let grad = grads.consume::<B>(&ops.node);
        let device = grad.device();
        let saved = ops.state;
        let d_h = host::<B>(grad);
        let g = saved.backward(&d_h);
        let (t, n, h) = (saved.steps, saved.rows, saved.hidden);
        if let Some(node) = node_gi {
            grads.register::<B>(node.id, B::float_from_data(TensorData::new(g.gi, [t, n, 3 * h]), &device));
        }
        if let Some(node) = node_w {
            grads.register::<B>(node.id, B::float_from_data(TensorData::new(g.w_hh, [h, 3 * h]), &device));
        }
        if let Some(node) = node_b {
            grads.register::<B>(node.id, B::float_from_data(TensorData::new(g.b_hh, [3 * h]), &device));
        }
    }
}

/// Run the forward on backend `B`'s tensors through the host kernel; with `save`, also keep
/// what the backward needs.
fn forward_on<B: Backend>(
    gi: FloatTensor<B>,
    w_hh: FloatTensor<B>,
    b_hh: FloatTensor<B>,
    save: bool,
) -> (FloatTensor<B>, Option<Arc<Saved>>) {
    let device = gi.device();
    let dims = gi.shape().dims::<3>();
    let [t, n, h3] = dims;
    let (w_dims, b_dims) = (w_hh.shape().dims::<2>(), b_hh.shape().dims::<1>());
    assert!(
        h3 % 3 == 0 && w_dims == [h3 / 3, h3] && b_dims == [h3],
        "gru_sequence: gi {dims:?}, w_hh {w_dims:?}, b_hh {b_dims:?} do not fit [T, N, 3H], [H, 3H], [3H]"
    );
    let saved = Saved::forward(&host::<B>(gi), host::<B>(w_hh), &host::<B>(b_hh), t, n, h3 / 3, save);
    let shape = [t, n, h3 / 3];
    if save {
        (B::float_from_data(TensorData::new(saved.hs.clone(), shape), &device), Some(Arc::new(saved)))
    } else {
        (B::float_from_data(TensorData::new(saved.hs, shape), &device), None)
    }
}

/// A backend tensor's values on the host (CPU backends hand them over without waiting).
fn host<B: Backend>(t: FloatTensor<B>) -> Vec<f32> {
    let data = block_on(B::float_into_data(t)).expect("reading a CPU tensor");
    data.try_into_vec::<f32>().expect("gru_sequence works on f32 tensors")
}

fn block_on<F: Future>(f: F) -> F::Output {
    let mut f = pin!(f);
    let mut cx = Context::from_waker(Waker::noop());
    loop {
        if let Poll::Ready(v) = f.as_mut().poll(&mut cx) {
            return v;
        }
        std::thread::yield_now();
    }
}

/// The forward's results and what its backward reads: hidden states and gate activations of
/// every step ([T, N, H] each, row-major), and the recurrent weights.
#[derive(Debug, Clone)]
pub struct Saved {
    steps: usize,
    rows: usize,
    hidden: usize,
    w_hh: Vec<f32>,
    hs: Vec<f32>,
    r: Vec<f32>,
    z: Vec<f32>,
    n: Vec<f32>,
    /// The hidden projection's candidate part `gh_n` (bias included), which `r` multiplies.
    gh_n: Vec<f32>,
}

/// Gradients of the three inputs.
pub struct SequenceGrads {
    pub gi: Vec<f32>,
    pub w_hh: Vec<f32>,
    pub b_hh: Vec<f32>,
}

/// dst [m, n] (row stride `dst_rs`) = (accumulate ? dst : 0) + lhs [m, k] * rhs [k, n], with
/// arbitrary row/column strides for lhs and rhs (a transposed operand is a swap of strides).
#[allow(clippy::too_many_arguments)]
fn matmul(
    m: usize,
    n: usize,
    k: usize,
    dst: &mut [f32],
    dst_rs: usize,
    accumulate: bool,
    lhs: &[f32],
    (lhs_rs, lhs_cs): (usize, usize),
    rhs: &[f32],
    (rhs_rs, rhs_cs): (usize, usize),
) {
    if m == 0 || n == 0 {
        return;
    }
    assert!(dst.len() > (m - 1) * dst_rs + n - 1, "matmul: destination too small");
    if k == 0 {
        if !accumulate {
            for i in 0..m {
                dst[i * dst_rs..i * dst_rs + n].fill(0.0);
            }
        }
        return;
    }
    assert!(lhs.len() > (m - 1) * lhs_rs + (k - 1) * lhs_cs, "matmul: lhs too small");
    assert!(rhs.len() > (k - 1) * rhs_rs + (n - 1) * rhs_cs, "matmul: rhs too small");
    // SAFETY: the asserts above keep every index gemm touches inside the three slices; dst is
    // borrowed mutably and does not alias lhs or rhs.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.as_mut_ptr(),
            1,
            dst_rs as isize,
            accumulate,
            lhs.as_ptr(),
            lhs_cs as isize,
            lhs_rs as isize,
            rhs.as_ptr(),
            rhs_cs as isize,
            rhs_rs as isize,
            1.0,
            1.0,
            false,
            false,
            false,
            gemm::Parallelism::None,
        );
    }
}

/// e^x, branch-free so loops over it vectorize (libm's `expf` is a call per element, which was
/// most of the forward's time): 2^k e^r with |r| <= ln2/2 and a degree-6 Taylor polynomial,
/// relative error about 1e-7, x clamped to [-87, 88] (no infinities, no denormal inputs).
#[inline(always)]
fn exp_approx(x: f32) -> f32 {
    const LOG2E: f32 = std::f32::consts::LOG2_E;
    const LN2_HI: f32 = 0.693_359_4;
    const LN2_LO: f32 = -2.121_944_4e-4;
    let x = x.clamp(-87.0, 88.0);
    let k = (x * LOG2E + 0.5).floor();
    let r = x - k * LN2_HI - k * LN2_LO;
    let p = 1.0 + r * (1.0 + r * (0.5 + r * (1.0 / 6.0 + r * (1.0 / 24.0 + r * (1.0 / 120.0 + r * (1.0 / 720.0))))));
    // 2^k from k's bits: adding 1.5 * 2^23 puts the integer k in the low mantissa bits (plain
    // integer lanes; a float-to-int `as` cast saturates, which does not vectorize as well).
    let k_bits = (k + 12_582_912.0).to_bits().wrapping_sub(0x4B40_0000);
    p * f32::from_bits(k_bits.wrapping_add(127) << 23)
}

#[inline(always)]
fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + exp_approx(-x))
}

#[inline(always)]
fn tanh_approx(x: f32) -> f32 {
    1.0 - 2.0 / (exp_approx(2.0 * x) + 1.0)
}

/// Run `body` compiled for AVX2 + FMA when the CPU has them (the crate is built for the
/// baseline x86-64, whose vectors are 4 wide), else as built.
macro_rules! with_simd {
    ($body:ident($($arg:expr),* $(,)?)) => {{
        #[cfg(target_arch = "x86_64")]
        {
            #[target_feature(enable = "avx2,fma")]
            unsafe fn wide<F: FnOnce()>(f: F) {
                f()
            }
            if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
                // SAFETY: both features were detected on this CPU at run time.
                unsafe { wide(|| $body($($arg),*)) };
            } else {
                $body($($arg),*);
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            $body($($arg),*);
        }
    }};
}

/// One step's gates for all rows: gi, gh [N, 3H], prev [N, H] -> h' (out) and the saved
/// activations r, z, n and gh_n [N, H].
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn gates_forward(
    h: usize,
    gi: &[f32],
    gh: &[f32],
    prev: &[f32],
    out: &mut [f32],
    r: &mut [f32],
    z: &mut [f32],
    c: &mut [f32],
    ghn: &mut [f32],
) {
    let h3 = 3 * h;
    for i in 0..out.len() / h {
        let (gi, gh) = (&gi[i * h3..(i + 1) * h3], &gh[i * h3..(i + 1) * h3]);
        let (gi_r, gi_z, gi_n) = (&gi[..h], &gi[h..2 * h], &gi[2 * h..h3]);
        let (gh_r, gh_z, gh_n) = (&gh[..h], &gh[h..2 * h], &gh[2 * h..h3]);
        let rows = i * h..(i + 1) * h;
        let (prev, out) = (&prev[rows.clone()], &mut out[rows.clone()]);
        let (r, z, c, ghn) = (&mut r[rows.clone()], &mut z[rows.clone()], &mut c[rows.clone()], &mut ghn[rows]);
        for j in 0..h {
            let rj = sigmoid(gi_r[j] + gh_r[j]);
            let zj = sigmoid(gi_z[j] + gh_z[j]);
            let cj = tanh_approx(gi_n[j] + rj * gh_n[j]);
            out[j] = cj + zj * (prev[j] - cj);
            r[j] = rj;
            z[j] = zj;
            c[j] = cj;
            ghn[j] = gh_n[j];
        }
    }
}

/// One step backward for all rows: dh = d_out + d_next [N, H] -> d(gi), d(gh) [N, 3H] and the
/// direct part of dh_{t-1} (d_prev = dh * z; the caller adds d(gh) W_hh^T).
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn gates_backward(
    h: usize,
    d_out: &[f32],
    d_next: &[f32],
    (r, z, c, ghn): (&[f32], &[f32], &[f32], &[f32]),
    prev: &[f32],
    d_prev: &mut [f32],
    d_gi: &mut [f32],
    d_gh: &mut [f32],
) {
    let h3 = 3 * h;
    for i in 0..d_out.len() / h {
        let o = i * h;
        let (d_out, d_next, prev, d_prev) = (&d_out[o..][..h], &d_next[o..][..h], &prev[o..][..h], &mut d_prev[o..][..h]);
        let (r, z, c, ghn) = (&r[o..][..h], &z[o..][..h], &c[o..][..h], &ghn[o..][..h]);
        let (d_gi, d_gh) = (&mut d_gi[i * h3..][..h3], &mut d_gh[i * h3..][..h3]);
        let (d_gi_r, rest) = d_gi.split_at_mut(h);
        let (d_gi_z, d_gi_n) = rest.split_at_mut(h);
        let (d_gh_r, rest) = d_gh.split_at_mut(h);
        let (d_gh_z, d_gh_n) = rest.split_at_mut(h);
        let (d_gi_r, d_gi_z, d_gi_n) = (&mut d_gi_r[..h], &mut d_gi_z[..h], &mut d_gi_n[..h]);
        let (d_gh_r, d_gh_z, d_gh_n) = (&mut d_gh_r[..h], &mut d_gh_z[..h], &mut d_gh_n[..h]);
        for j in 0..h {
            let dh = d_out[j] + d_next[j];
            let (rj, zj, cj) = (r[j], z[j], c[j]);
            let d_c = dh * (1.0 - zj) * (1.0 - cj * cj);
            let d_z = dh * (prev[j] - cj) * zj * (1.0 - zj);
            let d_r = d_c * ghn[j] * rj * (1.0 - rj);
            d_prev[j] = dh * zj;
            d_gi_r[j] = d_r;
            d_gi_z[j] = d_z;
            d_gi_n[j] = d_c;
            d_gh_r[j] = d_r;
            d_gh_z[j] = d_z;
            d_gh_n[j] = d_c * rj;
        }
    }
}

impl Saved {
    /// Unroll from h_0 = 0. `gi` [T, N, 3H], `w_hh` [H, 3H], `b_hh` [3H]. Without `keep`, the
    /// gate activations are not stored (inference, the target network).
    pub fn forward(gi: &[f32], w_hh: Vec<f32>, b_hh: &[f32], t: usize, n: usize, h: usize, keep: bool) -> Saved {
        let h3 = 3 * h;
        assert_eq!(gi.len(), t * n * h3, "gru_sequence: gi length");
        let step = n * h;
        let mut hs = vec![0.0f32; t * step];
        let keep_len = if keep { t * step } else { 0 };
        let (mut r_all, mut z_all, mut n_all, mut ghn_all) =
            (vec![0.0f32; keep_len], vec![0.0f32; keep_len], vec![0.0f32; keep_len], vec![0.0f32; keep_len]);
        let mut gh = vec![0.0f32; n * h3];
        // without `keep`, one step's worth of scratch for the activations
        let mut scratch = if keep { Vec::new() } else { vec![0.0f32; 4 * step] };
        let zeros = vec![0.0f32; step];
        for ti in 0..t {
            // gh = h_{t-1} W_hh + b_hh (h_{-1} = 0: just the bias)
            for row in gh.chunks_exact_mut(h3) {
                row.copy_from_slice(b_hh);
            }
            let (done, rest) = hs.split_at_mut(ti * step);
            let prev = if ti > 0 { &done[(ti - 1) * step..] } else { &zeros[..] };
            if ti > 0 {
                matmul(n, h3, h, &mut gh, h3, true, prev, (h, 1), &w_hh, (h3, 1));
            }
            let out = &mut rest[..step];
            let gi_t = &gi[ti * n * h3..(ti + 1) * n * h3];
            let keep_at = ti * step..(ti + 1) * step;
            let (r, z, c, ghn) = if keep {
                (&mut r_all[keep_at.clone()], &mut z_all[keep_at.clone()], &mut n_all[keep_at.clone()], &mut ghn_all[keep_at])
            } else {
                let (a, rest) = scratch.split_at_mut(step);
                let (b, rest) = rest.split_at_mut(step);
                let (c, d) = rest.split_at_mut(step);
                (a, b, c, d)
            };
            with_simd!(gates_forward(h, gi_t, &gh, &prev[..step], out, r, z, c, ghn));
        }
        Saved { steps: t, rows: n, hidden: h, w_hh, hs, r: r_all, z: z_all, n: n_all, gh_n: ghn_all }
    }

    /// Backpropagation through time of `d_hs` = dL/dh_t for every step [T, N, H].
    pub fn backward(&self, d_hs: &[f32]) -> SequenceGrads {
        let (t, n, h) = (self.steps, self.rows, self.hidden);
        let (h3, step) = (3 * h, n * h);
        assert_eq!(d_hs.len(), t * step, "gru_sequence: gradient length");
        assert_eq!(self.r.len(), t * step, "gru_sequence: backward needs a forward run with keep");
        let mut d_gi = vec![0.0f32; t * n * h3];
        // d(gh) of every step, kept for the weight gradient (one matmul over all steps at the end)
        let mut d_gh = vec![0.0f32; t * n * h3];
        let mut d_next = vec![0.0f32; step]; // dL/dh_{t} arriving from step t + 1
        let zeros = vec![0.0f32; step];
        let mut d_prev = vec![0.0f32; step];
        for ti in (0..t).rev() {
            let at = ti * step..(ti + 1) * step;
            let prev = if ti > 0 { &self.hs[(ti - 1) * step..ti * step] } else { &zeros[..] };
            let saved = (&self.r[at.clone()], &self.z[at.clone()], &self.n[at.clone()], &self.gh_n[at.clone()]);
            let g_at = ti * n * h3..(ti + 1) * n * h3;
            let (d_gi_t, d_gh_t) = (&mut d_gi[g_at.clone()], &mut d_gh[g_at.clone()]);
            with_simd!(gates_backward(h, &d_hs[at], &d_next, saved, prev, &mut d_prev, d_gi_t, d_gh_t));
            // dh_{t-1} += d(gh_t) W_hh^T  (W_hh [H, 3H] read transposed)
            if ti > 0 {
                matmul(n, h, h3, &mut d_prev, h, true, &d_gh[g_at], (h3, 1), &self.w_hh, (1, h3));
            }
            std::mem::swap(&mut d_next, &mut d_prev);
        }
        // dW_hh = sum_t h_{t-1}^T d(gh_t) over t >= 1 (h_{-1} = 0): one [H, (T-1) N] x [(T-1) N, 3H].
        let mut d_w = vec![0.0f32; h * h3];
        let k = (t.saturating_sub(1)) * n;
        matmul(h, h3, k, &mut d_w, h3, false, &self.hs, (1, h), &d_gh[n * h3..], (h3, 1));
        let mut d_b = vec![0.0f32; h3];
        for row in d_gh.chunks_exact(h3) {
            for (acc, v) in d_b.iter_mut().zip(row) {
                *acc += v;
            }
        }
        SequenceGrads { gi: d_gi, w_hh: d_w, b_hh: d_b }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::learn::agent::FusedGru;
    use crate::learn::LearnRng;
    use burn::module::Module;
    use burn::tensor::Device;

    fn random(rng: &mut LearnRng, shape: [usize; 2], device: &Device) -> Tensor<2> {
        let v: Vec<f32> = (0..shape[0] * shape[1]).map(|_| rng.uniform() * 4.0 - 2.0).collect();
        Tensor::from_data(TensorData::new(v, shape), device)
    }

    fn max_diff(a: Tensor<2>, b: Tensor<2>) -> f32 {
        (a - b).abs().max().into_scalar::<f32>()
    }

    /// The fused recurrence against the step-by-step burn cell: hidden states and the gradients
    /// of every parameter and of the inputs, to 1e-5, on the autodiff and the plain device.
    #[test]
    fn matches_the_step_by_step_cell() {
        let (t, n, hd) = (7, 5, 6);
        let dev = Device::default().autodiff();
        let mut rng = LearnRng::seed_from(3);
        let gru = FusedGru::new(&mut rng, hd, hd, &dev);
        let xs: Vec<Tensor<2>> = (0..t).map(|_| random(&mut rng, [n, hd], &dev).require_grad()).collect();
        let weights = random(&mut rng, [t * n, hd], &dev);

        // reference: the cell step by step
        let mut h = Tensor::zeros([n, hd], &dev);
        let mut hs = Vec::new();
        for x in &xs {
            h = gru.forward(x.clone(), h);
            hs.push(h.clone());
        }
        let reference = Tensor::cat(hs, 0);
        let ref_grads = (reference.clone() * weights.clone()).sum().backward();

        // fused
        let gi = gru.input.forward(Tensor::cat(xs.clone(), 0)).reshape([t, n, 3 * hd]);
        let bias = gru.hidden.bias.as_ref().expect("bias").val();
        let fused = gru_sequence(gi, gru.hidden.weight.val(), bias.clone()).reshape([t * n, hd]);
        assert!(max_diff(reference.clone().inner(), fused.clone().inner()) < 1e-5);
        let grads = (fused * weights).sum().backward();

        let w_in = &gru.input.weight;
        let w_hh = &gru.hidden.weight;
        for (name, a, b) in
            [("w_hh", w_hh.val().grad(&ref_grads), w_hh.val().grad(&grads)), ("w_ih", w_in.val().grad(&ref_grads), w_in.val().grad(&grads))]
        {
            let d = max_diff(a.expect("reference gradient"), b.expect("fused gradient"));
            assert!(d < 1e-5, "{name}: gradients differ by {d}");
        }
        let (a, b) = (bias.grad(&ref_grads).expect("bias gradient"), bias.grad(&grads).expect("fused bias gradient"));
        let d = (a - b).abs().max().into_scalar::<f32>();
        assert!(d < 1e-5, "b_hh: gradients differ by {d}");
        for (i, x) in xs.iter().enumerate() {
            let d = max_diff(x.grad(&ref_grads).expect("x gradient"), x.grad(&grads).expect("fused x gradient"));
            assert!(d < 1e-5, "input of step {i}: gradients differ by {d}");
        }

        // no autodiff: the same values
        let plain = gru.valid();
        let gi = plain.input.forward(Tensor::cat(xs.iter().map(|x| x.clone().inner()).collect(), 0)).reshape([t, n, 3 * hd]);
        let bias = plain.hidden.bias.as_ref().expect("bias").val();
        let out = gru_sequence(gi, plain.hidden.weight.val(), bias).reshape([t * n, hd]);
        assert!(max_diff(reference.inner(), out) < 1e-5);
    }

    /// One step and zero rows are valid sequences.
    #[test]
    fn edge_shapes() {
        let dev = Device::default();
        let one = gru_sequence(Tensor::ones([1, 3, 6], &dev), Tensor::ones([2, 6], &dev), Tensor::zeros([6], &dev));
        assert_eq!(one.dims(), [1, 3, 2]);
        let empty = gru_sequence(Tensor::ones([4, 0, 6], &dev), Tensor::ones([2, 6], &dev), Tensor::zeros([6], &dev));
        assert_eq!(empty.dims(), [4, 0, 2]);
    }
}
