//! A dense layer with what surrounds it as one burn operation:
//! `y = dropout(act(LayerNorm(x) W + b))`, the LayerNorm, the activation (ReLU or none) and the
//! dropout each optional.
//!
//! Through burn's CPU backend a layer is a chain of operations, each a pass over its output with
//! a fresh buffer: the matmul (whose output buffer the backend zeroes and then copies once more
//! to align it), the bias, the ReLU, the dropout mask's product, and for a LayerNorm nine more
//! (burn's autodiff runs the backend's decomposed LayerNorm and differentiates every step), and
//! backward about as many again. Over LMAC's [17,600 x 64] rows these passes cost more than the
//! layers' matmuls. Here the forward is one gemm into a fresh buffer it writes without zeroing
//! (`matmul_new`), then one pass for the bias, the activation and the mask (a layer with neither
//! has the gemm add onto rows that start as the bias); backward is one pass for the activation's
//! and mask's derivative, the two gemms, and one pass for the LayerNorm's.
//!
//! The dropout mask is drawn by the caller from its generator in row-major order, as
//! [`crate::methods::dropout`] draws it, so a seed gives the same mask either way; backward needs
//! no mask of its own beyond it: with a ReLU, y > 0 exactly where the pre-activation is positive
//! and the unit kept. Tested against the same layers as burn operations (values and gradients to
//! 1e-5), which stay the reference in the tests.
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
use burn::nn::{LayerNorm, Linear};
use burn::tensor::{Tensor, TensorData};

use crate::host_kernel::{add_column_sums, host, host_ref, host_values, matmul, matmul_new, register, with_simd, HostValues};
use crate::LearnRng;

/// The LayerNorms a dense layer reads are built with this epsilon (burn's default), which the
/// fused operation uses too.
pub const LAYER_NORM_EPSILON: f32 = 1e-5;

/// The activation after the affine map.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Activation {
    Identity,
    Relu,
}

/// `x` [N, in], gamma and beta [in] (LayerNorm; [0] for none), `w` [in, out], `b` [out], `mask`
/// [N, out] (dropout's kept-unit scale or 0; [0] for none) -> y [N, out].
#[backend_extension(Flex: cfg(feature = "flex"), NdArray: cfg(feature = "ndarray"), Autodiff)]
pub trait DenseBackend: Backend {
    fn dense(
        x: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        w: FloatTensor<Self>,
        b: FloatTensor<Self>,
        mask: FloatTensor<Self>,
        relu: bool,
    ) -> FloatTensor<Self>;
}

/// `dropout(act(norm(x) W + b))` over rows x [N, in] as one operation (see the file's header);
/// `dropout`: the rate and the generator the mask is drawn from. Differentiable in x and in the
/// layers' parameters.
pub fn dense(layer: &Linear, x: Tensor<2>, norm: Option<&LayerNorm>, act: Activation, dropout: Option<(f32, &mut LearnRng)>) -> Tensor<2> {
    let w = layer.weight.val();
    let out = w.dims()[1];
    let b = layer.bias.as_ref().map_or_else(|| Tensor::zeros([out], &x.device()), |b| b.val());
    dense_with(w, b, x, norm, act, dropout)
}

/// [`dense`] with the weight w [in, out] and bias b [out] given as tensors, for layers used side
/// by side as one (their weights concatenated: one gemm for both).
pub fn dense_with(
    w: Tensor<2>,
    b: Tensor<1>,
    x: Tensor<2>,
    norm: Option<&LayerNorm>,
    act: Activation,
    dropout: Option<(f32, &mut LearnRng)>,
) -> Tensor<2> {
    let device = x.device();
    let [n, _] = x.dims();
    let out = w.dims()[1];
    let none = || Tensor::<1>::zeros([0], &device);
    let (gamma, beta) = match norm {
        Some(norm) => {
            let gamma = norm.gamma.val();
            let beta = norm.beta.as_ref().map_or_else(|| Tensor::zeros(gamma.dims(), &device), |b| b.val());
            (gamma, beta)
        }
        None => (none(), none()),
    };
    let mask: Tensor<1> = match dropout {
        Some((p, rng)) if p > 0.0 => Tensor::from_data(TensorData::new(dropout_mask(n * out, p, rng), [n * out]), &device),
        _ => none(),
    };
    Tensor::from_dispatch(<Dispatch as DenseBackend>::dense(
        x.into_dispatch(),
        gamma.into_dispatch(),
        beta.into_dispatch(),
        w.into_dispatch(),
        b.into_dispatch(),
        mask.into_dispatch(),
        act == Activation::Relu,
    ))
}

/// A dropout mask of `n` values in row-major order: 0 with probability `p`, else 1 / (1 - p).
/// One uniform draw per value from `rng`, the draws [`crate::methods::dropout`] makes.
#[inline(never)] // its own symbol in a profile (the draws are a share of the update's time)
pub fn dropout_mask(n: usize, p: f32, rng: &mut LearnRng) -> Vec<f32> {
    let keep = 1.0 / (1.0 - p);
    // branch-free: which units drop is unpredictable, and a branch per value mispredicts
    let mut mask = Vec::with_capacity(n);
    for _ in 0..n {
        mask.push(keep * f32::from(u8::from(rng.uniform() >= p)));
    }
    mask
}

#[cfg(feature = "flex")]
impl DenseBackend for burn::backend::Flex {
    fn dense(
        x: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        w: FloatTensor<Self>,
        b: FloatTensor<Self>,
        mask: FloatTensor<Self>,
        relu: bool,
    ) -> FloatTensor<Self> {
        forward_on::<Self>(Inputs { x, gamma, beta, w, b, mask }, relu, false).0
    }
}

#[cfg(feature = "ndarray")]
impl DenseBackend for burn::backend::NdArray {
    fn dense(
        x: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        w: FloatTensor<Self>,
        b: FloatTensor<Self>,
        mask: FloatTensor<Self>,
        relu: bool,
    ) -> FloatTensor<Self> {
        forward_on::<Self>(Inputs { x, gamma, beta, w, b, mask }, relu, false).0
    }
}

impl<B: Backend + DenseBackend, C: CheckpointStrategy> DenseBackend for Autodiff<B, C> {
    fn dense(
        x: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        w: FloatTensor<Self>,
        b: FloatTensor<Self>,
        mask: FloatTensor<Self>,
        relu: bool,
    ) -> FloatTensor<Self> {
        let nodes = [x.node(), gamma.node(), beta.node(), w.node(), b.node()];
        let inputs = Inputs {
            x: x.into_primitive(),
            gamma: gamma.into_primitive(),
            beta: beta.into_primitive(),
            w: w.into_primitive(),
            b: b.into_primitive(),
            mask: mask.into_primitive(),
        };
        match DenseBackward.prepare::<C>(nodes).compute_bound().stateful() {
            OpsKind::Tracked(prep) => {
                let (y, saved) = forward_on::<B>(inputs, relu, true);
                prep.finish(saved.expect("saved activations"), y)
            }
            OpsKind::UnTracked(prep) => prep.finish(forward_on::<B>(inputs, relu, false).0),
        }
    }
}

struct Inputs<B: Backend> {
    x: FloatTensor<B>,
    gamma: FloatTensor<B>,
    beta: FloatTensor<B>,
    w: FloatTensor<B>,
    b: FloatTensor<B>,
    mask: FloatTensor<B>,
}

/// What backward reads. The tensors are the forward's own (shared, not copied).
#[derive(Debug, Clone)]
struct Saved {
    rows: usize,
    width: usize,
    out: usize,
    /// The matmul's input: x itself, or with a LayerNorm its output.
    input: HostValues,
    /// With a LayerNorm: the normalised rows (before gamma and beta), 1 / sqrt(var + eps) per
    /// row, and gamma.
    norm: Option<(Vec<f32>, Vec<f32>, HostValues)>,
    w: HostValues,
    y: HostValues,
    mask: Option<HostValues>,
    relu: bool,
}

fn forward_on<B: Backend>(inputs: Inputs<B>, relu: bool, save: bool) -> (FloatTensor<B>, Option<Arc<Saved>>) {
    let Inputs { x, gamma, beta, w, b, mask } = inputs;
    let device = x.device();
    let [rows, width] = x.shape().dims::<2>();
    let [w_in, out] = w.shape().dims::<2>();
    let (g_len, b_len, m_len) = (gamma.shape().num_elements(), beta.shape().num_elements(), mask.shape().num_elements());
    assert!(
        w_in == width
            && b.shape().dims::<1>() == [out]
            && (g_len == 0 || g_len == width)
            && b_len == g_len
            && (m_len == 0 || m_len == rows * out),
        "dense: x [{rows}, {width}], w [{w_in}, {out}], b {:?}, gamma {g_len}, beta {b_len}, mask {m_len} do not fit",
        b.shape().dims::<1>()
    );
    let normed = (g_len > 0).then(|| {
        let x = host_ref::<B>(&x);
        layer_norm(&x, width, &host_ref::<B>(&gamma), &host_ref::<B>(&beta))
    });
    let y = {
        let x_host;
        let a: &[f32] = match &normed {
            Some(n) => &n.output,
            None => {
                x_host = host_ref::<B>(&x);
                &x_host
            }
        };
        let (w_host, bias) = (host_ref::<B>(&w), host_ref::<B>(&b));
        if relu || m_len > 0 {
            // a pass follows anyway: the gemm writes a fresh buffer, the pass adds the bias
            let mut y = matmul_new(rows, out, width, a, (width, 1), &w_host, (out, 1));
            let mask_host = (m_len > 0).then(|| host_ref::<B>(&mask));
            with_simd!(activate(&mut y, &bias, relu, mask_host.as_deref()));
            y
        } else {
            // no pass follows: the gemm adds onto rows that start as the bias
            let mut y = Vec::with_capacity(rows * out);
            for _ in 0..rows {
                y.extend_from_slice(&bias);
            }
            matmul(rows, out, width, &mut y, out, true, a, (width, 1), &w_host, (out, 1));
            y
        }
    };
    let y = B::float_from_data(TensorData::new(y, [rows, out]), &device);
    if !save {
        return (y, None);
    }
    let (input, norm) = match normed {
        Some(n) => (HostValues::Copied(n.output), Some((n.normalised, n.rstd, host_values::<B>(gamma)))),
        None => (host_values::<B>(x), None),
    };
    let mask = (m_len > 0).then(|| host_values::<B>(mask));
    let saved = Saved { rows, width, out, input, norm, w: host_values::<B>(w), y: host_values::<B>(y.clone()), mask, relu };
    (y, Some(Arc::new(saved)))
}

/// A LayerNorm's forward over rows of `width`: its output, the normalised rows and each row's
/// 1 / sqrt(var + eps) (burn's decomposition: the mean, then the mean of the centred squares).
struct Normed {
    output: Vec<f32>,
    normalised: Vec<f32>,
    rstd: Vec<f32>,
}

fn layer_norm(x: &[f32], width: usize, gamma: &[f32], beta: &[f32]) -> Normed {
    let rows = x.len() / width.max(1);
    let mut normed = Normed { output: vec![0.0; x.len()], normalised: vec![0.0; x.len()], rstd: vec![0.0; rows] };
    with_simd!(layer_norm_rows(x, width, gamma, beta, &mut normed));
    normed
}

#[inline(always)]
fn layer_norm_rows(x: &[f32], width: usize, gamma: &[f32], beta: &[f32], normed: &mut Normed) {
    let inv = 1.0 / width as f32;
    let rows = x.chunks_exact(width).zip(normed.normalised.chunks_exact_mut(width)).zip(normed.output.chunks_exact_mut(width));
    for (((x, xhat), out), rstd) in rows.zip(normed.rstd.iter_mut()) {
        let mean = x.iter().sum::<f32>() * inv;
        let var = x.iter().map(|v| (v - mean) * (v - mean)).sum::<f32>() * inv;
        *rstd = 1.0 / (var + LAYER_NORM_EPSILON).sqrt();
        for j in 0..width {
            // a product, not burn's quotient: within a rounding of it, and a division per value
            // was most of this loop's time
            let h = (x[j] - mean) * *rstd;
            xhat[j] = h;
            out[j] = h * gamma[j] + beta[j];
        }
    }
}

/// y = dropout(act(y + bias)) in place, rows of bias.len(): the bias, then the ReLU and/or the
/// mask, in one pass.
#[inline(always)]
fn activate(y: &mut [f32], bias: &[f32], relu: bool, mask: Option<&[f32]>) {
    let out = bias.len();
    if out == 0 {
        return;
    }
    let masks = mask.map(|m| m.chunks_exact(out));
    let rows = y.chunks_exact_mut(out);
    match (relu, masks) {
        (true, Some(ms)) => rows.zip(ms).for_each(|(y, m)| {
            y.iter_mut().zip(bias).zip(m).for_each(|((v, b), m)| *v = (*v + b).max(0.0) * m);
        }),
        (true, None) => rows.for_each(|y| y.iter_mut().zip(bias).for_each(|(v, b)| *v = (*v + b).max(0.0))),
        (false, Some(ms)) => rows.zip(ms).for_each(|(y, m)| {
            y.iter_mut().zip(bias).zip(m).for_each(|((v, b), m)| *v = (*v + b) * m);
        }),
        (false, None) => rows.for_each(|y| y.iter_mut().zip(bias).for_each(|(v, b)| *v += b)),
    }
}

/// d(pre-activation) from dy, in place: with a ReLU zero where y is not positive (the unit was
/// negative or dropped), times the mask's scale where it was kept.
#[inline(always)]
fn deactivate(dy: &mut [f32], y: &[f32], relu: bool, mask: Option<&[f32]>) {
    match (relu, mask) {
        (true, Some(m)) => dy.iter_mut().zip(y).zip(m).for_each(|((d, y), m)| *d = if *y > 0.0 { *d * m } else { 0.0 }),
        (true, None) => dy.iter_mut().zip(y).for_each(|(d, y)| *d = if *y > 0.0 { *d } else { 0.0 }),
        (false, Some(m)) => dy.iter_mut().zip(m).for_each(|(d, m)| *d *= m),
        (false, None) => {}
    }
}

/// The LayerNorm's backward: from d(output) `d_out` (rows of `width`) to d(x), and the sums into
/// d(gamma) and d(beta).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn layer_norm_backward(
    d_out: &[f32],
    xhat: &[f32],
    rstd: &[f32],
    gamma: &[f32],
    width: usize,
    d_x: &mut [f32],
    d_gamma: &mut [f32],
    d_beta: &mut [f32],
) {
    let inv = 1.0 / width as f32;
    for (((d_out, xhat), d_x), rstd) in d_out.chunks_exact(width).zip(xhat.chunks_exact(width)).zip(d_x.chunks_exact_mut(width)).zip(rstd) {
        let (mut sum, mut dot) = (0.0f32, 0.0f32);
        for j in 0..width {
            d_gamma[j] += d_out[j] * xhat[j];
            d_beta[j] += d_out[j];
            let g = d_out[j] * gamma[j];
            sum += g;
            dot += g * xhat[j];
        }
        let (mean, mean_dot) = (sum * inv, dot * inv);
        for j in 0..width {
            d_x[j] = rstd * (d_out[j] * gamma[j] - mean - xhat[j] * mean_dot);
        }
    }
}

#[derive(Debug)]
struct DenseBackward;

impl<B: Backend> Backward<B, 5> for DenseBackward {
    type State = Arc<Saved>;

    fn backward(self, ops: Ops<Self::State, 5>, grads: &mut Gradients, _checkpointer: &mut Checkpointer) {
        let [node_x, node_gamma, node_beta, node_w, node_b] = ops.parents.map(|n| n.map(|n| n.id));
        let grad = grads.consume::<B>(&ops.node);
        let device = grad.device();
        let s = ops.state;
        let (rows, width, out) = (s.rows, s.width, s.out);
        let mut d_pre = host::<B>(grad);
        with_simd!(deactivate(&mut d_pre, &s.y, s.relu, s.mask.as_deref()));
        let mut parts = Vec::new();
        if node_b.is_some() {
            let mut d_b = vec![0.0f32; out];
            add_column_sums(&mut d_b, &d_pre);
            parts.push((node_b, d_b, vec![out]));
        }
        if node_w.is_some() {
            // dW = input^T d_pre (input read transposed)
            let d_w = matmul_new(width, out, rows, &s.input, (1, width), &d_pre, (out, 1));
            parts.push((node_w, d_w, vec![width, out]));
        }
        if node_x.is_some() || node_gamma.is_some() || node_beta.is_some() {
            // d(input) = d_pre W^T (W [in, out] read transposed)
            let d_in = matmul_new(rows, width, out, &d_pre, (out, 1), &s.w, (1, out));
            match &s.norm {
                None => parts.push((node_x, d_in, vec![rows, width])),
                Some((xhat, rstd, gamma)) => {
                    let (mut d_x, mut d_gamma, mut d_beta) = (vec![0.0f32; rows * width], vec![0.0f32; width], vec![0.0f32; width]);
                    with_simd!(layer_norm_backward(&d_in, xhat, rstd, gamma, width, &mut d_x, &mut d_gamma, &mut d_beta));
                    parts.extend([(node_x, d_x, vec![rows, width]), (node_gamma, d_gamma, vec![width]), (node_beta, d_beta, vec![width])]);
                }
            }
        }
        register::<B>(grads, &device, parts);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::host_kernel::test_support::{assert_same_grad, max_diff, random};
    use crate::init::linear;
    use burn::module::Module;
    use burn::nn::LayerNormConfig;
    use burn::tensor::activation::relu;
    use burn::tensor::Device;

    /// The same layer as burn operations, the reference the fused operation is tested against.
    fn dense_reference(
        layer: &Linear,
        x: Tensor<2>,
        norm: Option<&LayerNorm>,
        act: Activation,
        dropout: Option<(f32, &mut LearnRng)>,
    ) -> Tensor<2> {
        let x = match norm {
            Some(norm) => norm.forward(x),
            None => x,
        };
        let y = layer.forward(x);
        let y = match act {
            Activation::Relu => relu(y),
            Activation::Identity => y,
        };
        match dropout {
            Some((p, rng)) => crate::methods::dropout(y, p, rng),
            None => y,
        }
    }

    /// Every combination of LayerNorm, ReLU and dropout against burn's operations: values, the
    /// generator's state after the draws, and the gradients of x and of every parameter to 1e-5,
    /// with and without autodiff.
    #[test]
    fn matches_burns_operations() {
        let dev = Device::default().autodiff();
        let (n, width, out) = (37, 9, 6);
        for norm_on in [false, true] {
            for act in [Activation::Identity, Activation::Relu] {
                for p in [0.0f32, 0.3] {
                    let what = format!("norm {norm_on}, {act:?}, dropout {p}");
                    let mut rng = LearnRng::seed_from(5);
                    let layer = linear(&mut rng, width, out, &dev);
                    let mut norm = LayerNormConfig::new(width).with_epsilon(LAYER_NORM_EPSILON as f64).init(&dev);
                    // gamma and beta away from their initial ones and zeros, so their gradients matter
                    norm.gamma = burn::module::Param::from_tensor(random(&mut rng, [1, width], &dev).reshape([width]));
                    norm.beta = Some(burn::module::Param::from_tensor(random(&mut rng, [1, width], &dev).reshape([width])));
                    let norm = norm_on.then_some(&norm);
                    let x = random(&mut rng, [n, width], &dev).require_grad();
                    let weights = random(&mut rng, [n, out], &dev);

                    let (mut r1, mut r2) = (LearnRng::seed_from(8), LearnRng::seed_from(8));
                    let reference = dense_reference(&layer, x.clone(), norm, act, (p > 0.0).then_some((p, &mut r1)));
                    let fused = dense(&layer, x.clone(), norm, act, (p > 0.0).then_some((p, &mut r2)));
                    assert!(max_diff(reference.clone().inner(), fused.clone().inner()) < 1e-5, "{what}: values differ");
                    assert_eq!(r1.uniform(), r2.uniform(), "{what}: the same draws");

                    let ref_grads = (reference * weights.clone()).sum().backward();
                    let grads = (fused * weights).sum().backward();
                    assert_same_grad(&format!("{what}: x"), x.grad(&ref_grads), x.grad(&grads));
                    assert_same_grad(&format!("{what}: w"), layer.weight.val().grad(&ref_grads), layer.weight.val().grad(&grads));
                    let b = layer.bias.as_ref().expect("bias").val();
                    assert_same_grad(&format!("{what}: b"), b.grad(&ref_grads), b.grad(&grads));
                    if let Some(norm) = norm {
                        let (g, be) = (norm.gamma.val(), norm.beta.as_ref().expect("beta").val());
                        assert_same_grad(&format!("{what}: gamma"), g.grad(&ref_grads), g.grad(&grads));
                        assert_same_grad(&format!("{what}: beta"), be.grad(&ref_grads), be.grad(&grads));
                    }

                    // no autodiff: the same values
                    let (plain, plain_norm) = (layer.valid(), norm.map(|n| n.valid()));
                    let (mut r1, mut r2) = (LearnRng::seed_from(8), LearnRng::seed_from(8));
                    let x = x.inner();
                    let a = dense_reference(&plain, x.clone(), plain_norm.as_ref(), act, (p > 0.0).then_some((p, &mut r1)));
                    let b = dense(&plain, x, plain_norm.as_ref(), act, (p > 0.0).then_some((p, &mut r2)));
                    assert!(max_diff(a, b) < 1e-5, "{what}: values differ without autodiff");
                }
            }
        }
    }

    /// An input without a gradient (the embedding's first layer reads the batch) gets none, the
    /// parameters still do; zero rows are a valid input.
    #[test]
    fn untracked_input_and_edge_shapes() {
        let dev = Device::default().autodiff();
        let mut rng = LearnRng::seed_from(2);
        let layer = linear(&mut rng, 4, 3, &dev);
        let x = random(&mut rng, [5, 4], &dev);
        let grads = dense(&layer, x.clone(), None, Activation::Relu, None).sum().backward();
        assert!(x.grad(&grads).is_none());
        assert!(layer.weight.val().grad(&grads).is_some());
        let empty = dense(&layer.valid(), Tensor::zeros([0, 4], &Device::default()), None, Activation::Relu, None);
        assert_eq!(empty.dims(), [0, 3]);
    }

    /// The branch-free mask draws what the rule says: one uniform per unit, dropped below p.
    #[test]
    fn the_mask_is_one_draw_per_unit_dropped_below_p() {
        let (mut r1, mut r2) = (LearnRng::seed_from(4), LearnRng::seed_from(4));
        let keep = 1.0 / 0.9;
        let expected: Vec<f32> = (0..2000).map(|_| if r1.uniform() < 0.1 { 0.0 } else { keep }).collect();
        let mask = dropout_mask(2000, 0.1, &mut r2);
        assert_eq!(mask, expected);
        let dropped = mask.iter().filter(|&&m| m == 0.0).count();
        assert!((150..250).contains(&dropped), "{dropped} of 2000 dropped at p = 0.1");
    }
}
