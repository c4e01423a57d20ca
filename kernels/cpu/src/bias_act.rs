//! A convolution's epilogue as one op: `leaky_relu(y + bias)` (or `y + bias` for a layer
//! without activation), with a handwritten backward. The bias is per channel `[C]` or untied
//! `[C, H, W]` (one value per output pixel, the decoders' transposed convolutions).
//!
//! Why: burn's autodiff runs the bias add, its broadcast-reducing backward, the LeakyReLU
//! (`mask_where`) and its backward as separate passes over the decoders' feature maps (up to
//! 512 x 512 x C floats each) with a fresh buffer per pass; those passes took more time than
//! the decoders' matrix products on the CPU. Here the forward is one pass, and the backward
//! is one pass that forms the masked gradient and reduces the bias gradient at once.
//!
//! - forward: `out = z` where `z >= 0`, `slope · z` elsewhere, `z = y + bias`
//!   ([`LEAKY_RELU_SLOPE`]; burn's `leaky_relu` keeps `z` where it is not negative);
//! - backward from the saved output (`z >= 0` exactly where `out >= 0`, as `slope > 0`):
//!   `dz = dout` where `out >= 0`, `slope · dout` elsewhere; `dy = dz`; `dbias` = `dz`
//!   summed over the batch (untied) or over the batch and the pixels (per channel).
//!
//! Thread mapping (CPU): parallel over (batch item, channel) planes; the bias gradient is
//! reduced per channel plane, one task per channel.
//!
//! Backends: flex and ndarray run both passes here; burn's cubecl backend (wgpu) composes
//! burn's own tensor ops (the trait's default bodies). The reference twin is the plain
//! composition `leaky_relu(y + bias)` with burn's autodiff; the tests compare values and
//! gradients with it and check finite differences.

// burn-ndarray is deprecated in burn 0.22; the design keeps it alongside flex.
#![allow(deprecated)]

use burn::backend::autodiff::{Autodiff, checkpoint::strategy::CheckpointStrategy};
use burn::backend::tensor::FloatTensor;
use burn::backend::{
    AutodiffBackend, Backend, Cube, ExtensionType, TensorMetadata, backend_extension,
};
use burn::tensor::{Shape, Tensor};
use rayon::prelude::*;

use crate::autodiff;
use crate::constants::{LEAKY_RELU_SLOPE, planes_per_task};
use crate::host::{HostIo, floats};

// The host passes write LeakyReLU as `max(z, slope·z)`, which needs `0 < slope < 1`.
const _: () = assert!(LEAKY_RELU_SLOPE > 0.0 && LEAKY_RELU_SLOPE < 1.0);

/// A convolution's output and its bias.
///
/// # Shapes
/// - `y`: [N, C, H, W]; `bias`: `[C]` or [C, H, W]
#[derive(ExtensionType, Debug, Clone)]
pub struct OutBias<B: Backend> {
    pub y: FloatTensor<B>,
    pub bias: FloatTensor<B>,
}

/// Backends with the fused epilogue of this module.
#[backend_extension(NdArray, Flex, Cube, Autodiff)]
pub trait BiasActBackend: Backend {
    /// `leaky_relu(y + bias)` (with `act`) or `y + bias` → [N, C, H, W]. Default: burn's
    /// tensor ops.
    fn bias_act(#[extension_type] yb: OutBias<Self>, act: bool) -> FloatTensor<Self> {
        composed_forward::<Self>(yb, act)
    }

    /// Backward from the layer's output `out` and its gradient → the gradients of `y` and of
    /// the bias (`bias_shape`). Default: burn's tensor ops.
    fn bias_act_backward(
        out: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        act: bool,
        bias_shape: Vec<usize>,
    ) -> OutBias<Self> {
        composed_backward::<Self>(out, grad, act, bias_shape)
    }
}

/// The forward from burn's tensor ops: the trait's default body, and the bias and
/// activation of [`crate::conv_bias_act`]'s default body.
pub(super) fn composed_forward<B: Backend>(yb: OutBias<B>, act: bool) -> FloatTensor<B> {
    let z = B::float_add(yb.y, broadcast_bias::<B>(yb.bias));
    if act { leaky::<B>(z) } else { z }
}

/// The backward from burn's tensor ops: the trait's default body, and the bias and
/// activation part of [`crate::conv_bias_act`]'s default body.
pub(super) fn composed_backward<B: Backend>(
    out: FloatTensor<B>,
    grad: FloatTensor<B>,
    act: bool,
    bias_shape: Vec<usize>,
) -> OutBias<B> {
    let dz = if act {
        let negative = negative_mask::<B>(out);
        let scaled = B::float_mul_scalar(grad.clone(), LEAKY_RELU_SLOPE.into());
        B::float_mask_where(grad, negative, scaled)
    } else {
        grad
    };
    let mut db = B::float_sum_dim(dz.clone(), 0);
    if bias_shape.len() == 1 {
        db = B::float_sum_dim(B::float_sum_dim(db, 3), 2);
    }
    OutBias {
        y: dz,
        bias: B::float_reshape(db, Shape::from(bias_shape)),
    }
}

/// `[C]` → [1, C, 1, 1]; [C, H, W] → [1, C, H, W].
fn broadcast_bias<B: Backend>(bias: FloatTensor<B>) -> FloatTensor<B> {
    let s = bias.shape().to_vec();
    let shape = match s.as_slice() {
        [c] => vec![1, *c, 1, 1],
        [c, h, w] => vec![1, *c, *h, *w],
        _ => panic!("bias_act: the bias is {s:?}, not [C] or [C, H, W]"),
    };
    B::float_reshape(bias, Shape::from(shape))
}

/// burn's LeakyReLU on a primitive: `z` where `z >= 0`, `slope · z` elsewhere.
fn leaky<B: Backend>(z: FloatTensor<B>) -> FloatTensor<B> {
    B::leaky_relu(z, LEAKY_RELU_SLOPE.into())
}

/// Where `x < 0`, in the device's boolean type.
fn negative_mask<B: Backend>(x: FloatTensor<B>) -> burn::backend::tensor::BoolTensor<B> {
    let bool_dtype = burn::backend::get_or_init_device_settings::<B>(&x.device()).bool_dtype;
    B::float_lower_elem(x, 0f32.into(), bool_dtype)
}

/// `leaky_relu(y + bias)` with `act`, `y + bias` without: the decoders' layer epilogue on
/// any backend (see the module docs).
///
/// # Shapes
/// - `y`: [N, C, H, W]; `bias`: `[C]` or [C, H, W]
/// - returns [N, C, H, W]
///
/// # Panics
/// When the bias matches neither shape (the layers check their configuration when built).
pub fn bias_act<const D: usize>(y: Tensor<4>, bias: Tensor<D>, act: bool) -> Tensor<4> {
    let [_, c, h, w] = y.dims();
    let ok = match bias.dims().as_slice() {
        [bc] => *bc == c,
        [bc, bh, bw] => [*bc, *bh, *bw] == [c, h, w],
        _ => false,
    };
    assert!(
        ok,
        "bias_act: bias {:?} for an output [N, {c}, {h}, {w}]",
        bias.dims()
    );
    let yb = OutBias {
        y: y.into_dispatch(),
        bias: bias.into_dispatch(),
    };
    Tensor::from_dispatch(<burn::backend::Dispatch as BiasActBackend>::bias_act(
        yb, act,
    ))
}

// ---------------------------------------------------------------------------------------------
// Host implementation.

/// Sizes: batch, channels, pixels per plane, and whether the bias is untied.
pub(super) type EpilogueDims = (usize, usize, usize, bool);

/// The [`EpilogueDims`] of an output of shape `y` with a bias of shape `bias`.
pub(super) fn dims(y: &[usize], bias: &[usize]) -> EpilogueDims {
    (y[0], y[1], y[2] * y[3], bias.len() == 3)
}

/// The epilogue on one output plane of channel `ch`; `bias` is the whole bias, `[C]` or
/// `[C, H, W]` flattened.
pub(super) fn epilogue_plane(plane: &mut [f32], bias: &[f32], ch: usize, untied: bool, act: bool) {
    // Branch-free so that the loops vectorise: with `0 < slope < 1`, LeakyReLU is
    // `max(z, slope·z)`. A branch on the sign mispredicts on about half the values (the
    // signs are close to random), which made this pass several times slower.
    let s = if act { LEAKY_RELU_SLOPE as f32 } else { 1.0 };
    let apply = |v: &mut f32, b: f32| {
        let z = *v + b;
        *v = z.max(s * z);
    };
    if untied {
        let p = plane.len();
        let bp = &bias[ch * p..(ch + 1) * p];
        plane.iter_mut().zip(bp).for_each(|(v, b)| apply(v, *b));
    } else {
        let b = bias[ch];
        plane.iter_mut().for_each(|v| apply(v, b));
    }
}

fn host_forward(y: &mut [f32], bias: &[f32], (n, c, p, untied): EpilogueDims, act: bool) {
    if n == 0 || c == 0 || p == 0 {
        return;
    }
    y.par_chunks_mut(p)
        .enumerate()
        .with_min_len(planes_per_task(p))
        .for_each(|(i, plane)| {
            epilogue_plane(plane, bias, i % c, untied, act);
        });
}

/// `grad` becomes `dz` in place; returns the bias gradient.
pub(super) fn host_backward(
    out: &[f32],
    grad: &mut [f32],
    (n, c, p, untied): EpilogueDims,
    act: bool,
) -> Vec<f32> {
    let slope = LEAKY_RELU_SLOPE as f32;
    if act {
        grad.par_chunks_mut(p.max(1))
            .zip(out.par_chunks(p.max(1)))
            .with_min_len(planes_per_task(p))
            .for_each(|(g, o)| {
                // A select, not a branch (see `host_forward`).
                g.iter_mut()
                    .zip(o)
                    .for_each(|(g, o)| *g *= if *o < 0.0 { slope } else { 1.0 })
            });
    }
    let grad = &*grad;
    if untied {
        let mut db = vec![0.0f32; c * p];
        db.par_chunks_mut(p.max(1))
            .enumerate()
            .with_min_len(planes_per_task(p * n))
            .for_each(|(ch, d)| {
                for b in 0..n {
                    let g = &grad[(b * c + ch) * p..][..p];
                    d.iter_mut().zip(g).for_each(|(d, g)| *d += g);
                }
            });
        db
    } else {
        (0..c)
            .into_par_iter()
            .map(|ch| {
                (0..n)
                    .map(|b| {
                        grad[(b * c + ch) * p..][..p]
                            .iter()
                            .map(|v| *v as f64)
                            .sum::<f64>()
                    })
                    .sum::<f64>() as f32
            })
            .collect()
    }
}

impl<H: HostIo> BiasActBackend for H {
    fn bias_act(OutBias { y, bias }: OutBias<Self>, act: bool) -> FloatTensor<Self> {
        let device = y.device();
        let (ys, bs) = (y.shape().to_vec(), bias.shape().to_vec());
        let d = dims(&ys, &bs);
        let mut v = H::floats(y);
        host_forward(&mut v, &H::read(bias), d, act);
        floats::<H>(v, &ys, &device)
    }

    fn bias_act_backward(
        out: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        act: bool,
        bias_shape: Vec<usize>,
    ) -> OutBias<Self> {
        let device = out.device();
        let ys = out.shape().to_vec();
        let d = dims(&ys, &bias_shape);
        let mut g = H::floats(grad);
        let db = host_backward(&H::read(out), &mut g, d, act);
        OutBias {
            y: floats::<H>(g, &ys, &device),
            bias: floats::<H>(db, &bias_shape, &device),
        }
    }
}

/// The GPU backend composes burn's tensor ops (the trait's default bodies).
impl BiasActBackend for Cube {}

// ---------------------------------------------------------------------------------------------
// Autodiff: the handwritten backward.

crate::backward_op!(
    BiasActBackwardOp<2>: BiasActBackend,
    (FloatTensor<B>, bool, Vec<usize>),
    |(out, act, bias_shape), grad| {
        let g = B::bias_act_backward(out, grad, act, bias_shape);
        [g.y, g.bias]
    }
);

impl<B: Backend + BiasActBackend, C: CheckpointStrategy> BiasActBackend for Autodiff<B, C> {
    fn bias_act(OutBias { y, bias }: OutBias<Self>, act: bool) -> FloatTensor<Self> {
        let nodes = [y.node(), bias.node()];
        let inner = OutBias {
            y: y.into_primitive(),
            bias: bias.into_primitive(),
        };
        let bias_shape = TensorMetadata::shape(&inner.bias).to_vec();
        let run = |yb| B::bias_act(yb, act);
        let keep = |_, out: &FloatTensor<B>| (out.clone(), act, bias_shape);
        autodiff::forward::<B, C, _, _, 2>(BiasActBackwardOp, nodes, inner, run, keep)
    }

    fn bias_act_backward(
        out: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        act: bool,
        bias_shape: Vec<usize>,
    ) -> OutBias<Self> {
        let g = B::bias_act_backward(out.into_primitive(), grad.into_primitive(), act, bias_shape);
        OutBias {
            y: Self::from_inner(g.y),
            bias: Self::from_inner(g.bias),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::check::on_cpu_backends;
    use burn::tensor::{Device, Distribution, TensorData};

    use crate::check::{check_finite_differences, host, output_and_gradients, pattern};

    fn max_rel(a: &[f32], b: &[f32]) -> f32 {
        crate::check::max_rel(a, b, 1e-3)
    }

    /// The reference twin: burn's own ops under autodiff.
    fn reference<const D: usize>(y: Tensor<4>, bias: Tensor<D>, act: bool) -> Tensor<4> {
        let [_, c, h, w] = y.dims();
        let b = if D == 1 {
            bias.reshape([1, c, 1, 1])
        } else {
            bias.reshape([1, c, h, w])
        };
        let z = y + b;
        if act {
            burn::tensor::activation::leaky_relu(z, LEAKY_RELU_SLOPE)
        } else {
            z
        }
    }

    fn check<const D: usize>(device: &Device, bias_shape: [usize; D], act: bool) {
        let (n, c, h, w) = (2, 3, 5, 4);
        device.seed(D as u64 + act as u64);
        let y = Tensor::<4>::random([n, c, h, w], Distribution::Normal(0.0, 1.0), device);
        let b = Tensor::<D>::random(bias_shape, Distribution::Normal(0.0, 1.0), device);
        let g = Tensor::<4>::random([n, c, h, w], Distribution::Normal(0.0, 1.0), device);
        let [o, dy, db] = output_and_gradients(&y, &b, &g, |y, b| bias_act(y, b, act));
        let [o_ref, dy_ref, db_ref] = output_and_gradients(&y, &b, &g, |y, b| reference(y, b, act));
        let what = format!("bias {bias_shape:?}, act {act}");
        assert!(max_rel(&o, &o_ref) < 1e-6, "{what}: forward");
        assert!(max_rel(&dy, &dy_ref) < 1e-6, "{what}: grad y");
        assert!(max_rel(&db, &db_ref) < 1e-5, "{what}: grad bias");
    }

    fn check_all(device: Device) {
        for act in [false, true] {
            check(&device, [3], act);
            check(&device, [3, 5, 4], act);
        }
    }

    on_cpu_backends!(check_all: matches_burn_on_flex, matches_burn_on_ndarray);

    /// Central finite differences of `sum(bias_act(y, b) * g)` away from the kink.
    #[test]
    fn finite_differences() {
        let device = Device::flex().autodiff();
        let (n, c, h, w) = (1, 2, 2, 3);
        let len = n * c * h * w;
        // |z| >= 0.1 everywhere, so a step of 1e-2 never crosses the kink.
        let ys: Vec<f32> = (0..len)
            .map(|i| {
                if i % 2 == 0 {
                    0.3 + 0.1 * i as f32
                } else {
                    -0.4 - 0.1 * i as f32
                }
            })
            .collect();
        let bs: Vec<f32> = (0..c * h * w).map(|i| 0.01 * i as f32 - 0.03).collect();
        let gs: Vec<f32> = pattern(len, 7, 5, 2.0);
        let f = |yv: &[f32], bv: &[f32]| -> f64 {
            let y = Tensor::<4>::from_data(TensorData::new(yv.to_vec(), [n, c, h, w]), &device);
            let b = Tensor::<3>::from_data(TensorData::new(bv.to_vec(), [c, h, w]), &device);
            host(bias_act(y, b, true))
                .iter()
                .zip(&gs)
                .map(|(o, g)| *o as f64 * *g as f64)
                .sum()
        };
        let y = Tensor::<4>::from_data(TensorData::new(ys.clone(), [n, c, h, w]), &device)
            .require_grad();
        let b =
            Tensor::<3>::from_data(TensorData::new(bs.clone(), [c, h, w]), &device).require_grad();
        let g = Tensor::<4>::from_data(TensorData::new(gs.clone(), [n, c, h, w]), &device);
        let grads = (bias_act(y.clone(), b.clone(), true) * g).sum().backward();
        let dy = host(y.grad(&grads).expect("y grad"));
        let db = host(b.grad(&grads).expect("b grad"));
        check_finite_differences([&ys, &bs], [&dy, &db], f, 1e-2, 1e-4);
    }
}
