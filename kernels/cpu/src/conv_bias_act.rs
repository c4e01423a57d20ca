//! A convolution layer as one op: a convolution of either kind ([`crate::conv`]), its bias
//! (untied `[C, H, W]` or per channel `[C]`) and LeakyReLU (or none, for a decoder's last
//! layer), with one handwritten backward.
//!
//! Why: as two ops (the convolution, then [`crate::bias_act`]) the forward wrote every
//! output plane twice, once in the product (or scattered by `col2im`) and once more, after
//! all planes were done and out of cache, by the bias and activation pass, with a second
//! buffer, and the graph held two nodes. Here the bias and the activation are applied to
//! each plane right after the convolution wrote it, in the one buffer (the transposed kind in
//! the task that scatters the plane, the plain kind in a pass over each batch item's planes
//! right after its product), and the backward forms the masked gradient and the bias
//! gradient in one pass (as `bias_act` does) and hands it to the convolution's backward.
//!
//! - forward: `out = act(conv(x, W) + bias)`, `act(z) = max(z, slope·z)`;
//! - backward from the saved output: `dz = dout` where `out >= 0`, `slope · dout` elsewhere;
//!   `dbias` = `dz` summed over the batch (untied) or the batch and pixels (per channel);
//!   `dx`, `dW` = the convolution's backward of `dz`.
//!
//! Thread mapping (CPU): as the convolution's; the epilogue and `bias_act`'s backward over
//! output planes.
//!
//! Backends: flex and ndarray run both passes here; burn's cubecl backend (wgpu) composes
//! burn's convolution and its backward functions with `bias_act`'s composition of burn's
//! tensor ops (the trait's default bodies). The reference twin is burn's convolution of the
//! same kind, bias add and `leaky_relu` under burn's autodiff; the tests compare values and
//! all three gradients with it and check finite differences.

// burn-ndarray is deprecated in burn 0.22; the design keeps it alongside flex.
#![allow(deprecated)]

use burn::backend::autodiff::{Autodiff, checkpoint::strategy::CheckpointStrategy};
use burn::backend::tensor::FloatTensor;
use burn::backend::{
    AutodiffBackend, Backend, Cube, ExtensionType, TensorMetadata, backend_extension,
};
use burn::tensor::Tensor;

use crate::autodiff;
use crate::bias_act::{self, OutBias, epilogue_plane};
use crate::conv::{ConvPair, ConvParams};
use crate::host::{HostIo, floats};

/// A layer's three tensors: its input, weight and bias, or their gradients.
///
/// # Shapes
/// - `x`: [N, C_in, H, W]; `weight`: as [`ConvPair`]; `bias`: `[C_out]` or
///   [C_out, H_out, W_out]
#[derive(ExtensionType, Debug, Clone)]
pub struct ConvBias<B: Backend> {
    pub x: FloatTensor<B>,
    pub weight: FloatTensor<B>,
    pub bias: FloatTensor<B>,
}

/// Backends with the fused layer of this module.
#[backend_extension(NdArray, Flex, Cube, Autodiff)]
pub trait ConvBiasActBackend: Backend {
    /// `act(conv(x, weight) + bias)` (`act` LeakyReLU or the identity) →
    /// `[N, C_out, H_out, W_out]`. Default: burn's convolution of the kind, then
    /// `bias_act`'s composition of burn's ops.
    fn conv_bias_act(
        #[extension_type] l: ConvBias<Self>,
        p: ConvParams,
        act: bool,
    ) -> FloatTensor<Self> {
        let y = p.composed::<Self>(l.x, l.weight);
        bias_act::composed_forward::<Self>(OutBias { y, bias: l.bias }, act)
    }

    /// Backward from the layer's input, weight, output `out` and its gradient → the gradients
    /// of `x`, `weight` and the bias. Default: `bias_act`'s composition of burn's ops, then
    /// burn's backward functions of the convolution.
    fn conv_bias_act_backward(
        #[extension_type] xw: ConvBias<Self>,
        out: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        p: ConvParams,
        act: bool,
    ) -> ConvBias<Self> {
        let bias_shape = xw.bias.shape().to_vec();
        let dz = bias_act::composed_backward::<Self>(out, grad, act, bias_shape);
        let pair = ConvPair {
            x: xw.x,
            weight: xw.weight,
        };
        let g = p.composed_backward::<Self>(pair, dz.y);
        ConvBias {
            x: g.x,
            weight: g.weight,
            bias: dz.bias,
        }
    }
}

/// `act(conv(x, weight) + bias)` on any backend (see the module docs): LeakyReLU
/// ([`crate::constants::LEAKY_RELU_SLOPE`]) with `act`, the identity without.
///
/// # Shapes
/// - `x`: [N, C_in, H, W]; `weight`: as [`ConvPair`]
/// - `bias`: `[C_out]` or [C_out, H_out, W_out]
/// - returns [N, C_out, H_out, W_out]
///
/// # Panics
/// When the channel counts disagree, the convolution has no output or the bias matches
/// neither shape (the layers check their configuration when they are built).
pub fn conv_bias_act<const D: usize>(
    x: Tensor<4>,
    weight: Tensor<4>,
    bias: Tensor<D>,
    p: ConvParams,
    act: bool,
) -> Tensor<4> {
    let [co, ho, wo] = p.check("conv_bias_act", x.dims(), weight.dims());
    let ok = match bias.dims().as_slice() {
        [bc] => *bc == co,
        [bc, bh, bw] => [*bc, *bh, *bw] == [co, ho, wo],
        _ => false,
    };
    assert!(
        ok,
        "conv_bias_act: bias {:?} for an output [N, {co}, {ho}, {wo}]",
        bias.dims()
    );
    let l = ConvBias {
        x: x.into_dispatch(),
        weight: weight.into_dispatch(),
        bias: bias.into_dispatch(),
    };
    Tensor::from_dispatch(<burn::backend::Dispatch as ConvBiasActBackend>::conv_bias_act(l, p, act))
}

// ---------------------------------------------------------------------------------------------
// Host implementation.

impl<H: HostIo> ConvBiasActBackend for H {
    fn conv_bias_act(l: ConvBias<Self>, p: ConvParams, act: bool) -> FloatTensor<Self> {
        let device = l.x.device();
        let untied = l.bias.shape().to_vec().len() == 3;
        let d = p.dims(&l.x.shape().to_vec(), &l.weight.shape().to_vec());
        let bias = H::read(l.bias);
        let epilogue = |c: usize, plane: &mut [f32]| epilogue_plane(plane, &bias, c, untied, act);
        let out = p.host_forward_then(&H::read(l.x), &H::read(l.weight), d, Some(epilogue));
        floats::<H>(out, &p.shapes(&d).0, &device)
    }

    fn conv_bias_act_backward(
        xw: ConvBias<Self>,
        out: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        p: ConvParams,
        act: bool,
    ) -> ConvBias<Self> {
        let device = out.device();
        let bias_shape = xw.bias.shape().to_vec();
        let out_shape = out.shape().to_vec();
        let d = p.dims(&xw.x.shape().to_vec(), &xw.weight.shape().to_vec());
        // dz in place of the output gradient, and the bias gradient, in one pass.
        let mut dz = H::floats(grad);
        let db = bias_act::host_backward(
            &H::read(out),
            &mut dz,
            bias_act::dims(&out_shape, &bias_shape),
            act,
        );
        let (dx, dw) = p.host_backward(&H::read(xw.x), &H::read(xw.weight), &dz, d);
        ConvBias {
            x: floats::<H>(dx, &p.shapes(&d).1, &device),
            weight: floats::<H>(dw, &[d.ci, d.co, d.kh, d.kw], &device),
            bias: floats::<H>(db, &bias_shape, &device),
        }
    }
}

/// The GPU backend composes burn's ops (the trait's default bodies).
impl ConvBiasActBackend for Cube {}

// ---------------------------------------------------------------------------------------------
// Autodiff: the handwritten backward.

/// The saved input, weight, bias (for its shape), output, convolution and `act`.
type SavedState<B> = (ConvBias<B>, FloatTensor<B>, ConvParams, bool);

crate::backward_op!(
    ConvBiasActBackwardOp<3>: ConvBiasActBackend,
    SavedState<B>,
    |(xw, out, p, act), grad| {
        let g = B::conv_bias_act_backward(xw, out, grad, p, act);
        [g.x, g.weight, g.bias]
    }
);

impl<B: Backend + ConvBiasActBackend, C: CheckpointStrategy> ConvBiasActBackend for Autodiff<B, C> {
    fn conv_bias_act(l: ConvBias<Self>, p: ConvParams, act: bool) -> FloatTensor<Self> {
        let nodes = [l.x.node(), l.weight.node(), l.bias.node()];
        let inner = ConvBias {
            x: l.x.into_primitive(),
            weight: l.weight.into_primitive(),
            bias: l.bias.into_primitive(),
        };
        let run = |l| B::conv_bias_act(l, p, act);
        let keep = |l, out: &FloatTensor<B>| (l, out.clone(), p, act);
        autodiff::forward::<B, C, _, _, 3>(ConvBiasActBackwardOp, nodes, inner, run, keep)
    }

    fn conv_bias_act_backward(
        xw: ConvBias<Self>,
        out: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        p: ConvParams,
        act: bool,
    ) -> ConvBias<Self> {
        let inner = ConvBias {
            x: xw.x.into_primitive(),
            weight: xw.weight.into_primitive(),
            bias: xw.bias.into_primitive(),
        };
        let g =
            B::conv_bias_act_backward(inner, out.into_primitive(), grad.into_primitive(), p, act);
        ConvBias {
            x: Self::from_inner(g.x),
            weight: Self::from_inner(g.weight),
            bias: Self::from_inner(g.bias),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::check::on_cpu_backends;
    use crate::check::{
        check_finite_differences, compare_outputs, host, layer_output_and_gradients, pattern,
    };
    use crate::constants::LEAKY_RELU_SLOPE;
    use crate::conv::tests::{Case, case_tensors};
    use crate::conv::{ConvKind, conv};
    use burn::tensor::{Device, Distribution, TensorData};

    /// The reference twin: burn's convolution of the kind (through [`conv`]'s twin, burn's
    /// own, on the autodiff backend's default), bias add and `leaky_relu`.
    fn reference<const D: usize>(
        x: Tensor<4>,
        w: Tensor<4>,
        bias: Tensor<D>,
        p: ConvParams,
        act: bool,
    ) -> Tensor<4> {
        let y = match p.kind {
            ConvKind::Plain => burn::tensor::module::conv2d(
                x,
                w,
                None,
                burn::tensor::ops::ConvOptions::new(p.stride, p.padding, [1, 1], 1),
            ),
            ConvKind::Transposed => burn::tensor::module::conv_transpose2d(
                x,
                w,
                None,
                burn::tensor::ops::ConvTransposeOptions::new(
                    p.stride,
                    p.padding,
                    [0, 0],
                    [1, 1],
                    1,
                ),
            ),
        };
        let [_, c, h, wd] = y.dims();
        let b = if D == 1 {
            bias.reshape([1, c, 1, 1])
        } else {
            bias.reshape([1, c, h, wd])
        };
        let z = y + b;
        if act {
            burn::tensor::activation::leaky_relu(z, LEAKY_RELU_SLOPE)
        } else {
            z
        }
    }

    /// Plain: the appearance decoder's middle (3x3 s1 p1), the view encoder's layer (3x3 s2
    /// p1, an even side, so its last row is read only by border taps) and a map whose stride
    /// is larger than the kernel (input pixels no tap reads get a zero gradient). Transposed:
    /// the decoders' layer (k4 s2 p1) and two other index maps.
    const CASES: [(ConvKind, Case); 6] = [
        (ConvKind::Plain, ([3, 3], [1, 1], [1, 1], [5, 6], 2)),
        (ConvKind::Plain, ([3, 3], [2, 2], [1, 1], [8, 8], 1)),
        (ConvKind::Plain, ([2, 1], [3, 2], [0, 0], [8, 5], 2)),
        (ConvKind::Transposed, ([4, 4], [2, 2], [1, 1], [5, 6], 2)),
        (ConvKind::Transposed, ([3, 3], [1, 1], [1, 1], [4, 3], 1)),
        (ConvKind::Transposed, ([2, 1], [3, 2], [0, 0], [3, 2], 2)),
    ];

    /// [`CASES`] with both bias kinds, with and without the activation, against the
    /// reference twin.
    fn check_against_burn(device: Device) {
        for (i, (kind, case)) in CASES.into_iter().enumerate() {
            let (p, [x, wt, up], out) = case_tensors(kind, case, i as u64, &device);
            let [_, co, ho, wo] = out;
            let normal = Distribution::Normal(0.0, 1.0);
            let untied = Tensor::<3>::random([co, ho, wo], normal, &device);
            let per_channel = Tensor::<1>::random([co], normal, &device);
            for act in [false, true] {
                let what = format!("{kind:?} case {i}, act {act}");
                let ours = layer_output_and_gradients([&x, &wt], &untied, &up, |x, w, b| {
                    conv_bias_act(x, w, b, p, act)
                });
                let want = layer_output_and_gradients([&x, &wt], &untied, &up, |x, w, b| {
                    reference(x, w, b, p, act)
                });
                compare_outputs(&ours, &want, &format!("{what}, untied"));
                let ours = layer_output_and_gradients([&x, &wt], &per_channel, &up, |x, w, b| {
                    conv_bias_act(x, w, b, p, act)
                });
                let want = layer_output_and_gradients([&x, &wt], &per_channel, &up, |x, w, b| {
                    reference(x, w, b, p, act)
                });
                compare_outputs(&ours, &want, &format!("{what}, per channel"));
            }
        }
    }

    on_cpu_backends!(check_against_burn: matches_burn_on_flex, matches_burn_on_ndarray);

    /// Central finite differences of `sum(layer(x, w, b) · up)` with the activation, for all
    /// three inputs, on the view encoder's index map (3x3, stride 2, padding 1) and the
    /// decoders' (4x4, stride 2, padding 1). The pre-activations stay at least 0.05 from the
    /// kink (built and checked below), and a step of 1e-2 in one entry moves a
    /// pre-activation by at most 1e-2 (inputs and weights below 1 in magnitude where the
    /// kernel is large), so no step crosses it.
    #[test]
    fn finite_differences() {
        let device = Device::flex().autodiff();
        for (p, [h, w, k], scale) in [
            (ConvParams::plain([2, 2], [1, 1]), [4, 5, 3], [25.0, 30.0]),
            (
                ConvParams::transposed([2, 2], [1, 1]),
                [2, 3, 4],
                [5.0, 6.0],
            ),
        ] {
            let (n, ci, co) = (1, 2, 2);
            let wshape = match p.kind {
                ConvKind::Plain => [co, ci, k, k],
                ConvKind::Transposed => [ci, co, k, k],
            };
            let [ho, wo] = p.output_size([h, w], [k, k]).expect("valid");
            let xs: Vec<f32> = pattern(n * ci * h * w, 37, 11, scale[0]);
            let ws: Vec<f32> = pattern(co * ci * k * k, 53, 13, scale[1]);
            let ups: Vec<f32> = pattern(n * co * ho * wo, 29, 7, 3.0);
            let t4 = |v: &[f32], s: [usize; 4]| {
                Tensor::<4>::from_data(TensorData::new(v.to_vec(), s), &device)
            };
            let t3 = |v: &[f32]| {
                Tensor::<3>::from_data(TensorData::new(v.to_vec(), [co, ho, wo]), &device)
            };
            let layer = |xv: &[f32], wv: &[f32], bv: &[f32], act: bool| {
                host(conv_bias_act(
                    t4(xv, [n, ci, h, w]),
                    t4(wv, wshape),
                    t3(bv),
                    p,
                    act,
                ))
            };
            // An untied bias that puts every pre-activation at ±0.2 (alternating signs), so
            // both sides of the LeakyReLU are exercised and none is near the kink.
            let y = layer(&xs, &ws, &vec![0.0; co * ho * wo], false);
            let bs: Vec<f32> = y
                .iter()
                .enumerate()
                .map(|(i, y)| if i % 2 == 0 { 0.2 } else { -0.2 } - y)
                .collect();
            let pre = layer(&xs, &ws, &bs, false);
            let margin = pre.iter().fold(f32::INFINITY, |m, z| m.min(z.abs()));
            assert!(
                margin >= 0.05,
                "the inputs put a pre-activation {margin} from the kink"
            );
            let [_, dx, dw, db] = layer_output_and_gradients(
                [&t4(&xs, [n, ci, h, w]), &t4(&ws, wshape)],
                &t3(&bs),
                &t4(&ups, [n, co, ho, wo]),
                |x, w, b| conv_bias_act(x, w, b, p, true),
            );
            let loss = |out: Vec<f32>| -> f64 {
                out.iter()
                    .zip(&ups)
                    .map(|(a, b)| *a as f64 * *b as f64)
                    .sum()
            };
            check_finite_differences(
                [&xs, &ws],
                [&dx, &dw],
                |xv, wv| loss(layer(xv, wv, &bs, true)),
                1e-2,
                1e-3,
            );
            check_finite_differences(
                [&bs, &xs],
                [&db, &dx],
                |bv, xv| loss(layer(xv, &ws, bv, true)),
                1e-2,
                1e-3,
            );
            // The layer without bias and activation is the convolution op itself.
            let plain = host(conv(t4(&xs, [n, ci, h, w]), t4(&ws, wshape), p));
            assert_eq!(layer(&xs, &ws, &vec![0.0; co * ho * wo], false), plain);
        }
    }
}
