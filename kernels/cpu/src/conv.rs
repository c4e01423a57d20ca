//! 2D convolutions, plain and transposed (no bias, one group, dilation 1, no output
//! padding), as one burn backend extension with a handwritten backward.
//!
//! Why: burn-flex 0.22 evaluates a convolution's input gradient as a transposed convolution
//! through a direct per-pixel loop and the weight gradients through generic formulas (the
//! transposed convolution's is a convolution whose kernel is the whole input image), which
//! made the decoders' backward five times their forward, and burn-ndarray's own
//! `conv_transpose2d` is two orders of magnitude slower than the column formulation. Here
//! both kinds run the column formulation on this crate's `gemm` (the one burn-flex uses):
//! one index map ([`crate::conv_transpose`]'s `im2col` / `col2im`), read one way by the
//! transposed convolution and the other way by the plain one ([`crate::conv2d`]), since a
//! convolution is the adjoint of the transposed convolution with the same kernel, stride and
//! padding.
//!
//! Backends: flex and ndarray run both passes on host memory; burn's cubecl backend (wgpu)
//! keeps burn's `conv2d` / `conv_transpose2d` and their backward functions (the trait's
//! default bodies). The reference twin is burn's own convolution of the same kind; the tests
//! compare values and gradients with it on both CPU backends and check finite differences.
//!
//! The layers call this through [`crate::conv_bias_act`], which adds the bias and the
//! activation in the same pass; this op alone serves layers without a bias.

// burn-ndarray is deprecated in burn 0.22; the design keeps it alongside flex.
#![allow(deprecated)]

use burn::backend::autodiff::{Autodiff, checkpoint::strategy::CheckpointStrategy};
use burn::backend::tensor::FloatTensor;
use burn::backend::{
    AutodiffBackend, Backend, Cube, ExtensionType, TensorMetadata, backend_extension,
};
use burn::tensor::Tensor;
use burn::tensor::ops::{ConvOptions, ConvTransposeOptions};

use crate::autodiff;
use crate::conv_transpose::{Dims, IndexMap};
use crate::host::{HostIo, floats};
use crate::{conv_transpose, conv2d};

/// Which convolution, in PyTorch's weight layouts.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ConvKind {
    /// `conv2d`: weight `[C_out, C_in, k_h, k_w]`,
    /// `H_out = (H + 2·padding - k_h) / stride + 1`.
    Plain,
    /// `conv_transpose2d`: weight `[C_in, C_out, k_h, k_w]`,
    /// `H_out = (H - 1)·stride - 2·padding + k_h`.
    Transposed,
}

/// One convolution: its kind, stride and padding (likewise for the width).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct ConvParams {
    pub kind: ConvKind,
    /// Stride (height, width).
    pub stride: [usize; 2],
    /// Plain: zero padding added to each side of the input. Transposed: padding removed from
    /// each side of the full output.
    pub padding: [usize; 2],
}

impl ConvParams {
    /// A plain convolution.
    pub fn plain(stride: [usize; 2], padding: [usize; 2]) -> Self {
        let kind = ConvKind::Plain;
        Self {
            kind,
            stride,
            padding,
        }
    }

    /// A transposed convolution.
    pub fn transposed(stride: [usize; 2], padding: [usize; 2]) -> Self {
        let kind = ConvKind::Transposed;
        Self {
            kind,
            stride,
            padding,
        }
    }

    /// The output size for an input `[h, w]` and kernel `[kh, kw]`, or `None` where there is
    /// none: a plain kernel larger than the padded input or a zero stride, or a transposed
    /// convolution's padding that removes everything.
    pub fn output_size(&self, [h, w]: [usize; 2], [kh, kw]: [usize; 2]) -> Option<[usize; 2]> {
        let side = |i: usize, len: usize, k: usize| {
            let (s, pad) = (self.stride[i], self.padding[i]);
            match self.kind {
                ConvKind::Plain => (s > 0 && len > 0 && k > 0)
                    .then(|| (len + 2 * pad).checked_sub(k))
                    .flatten()
                    .map(|span| span / s + 1),
                ConvKind::Transposed => ((len.max(1) - 1) * s + k)
                    .checked_sub(2 * pad)
                    .filter(|&o| len > 0 && o > 0),
            }
        };
        Some([side(0, h, kh)?, side(1, w, kw)?])
    }

    /// The dimension of the weight `[_, _, k_h, k_w]` that indexes the output channels: 0
    /// for a plain convolution, 1 for a transposed one.
    pub fn out_dim(&self) -> usize {
        match self.kind {
            ConvKind::Plain => 0,
            ConvKind::Transposed => 1,
        }
    }

    /// The stride and padding as the shared index map takes them.
    pub(crate) fn map(&self) -> IndexMap {
        IndexMap {
            stride: self.stride,
            padding: self.padding,
        }
    }

    /// The index map's sizes for a convolution of `x` by `weight`.
    pub(crate) fn dims(&self, x: &[usize], weight: &[usize]) -> Dims {
        match self.kind {
            ConvKind::Plain => conv2d::dims(x, weight, self),
            ConvKind::Transposed => Dims::new(x, weight, self),
        }
    }

    /// The output's shape `[N, C_out, H_out, W_out]` and the input's `[N, C_in, H, W]` in
    /// the index map's names (the plain convolution runs the map the other way).
    pub(crate) fn shapes(&self, d: &Dims) -> ([usize; 4], [usize; 4]) {
        let (map_in, map_out) = ([d.n, d.ci, d.h, d.w], [d.n, d.co, d.ho, d.wo]);
        match self.kind {
            ConvKind::Plain => (map_in, map_out),
            ConvKind::Transposed => (map_out, map_in),
        }
    }

    /// The forward pass on host memory, then `epilogue(c, plane)` on every output plane of
    /// channel `c` while it is warm in cache.
    pub(crate) fn host_forward_then(
        &self,
        x: &[f32],
        weight: &[f32],
        d: Dims,
        epilogue: Option<impl Fn(usize, &mut [f32]) + Sync>,
    ) -> Vec<f32> {
        let m = self.map();
        match self.kind {
            ConvKind::Plain => conv2d::host_forward_then(x, weight, d, &m, epilogue),
            ConvKind::Transposed => {
                conv_transpose::host_forward_then(x, weight, d, &m, |c, plane| {
                    if let Some(f) = &epilogue {
                        f(c, plane)
                    }
                })
            }
        }
    }

    /// The backward pass on host memory → (dx, dweight), in the input's and the weight's
    /// layouts.
    pub(crate) fn host_backward(
        &self,
        x: &[f32],
        weight: &[f32],
        g: &[f32],
        d: Dims,
    ) -> (Vec<f32>, Vec<f32>) {
        let m = self.map();
        match self.kind {
            ConvKind::Plain => conv2d::host_backward(x, weight, g, d, &m),
            ConvKind::Transposed => conv_transpose::host_backward(x, weight, g, d, &m),
        }
    }

    fn options(&self) -> ConvOptions<2> {
        ConvOptions::new(self.stride, self.padding, [1, 1], 1)
    }

    fn options_t(&self) -> ConvTransposeOptions<2> {
        ConvTransposeOptions::new(self.stride, self.padding, [0, 0], [1, 1], 1)
    }

    /// burn's own convolution of this kind.
    pub(crate) fn composed<B: Backend>(
        &self,
        x: FloatTensor<B>,
        weight: FloatTensor<B>,
    ) -> FloatTensor<B> {
        match self.kind {
            ConvKind::Plain => B::conv2d(x, weight, None, self.options()),
            ConvKind::Transposed => B::conv_transpose2d(x, weight, None, self.options_t()),
        }
    }

    /// burn's own backward functions of this kind → the gradients of `x` and `weight`.
    pub(crate) fn composed_backward<B: Backend>(
        &self,
        ConvPair { x, weight }: ConvPair<B>,
        g: FloatTensor<B>,
    ) -> ConvPair<B> {
        let (dx, dw) = match self.kind {
            ConvKind::Plain => {
                let o = self.options();
                let dx = B::conv2d_x_backward(x.clone(), weight.clone(), g.clone(), o.clone());
                (dx, B::conv2d_weight_backward(x, weight, g, o))
            }
            ConvKind::Transposed => {
                let o = self.options_t();
                let dx = B::conv_transpose2d_x_backward(weight.clone(), g.clone(), o.clone());
                (dx, B::conv_transpose2d_weight_backward(x, weight, g, o))
            }
        };
        ConvPair { x: dx, weight: dw }
    }

    /// Checks the shapes of a call (`what` names it) and returns the output's `[C_out,
    /// H_out, W_out]`.
    ///
    /// # Panics
    /// When the channel counts disagree or the convolution has no output.
    pub(crate) fn check(&self, what: &str, x: [usize; 4], weight: [usize; 4]) -> [usize; 3] {
        let [_, ci, h, w] = x;
        let [_, _, kh, kw] = weight;
        let (wci, co) = (weight[1 - self.out_dim()], weight[self.out_dim()]);
        assert_eq!(ci, wci, "{what}: input channels {ci}, weight {wci}");
        let Some([ho, wo]) = self.output_size([h, w], [kh, kw]) else {
            panic!(
                "{what}: a {kh}x{kw} kernel with stride {:?} and padding {:?} has no output \
                 for a {h}x{w} input ({:?})",
                self.stride, self.padding, self.kind
            );
        };
        [co, ho, wo]
    }
}

/// A convolution's two tensors: its inputs, or their gradients.
///
/// # Shapes
/// - `x`: [N, C_in, H, W]; `weight`: [C_out, C_in, k_h, k_w] (plain) or [C_in, C_out, k_h,
///   k_w] (transposed)
#[derive(ExtensionType, Debug, Clone)]
pub struct ConvPair<B: Backend> {
    pub x: FloatTensor<B>,
    pub weight: FloatTensor<B>,
}

/// Backends with the convolutions of this module.
#[backend_extension(NdArray, Flex, Cube, Autodiff)]
pub trait ConvBackend: Backend {
    /// `xw.x` `[N, C_in, H, W]` by `xw.weight` → `[N, C_out, H_out, W_out]`. Default: the
    /// backend's own convolution of the kind.
    fn conv(#[extension_type] xw: ConvPair<Self>, p: ConvParams) -> FloatTensor<Self> {
        p.composed::<Self>(xw.x, xw.weight)
    }

    /// Backward: `grad_out` `[N, C_out, H_out, W_out]` → gradients of `x` and `weight`.
    /// Default: the backend's own backward functions of the kind.
    fn conv_backward(
        #[extension_type] xw: ConvPair<Self>,
        grad_out: FloatTensor<Self>,
        p: ConvParams,
    ) -> ConvPair<Self> {
        p.composed_backward::<Self>(xw, grad_out)
    }
}

/// The convolution of this module on any backend (see the module docs).
///
/// # Shapes
/// - `x`: [N, C_in, H, W]; `weight`: as [`ConvPair`]
/// - returns [N, C_out, H_out, W_out]
///
/// # Panics
/// When the channel counts disagree or the convolution has no output (the layers that call
/// this check their configuration when they are built).
pub fn conv(x: Tensor<4>, weight: Tensor<4>, p: ConvParams) -> Tensor<4> {
    p.check("conv", x.dims(), weight.dims());
    let xw = ConvPair {
        x: x.into_dispatch(),
        weight: weight.into_dispatch(),
    };
    Tensor::from_dispatch(<burn::backend::Dispatch as ConvBackend>::conv(xw, p))
}

impl<H: HostIo> ConvBackend for H {
    fn conv(ConvPair { x, weight }: ConvPair<Self>, p: ConvParams) -> FloatTensor<Self> {
        let device = x.device();
        let d = p.dims(&x.shape().to_vec(), &weight.shape().to_vec());
        let none = None::<fn(usize, &mut [f32])>;
        let out = p.host_forward_then(&H::read(x), &H::read(weight), d, none);
        floats::<H>(out, &p.shapes(&d).0, &device)
    }

    fn conv_backward(
        ConvPair { x, weight }: ConvPair<Self>,
        grad_out: FloatTensor<Self>,
        p: ConvParams,
    ) -> ConvPair<Self> {
        let device = x.device();
        let d = p.dims(&x.shape().to_vec(), &weight.shape().to_vec());
        let g = H::read(grad_out);
        let (dx, dw) = p.host_backward(&H::read(x), &H::read(weight), &g, d);
        ConvPair {
            x: floats::<H>(dx, &p.shapes(&d).1, &device),
            weight: floats::<H>(dw, &[d.ci, d.co, d.kh, d.kw], &device),
        }
    }
}

/// The GPU backend keeps burn's CubeCL passes.
impl ConvBackend for Cube {}

// ---------------------------------------------------------------------------------------------
// Autodiff: the handwritten backward.

crate::backward_op!(
    ConvBackwardOp<2>: ConvBackend,
    (ConvPair<B>, ConvParams),
    |(xw, p), g| {
        let g = B::conv_backward(xw, g, p);
        [g.x, g.weight]
    }
);

impl<B: Backend + ConvBackend, C: CheckpointStrategy> ConvBackend for Autodiff<B, C> {
    fn conv(ConvPair { x, weight }: ConvPair<Self>, p: ConvParams) -> FloatTensor<Self> {
        let nodes = [x.node(), weight.node()];
        let inner = ConvPair {
            x: x.into_primitive(),
            weight: weight.into_primitive(),
        };
        let run = |xw| B::conv(xw, p);
        autodiff::forward::<B, C, _, _, 2>(ConvBackwardOp, nodes, inner, run, |xw, _| (xw, p))
    }

    fn conv_backward(
        xw: ConvPair<Self>,
        grad_out: FloatTensor<Self>,
        p: ConvParams,
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
pub(crate) mod tests {
    use super::*;
    use crate::check::on_cpu_backends;
    use crate::check::{check_finite_differences, host, max_rel, output_and_gradients, pattern};
    use burn::tensor::{Device, Distribution, TensorData};

    /// Kernel, stride, padding, input size, batch.
    pub(crate) type Case = ([usize; 2], [usize; 2], [usize; 2], [usize; 2], usize);

    /// Index-map cases of the plain convolution.
    const PLAIN: [Case; 7] = [
        ([3, 3], [1, 1], [1, 1], [5, 6], 2), // the appearance decoder's middle
        ([3, 3], [2, 2], [1, 1], [8, 8], 1), // the view encoder: the last row is read
        ([3, 3], [2, 2], [1, 1], [7, 9], 2), // odd sides
        ([3, 2], [2, 3], [0, 1], [5, 7], 1),
        ([1, 1], [1, 1], [0, 0], [2, 2], 3),
        ([5, 5], [3, 2], [2, 1], [4, 5], 1),
        // A stride larger than the kernel: input pixels that no tap reads get zero gradient.
        ([2, 1], [3, 2], [0, 0], [8, 5], 2),
    ];

    /// Index-map cases of the transposed convolution.
    pub(crate) const TRANSPOSED: [Case; 7] = [
        ([4, 4], [2, 2], [1, 1], [5, 6], 2), // the decoders' layer
        ([3, 3], [1, 1], [1, 1], [4, 3], 1),
        ([3, 2], [2, 3], [0, 1], [3, 4], 1),
        ([1, 1], [1, 1], [0, 0], [2, 2], 3),
        ([5, 5], [3, 2], [2, 1], [2, 3], 1),
        ([4, 4], [2, 2], [1, 1], [1, 1], 1),
        // Kernels smaller than the stride: output pixels that no tap reaches stay zero.
        ([2, 1], [3, 2], [0, 0], [3, 2], 2),
    ];

    /// The parameters of `case` of `kind`, and the shapes of its weight (3 input and 2
    /// output channels) and output.
    pub(crate) fn case_shapes(
        kind: ConvKind,
        (k, stride, padding, [h, w], n): Case,
    ) -> (ConvParams, [usize; 4], [usize; 4]) {
        let p = ConvParams {
            kind,
            stride,
            padding,
        };
        let (ci, co) = (3, 2);
        let weight = match kind {
            ConvKind::Plain => [co, ci, k[0], k[1]],
            ConvKind::Transposed => [ci, co, k[0], k[1]],
        };
        let [ho, wo] = p.output_size([h, w], k).expect("valid case");
        (p, weight, [n, co, ho, wo])
    }

    /// `case` of `kind` with random input, weight and output gradient on `device`, seeded
    /// with `seed`: its parameters, the three tensors and the output's shape.
    pub(crate) fn case_tensors(
        kind: ConvKind,
        case: Case,
        seed: u64,
        device: &Device,
    ) -> (ConvParams, [Tensor<4>; 3], [usize; 4]) {
        let (p, wshape, out) = case_shapes(kind, case);
        let (_, _, _, [h, w], n) = case;
        device.seed(seed);
        let normal = Distribution::Normal(0.0, 1.0);
        let x = Tensor::<4>::random([n, 3, h, w], normal, device);
        let wt = Tensor::<4>::random(wshape, normal, device);
        let up = Tensor::<4>::random(out, normal, device);
        (p, [x, wt, up], out)
    }

    /// Values and gradients against burn's own convolution of each kind (the reference
    /// twin).
    fn check_against_burn(device: Device) {
        let cases = PLAIN.map(|c| (ConvKind::Plain, c));
        for (i, (kind, case)) in cases
            .into_iter()
            .chain(TRANSPOSED.map(|c| (ConvKind::Transposed, c)))
            .enumerate()
        {
            let (p, [x, wt, up], out) = case_tensors(kind, case, i as u64, &device);
            let ours = output_and_gradients(&x, &wt, &up, |x, w| conv(x, w, p));
            let reference = output_and_gradients(&x, &wt, &up, |x, w| match kind {
                ConvKind::Plain => burn::tensor::module::conv2d(x, w, None, p.options()),
                ConvKind::Transposed => {
                    burn::tensor::module::conv_transpose2d(x, w, None, p.options_t())
                }
            });
            assert_eq!(ours[0].len(), out.iter().product::<usize>(), "case {i}");
            for (what, a, b) in [
                ("forward", &ours[0], &reference[0]),
                ("grad x", &ours[1], &reference[1]),
                ("grad weight", &ours[2], &reference[2]),
            ] {
                let e = max_rel(a, b, 1e-3);
                assert!(e < 1e-5, "{kind:?} case {i}: {what} differs by {e}");
            }
        }
    }

    on_cpu_backends!(check_against_burn: matches_burn_on_flex, matches_burn_on_ndarray);

    /// Central finite differences of `sum(conv(x, w) * up)` for each kind: the view
    /// encoder's map (3x3, stride 2, padding 1) on an even side, so the last row and column
    /// are read only by the border taps, and the decoders' (4x4, stride 2, padding 1). The
    /// loss is linear in each input, so a large step is exact up to rounding.
    #[test]
    fn finite_differences() {
        let device = Device::flex().autodiff();
        for (p, k, [h, w]) in [
            (ConvParams::plain([2, 2], [1, 1]), 3, [4, 4]),
            (ConvParams::transposed([2, 2], [1, 1]), 4, [3, 3]),
        ] {
            let (n, ci, co) = (1, 2, 2);
            let wshape = match p.kind {
                ConvKind::Plain => [co, ci, k, k],
                ConvKind::Transposed => [ci, co, k, k],
            };
            let xs: Vec<f32> = pattern(n * ci * h * w, 37, 11, 5.0);
            let ws: Vec<f32> = pattern(co * ci * k * k, 53, 13, 6.0);
            let [ho, wo] = p.output_size([h, w], [k, k]).expect("valid");
            let ups: Vec<f32> = pattern(n * co * ho * wo, 29, 7, 3.0);
            let tensor = |v: &[f32], shape: [usize; 4]| {
                Tensor::<4>::from_data(TensorData::new(v.to_vec(), shape), &device)
            };
            let up = tensor(&ups, [n, co, ho, wo]);
            let [_, dx, dw] = output_and_gradients(
                &tensor(&xs, [n, ci, h, w]),
                &tensor(&ws, wshape),
                &up,
                |x, w| conv(x, w, p),
            );
            let loss = |xv: &[f32], wv: &[f32]| -> f64 {
                let y = host(conv(tensor(xv, [n, ci, h, w]), tensor(wv, wshape), p));
                y.iter().zip(&ups).map(|(a, b)| *a as f64 * *b as f64).sum()
            };
            check_finite_differences([&xs, &ws], [&dx, &dw], loss, 0.5, 1e-4);
        }
    }

    /// burn's (and PyTorch's) output sizes: `floor((H + 2p - k) / s) + 1` for the plain
    /// kind and `None` where the kernel does not fit; `(H - 1)·s - 2p + k` for the
    /// transposed kind and `None` where the padding removes everything.
    #[test]
    fn output_sizes() {
        let p = ConvParams::plain([2, 2], [1, 1]);
        assert_eq!(p.output_size([128, 128], [3, 3]), Some([64, 64]));
        assert_eq!(p.output_size([7, 9], [3, 3]), Some([4, 5]));
        let tight = ConvParams::plain([1, 1], [0, 0]);
        assert_eq!(tight.output_size([2, 2], [3, 3]), None);
        assert_eq!(tight.output_size([3, 3], [3, 3]), Some([1, 1]));
        let t = ConvParams::transposed([1, 1], [2, 2]);
        assert_eq!(t.output_size([1, 1], [3, 3]), None);
        assert_eq!(t.output_size([2, 2], [4, 4]), Some([1, 1]));
        let up = ConvParams::transposed([2, 2], [1, 1]);
        assert_eq!(up.output_size([8, 8], [4, 4]), Some([16, 16]));
    }
}
