//! What the hand-written training kernels share (`gru_sequence.rs`, `window_attention.rs`):
//! reading a CPU backend tensor on the host, a strided gemm call, a vectorizable exp, and
//! running a loop compiled for AVX-512 or AVX2 + FMA when the CPU has them.
// burn marks its ndarray backend deprecated; the `ndarray` feature still selects it.
#![cfg_attr(feature = "ndarray", allow(deprecated))]

#[cfg(feature = "flex")]
use std::any::Any;
use std::borrow::Cow;
use std::future::Future;
use std::pin::pin;
use std::task::{Context, Poll, Waker};

use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::NodeId;
use burn::backend::tensor::FloatTensor;
use burn::backend::Backend;
use burn::tensor::TensorData;

/// A backend tensor's values on the host (CPU backends hand them over without waiting).
pub(crate) fn host<B: Backend>(t: FloatTensor<B>) -> Vec<f32> {
    let data = block_on(B::float_into_data(t)).expect("reading a CPU tensor");
    data.try_into_vec::<f32>().expect("gru_sequence works on f32 tensors")
}

/// A backend tensor's values on the host without taking it: borrowed where the tensor is a
/// contiguous f32 tensor of the flex backend (every tensor a layer makes), else a copy.
pub(crate) fn host_ref<B: Backend>(t: &FloatTensor<B>) -> Cow<'_, [f32]> {
    #[cfg(feature = "flex")]
    if let Some(slice) = (t as &dyn Any).downcast_ref::<FloatTensor<burn::backend::Flex>>().and_then(|f| f.as_slice::<f32>()) {
        return Cow::Borrowed(slice);
    }
    Cow::Owned(host::<B>(t.clone()))
}

/// A backend tensor's values on the host, kept: shared with the tensor where it is a contiguous
/// f32 tensor of the flex backend (no copy; the data is immutable while shared), else a copy.
/// What a hand-written backward keeps of its forward's inputs and outputs.
#[derive(Debug, Clone)]
pub enum HostValues {
    Copied(Vec<f32>),
    #[cfg(feature = "flex")]
    Shared(FloatTensor<burn::backend::Flex>),
}

impl std::ops::Deref for HostValues {
    type Target = [f32];
    fn deref(&self) -> &[f32] {
        match self {
            HostValues::Copied(v) => v,
            #[cfg(feature = "flex")]
            HostValues::Shared(t) => t.as_slice::<f32>().expect("a shared tensor is contiguous f32 (checked when kept)"),
        }
    }
}

impl HostValues {
    /// The values as an owned vector (a copy only when shared).
    pub fn into_vec(self) -> Vec<f32> {
        match self {
            HostValues::Copied(v) => v,
            #[cfg(feature = "flex")]
            HostValues::Shared(t) => t.as_slice::<f32>().expect("contiguous f32").to_vec(),
        }
    }
}

pub(crate) fn host_values<B: Backend>(t: FloatTensor<B>) -> HostValues {
    #[cfg(feature = "flex")]
    let t = {
        let any: Box<dyn Any> = Box::new(t);
        match any.downcast::<FloatTensor<burn::backend::Flex>>() {
            Ok(f) if f.as_slice::<f32>().is_some() => return HostValues::Shared(*f),
            Ok(f) => return HostValues::Copied(host::<burn::backend::Flex>(*f)),
            Err(any) => *any.downcast::<FloatTensor<B>>().expect("the same type"),
        }
    };
    HostValues::Copied(host::<B>(t))
}

/// Hand each tracked parent its gradient (values with their shape); untracked parents get none.
pub(crate) fn register<B: Backend>(
    grads: &mut Gradients,
    device: &B::Device,
    parts: impl IntoIterator<Item = (Option<NodeId>, Vec<f32>, Vec<usize>)>,
) {
    for (node, values, shape) in parts {
        if let Some(id) = node {
            grads.register::<B>(id, B::float_from_data(TensorData::new(values, shape), device));
        }
    }
}

/// acc[j] += the sum over rows of rows[.., j] (rows laid out with acc.len() columns): a bias's
/// gradient from its output's.
pub(crate) fn add_column_sums(acc: &mut [f32], rows: &[f32]) {
    for row in rows.chunks_exact(acc.len()) {
        for (a, v) in acc.iter_mut().zip(row) {
            *a += v;
        }
    }
}

pub(crate) fn block_on<F: Future>(f: F) -> F::Output {
    let mut f = pin!(f);
    let mut cx = Context::from_waker(Waker::noop());
    loop {
        if let Poll::Ready(v) = f.as_mut().poll(&mut cx) {
            return v;
        }
        std::thread::yield_now();
    }
}

/// lhs [m, k] * rhs [k, n] as a new row-major vector, strides as in [`matmul`]. gemm writes
/// every value without reading any (its destination is not read when it does not accumulate), so
/// the vector is not zeroed first: a pass over the output saved.
pub(crate) fn matmul_new(
    m: usize,
    n: usize,
    k: usize,
    lhs: &[f32],
    lhs_strides: (usize, usize),
    rhs: &[f32],
    rhs_strides: (usize, usize),
) -> Vec<f32> {
    let len = m * n;
    if len == 0 || k == 0 {
        return vec![0.0; len];
    }
    let mut dst = Vec::<f32>::with_capacity(len);
    // SAFETY: gemm_raw checks lhs and rhs; dst's allocation holds
    // m * n values at row stride n; with read_dst false gemm writes each of them and reads none
    // (gemm-common: alpha is zeroed and never applied to dst), so the length is set after the
    // writes and no uninitialised value is ever read.
    unsafe {
        gemm_raw(m, n, k, dst.as_mut_ptr(), n, false, lhs, lhs_strides, rhs, rhs_strides);
        dst.set_len(len);
    }
    dst
}

/// dst [m, n] (row stride `dst_rs`) = (accumulate ? dst : 0) + lhs [m, k] * rhs [k, n], with
/// arbitrary row/column strides for lhs and rhs (a transposed operand is a swap of strides).
#[allow(clippy::too_many_arguments)]
pub(crate) fn matmul(
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
    // SAFETY: the assert above keeps every index of dst inside it (gemm_raw checks lhs and rhs);
    // dst is borrowed mutably and does not alias lhs or rhs.
    unsafe { gemm_raw(m, n, k, dst.as_mut_ptr(), dst_rs, accumulate, lhs, (lhs_rs, lhs_cs), rhs, (rhs_rs, rhs_cs)) }
}

/// The one gemm call behind [`matmul`] and [`matmul_new`]: dst [m, n] at row stride `dst_rs`
/// (read only when `accumulate`), one thread; m, n and k at least 1. It checks that lhs and rhs
/// hold every index it reads.
///
/// # Safety
/// The allocation behind `dst` must hold every index [m, n] at row stride `dst_rs` reaches, and
/// `dst` must not alias either operand.
#[allow(clippy::too_many_arguments)]
unsafe fn gemm_raw(
    m: usize,
    n: usize,
    k: usize,
    dst: *mut f32,
    dst_rs: usize,
    accumulate: bool,
    lhs: &[f32],
    (lhs_rs, lhs_cs): (usize, usize),
    rhs: &[f32],
    (rhs_rs, rhs_cs): (usize, usize),
) {
    assert!(lhs.len() > (m - 1) * lhs_rs + (k - 1) * lhs_cs, "matmul: lhs too small");
    assert!(rhs.len() > (k - 1) * rhs_rs + (n - 1) * rhs_cs, "matmul: rhs too small");
    // SAFETY: the asserts above for lhs and rhs, the caller's contract for dst.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst,
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
        )
    }
}

/// e^x, branch-free so loops over it vectorize (libm's `expf` is a call per element, which was
/// most of the forward's time): 2^k e^r with |r| <= ln2/2 and a degree-6 Taylor polynomial,
/// relative error about 1e-7, x clamped to [-87, 88] (no infinities, no denormal inputs).
#[inline(always)]
pub(crate) fn exp_approx(x: f32) -> f32 {
    const LOG2E: f32 = std::f32::consts::LOG2_E;
    const LN2_HI: f32 = 0.693_359_4;
    const LN2_LO: f32 = -2.121_944_4e-4;
    let x = x.clamp(-87.0, 88.0);
    let k = x.mul_add(LOG2E, 0.5).floor();
    let r = k.mul_add(-LN2_LO, k.mul_add(-LN2_HI, x));
    // Horner's rule in fused multiply-adds (one instruction each where `with_simd!` enables FMA)
    let p = r.mul_add(1.0 / 720.0, 1.0 / 120.0);
    let p = r.mul_add(p, 1.0 / 24.0);
    let p = r.mul_add(p, 1.0 / 6.0);
    let p = r.mul_add(p, 0.5);
    let p = r.mul_add(p, 1.0);
    let p = r.mul_add(p, 1.0);
    // 2^k from k's bits: adding 1.5 * 2^23 puts the integer k in the low mantissa bits (plain
    // integer lanes; a float-to-int `as` cast saturates, which does not vectorize as well).
    let k_bits = (k + 12_582_912.0).to_bits().wrapping_sub(0x4B40_0000);
    p * f32::from_bits(k_bits.wrapping_add(127) << 23)
}

#[inline(always)]
pub(crate) fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + exp_approx(-x))
}

#[inline(always)]
pub(crate) fn tanh_approx(x: f32) -> f32 {
    1.0 - 2.0 / (exp_approx(2.0 * x) + 1.0)
}

/// Run `body` compiled for AVX-512 when the CPU has it, else for AVX2 + FMA when it has them
/// (the crate is built for the baseline x86-64, whose vectors are 4 wide), else as built.
macro_rules! with_simd {
    ($body:ident::<$d:literal>($($arg:expr),* $(,)?)) => {
        $crate::host_kernel::with_simd!(@run $body::<$d>($($arg),*))
    };
    ($body:ident($($arg:expr),* $(,)?)) => {
        $crate::host_kernel::with_simd!(@run $body($($arg),*))
    };
    (@run $call:expr) => {{
        #[cfg(target_arch = "x86_64")]
        {
            #[target_feature(enable = "avx512f,avx512vl,avx512bw,avx512dq,avx2,fma")]
            unsafe fn widest<F: FnOnce()>(f: F) {
                f()
            }
            #[target_feature(enable = "avx2,fma")]
            unsafe fn wide<F: FnOnce()>(f: F) {
                f()
            }
            let has = |f: &str| match f {
                "avx512" => {
                    std::arch::is_x86_feature_detected!("avx512f")
                        && std::arch::is_x86_feature_detected!("avx512vl")
                        && std::arch::is_x86_feature_detected!("avx512bw")
                        && std::arch::is_x86_feature_detected!("avx512dq")
                }
                _ => std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma"),
            };
            if has("avx512") && has("avx2") {
                // SAFETY: every feature enabled was detected on this CPU at run time.
                unsafe { widest(|| $call) };
            } else if has("avx2") {
                // SAFETY: both features were detected on this CPU at run time.
                unsafe { wide(|| $call) };
            } else {
                $call;
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            $call;
        }
    }};
}
pub(crate) use with_simd;

/// What the hand-written kernels' tests share: random inputs and comparisons to 1e-5.
#[cfg(test)]
pub(crate) mod test_support {
    use burn::tensor::{Device, Tensor, TensorData};

    use crate::LearnRng;

    /// Values uniform in [-2, 2).
    pub fn random(rng: &mut LearnRng, shape: [usize; 2], device: &Device) -> Tensor<2> {
        let v: Vec<f32> = (0..shape[0] * shape[1]).map(|_| rng.uniform() * 4.0 - 2.0).collect();
        Tensor::from_data(TensorData::new(v, shape), device)
    }

    /// The largest absolute difference; tensors of no values (and the same shape) differ by 0.
    pub fn max_diff<const D: usize>(a: Tensor<D>, b: Tensor<D>) -> f32 {
        assert_eq!(a.dims(), b.dims(), "shapes");
        if a.dims().contains(&0) {
            return 0.0;
        }
        (a - b).abs().max().into_scalar::<f32>()
    }

    /// The reference's and the fused form's gradients of one tensor agree to 1e-5.
    pub fn assert_same_grad<const D: usize>(what: &str, reference: Option<Tensor<D>>, fused: Option<Tensor<D>>) {
        let d = max_diff(reference.expect("reference gradient"), fused.expect("fused gradient"));
        assert!(d < 1e-5, "{what}: gradients differ by {d}");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn exps(xs: &[f32], out: &mut [f32]) {
        out.iter_mut().zip(xs).for_each(|(o, x)| *o = exp_approx(*x));
    }

    /// A fresh product equals the accumulating one into zeros, for the shapes that take gemm's
    /// blocked, matrix-vector and outer-product paths and for transposed operands, with the
    /// allocator handed memory full of NaN first (a value read from the unwritten buffer would
    /// show as NaN).
    #[test]
    fn a_fresh_product_reads_nothing_it_did_not_write() {
        let mut rng = crate::LearnRng::seed_from(4);
        for (m, n, k) in [(37, 19, 70), (64, 1, 9), (1, 33, 12), (17, 5, 2), (300, 64, 259), (3, 4, 0)] {
            let lhs: Vec<f32> = (0..m * k).map(|_| rng.uniform() - 0.5).collect();
            let rhs: Vec<f32> = (0..k * n).map(|_| rng.uniform() - 0.5).collect();
            for transposed in [false, true] {
                let lhs_strides = if transposed { (1, m) } else { (k, 1) };
                let mut want = vec![0.0f32; m * n];
                matmul(m, n, k, &mut want, n, false, &lhs, lhs_strides, &rhs, (n, 1));
                drop(std::hint::black_box(vec![f32::NAN; m * n]));
                let got = matmul_new(m, n, k, &lhs, lhs_strides, &rhs, (n, 1));
                assert_eq!(got, want, "{m} x {n} x {k}, lhs transposed {transposed}");
            }
        }
    }

    /// e^x to a relative 3e-7 of f64's over the clamped range, as built and as `with_simd!` runs
    /// it (fused multiply-adds there); sigmoid and tanh to 1e-6.
    #[test]
    fn the_approximations_hold_their_error() {
        let xs: Vec<f32> = (0..175_000).map(|i| -87.0 + i as f32 * 0.001).collect();
        let mut fused = vec![0.0f32; xs.len()];
        with_simd!(exps(&xs, &mut fused));
        for (x, f) in xs.iter().zip(&fused) {
            let want = (*x as f64).exp();
            for (what, got) in [("as built", exp_approx(*x)), ("with_simd", *f)] {
                let rel = ((got as f64 - want) / want).abs();
                assert!(rel < 3e-7, "exp({x}) {what}: {got} against {want} (relative {rel})");
            }
            if x.abs() < 20.0 {
                let (s, t) = (1.0 / (1.0 + (-*x as f64).exp()), (*x as f64).tanh());
                assert!((sigmoid(*x) as f64 - s).abs() < 1e-6 && (tanh_approx(*x) as f64 - t).abs() < 1e-6, "at {x}");
            }
        }
    }
}
