//! A GRU unrolled over a whole sequence as one burn operation.
//!
//! The agent's update is small matrices over sequential steps, so its cost was per-operation
//! overhead, not arithmetic: a plain burn unroll makes about fifteen tensor operations per
//! step forward and as many backward, each allocating. Here the time-independent parts (the
//! first layer and the GRU's input projection) run once over all steps as ordinary burn ops,
//! and only the recurrence is this one custom operation: forward and its backward through time
//! are plain loops over host slices with one `gemm` call per step, registered with burn's
//! autodiff as a single node (`#[backend_extension]`, hand-written `Backward`).
//!
//! `gru_sequence_projected` also takes the input projection into the loop: each step's
//! `gi_t = x_t W_ih + b_ih` is computed into a one-step buffer just before its gates read it, and
//! backward turns each step's d(gi_t) into d(x_t) and the W_ih gradient at once, so the
//! [T, N, 3H] projection and its gradient never exist whole. On 1o_10b's update (17,600 rows,
//! 13.5 MB of gi) writing and rereading that array made the one large matmul run at about half
//! the rate the same product reaches one step at a time (`lmac bench learner`'s shape ceiling).
//!
//! Conventions are torch's `GRUCell` with burn's row layout (weights [in, out], gates r, z, n):
//! `gh = h W_hh + b_hh`, `r = sigmoid(gi_r + gh_r)`, `z = sigmoid(gi_z + gh_z)`,
//! `n = tanh(gi_n + r * gh_n)`, `h' = n + z (h - n)`, from `h_0 = 0`. `gi = x W_ih + b_ih` is
//! the caller's. Tested against the step-by-step burn cell (values and gradients to 1e-5).
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

use super::host_kernel::{add_column_sums, host, host_values, matmul, register, sigmoid, tanh_approx, with_simd, HostValues};

/// The recurrence as a backend operation: gi [T, N, 3H], w_hh [H, 3H], b_hh [3H] -> h [T, N, H];
/// the projected forms take x [T, N, I] and the input projection instead of gi, and
/// `gru_sequence_projected_carry` adds each step's x to its new state before it is carried on.
#[backend_extension(Flex: cfg(feature = "flex"), NdArray: cfg(feature = "ndarray"), Autodiff)]
pub trait GruSequenceBackend: Backend {
    fn gru_sequence(gi: FloatTensor<Self>, w_hh: FloatTensor<Self>, b_hh: FloatTensor<Self>) -> FloatTensor<Self>;
    fn gru_sequence_projected(
        x: FloatTensor<Self>,
        w_ih: FloatTensor<Self>,
        b_ih: FloatTensor<Self>,
        w_hh: FloatTensor<Self>,
        b_hh: FloatTensor<Self>,
    ) -> FloatTensor<Self>;
    fn gru_sequence_projected_carry(
        x: FloatTensor<Self>,
        w_ih: FloatTensor<Self>,
        b_ih: FloatTensor<Self>,
        w_hh: FloatTensor<Self>,
        b_hh: FloatTensor<Self>,
    ) -> FloatTensor<Self>;
}

/// The hidden states of the GRU over time: `gi` [T, N, 3H] (input projections of all steps,
/// bias included), `w_hh` [H, 3H], `b_hh` [3H] -> [T, N, H]. Differentiable in all three.
pub fn gru_sequence(gi: Tensor<3>, w_hh: Tensor<2>, b_hh: Tensor<1>) -> Tensor<3> {
    Tensor::from_dispatch(<Dispatch as GruSequenceBackend>::gru_sequence(gi.into_dispatch(), w_hh.into_dispatch(), b_hh.into_dispatch()))
}

/// [`gru_sequence`] with the input projection inside the loop: `x` [T, N, I], `w_ih` [I, 3H],
/// `b_ih` [3H] give gi_t = x_t W_ih + b_ih one step at a time. Differentiable in all five.
pub fn gru_sequence_projected(x: Tensor<3>, w_ih: Tensor<2>, b_ih: Tensor<1>, w_hh: Tensor<2>, b_hh: Tensor<1>) -> Tensor<3> {
    Tensor::from_dispatch(<Dispatch as GruSequenceBackend>::gru_sequence_projected(
        x.into_dispatch(),
        w_ih.into_dispatch(),
        b_ih.into_dispatch(),
        w_hh.into_dispatch(),
        b_hh.into_dispatch(),
    ))
}

/// [`gru_sequence_projected`] with each step's input carried too: c_t = GRUCell(x_t W_ih + b_ih,
/// c_{t-1}) + x_t from c_{-1} = 0 (input width = hidden width), [T, N, H]. The LMAC encoder of
/// the released code carries h + x this way (`meta.py`). Differentiable in all five.
pub fn gru_sequence_projected_carry(x: Tensor<3>, w_ih: Tensor<2>, b_ih: Tensor<1>, w_hh: Tensor<2>, b_hh: Tensor<1>) -> Tensor<3> {
    Tensor::from_dispatch(<Dispatch as GruSequenceBackend>::gru_sequence_projected_carry(
        x.into_dispatch(),
        w_ih.into_dispatch(),
        b_ih.into_dispatch(),
        w_hh.into_dispatch(),
        b_hh.into_dispatch(),
    ))
}

#[cfg(feature = "flex")]
impl GruSequenceBackend for burn::backend::Flex {
    fn gru_sequence(gi: FloatTensor<Self>, w_hh: FloatTensor<Self>, b_hh: FloatTensor<Self>) -> FloatTensor<Self> {
        forward_on::<Self>(gi, w_hh, b_hh, false).0
    }
    fn gru_sequence_projected(
        x: FloatTensor<Self>,
        w_ih: FloatTensor<Self>,
        b_ih: FloatTensor<Self>,
        w_hh: FloatTensor<Self>,
        b_hh: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        projected_on::<Self>(x, w_ih, b_ih, w_hh, b_hh, false, false).0
    }
    fn gru_sequence_projected_carry(
        x: FloatTensor<Self>,
        w_ih: FloatTensor<Self>,
        b_ih: FloatTensor<Self>,
        w_hh: FloatTensor<Self>,
        b_hh: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        projected_on::<Self>(x, w_ih, b_ih, w_hh, b_hh, true, false).0
    }
}

#[cfg(feature = "ndarray")]
impl GruSequenceBackend for burn::backend::NdArray {
    fn gru_sequence(gi: FloatTensor<Self>, w_hh: FloatTensor<Self>, b_hh: FloatTensor<Self>) -> FloatTensor<Self> {
        forward_on::<Self>(gi, w_hh, b_hh, false).0
    }
    fn gru_sequence_projected(
        x: FloatTensor<Self>,
        w_ih: FloatTensor<Self>,
        b_ih: FloatTensor<Self>,
        w_hh: FloatTensor<Self>,
        b_hh: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        projected_on::<Self>(x, w_ih, b_ih, w_hh, b_hh, false, false).0
    }
    fn gru_sequence_projected_carry(
        x: FloatTensor<Self>,
        w_ih: FloatTensor<Self>,
        b_ih: FloatTensor<Self>,
        w_hh: FloatTensor<Self>,
        b_hh: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        projected_on::<Self>(x, w_ih, b_ih, w_hh, b_hh, true, false).0
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

    fn gru_sequence_projected(
        x: FloatTensor<Self>,
        w_ih: FloatTensor<Self>,
        b_ih: FloatTensor<Self>,
        w_hh: FloatTensor<Self>,
        b_hh: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        projected_tracked::<B, C>([x, w_ih, b_ih, w_hh, b_hh], false)
    }

    fn gru_sequence_projected_carry(
        x: FloatTensor<Self>,
        w_ih: FloatTensor<Self>,
        b_ih: FloatTensor<Self>,
        w_hh: FloatTensor<Self>,
        b_hh: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        projected_tracked::<B, C>([x, w_ih, b_ih, w_hh, b_hh], true)
    }
}

/// The projected forms on the autodiff backend: [x, w_ih, b_ih, w_hh, b_hh], each step's input
/// carried too when `carry` (its gradient then includes the residual's).
fn projected_tracked<B: Backend + GruSequenceBackend, C: CheckpointStrategy>(
    inputs: [FloatTensor<Autodiff<B, C>>; 5],
    carry: bool,
) -> FloatTensor<Autodiff<B, C>> {
    let nodes = inputs.each_ref().map(|t| t.node());
    let [x, w_ih, b_ih, w_hh, b_hh] = inputs.map(|t| t.into_primitive());
    match GruProjectedBackward.prepare::<C>(nodes).compute_bound().stateful() {
        OpsKind::Tracked(prep) => {
            let (out, saved) = projected_on::<B>(x, w_ih, b_ih, w_hh, b_hh, carry, true);
            prep.finish(saved.expect("saved activations"), out)
        }
        OpsKind::UnTracked(prep) => prep.finish(projected_on::<B>(x, w_ih, b_ih, w_hh, b_hh, carry, false).0),
    }
}

#[derive(Debug)]
struct GruProjectedBackward;

impl<B: Backend> Backward<B, 5> for GruProjectedBackward {
    type State = Arc<Saved>;

    fn backward(self, ops: Ops<Self::State, 5>, grads: &mut Gradients, _checkpointer: &mut Checkpointer) {
        let [node_x, node_w_ih, node_b_ih, node_w, node_b] = ops.parents;
        let grad = grads.consume::<B>(&ops.node);
        let device = grad.device();
        let saved = ops.state;
        let g = saved.backward(&host::<B>(grad));
        let (t, n, h) = (saved.steps, saved.rows, saved.hidden);
        let width = saved.projection.as_ref().map_or(0, |p| p.width);
        let parts = [
            (node_x.map(|n| n.id), g.x, vec![t, n, width]),
            (node_w_ih.map(|n| n.id), g.w_ih, vec![width, 3 * h]),
            (node_b_ih.map(|n| n.id), g.b_ih, vec![3 * h]),
            (node_w.map(|n| n.id), g.w_hh, vec![h, 3 * h]),
            (node_b.map(|n| n.id), g.b_hh, vec![3 * h]),
        ];
        register::<B>(grads, &device, parts);
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
        let parts = [
            (node_gi.map(|n| n.id), g.gi, vec![t, n, 3 * h]),
            (node_w.map(|n| n.id), g.w_hh, vec![h, 3 * h]),
            (node_b.map(|n| n.id), g.b_hh, vec![3 * h]),
        ];
        register::<B>(grads, &device, parts);
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
    let gi = host::<B>(gi);
    let saved = Saved::unroll(StepInput::Given(&gi), host::<B>(w_hh), &host::<B>(b_hh), t, n, h3 / 3, save);
    finish_on::<B>(saved, save, &device)
}

/// [`forward_on`] of the projected form: x [T, N, I], w_ih [I, 3H], b_ih [3H]; with `carry`,
/// each step's x is added to its new state (I = H).
fn projected_on<B: Backend>(
    x: FloatTensor<B>,
    w_ih: FloatTensor<B>,
    b_ih: FloatTensor<B>,
    w_hh: FloatTensor<B>,
    b_hh: FloatTensor<B>,
    carry: bool,
    save: bool,
) -> (FloatTensor<B>, Option<Arc<Saved>>) {
    let device = x.device();
    let [t, n, width] = x.shape().dims::<3>();
    let (wi_dims, bi_dims, w_dims, b_dims) =
        (w_ih.shape().dims::<2>(), b_ih.shape().dims::<1>(), w_hh.shape().dims::<2>(), b_hh.shape().dims::<1>());
    let h3 = b_dims[0];
    assert!(
        h3 % 3 == 0 && wi_dims == [width, h3] && bi_dims == [h3] && w_dims == [h3 / 3, h3],
        "gru_sequence_projected: x {:?}, w_ih {wi_dims:?}, b_ih {bi_dims:?}, w_hh {w_dims:?}, b_hh {b_dims:?} do not fit [T, N, I], [I, 3H], [3H], [H, 3H], [3H]",
        [t, n, width]
    );
    let input = StepInput::Project { x: host_values::<B>(x), w_ih: host::<B>(w_ih), b_ih: host::<B>(b_ih), width, carry };
    let saved = Saved::unroll(input, host::<B>(w_hh), &host::<B>(b_hh), t, n, h3 / 3, save);
    finish_on::<B>(saved, save, &device)
}

/// The hidden states as a backend tensor, and what backward reads when `save`.
/// The states are handed to the output tensor, and kept for backward by sharing it.
fn finish_on<B: Backend>(mut saved: Saved, save: bool, device: &B::Device) -> (FloatTensor<B>, Option<Arc<Saved>>) {
    let shape = [saved.steps, saved.rows, saved.hidden];
    let hs = std::mem::replace(&mut saved.hs, HostValues::Copied(Vec::new())).into_vec();
    let out = B::float_from_data(TensorData::new(hs, shape), device);
    if !save {
        return (out, None);
    }
    saved.hs = host_values::<B>(out.clone());
    (out, Some(Arc::new(saved)))
}

/// Where each step's input projection gi_t [N, 3H] comes from.
pub enum StepInput<'a> {
    /// The caller's, for every step: gi [T, N, 3H].
    Given(&'a [f32]),
    /// Computed at each step: gi_t = x_t W_ih + b_ih from x [T, N, width], W_ih [width, 3H];
    /// with `carry`, x_t is also added to the step's new state (width = H).
    Project { x: HostValues, w_ih: Vec<f32>, b_ih: Vec<f32>, width: usize, carry: bool },
}

/// What backward needs of a projected input: the inputs and the projection's weights.
#[derive(Debug, Clone)]
pub struct Projection {
    x: HostValues,
    w_ih: Vec<f32>,
    width: usize,
    /// Whether x was also each step's residual: its gradient then includes the residual's.
    carry: bool,
}

/// The forward's results and what its backward reads: hidden states and gate activations of
/// every step ([T, N, H] each, row-major), and the recurrent weights.
#[derive(Debug, Clone)]
pub struct Saved {
    steps: usize,
    rows: usize,
    hidden: usize,
    w_hh: Vec<f32>,
    hs: HostValues,
    r: Vec<f32>,
    z: Vec<f32>,
    n: Vec<f32>,
    /// The hidden projection's candidate part `gh_n` (bias included), which `r` multiplies.
    gh_n: Vec<f32>,
    /// The input projection, when the unroll computed it (`gru_sequence_projected`).
    projection: Option<Projection>,
}

/// Gradients of the inputs: of gi, or with a projected input of x (through the residual too when
/// carried), w_ih and b_ih instead (the others empty).
pub struct SequenceGrads {
    pub gi: Vec<f32>,
    pub x: Vec<f32>,
    pub w_ih: Vec<f32>,
    pub b_ih: Vec<f32>,
    pub w_hh: Vec<f32>,
    pub b_hh: Vec<f32>,
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
            let cj = tanh_approx(rj.mul_add(gh_n[j], gi_n[j]));
            out[j] = zj.mul_add(prev[j] - cj, cj);
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
        Self::unroll(StepInput::Given(gi), w_hh, b_hh, t, n, h, keep)
    }

    /// The unroll behind every form: each step's gi_t from `input`.
    #[allow(clippy::too_many_arguments)]
    pub fn unroll(input: StepInput<'_>, w_hh: Vec<f32>, b_hh: &[f32], t: usize, n: usize, h: usize, keep: bool) -> Saved {
        let h3 = 3 * h;
        match &input {
            StepInput::Given(gi) => assert_eq!(gi.len(), t * n * h3, "gru_sequence: gi length"),
            StepInput::Project { x, w_ih, b_ih, width, carry } => {
                assert_eq!(x.len(), t * n * width, "gru_sequence_projected: x length");
                assert!(!carry || *width == h, "gru_sequence_projected_carry: x's width {width} is not the hidden width {h}");
                assert_eq!(w_ih.len(), width * h3, "gru_sequence_projected: w_ih length");
                assert_eq!(b_ih.len(), h3, "gru_sequence_projected: b_ih length");
            }
        }
        // One step's input projection when the unroll computes it.
        let mut gi_buf = match &input {
            StepInput::Given(_) => Vec::new(),
            StepInput::Project { .. } => vec![0.0f32; n * h3],
        };
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
            let gi_t: &[f32] = match &input {
                StepInput::Given(gi) => &gi[ti * n * h3..(ti + 1) * n * h3],
                StepInput::Project { x, w_ih, b_ih, width, .. } => {
                    // gi_t = b_ih + x_t W_ih, one step's rows while they are in cache
                    for row in gi_buf.chunks_exact_mut(h3) {
                        row.copy_from_slice(b_ih);
                    }
                    matmul(n, h3, *width, &mut gi_buf, h3, true, &x[ti * n * width..], (*width, 1), w_ih, (h3, 1));
                    &gi_buf
                }
            };
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
            if let StepInput::Project { x, carry: true, .. } = &input {
                for (o, x) in out.iter_mut().zip(&x[ti * step..(ti + 1) * step]) {
                    *o += x;
                }
            }
        }
        let projection = match input {
            StepInput::Project { x, w_ih, width, carry, .. } if keep => Some(Projection { x, w_ih, width, carry }),
            _ => None,
        };
        Saved { steps: t, rows: n, hidden: h, w_hh, hs: HostValues::Copied(hs), r: r_all, z: z_all, n: n_all, gh_n: ghn_all, projection }
    }

    /// Backpropagation through time of `d_hs` = dL/dh_t for every step [T, N, H].
    pub fn backward(&self, d_hs: &[f32]) -> SequenceGrads {
        let (t, n, h) = (self.steps, self.rows, self.hidden);
        let (h3, step) = (3 * h, n * h);
        assert_eq!(d_hs.len(), t * step, "gru_sequence: gradient length");
        assert_eq!(self.r.len(), t * step, "gru_sequence: backward needs a forward run with keep");
        // d(gi): of every step when gi was given; one step's, turned into d(x_t) and the W_ih
        // gradient at once, when the unroll projected x itself.
        let proj = self.projection.as_ref();
        let mut d_gi = vec![0.0f32; if proj.is_some() { n * h3 } else { t * n * h3 }];
        let width = proj.map_or(0, |p| p.width);
        let mut d_x = vec![0.0f32; t * n * width];
        let mut d_w_ih = vec![0.0f32; width * h3];
        let mut d_b_ih = vec![0.0f32; if proj.is_some() { h3 } else { 0 }];
        // One step's d(gh): W_hh's gradient takes it step by step like W_ih's (one product over
        // all steps read a [T N, 3H] array back from memory, at about 60% of the per-step rate).
        let mut d_gh = vec![0.0f32; n * h3];
        let mut d_w = vec![0.0f32; h * h3];
        let mut d_b = vec![0.0f32; h3];
        let mut d_next = vec![0.0f32; step]; // dL/dh_{t} arriving from step t + 1
        let zeros = vec![0.0f32; step];
        let mut d_prev = vec![0.0f32; step];
        for ti in (0..t).rev() {
            let at = ti * step..(ti + 1) * step;
            let prev = if ti > 0 { &self.hs[(ti - 1) * step..ti * step] } else { &zeros[..] };
            let saved = (&self.r[at.clone()], &self.z[at.clone()], &self.n[at.clone()], &self.gh_n[at.clone()]);
            let g_at = ti * n * h3..(ti + 1) * n * h3;
            let gi_at = if proj.is_some() { 0..n * h3 } else { g_at.clone() };
            let (d_gi_t, d_gh_t) = (&mut d_gi[gi_at], &mut d_gh[..]);
            with_simd!(gates_backward(h, &d_hs[at.clone()], &d_next, saved, prev, &mut d_prev, d_gi_t, d_gh_t));
            if let Some(p) = proj {
                let w = p.width;
                // d(x_t) = d(gi_t) W_ih^T; dW_ih += x_t^T d(gi_t); db_ih += column sums of d(gi_t)
                matmul(n, w, h3, &mut d_x[ti * n * w..], w, false, d_gi_t, (h3, 1), &p.w_ih, (1, h3));
                if p.carry {
                    // x_t was also added to c_t (w = H): it gets the whole gradient arriving there
                    for ((d, a), b) in d_x[at.clone()].iter_mut().zip(&d_hs[at.clone()]).zip(&d_next) {
                        *d += a + b;
                    }
                }
                matmul(w, h3, n, &mut d_w_ih, h3, ti + 1 < t, &p.x[ti * n * w..], (1, w), d_gi_t, (h3, 1));
                add_column_sums(&mut d_b_ih, d_gi_t);
            }
            add_column_sums(&mut d_b, &d_gh);
            if ti > 0 {
                // dh_{t-1} += d(gh_t) W_hh^T (W_hh [H, 3H] read transposed); dW_hh += h_{t-1}^T
                // d(gh_t) (h_{-1} = 0 adds nothing; d_w starts at zero)
                matmul(n, h, h3, &mut d_prev, h, true, &d_gh, (h3, 1), &self.w_hh, (1, h3));
                matmul(h, h3, n, &mut d_w, h3, true, prev, (1, h), &d_gh, (h3, 1));
            }
            std::mem::swap(&mut d_next, &mut d_prev);
        }
        // with a projection d_gi was one step's scratch, not a gradient of any input
        let d_gi = if proj.is_some() { Vec::new() } else { d_gi };
        SequenceGrads { gi: d_gi, x: d_x, w_ih: d_w_ih, b_ih: d_b_ih, w_hh: d_w, b_hh: d_b }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::agent::FusedGru;
    use crate::host_kernel::test_support::{assert_same_grad, max_diff, random};
    use crate::LearnRng;
    use burn::module::Module;
    use burn::tensor::Device;

    /// burn's cell stepped by hand from zero over `xs`, each new state plus its input when
    /// `carry`: every step's state, [T * N, H].
    fn stepped(gru: &FusedGru, xs: &[Tensor<2>], carry: bool) -> Tensor<2> {
        let [n, _] = xs[0].dims();
        let mut h = Tensor::zeros([n, gru.hidden_dim], &xs[0].device());
        let mut hs = Vec::new();
        for x in xs {
            h = gru.forward(x.clone(), h);
            if carry {
                h = h + x.clone();
            }
            hs.push(h.clone());
        }
        Tensor::cat(hs, 0)
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
        let reference = stepped(&gru, &xs, false);
        let ref_grads = (reference.clone() * weights.clone()).sum().backward();

        // fused
        let gi = gru.input.forward(Tensor::cat(xs.clone(), 0)).reshape([t, n, 3 * hd]);
        let bias = gru.hidden.bias.as_ref().expect("bias").val();
        let fused = gru_sequence(gi, gru.hidden.weight.val(), bias.clone()).reshape([t * n, hd]);
        assert!(max_diff(reference.clone().inner(), fused.clone().inner()) < 1e-5);
        let grads = (fused * weights).sum().backward();

        for (name, p) in [("w_hh", &gru.hidden.weight), ("w_ih", &gru.input.weight)] {
            assert_same_grad(name, p.val().grad(&ref_grads), p.val().grad(&grads));
        }
        assert_same_grad("b_hh", bias.grad(&ref_grads), bias.grad(&grads));
        for (i, x) in xs.iter().enumerate() {
            assert_same_grad(&format!("input of step {i}"), x.grad(&ref_grads), x.grad(&grads));
        }

        // no autodiff: the same values
        let plain = gru.valid();
        let gi = plain.input.forward(Tensor::cat(xs.iter().map(|x| x.clone().inner()).collect(), 0)).reshape([t, n, 3 * hd]);
        let bias = plain.hidden.bias.as_ref().expect("bias").val();
        let out = gru_sequence(gi, plain.hidden.weight.val(), bias).reshape([t * n, hd]);
        assert!(max_diff(reference.inner(), out) < 1e-5);
    }

    /// The projected form (`FusedGru::sequence`: each step's input projection inside the loop)
    /// against the step-by-step cell, with an input width unlike the hidden width: hidden states
    /// and the gradients of x and of all four parameters to 1e-5, with and without autodiff.
    #[test]
    fn the_projected_form_matches_the_step_by_step_cell() {
        let (t, n, width, hd) = (6, 5, 7, 4);
        let dev = Device::default().autodiff();
        let mut rng = LearnRng::seed_from(11);
        let gru = FusedGru::new(&mut rng, width, hd, &dev);
        let xs: Vec<Tensor<2>> = (0..t).map(|_| random(&mut rng, [n, width], &dev).require_grad()).collect();
        let weights = random(&mut rng, [t * n, hd], &dev);
        let reference = stepped(&gru, &xs, false);
        let ref_grads = (reference.clone() * weights.clone()).sum().backward();
        let fused = gru.sequence(Tensor::cat(xs.clone(), 0), t).reshape([t * n, hd]);
        assert!(max_diff(reference.clone().inner(), fused.clone().inner()) < 1e-5);
        let grads = (fused * weights).sum().backward();
        for (name, p) in [("w_ih", &gru.input.weight), ("w_hh", &gru.hidden.weight)] {
            assert_same_grad(name, p.val().grad(&ref_grads), p.val().grad(&grads));
        }
        for (name, b) in [("b_ih", &gru.input.bias), ("b_hh", &gru.hidden.bias)] {
            let b = b.as_ref().expect("bias").val();
            assert_same_grad(name, b.grad(&ref_grads), b.grad(&grads));
        }
        for (i, x) in xs.iter().enumerate() {
            assert_same_grad(&format!("input of step {i}"), x.grad(&ref_grads), x.grad(&grads));
        }
        let plain = gru.valid();
        let out = plain.sequence(Tensor::cat(xs.iter().map(|x| x.clone().inner()).collect(), 0), t).reshape([t * n, hd]);
        assert!(max_diff(reference.inner(), out) < 1e-5);
        let one = plain.sequence(Tensor::ones([3, width], &Device::default()), 1);
        assert_eq!(one.dims(), [1, 3, hd]);
    }

    /// The carried form c_t = GRU(x_t, c_{t-1}) + x_t (`FusedGru::sequence_carry`, its input
    /// projection inside the loop) against the cell stepped by hand: values and the gradients of
    /// x (the residual's included) and of all four parameters to 1e-5, with and without autodiff.
    #[test]
    fn the_carried_residual_matches_the_step_by_step_cell() {
        let (t, n, hd) = (6, 4, 5);
        let dev = Device::default().autodiff();
        let mut rng = LearnRng::seed_from(9);
        let gru = FusedGru::new(&mut rng, hd, hd, &dev);
        let xs: Vec<Tensor<2>> = (0..t).map(|_| random(&mut rng, [n, hd], &dev).require_grad()).collect();
        let weights = random(&mut rng, [t * n, hd], &dev);
        let reference = stepped(&gru, &xs, true);
        let ref_grads = (reference.clone() * weights.clone()).sum().backward();
        let fused = gru.sequence_carry(Tensor::cat(xs.clone(), 0), t).reshape([t * n, hd]);
        assert!(max_diff(reference.clone().inner(), fused.clone().inner()) < 1e-5);
        let grads = (fused * weights).sum().backward();
        for (name, p) in [("w_ih", &gru.input.weight), ("w_hh", &gru.hidden.weight)] {
            assert_same_grad(name, p.val().grad(&ref_grads), p.val().grad(&grads));
        }
        for (name, b) in [("b_ih", &gru.input.bias), ("b_hh", &gru.hidden.bias)] {
            let b = b.as_ref().expect("bias").val();
            assert_same_grad(name, b.grad(&ref_grads), b.grad(&grads));
        }
        for (i, x) in xs.iter().enumerate() {
            assert_same_grad(&format!("input of step {i} (through the GRU and the residual)"), x.grad(&ref_grads), x.grad(&grads));
        }
        let plain = gru.valid();
        let out = plain.sequence_carry(Tensor::cat(xs.iter().map(|x| x.clone().inner()).collect(), 0), t).reshape([t * n, hd]);
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
