//! 2D convolution (no bias, one group, dilation 1) as a burn backend extension, with a
//! handwritten backward: the 3x3 convolutions of the view encoder and of the appearance
//! decoder's middle.
//!
//! Why: burn-flex 0.22 evaluates a convolution's input gradient as a transposed convolution
//! through a direct per-pixel loop (`conv_transpose3d_impl`, a visible share of the `cpu`
//! decoders' time) and its weight gradient through burn's generic formula. Here all three
//! products are the column formulation on this crate's `gemm` (the one burn-flex uses):
//!
//! - forward, per batch item: `col = im2col(X)` ([C_in·k_h·k_w, H_out·W_out]), then
//!   `Y = W · col` ([C_out, H_out·W_out]);
//! - backward: `dW += dY · colᵀ` (the column matrix gathered again rather than kept), and
//!   `dcol = Wᵀ · dY`, scatter-added back to the input planes (`col2im`).
//!
//! This is [`super::conv_transpose`]'s index map read the other way: a convolution is the
//! adjoint of the transposed convolution with the same kernel, stride and padding, so the
//! gather and scatter are that module's `im2col` and `col2im_plane`, with the convolution's
//! output on the map's input side and its input on the map's output side. The input's size is
//! given rather than derived, so an input row or column that no output reads (when
//! `H + 2·padding - k_h` is not a multiple of the stride) gets a zero gradient.
//!
//! Thread mapping (CPU): the products run on rayon through `gemm`; `im2col` is parallel over
//! the rows of `col`; `col2im` over input channels (one task per input plane, so no two tasks
//! write one pixel).
//!
//! Backends: flex and ndarray run both passes here on host memory; burn's cubecl backend
//! (wgpu) keeps burn's `conv2d` and its backward functions (the trait's default bodies). The
//! reference twin is burn's `conv2d` itself; the tests compare values and gradients with it
//! on both CPU backends and check finite differences.

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
    AutodiffBackend, Backend, Cube, ExtensionType, TensorMetadata, backend_extension,
};
use burn::tensor::Tensor;
use burn::tensor::ops::ConvOptions;
use rayon::prelude::*;

use super::conv_transpose::{ConvTParams, Dims, col2im_plane, im2col, with_columns};
use crate::constants::planes_per_task;
use crate::gemm::{GradientSum, matmul, matmul_uninit};
use crate::host::{HostIo, floats};

/// Stride and padding of a convolution (dilation 1, one group):
/// `H_out = (H + 2·padding - k_h) / stride + 1`, likewise for the width.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Conv2dParams {
    /// Stride (height, width).
    pub stride: [usize; 2],
    /// Zero padding added to each side of the input (height, width).
    pub padding: [usize; 2],
}

impl Conv2dParams {
    pub(super) fn options(&self) -> ConvOptions<2> {
        ConvOptions::new(self.stride, self.padding, [1, 1], 1)
    }

    /// The same stride and padding for the shared index map.
    pub(super) fn map(&self) -> ConvTParams {
        ConvTParams {
            stride: self.stride,
            padding: self.padding,
        }
    }

    /// The output size for an input `[h, w]` and kernel `[kh, kw]`, or `None` when the
    /// padded input is smaller than the kernel or a stride is zero.
    pub fn output_size(&self, [h, w]: [usize; 2], [kh, kw]: [usize; 2]) -> Option<[usize; 2]> {
        let side = |len: usize, pad: usize, k: usize, s: usize| {
            (s > 0 && len > 0 && k > 0)
                .then(|| (len + 2 * pad).checked_sub(k))
                .flatten()
                .map(|span| span / s + 1)
        };
        Some([
            side(h, self.padding[0], kh, self.stride[0])?,
            side(w, self.padding[1], kw, self.stride[1])?,
        ])
    }
}

/// A convolution's two tensors: its inputs, or their gradients.
///
/// # Shapes
/// - `x`: [N, C_in, H, W]; `weight`: [C_out, C_in, k_h, k_w]
#[derive(ExtensionType, Debug, Clone)]
pub struct ConvPair<B: Backend> {
    pub x: FloatTensor<B>,
    pub weight: FloatTensor<B>,
}

/// Backends with the convolution of this module.
#[backend_extension(NdArray, Flex, Cube, Autodiff)]
pub trait Conv2dBackend: Backend {
    /// `xw.x` `[N, C_in, H, W]`, `xw.weight` `[C_out, C_in, k_h, k_w]` (PyTorch's layout) →
    /// `[N, C_out, H_out, W_out]`. Default: the backend's own `conv2d`.
    fn conv(#[extension_type] xw: ConvPair<Self>, p: Conv2dParams) -> FloatTensor<Self> {
        use burn::backend::ops::ModuleOps;
        <Self as ModuleOps<Self>>::conv2d(xw.x, xw.weight, None, p.options())
    }

    /// Backward: `grad_out` `[N, C_out, H_out, W_out]` → gradients of `x` and `weight`.
    /// Default: the backend's own input and weight backward passes.
    fn conv_backward(
        #[extension_type] xw: ConvPair<Self>,
        grad_out: FloatTensor<Self>,
        p: Conv2dParams,
    ) -> ConvPair<Self> {
        use burn::backend::ops::ModuleOps;
        let ConvPair { x, weight } = xw;
        let o = p.options();
        ConvPair {
            x: <Self as ModuleOps<Self>>::conv2d_x_backward(
                x.clone(),
                weight.clone(),
                grad_out.clone(),
                o.clone(),
            ),
            weight: <Self as ModuleOps<Self>>::conv2d_weight_backward(x, weight, grad_out, o),
        }
    }
}

/// The convolution of this module on any backend (see the module docs).
///
/// # Shapes
/// - `x`: [N, C_in, H, W]; `weight`: [C_out, C_in, k_h, k_w]
/// - returns [N, C_out, H_out, W_out]
///
/// # Panics
/// When the channel counts disagree or the kernel does not fit the padded input (the layers
/// that call this check their configuration when they are built).
pub fn conv2d(x: Tensor<4>, weight: Tensor<4>, p: Conv2dParams) -> Tensor<4> {
    let [_, ci, h, w] = x.dims();
    let [_, wci, kh, kw] = weight.dims();
    assert_eq!(ci, wci, "conv2d: input channels {ci}, weight {wci}");
    assert!(
        p.output_size([h, w], [kh, kw]).is_some(),
        "conv2d: a {kh}x{kw} kernel with stride {:?} and padding {:?} does not fit a {h}x{w} input",
        p.stride,
        p.padding
    );
    let xw = ConvPair {
        x: x.into_dispatch(),
        weight: weight.into_dispatch(),
    };
    Tensor::from_dispatch(<burn::backend::Dispatch as Conv2dBackend>::conv(xw, p))
}

// ---------------------------------------------------------------------------------------------
// Host implementation.

/// The shared index map's sizes for a convolution of `x` by `weight`: the convolution's
/// output takes the map's input side (`ci` = C_out, `h x w` = H_out x W_out), its input the
/// map's output side (`co` = C_in, `ho x wo` = H x W).
pub(super) fn dims(x: &[usize], weight: &[usize], p: &Conv2dParams) -> Dims {
    let [n, ci, h, w] = [x[0], x[1], x[2], x[3]];
    let [co, kh, kw] = [weight[0], weight[2], weight[3]];
    let [ho, wo] = p.output_size([h, w], [kh, kw]).unwrap_or([0, 0]);
    Dims {
        n,
        ci: co,
        co: ci,
        h: ho,
        w: wo,
        kh,
        kw,
        ho: h,
        wo: w,
    }
}

/// Forward on host memory: `x` [N, C_in, H, W], `weight` [C_out, C_in·k_h·k_w] → [N, C_out,
/// H_out, W_out]. In the map's names: C_out = `d.ci`, C_in = `d.co`, the output plane
/// `d.p()`, the input plane `d.ho · d.wo`.
fn host_forward(x: &[f32], weight: &[f32], d: Dims, p: &ConvTParams) -> Vec<f32> {
    host_forward_then(x, weight, d, p, None::<fn(usize, &mut [f32])>)
}

/// [`host_forward`], then `epilogue(c, plane)` on every output plane of channel `c` of a
/// batch item right after that item's product wrote it (parallel over the planes), while
/// the item's output is still warm in cache.
///
/// The epilogue is an `Option`, unlike `conv_transpose::host_forward_then`'s closure: here
/// it is a parallel pass of its own after the product, which `None` skips, while the
/// transposed convolution runs its epilogue inside the task that builds each plane, where an
/// empty closure costs nothing.
pub(super) fn host_forward_then(
    x: &[f32],
    weight: &[f32],
    d: Dims,
    p: &ConvTParams,
    epilogue: Option<impl Fn(usize, &mut [f32]) + Sync>,
) -> Vec<f32> {
    let (pp, q, plane) = (d.p(), d.q(), d.ho * d.wo);
    let mut out = Vec::with_capacity(d.n * d.ci * pp);
    with_columns(q * pp, |col| {
        for b in 0..d.n {
            im2col(&x[b * d.co * plane..(b + 1) * d.co * plane], col, d, p);
            // Y [C_out, P] = W [C_out, q] · col [q, P]
            let ob = &mut out.spare_capacity_mut()[b * d.ci * pp..(b + 1) * d.ci * pp];
            matmul_uninit([d.ci, pp, q], ob, weight, [q, 1], col, [pp, 1]);
            if let (Some(f), true) = (&epilogue, pp > 0) {
                // SAFETY: `matmul_uninit` just wrote all `C_out·P` values of `ob`, and
                // `MaybeUninit<f32>` has `f32`'s layout.
                let ob = unsafe { &mut *(ob as *mut [std::mem::MaybeUninit<f32>] as *mut [f32]) };
                ob.par_chunks_mut(pp)
                    .enumerate()
                    .with_min_len(planes_per_task(pp))
                    .for_each(|(c, o)| f(c, o));
            }
        }
    });
    // SAFETY: `matmul_uninit` wrote the `C_out·P` values of every batch item.
    unsafe { out.set_len(d.n * d.ci * pp) };
    out
}

/// Backward on host memory → (dx [N, C_in, H, W], dweight [C_out, C_in, k_h, k_w]).
pub(super) fn host_backward(
    x: &[f32],
    weight: &[f32],
    g: &[f32],
    d: Dims,
    p: &ConvTParams,
) -> (Vec<f32>, Vec<f32>) {
    let (pp, q, plane) = (d.p(), d.q(), d.ho * d.wo);
    let mut dx = vec![0.0f32; d.n * d.co * plane];
    let mut dw = GradientSum::new(d.ci, q, d.n * d.p());
    with_columns(q * pp, |col| {
        for b in 0..d.n {
            let gb = &g[b * d.ci * pp..(b + 1) * d.ci * pp];
            im2col(&x[b * d.co * plane..(b + 1) * d.co * plane], col, d, p);
            // dW [C_out, q] += dY [C_out, P] · colᵀ [P, q]
            dw.add(pp, gb, pp, col, pp);
            // dcol [q, P] = Wᵀ [q, C_out] · dY [C_out, P], into the column buffer (read
            // above).
            matmul(
                [q, pp, d.ci],
                col,
                [pp, 1],
                false,
                weight,
                [1, q],
                gb,
                [pp, 1],
            );
            dx[b * d.co * plane..(b + 1) * d.co * plane]
                .par_chunks_mut(plane)
                .enumerate()
                .with_min_len(planes_per_task(plane))
                .for_each(|(c, o)| col2im_plane(col, o, c, d, p));
        }
    });
    (dx, dw.into_row_major())
}

impl<H: HostIo> Conv2dBackend for H {
    fn conv(ConvPair { x, weight }: ConvPair<Self>, p: Conv2dParams) -> FloatTensor<Self> {
        let device = x.device();
        let d = dims(&x.shape().to_vec(), &weight.shape().to_vec(), &p);
        let out = host_forward(&H::read(x), &H::read(weight), d, &p.map());
        floats::<H>(out, &[d.n, d.ci, d.h, d.w], &device)
    }

    fn conv_backward(
        ConvPair { x, weight }: ConvPair<Self>,
        grad_out: FloatTensor<Self>,
        p: Conv2dParams,
    ) -> ConvPair<Self> {
        let device = x.device();
        let d = dims(&x.shape().to_vec(), &weight.shape().to_vec(), &p);
        let (dx, dw) = host_backward(
            &H::read(x),
            &H::read(weight),
            &H::read(grad_out),
            d,
            &p.map(),
        );
        ConvPair {
            x: floats::<H>(dx, &[d.n, d.co, d.ho, d.wo], &device),
            weight: floats::<H>(dw, &[d.ci, d.co, d.kh, d.kw], &device),
        }
    }
}

/// The GPU backend keeps burn's CubeCL passes.
impl Conv2dBackend for Cube {}

// ---------------------------------------------------------------------------------------------
// Autodiff: the handwritten backward.

#[derive(Debug)]
struct ConvBackwardOp;

impl<B: Backend + Conv2dBackend> Backward<B, 2> for ConvBackwardOp {
    type State = (FloatTensor<B>, FloatTensor<B>, Conv2dParams);

    fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, _: &mut Checkpointer) {
        let grad_out = grads.consume::<B>(&ops.node);
        let (x, weight, p) = ops.state;
        let g = B::conv_backward(ConvPair { x, weight }, grad_out, p);
        let [x_node, weight_node] = ops.parents;
        for (node, grad) in [(x_node, g.x), (weight_node, g.weight)] {
            if let Some(node) = node {
                grads.register::<B>(node.id, grad);
            }
        }
    }
}

impl<B: Backend + Conv2dBackend, C: CheckpointStrategy> Conv2dBackend for Autodiff<B, C> {
    fn conv(ConvPair { x, weight }: ConvPair<Self>, p: Conv2dParams) -> FloatTensor<Self> {
        let nodes = [x.node(), weight.node()];
        let inner = ConvPair {
            x: x.into_primitive(),
            weight: weight.into_primitive(),
        };
        match ConvBackwardOp
            .prepare::<C>(nodes)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                let out = B::conv(inner.clone(), p);
                prep.finish((inner.x, inner.weight, p), out)
            }
            OpsKind::UnTracked(prep) => prep.finish(B::conv(inner, p)),
        }
    }

    fn conv_backward(
        xw: ConvPair<Self>,
        grad_out: FloatTensor<Self>,
        p: Conv2dParams,
    ) -> ConvPair<Self> {
        let inner = ConvPair {
            x: xw.x.into_primitive(),
            weight: xw.weight.into_primitive(),
        };
        let g = B::conv_backward(inner, grad_out.into_primitive(), p);
        ConvPair {
            x: Self::from_inner(g.x),
            weight: Self::from_inner(g.weight),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::check::{check_finite_differences, host, max_rel, output_and_gradients};
    use burn::tensor::{Device, Distribution, TensorData};

    /// Kernel, stride, padding, input size, batch.
    type Case = ([usize; 2], [usize; 2], [usize; 2], [usize; 2], usize);

    /// Index-map cases.
    const CASES: [Case; 7] = [
        ([3, 3], [1, 1], [1, 1], [5, 6], 2), // the appearance decoder's middle
        ([3, 3], [2, 2], [1, 1], [8, 8], 1), // the view encoder: the last row is read
        ([3, 3], [2, 2], [1, 1], [7, 9], 2), // odd sides
        ([3, 2], [2, 3], [0, 1], [5, 7], 1),
        ([1, 1], [1, 1], [0, 0], [2, 2], 3),
        ([5, 5], [3, 2], [2, 1], [4, 5], 1),
        // A stride larger than the kernel: input pixels that no tap reads get zero gradient.
        ([2, 1], [3, 2], [0, 0], [8, 5], 2),
    ];

    /// Values and gradients against burn's `conv2d` (the reference twin).
    fn check_against_burn(device: Device) {
        for (i, &(k, stride, padding, [h, w], n)) in CASES.iter().enumerate() {
            let (ci, co) = (3, 2);
            let p = Conv2dParams { stride, padding };
            device.seed(i as u64);
            let normal = Distribution::Normal(0.0, 1.0);
            let x = Tensor::<4>::random([n, ci, h, w], normal, &device);
            let wt = Tensor::<4>::random([co, ci, k[0], k[1]], normal, &device);
            let [ho, wo] = p.output_size([h, w], k).expect("valid case");
            let up = Tensor::<4>::random([n, co, ho, wo], normal, &device);
            let ours = output_and_gradients(&x, &wt, &up, |x, w| conv2d(x, w, p));
            let reference = output_and_gradients(&x, &wt, &up, |x, w| {
                burn::tensor::module::conv2d(x, w, None, p.options())
            });
            assert_eq!(ours[0].len(), n * co * ho * wo, "case {i}");
            for (what, a, b) in [
                ("forward", &ours[0], &reference[0]),
                ("grad x", &ours[1], &reference[1]),
                ("grad weight", &ours[2], &reference[2]),
            ] {
                let e = max_rel(a, b, 1e-3);
                assert!(e < 1e-5, "case {i}: {what} differs by {e}");
            }
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

    /// Central finite differences of `sum(conv2d(x, w) * up)`, the view encoder's shape
    /// (3x3, stride 2, padding 1) on an even side, so the last row and column are read
    /// only by the border taps. The loss is linear in each input, so a large step is exact up
    /// to rounding.
    #[test]
    fn finite_differences() {
        let device = Device::flex().autodiff();
        let p = Conv2dParams {
            stride: [2, 2],
            padding: [1, 1],
        };
        let (n, ci, co, h, w, k) = (1, 2, 2, 4, 4, 3);
        let xs: Vec<f32> = (0..n * ci * h * w)
            .map(|i| ((i * 37 % 11) as f32 - 5.0) / 5.0)
            .collect();
        let ws: Vec<f32> = (0..co * ci * k * k)
            .map(|i| ((i * 53 % 13) as f32 - 6.0) / 6.0)
            .collect();
        let [ho, wo] = p.output_size([h, w], [k, k]).expect("valid");
        let ups: Vec<f32> = (0..n * co * ho * wo)
            .map(|i| ((i * 29 % 7) as f32 - 3.0) / 3.0)
            .collect();
        let tensor = |v: &[f32], shape: [usize; 4]| {
            Tensor::<4>::from_data(TensorData::new(v.to_vec(), shape), &device)
        };
        let up = tensor(&ups, [n, co, ho, wo]);
        let [_, dx, dw] = output_and_gradients(
            &tensor(&xs, [n, ci, h, w]),
            &tensor(&ws, [co, ci, k, k]),
            &up,
            |x, w| conv2d(x, w, p),
        );
        let loss = |xv: &[f32], wv: &[f32]| -> f64 {
            let y = host(conv2d(
                tensor(xv, [n, ci, h, w]),
                tensor(wv, [co, ci, k, k]),
                p,
            ));
            y.iter().zip(&ups).map(|(a, b)| *a as f64 * *b as f64).sum()
        };
        check_finite_differences([&xs, &ws], [&dx, &dw], loss, 0.5, 1e-4);
    }

    /// burn's (and PyTorch's) output size, `floor((H + 2p - k) / s) + 1`, and `None` where
    /// the kernel does not fit.
    #[test]
    fn output_size_floors_and_rejects() {
        let p = Conv2dParams {
            stride: [2, 2],
            padding: [1, 1],
        };
        assert_eq!(p.output_size([128, 128], [3, 3]), Some([64, 64]));
        assert_eq!(p.output_size([7, 9], [3, 3]), Some([4, 5]));
        let tight = Conv2dParams {
            stride: [1, 1],
            padding: [0, 0],
        };
        assert_eq!(tight.output_size([2, 2], [3, 3]), None);
        assert_eq!(tight.output_size([3, 3], [3, 3]), Some([1, 1]));
    }
}
