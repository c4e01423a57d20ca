//! 2D transposed convolution (no bias, no groups, no dilation) as a burn backend extension,
//! with a handwritten backward.
//!
//! Why: the decoders are stacks of transposed convolutions up to 512 x 512. On the CPU
//! backends, burn 0.22 differentiates `conv_transpose2d` with generic formulas: the weight
//! gradient is a convolution whose kernel is the whole input image (dilated by the stride),
//! which burn-flex evaluates through an im2col of element-by-element copies and thin
//! matrix products. That made the decoders' backward five times their forward. Here both
//! passes are the textbook "column" formulation, three large matrix products (the `gemm`
//! crate burn-flex itself uses) and one gather/scatter:
//!
//! - forward, per batch item: `col = Wᵀ · X` ([C_out·k_h·k_w, H·W]), then `col2im`
//!   sums into every output pixel the column entries that land on it;
//! - backward: `dcol = im2col(dY)` (the same index map read the other way), then
//!   `dX = W · dcol` and `dW += X · dcolᵀ`.
//!
//! Thread mapping (CPU): the products run on rayon through `gemm`; `col2im` is parallel over
//! output channels (each task owns one output plane, so no two tasks write one pixel);
//! `im2col` is parallel over the rows of `dcol`.
//!
//! Backends: flex and ndarray run both passes here on host memory (see [`HostConvT`]); on
//! burn's cubecl backend (wgpu) both passes call burn's own `conv_transpose2d` and its
//! backward functions. The reference twin is burn's `conv_transpose2d` itself; the tests
//! compare values and gradients with it and check finite differences.
//!
//! The decoders call this through [`super::conv_t_bias_act`], which adds the bias and the
//! activation in the same pass; this op alone serves layers without a bias.

// burn-ndarray is deprecated in burn 0.22; the design keeps it alongside flex.
#![allow(deprecated)]

use burn::backend::autodiff::{
    Autodiff,
    checkpoint::{base::Checkpointer, strategy::CheckpointStrategy},
    grads::Gradients,
    ops::{Backward, Ops, OpsKind},
};
use burn::backend::tensor::FloatTensor;
use burn::backend::{
    AutodiffBackend, Backend, Cube, ExtensionType, Flex, NdArray, TensorMetadata, backend_extension,
};
use burn::tensor::Tensor;
use burn::tensor::ops::ConvTransposeOptions;
use rayon::prelude::*;

use crate::constants::{COLUMN_BLOCK, planes_per_task};
use crate::gemm::{GradientSum, matmul, matmul_into_uninit};
use crate::host::{HostIo, floats};

/// Stride and padding of a transposed convolution (dilation 1, one group, no output
/// padding): `H_out = (H - 1)·stride - 2·padding + k_h`, likewise for the width.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ConvTParams {
    /// Stride (height, width).
    pub stride: [usize; 2],
    /// Padding removed from each side of the full output (height, width).
    pub padding: [usize; 2],
}

impl ConvTParams {
    pub(super) fn options(&self) -> ConvTransposeOptions<2> {
        ConvTransposeOptions::new(self.stride, self.padding, [0, 0], [1, 1], 1)
    }

    /// The output size for an input `[h, w]` and kernel `[kh, kw]`, or `None` when the
    /// padding removes everything.
    pub fn output_size(&self, [h, w]: [usize; 2], [kh, kw]: [usize; 2]) -> Option<[usize; 2]> {
        let ho = ((h.max(1) - 1) * self.stride[0] + kh).checked_sub(2 * self.padding[0])?;
        let wo = ((w.max(1) - 1) * self.stride[1] + kw).checked_sub(2 * self.padding[1])?;
        (h > 0 && w > 0 && ho > 0 && wo > 0).then_some([ho, wo])
    }
}

/// A transposed convolution's two tensors: its inputs, or their gradients.
///
/// # Shapes
/// - `x`: [N, C_in, H, W]; `weight`: [C_in, C_out, k_h, k_w]
#[derive(ExtensionType, Debug, Clone)]
pub struct ConvTPair<B: Backend> {
    pub x: FloatTensor<B>,
    pub weight: FloatTensor<B>,
}

/// Backends with the transposed convolution of this module.
#[backend_extension(NdArray, Flex, Cube, Autodiff)]
pub trait ConvTBackend: Backend {
    /// `xw.x` `[N, C_in, H, W]`, `xw.weight` `[C_in, C_out, k_h, k_w]` (PyTorch's layout) →
    /// `[N, C_out, H_out, W_out]`. Default: the backend's own `conv_transpose2d`.
    fn conv_t(#[extension_type] xw: ConvTPair<Self>, p: ConvTParams) -> FloatTensor<Self> {
        use burn::backend::ops::ModuleOps;
        <Self as ModuleOps<Self>>::conv_transpose2d(xw.x, xw.weight, None, p.options())
    }

    /// Backward: `grad_out` `[N, C_out, H_out, W_out]` → gradients of `x` and `weight`.
    /// Default: the backend's own input and weight backward passes.
    fn conv_t_backward(
        #[extension_type] xw: ConvTPair<Self>,
        grad_out: FloatTensor<Self>,
        p: ConvTParams,
    ) -> ConvTPair<Self> {
        use burn::backend::ops::ModuleOps;
        let ConvTPair { x, weight } = xw;
        let o = p.options();
        ConvTPair {
            x: <Self as ModuleOps<Self>>::conv_transpose2d_x_backward(
                weight.clone(),
                grad_out.clone(),
                o.clone(),
            ),
            weight: <Self as ModuleOps<Self>>::conv_transpose2d_weight_backward(
                x, weight, grad_out, o,
            ),
        }
    }
}

/// The transposed convolution of this module on any backend (see the module docs).
///
/// # Shapes
/// - `x`: [N, C_in, H, W]; `weight`: [C_in, C_out, k_h, k_w]
/// - returns [N, C_out, H_out, W_out]
///
/// # Panics
/// When the channel counts disagree or the padding leaves no output (the layers that call
/// this check their configuration when they are built).
pub fn conv_transpose2d(x: Tensor<4>, weight: Tensor<4>, p: ConvTParams) -> Tensor<4> {
    let [_, ci, h, w] = x.dims();
    let [wci, _, kh, kw] = weight.dims();
    assert_eq!(
        ci, wci,
        "conv_transpose2d: input channels {ci}, weight {wci}"
    );
    assert!(
        p.output_size([h, w], [kh, kw]).is_some(),
        "conv_transpose2d: padding {:?} leaves no output for a {h}x{w} input and a {kh}x{kw} kernel",
        p.padding
    );
    let xw = ConvTPair {
        x: x.into_dispatch(),
        weight: weight.into_dispatch(),
    };
    Tensor::from_dispatch(<burn::backend::Dispatch as ConvTBackend>::conv_t(xw, p))
}

// ---------------------------------------------------------------------------------------------
// Host implementation.

/// The sizes of one call: the transposed convolution's input (`ci` x `h` x `w`) and output
/// (`co` x `ho` x `wo`). [`super::conv2d`] runs the same index map the other way, with its
/// own output in the input's place and its own input in the output's.
#[derive(Clone, Copy, Debug)]
pub(super) struct Dims {
    pub(super) n: usize,
    pub(super) ci: usize,
    pub(super) co: usize,
    pub(super) h: usize,
    pub(super) w: usize,
    pub(super) kh: usize,
    pub(super) kw: usize,
    pub(super) ho: usize,
    pub(super) wo: usize,
}

impl Dims {
    pub(super) fn new(x: &[usize], weight: &[usize], p: &ConvTParams) -> Self {
        let [n, ci, h, w] = [x[0], x[1], x[2], x[3]];
        let [co, kh, kw] = [weight[1], weight[2], weight[3]];
        let [ho, wo] = p.output_size([h, w], [kh, kw]).unwrap_or([0, 0]);
        Dims {
            n,
            ci,
            co,
            h,
            w,
            kh,
            kw,
            ho,
            wo,
        }
    }

    /// Input pixels per plane.
    pub(super) fn p(&self) -> usize {
        self.h * self.w
    }

    /// Rows of the column matrix (C_out · k_h · k_w).
    pub(super) fn q(&self) -> usize {
        self.co * self.kh * self.kw
    }
}

/// The input index `i` whose output `i·stride + k - pad` is `o`, for every input `i`:
/// returns the input range `[lo, hi)` that lands inside `0..out` for kernel tap `k`.
pub(super) fn valid_inputs(
    len: usize,
    out: usize,
    stride: usize,
    pad: usize,
    k: usize,
) -> (usize, usize) {
    // o = i·s + k - pad ∈ [0, out)  ⇔  i·s ≥ pad - k  and  i·s < out + pad - k.
    let lo = pad.saturating_sub(k).div_ceil(stride);
    let hi = if out + pad > k {
        (out + pad - k).div_ceil(stride).min(len)
    } else {
        0
    };
    (lo.min(hi), hi)
}

/// Forward on host memory: `x` [N, C_in, H, W], `weight` [C_in, C_out, k_h, k_w].
fn host_forward(x: &[f32], weight: &[f32], d: Dims, p: &ConvTParams) -> Vec<f32> {
    host_forward_then(x, weight, d, p, |_, _| {})
}

/// [`host_forward`], then `epilogue(channel, plane)` on every output plane (for
/// [`super::conv_t_bias_act`]'s bias and activation): in the task that scattered it, while
/// it is still in cache, when the column matrix is one block; in a pass of its own after
/// the last block otherwise.
///
/// The input is taken in blocks of [`input_rows_per_block`] rows (all of it for the small
/// layers): per block, `col = Wᵀ · X[:, block]`, then every output row the block reaches
/// gets its share added (neighbouring blocks reach some output rows both), so the blocks
/// run one after another into the zeroed output; the whole-input case writes instead.
pub(super) fn host_forward_then(
    x: &[f32],
    weight: &[f32],
    d: Dims,
    p: &ConvTParams,
    epilogue: impl Fn(usize, &mut [f32]) + Sync,
) -> Vec<f32> {
    host_forward_blocked(
        x,
        weight,
        d,
        p,
        input_rows_per_block(d, COLUMN_BLOCK),
        epilogue,
    )
}

/// Input rows per block of the host passes: as many as keep the block's column matrix
/// within `block` values, at least one and at most the input's height.
fn input_rows_per_block(d: Dims, block: usize) -> usize {
    (block / (d.q() * d.w).max(1)).clamp(1, d.h.max(1))
}

/// [`host_forward_then`] with `rows` input rows per block (the tests set it small).
fn host_forward_blocked(
    x: &[f32],
    weight: &[f32],
    d: Dims,
    p: &ConvTParams,
    rows: usize,
    epilogue: impl Fn(usize, &mut [f32]) + Sync,
) -> Vec<f32> {
    let (pp, q, plane) = (d.p(), d.q(), d.ho * d.wo);
    let whole = rows >= d.h;
    let mut out = vec![0.0f32; d.n * d.co * plane];
    with_columns(q * rows * d.w, |col| {
        for b in 0..d.n {
            let xb = &x[b * d.ci * pp..(b + 1) * d.ci * pp];
            let ob = &mut out[b * d.co * plane..(b + 1) * d.co * plane];
            for r0 in (0..d.h).step_by(rows) {
                let r1 = (r0 + rows).min(d.h);
                let n = (r1 - r0) * d.w;
                let col = &mut col[..q * n];
                // col [q, n] = Wᵀ [q, C_in] · X[:, block] [C_in, n]; W is [C_in, q]
                // row-major, the block's pixels are contiguous in every input plane.
                matmul(
                    [q, n, d.ci],
                    col,
                    [n, 1],
                    false,
                    weight,
                    [1, q],
                    &xb[r0 * d.w..],
                    [pp, 1],
                );
                let col = &*col;
                ob.par_chunks_mut(plane)
                    .enumerate()
                    .with_min_len(planes_per_task(plane))
                    .for_each(|(c, o)| {
                        col2im_rows(col, o, c, d, p, (r0, r1), !whole);
                        if whole {
                            epilogue(c, o);
                        }
                    });
            }
            if !whole {
                ob.par_chunks_mut(plane)
                    .enumerate()
                    .with_min_len(planes_per_task(plane))
                    .for_each(|(c, o)| epilogue(c, o));
            }
        }
    });
    out
}

/// Writes output channel `c`'s plane `o` [H_out, W_out] from its column rows over the whole
/// input: every output pixel is the sum of the column entries that land on it (what was
/// written there before is replaced).
pub(super) fn col2im_plane(col: &[f32], o: &mut [f32], c: usize, d: Dims, p: &ConvTParams) {
    col2im_rows(col, o, c, d, p, (0, d.h), false);
}

/// The share of input rows `r0..r1` in output channel `c`'s plane `o` [H_out, W_out], from
/// the block's column rows (`col` [q, (r1 - r0)·W]): added to the output rows the block
/// reaches with `accumulate`, written into every output row without it (then the block
/// must be the whole input).
///
/// Row by row: output row `oy` takes input row `iy` of tap `ky` when `iy·s_y + ky - p_y = oy`.
/// A tap `kx` sends input columns to the output columns `ix·s_x + kx - p_x`, which step by
/// `s_x`; so the row is summed in `s_x` phase rows (phase `r` holds the output columns
/// `m·s_x + r`), where every tap's contribution is one contiguous, vectorisable add, and
/// the phases are interleaved into `o`'s row once at the end. Adding each tap into `o` with a
/// stride of `s_x` instead is scalar code, one value at a time, and was a large part of the
/// `paper` decoders' forward + backward.
fn col2im_rows(
    col: &[f32],
    o: &mut [f32],
    c: usize,
    d: Dims,
    p: &ConvTParams,
    (r0, r1): (usize, usize),
    accumulate: bool,
) {
    let pp = (r1 - r0) * d.w;
    let [sy, sx] = p.stride;
    let [py, px] = p.padding;
    if d.wo == 0 || r0 >= r1 {
        return;
    }
    // The output rows the block reaches: r0·s_y - p_y ..= (r1 - 1)·s_y + k_h - 1 - p_y.
    let (oy0, oy1) = if accumulate {
        (
            (r0 * sy).saturating_sub(py),
            ((r1 - 1) * sy + d.kh).saturating_sub(py).min(d.ho),
        )
    } else {
        (0, d.ho)
    };
    let mw = d.wo.div_ceil(sx);
    let mut phases = vec![0.0f32; sx * mw];
    for (oy, out_row) in o.chunks_exact_mut(d.wo).enumerate().take(oy1).skip(oy0) {
        phases.fill(0.0);
        for ky in 0..d.kh {
            // iy·sy = oy + py - ky, with r0 <= iy < r1.
            let Some(t) = (oy + py).checked_sub(ky) else {
                continue;
            };
            if t % sy != 0 || t / sy < r0 || t / sy >= r1 {
                continue;
            }
            let iy = t / sy - r0;
            for kx in 0..d.kw {
                let (ix0, ix1) = valid_inputs(d.w, d.wo, sx, px, kx);
                if ix0 == ix1 {
                    continue;
                }
                let row = &col[((c * d.kh + ky) * d.kw + kx) * pp..][..pp];
                let src = &row[iy * d.w + ix0..iy * d.w + ix1];
                // Output column of input column ix0; the others follow every sx.
                let ox0 = ix0 * sx + kx - px;
                let at = (ox0 % sx) * mw + ox0 / sx;
                phases[at..at + src.len()]
                    .iter_mut()
                    .zip(src)
                    .for_each(|(a, v)| *a += v);
            }
        }
        interleave(&phases, mw, sx, out_row, accumulate);
    }
}

/// `out[m·s + r] (+)= phases[r·mw + m]` for every output column (added with `accumulate`).
fn interleave(phases: &[f32], mw: usize, s: usize, out: &mut [f32], accumulate: bool) {
    // One loop per mode, not a branch per value in the hot loop.
    if accumulate {
        interleave_with(phases, mw, s, out, |v, x| *v += x);
    } else {
        interleave_with(phases, mw, s, out, |v, x| *v = x);
    }
}

/// [`interleave`] with `put(out value, phase value)`.
fn interleave_with(
    phases: &[f32],
    mw: usize,
    s: usize,
    out: &mut [f32],
    put: impl Fn(&mut f32, f32),
) {
    match s {
        1 => out.iter_mut().zip(phases).for_each(|(v, x)| put(v, *x)),
        2 => {
            let (even, odd) = phases.split_at(mw);
            let mut pairs = out.chunks_exact_mut(2);
            for ((pair, e), o) in (&mut pairs).zip(even).zip(odd) {
                put(&mut pair[0], *e);
                put(&mut pair[1], *o);
            }
            if let [last] = pairs.into_remainder() {
                put(last, even[mw - 1]);
            }
        }
        _ => out
            .iter_mut()
            .enumerate()
            .for_each(|(ox, v)| put(v, phases[(ox % s) * mw + ox / s])),
    }
}

/// Gathers `dcol` [q, P] from one batch item's output gradient `g` [C_out, H_out, W_out].
pub(super) fn im2col(g: &[f32], dcol: &mut [f32], d: Dims, p: &ConvTParams) {
    im2col_rows(g, dcol, d, p, (0, d.h));
}

/// Gathers the block of input rows `r0..r1` of `dcol` ([q, (r1 - r0)·W]) from one batch
/// item's output gradient `g` [C_out, H_out, W_out].
fn im2col_rows(g: &[f32], dcol: &mut [f32], d: Dims, p: &ConvTParams, (r0, r1): (usize, usize)) {
    let pp = (r1 - r0) * d.w;
    let plane = d.ho * d.wo;
    let [sy, sx] = p.stride;
    let [py, px] = p.padding;
    dcol.par_chunks_mut(pp)
        .enumerate()
        .with_min_len(planes_per_task(pp))
        .for_each(|(r, row)| {
            let (c, ky, kx) = (r / (d.kh * d.kw), (r / d.kw) % d.kh, r % d.kw);
            let gc = &g[c * plane..(c + 1) * plane];
            let (iy0, iy1) = valid_inputs(d.h, d.ho, sy, py, ky);
            // The valid rows inside the block, counted from its first row.
            let iy1 = iy1.clamp(r0, r1) - r0;
            let iy0 = iy0.clamp(r0, r1) - r0;
            let iy0 = iy0.min(iy1);
            let (ix0, ix1) = valid_inputs(d.w, d.wo, sx, px, kx);
            // Only the entries no tap reaches are zeroed; the rest are written once.
            row[..iy0 * d.w].fill(0.0);
            row[iy1 * d.w..].fill(0.0);
            let ox0 = ix0 * sx + kx - px;
            for iy in iy0..iy1 {
                let oy = (iy + r0) * sy + ky - py;
                let dst = &mut row[iy * d.w..(iy + 1) * d.w];
                dst[..ix0].fill(0.0);
                dst[ix1..].fill(0.0);
                if ix0 == ix1 {
                    continue;
                }
                let src = &gc[oy * d.wo + ox0..(oy + 1) * d.wo];
                let n = ix1 - ix0;
                if sx == 1 {
                    dst[ix0..ix1].copy_from_slice(&src[..n]);
                } else if sx == 2 {
                    // The decoders' stride, written out as pairs so that the compiler
                    // vectorises it (a `step_by(2)` gather compiles to scalar code).
                    let (body, last) = dst[ix0..ix1].split_at_mut(n - 1);
                    body.iter_mut()
                        .zip(src[..2 * (n - 1)].chunks_exact(2))
                        .for_each(|(d, pair)| *d = pair[0]);
                    last[0] = src[2 * (n - 1)];
                } else {
                    dst[ix0..ix1]
                        .iter_mut()
                        .zip(src.iter().step_by(sx))
                        .for_each(|(d, s)| *d = *s);
                }
            }
        });
}

/// Backward on host memory → (dx [N, C_in, H, W], dweight [C_in, C_out, k_h, k_w]), in
/// blocks of input rows as the forward ([`host_forward_then`]): per block, `dcol` from the
/// output gradient, `dX[:, block] = W · dcol` and `dW += X[:, block] · dcolᵀ`.
pub(super) fn host_backward(
    x: &[f32],
    weight: &[f32],
    g: &[f32],
    d: Dims,
    p: &ConvTParams,
) -> (Vec<f32>, Vec<f32>) {
    host_backward_blocked(x, weight, g, d, p, input_rows_per_block(d, COLUMN_BLOCK))
}

/// [`host_backward`] with `rows` input rows per block (the tests set it small).
fn host_backward_blocked(
    x: &[f32],
    weight: &[f32],
    g: &[f32],
    d: Dims,
    p: &ConvTParams,
    rows: usize,
) -> (Vec<f32>, Vec<f32>) {
    let (pp, q, plane) = (d.p(), d.q(), d.ho * d.wo);
    let mut dx = Vec::with_capacity(d.n * d.ci * pp);
    let mut dw = GradientSum::new(d.ci, q, d.n * d.p());
    with_columns(q * rows * d.w, |dcol| {
        for b in 0..d.n {
            let gb = &g[b * d.co * plane..(b + 1) * d.co * plane];
            let xb = &x[b * d.ci * pp..(b + 1) * d.ci * pp];
            let dxb = &mut dx.spare_capacity_mut()[b * d.ci * pp..(b + 1) * d.ci * pp];
            for r0 in (0..d.h).step_by(rows) {
                let r1 = (r0 + rows).min(d.h);
                let n = (r1 - r0) * d.w;
                let dcol = &mut dcol[..q * n];
                im2col_rows(gb, dcol, d, p, (r0, r1));
                // dX[:, block] [C_in, n] = W [C_in, q] · dcol [q, n]
                matmul_into_uninit(
                    [d.ci, n, q],
                    &mut dxb[r0 * d.w..],
                    [pp, 1],
                    weight,
                    [q, 1],
                    dcol,
                    [n, 1],
                );
                // dW [C_in, q] += X[:, block] [C_in, n] · dcolᵀ [n, q]
                dw.add(n, &xb[r0 * d.w..], pp, dcol, n);
            }
        }
    });
    // SAFETY: the blocks' products wrote the `C_in·P` values of every batch item.
    unsafe { dx.set_len(d.n * d.ci * pp) };
    (dx, dw.into_row_major())
}

thread_local! {
    /// The calling thread's column buffer, kept between calls ([`with_columns`]).
    static COLUMNS: std::cell::Cell<Vec<f32>> = const { std::cell::Cell::new(Vec::new()) };
}

/// Runs `f` on a column buffer of `len` values whose contents are unspecified (`f` writes
/// before it reads), reused across calls on one thread so the column matrices of every layer
/// and step do not each cost a fresh, zeroed allocation. A nested call gets a buffer of its
/// own.
pub(super) fn with_columns<R>(len: usize, f: impl FnOnce(&mut [f32]) -> R) -> R {
    let mut buf = COLUMNS.take();
    if buf.len() < len {
        buf.resize(len, 0.0);
    }
    let out = f(&mut buf[..len]);
    COLUMNS.set(buf);
    out
}

fn host_conv_t<H: HostIo>(ConvTPair { x, weight }: ConvTPair<H>, p: ConvTParams) -> FloatTensor<H> {
    let device = x.device();
    let d = Dims::new(&x.shape().to_vec(), &weight.shape().to_vec(), &p);
    let out = host_forward(&H::read(x), &H::read(weight), d, &p);
    floats::<H>(out, &[d.n, d.co, d.ho, d.wo], &device)
}

fn host_conv_t_backward<H: HostIo>(
    ConvTPair { x, weight }: ConvTPair<H>,
    grad_out: FloatTensor<H>,
    p: ConvTParams,
) -> ConvTPair<H> {
    let device = x.device();
    let d = Dims::new(&x.shape().to_vec(), &weight.shape().to_vec(), &p);
    let (dx, dw) = host_backward(&H::read(x), &H::read(weight), &H::read(grad_out), d, &p);
    ConvTPair {
        x: floats::<H>(dx, &[d.n, d.ci, d.h, d.w], &device),
        weight: floats::<H>(dw, &[d.ci, d.co, d.kh, d.kw], &device),
    }
}

/// The CPU backends: this module's backward on the host (gemm + im2col) and, where
/// [`HostConvT::HOST_FORWARD`], its forward too.
pub trait HostConvT: HostIo {
    /// Whether the forward pass is ours rather than the backend's own `conv_transpose2d`.
    const HOST_FORWARD: bool;
}

/// burn-ndarray's own `conv_transpose2d` is two orders of magnitude slower than the column
/// formulation here: both passes are ours.
impl HostConvT for NdArray {
    const HOST_FORWARD: bool = true;
}

/// burn-flex has a tiled forward of its own; ours, whose `col2im` has no bounds-checked
/// per-pixel loop, is at least as fast on the decoders (`cargo bench --bench cpu_vs_torch`,
/// docs/performance.md), and the decoders' fused layer ([`super::conv_t_bias_act`]) is built
/// on it.
impl HostConvT for Flex {
    const HOST_FORWARD: bool = true;
}

impl<H: HostConvT> ConvTBackend for H {
    fn conv_t(xw: ConvTPair<Self>, p: ConvTParams) -> FloatTensor<Self> {
        if H::HOST_FORWARD {
            host_conv_t::<Self>(xw, p)
        } else {
            use burn::backend::ops::ModuleOps;
            <Self as ModuleOps<Self>>::conv_transpose2d(xw.x, xw.weight, None, p.options())
        }
    }

    fn conv_t_backward(
        xw: ConvTPair<Self>,
        grad_out: FloatTensor<Self>,
        p: ConvTParams,
    ) -> ConvTPair<Self> {
        host_conv_t_backward::<Self>(xw, grad_out, p)
    }
}

/// The GPU backend keeps burn's CubeCL passes.
impl ConvTBackend for Cube {}

// ---------------------------------------------------------------------------------------------
// Autodiff: the handwritten backward.

#[derive(Debug)]
struct ConvTBackwardOp;

impl<B: Backend + ConvTBackend> Backward<B, 2> for ConvTBackwardOp {
    type State = (FloatTensor<B>, FloatTensor<B>, ConvTParams);

    fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, _: &mut Checkpointer) {
        let grad_out = grads.consume::<B>(&ops.node);
        let (x, weight, p) = ops.state;
        let g = B::conv_t_backward(ConvTPair { x, weight }, grad_out, p);
        let [x_node, weight_node] = ops.parents;
        for (node, grad) in [(x_node, g.x), (weight_node, g.weight)] {
            if let Some(node) = node {
                grads.register::<B>(node.id, grad);
            }
        }
    }
}

impl<B: Backend + ConvTBackend, C: CheckpointStrategy> ConvTBackend for Autodiff<B, C> {
    fn conv_t(ConvTPair { x, weight }: ConvTPair<Self>, p: ConvTParams) -> FloatTensor<Self> {
        let nodes = [x.node(), weight.node()];
        let inner = ConvTPair {
            x: x.into_primitive(),
            weight: weight.into_primitive(),
        };
        match ConvTBackwardOp
            .prepare::<C>(nodes)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                let out = B::conv_t(inner.clone(), p);
                prep.finish((inner.x, inner.weight, p), out)
            }
            OpsKind::UnTracked(prep) => prep.finish(B::conv_t(inner, p)),
        }
    }

    fn conv_t_backward(
        xw: ConvTPair<Self>,
        grad_out: FloatTensor<Self>,
        p: ConvTParams,
    ) -> ConvTPair<Self> {
        let inner = ConvTPair {
            x: xw.x.into_primitive(),
            weight: xw.weight.into_primitive(),
        };
        let g = B::conv_t_backward(inner, grad_out.into_primitive(), p);
        ConvTPair {
            x: Self::from_inner(g.x),
            weight: Self::from_inner(g.weight),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::{Device, Distribution, TensorData};

    fn host<const D: usize>(t: Tensor<D>) -> Vec<f32> {
        t.into_data().iter::<f32>().collect()
    }

    fn max_rel(a: &[f32], b: &[f32]) -> f32 {
        assert_eq!(a.len(), b.len());
        let scale = b.iter().fold(1e-3f32, |m, v| m.max(v.abs()));
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs() / scale)
            .fold(0.0, f32::max)
    }

    /// Kernel, stride, padding, input size, batch.
    type Case = ([usize; 2], [usize; 2], [usize; 2], [usize; 2], usize);

    /// Index-map cases.
    const CASES: [Case; 7] = [
        ([4, 4], [2, 2], [1, 1], [5, 6], 2), // the decoders' layer
        ([3, 3], [1, 1], [1, 1], [4, 3], 1),
        ([3, 2], [2, 3], [0, 1], [3, 4], 1),
        ([1, 1], [1, 1], [0, 0], [2, 2], 3),
        ([5, 5], [3, 2], [2, 1], [2, 3], 1),
        ([4, 4], [2, 2], [1, 1], [1, 1], 1),
        // Kernels smaller than the stride: output pixels that no tap reaches stay zero.
        ([2, 1], [3, 2], [0, 0], [3, 2], 2),
    ];

    /// Case `i`'s parameters and random input, weight and output gradient on `device`.
    fn case_tensors(
        i: usize,
        seed: u64,
        device: &Device,
    ) -> (ConvTParams, [Tensor<4>; 3], [usize; 4]) {
        let (k, stride, padding, [h, w], n) = CASES[i];
        let (ci, co) = (3, 2);
        let p = ConvTParams { stride, padding };
        device.seed(seed);
        let x = Tensor::<4>::random([n, ci, h, w], Distribution::Normal(0.0, 1.0), device);
        let wt = Tensor::<4>::random([ci, co, k[0], k[1]], Distribution::Normal(0.0, 1.0), device);
        let [ho, wo] = p.output_size([h, w], k).expect("valid case");
        let g = Tensor::<4>::random([n, co, ho, wo], Distribution::Normal(0.0, 1.0), device);
        (p, [x, wt, g], [n, co, ho, wo])
    }

    /// The output and the gradients of `x` and `wt` for the output gradient `g`, by `conv`
    /// under burn's autodiff.
    fn values_and_grads(
        [x, wt, g]: [Tensor<4>; 3],
        conv: impl Fn(Tensor<4>, Tensor<4>) -> Tensor<4>,
    ) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let xa = x.require_grad();
        let wa = wt.require_grad();
        let y = conv(xa.clone(), wa.clone());
        let grads = (y.clone() * g).sum().backward();
        (
            host(y),
            host(xa.grad(&grads).expect("x grad")),
            host(wa.grad(&grads).expect("w grad")),
        )
    }

    /// burn's `conv_transpose2d` (the reference twin) as `values_and_grads` takes it.
    fn burn_conv(p: ConvTParams) -> impl Fn(Tensor<4>, Tensor<4>) -> Tensor<4> {
        move |x, w| burn::tensor::module::conv_transpose2d(x, w, None, p.options())
    }

    /// Values and gradients against burn's `conv_transpose2d` (the reference twin).
    fn check_against_burn(device: Device) {
        for i in 0..CASES.len() {
            let (p, xwg, [n, co, ho, wo]) = case_tensors(i, i as u64, &device);
            let (y, dx, dw) = values_and_grads(xwg.clone(), |x, w| conv_transpose2d(x, w, p));
            let (y_ref, dx_ref, dw_ref) = values_and_grads(xwg, burn_conv(p));
            assert_eq!(y.len(), n * co * ho * wo, "case {i}");
            assert!(max_rel(&y, &y_ref) < 1e-5, "case {i}: forward");
            assert!(max_rel(&dx, &dx_ref) < 1e-5, "case {i}: grad x");
            assert!(max_rel(&dw, &dw_ref) < 1e-5, "case {i}: grad weight");
        }
    }

    #[test]
    fn matches_burn_on_ndarray() {
        check_against_burn(Device::ndarray().autodiff());
    }

    #[test]
    fn matches_burn_on_flex() {
        check_against_burn(Device::flex().autodiff());
    }

    /// Central finite differences of `sum(conv_t(x, w) * gw)` in float64 arithmetic
    /// computed from the float32 forward with a large step (the loss is linear in each input,
    /// so the difference quotient is exact up to rounding).
    #[test]
    fn finite_differences() {
        let device = Device::flex().autodiff();
        let p = ConvTParams {
            stride: [2, 2],
            padding: [1, 1],
        };
        let (n, ci, co, h, w, k) = (1, 2, 2, 3, 3, 4);
        let xs: Vec<f32> = (0..n * ci * h * w)
            .map(|i| ((i * 37 % 11) as f32 - 5.0) / 5.0)
            .collect();
        let ws: Vec<f32> = (0..ci * co * k * k)
            .map(|i| ((i * 53 % 13) as f32 - 6.0) / 6.0)
            .collect();
        let [ho, wo] = p.output_size([h, w], [k, k]).expect("valid");
        let gs: Vec<f32> = (0..n * co * ho * wo)
            .map(|i| ((i * 29 % 7) as f32 - 3.0) / 3.0)
            .collect();
        let loss = |xv: &[f32], wv: &[f32]| -> f64 {
            let x = Tensor::<4>::from_data(TensorData::new(xv.to_vec(), [n, ci, h, w]), &device);
            let wt = Tensor::<4>::from_data(TensorData::new(wv.to_vec(), [ci, co, k, k]), &device);
            let y = host(conv_transpose2d(x, wt, p));
            y.iter().zip(&gs).map(|(a, b)| *a as f64 * *b as f64).sum()
        };
        let x = Tensor::<4>::from_data(TensorData::new(xs.clone(), [n, ci, h, w]), &device)
            .require_grad();
        let wt = Tensor::<4>::from_data(TensorData::new(ws.clone(), [ci, co, k, k]), &device)
            .require_grad();
        let g = Tensor::<4>::from_data(TensorData::new(gs.clone(), [n, co, ho, wo]), &device);
        let grads = (conv_transpose2d(x.clone(), wt.clone(), p) * g)
            .sum()
            .backward();
        let dx = host(x.grad(&grads).expect("x grad"));
        let dw = host(wt.grad(&grads).expect("w grad"));
        let eps = 0.5f32;
        // Central differences of the loss in each input value (`which` 0: x, 1: the weight).
        for (which, analytic) in [(0, &dx), (1, &dw)] {
            for (i, g) in analytic.iter().enumerate() {
                let (mut a, mut b) = (xs.clone(), ws.clone());
                let (mut c, mut d) = (xs.clone(), ws.clone());
                if which == 0 {
                    a[i] += eps;
                    c[i] -= eps;
                } else {
                    b[i] += eps;
                    d[i] -= eps;
                }
                let fd = (loss(&a, &b) - loss(&c, &d)) / (2.0 * eps as f64);
                assert!(
                    (fd - *g as f64).abs() < 1e-4,
                    "input {which} [{i}]: {fd} vs {g}"
                );
            }
        }
    }

    /// The passes in blocks of every possible number of input rows (down to one, so that
    /// every block boundary falls between output rows that two blocks share) against burn's
    /// `conv_transpose2d` and its backward on ndarray, on every index map of [`CASES`]; the
    /// epilogue runs once per plane, after the last block.
    #[test]
    fn blocks_match_burn() {
        let device = Device::ndarray().autodiff();
        for (i, &(k, _, _, [h, w], n)) in CASES.iter().enumerate() {
            let (p, xwg, [_, co, ho, wo]) = case_tensors(i, 100 + i as u64, &device);
            let ci = xwg[0].dims()[1];
            let (y_ref, dx_ref, dw_ref) = values_and_grads(xwg.clone(), burn_conv(p));
            let [xs, ws, gs] = xwg.map(host);
            let d = Dims::new(&[n, ci, h, w], &[ci, co, k[0], k[1]], &p);
            let plane = ho * wo;
            for rows in 1..=h {
                // The epilogue adds 10 + the channel, so a plane it misses or visits twice shows.
                let y = host_forward_blocked(&xs, &ws, d, &p, rows, |c, o: &mut [f32]| {
                    o.iter_mut().for_each(|v| *v += 10.0 + c as f32)
                });
                let y: Vec<f32> = y
                    .iter()
                    .enumerate()
                    .map(|(j, v)| v - 10.0 - ((j / plane) % co) as f32)
                    .collect();
                assert!(max_rel(&y, &y_ref) < 1e-5, "case {i}, {rows} rows: forward");
                let (dx, dw) = host_backward_blocked(&xs, &ws, &gs, d, &p, rows);
                assert!(
                    max_rel(&dx, &dx_ref) < 1e-5,
                    "case {i}, {rows} rows: grad x"
                );
                assert!(
                    max_rel(&dw, &dw_ref) < 1e-5,
                    "case {i}, {rows} rows: grad weight"
                );
            }
        }
    }

    /// Blocks of [`COLUMN_BLOCK`] values: the `paper` decoders' last geometry layer (32 to 11
    /// channels, 256 to 512) in blocks of 5 input rows, its first (8 x 8) in one.
    #[test]
    fn rows_per_block() {
        let p = ConvTParams {
            stride: [2, 2],
            padding: [1, 1],
        };
        let d = |ci: usize, co: usize, h: usize| Dims::new(&[1, ci, h, h], &[ci, co, 4, 4], &p);
        assert_eq!(input_rows_per_block(d(32, 11, 256), COLUMN_BLOCK), 5);
        assert_eq!(input_rows_per_block(d(256, 256, 8), COLUMN_BLOCK), 8);
        assert_eq!(input_rows_per_block(d(3, 1, 4), 1), 1);
    }

    #[test]
    fn valid_inputs_cover_exactly_the_output() {
        for &(len, out, stride, pad, k) in &[
            (5usize, 10usize, 2usize, 1usize, 0usize),
            (5, 10, 2, 1, 3),
            (3, 7, 3, 2, 4),
            (1, 2, 2, 1, 0),
        ] {
            let (lo, hi) = valid_inputs(len, out, stride, pad, k);
            for i in 0..len {
                let o = (i * stride + k) as isize - pad as isize;
                let inside = o >= 0 && (o as usize) < out;
                assert_eq!(
                    inside,
                    (lo..hi).contains(&i),
                    "{len} {out} {stride} {pad} {k} {i}"
                );
            }
        }
    }

    #[test]
    fn output_size_rejects_empty_outputs() {
        let p = ConvTParams {
            stride: [1, 1],
            padding: [2, 2],
        };
        assert_eq!(p.output_size([1, 1], [3, 3]), None);
        assert_eq!(p.output_size([2, 2], [4, 4]), Some([1, 1]));
    }
}
