//! The weight norm of every decoder layer as one op, `w = g · v / ||v||` (RGCA's form: one
//! norm over the whole of `v`, `g` per output channel), with a handwritten backward.
//!
//! Why: composed from burn's ops, the forward is four passes over `v` (square, sum, the
//! broadcast product and its scale) and the backward about eight, each with a fresh buffer
//! (the product's two gradients, the broadcast sum back to a scalar, the square's backward,
//! the scalar's expansion, the sum of the two parts). Some weights are large:
//! Exp2Code's linear layer alone is `64·C_code x C_cond`
//! (16,384 x 243 = 4.0 M values in the `paper` configuration). Here the forward is two
//! passes (the norm, then `w`) and the backward three (the norm again, the per-channel
//! dot products, then `dv`), which makes the decoders' forward + backward faster (`cargo
//! bench --bench cpu_vs_torch`, docs/performance.md). The convolutions use it; the linear
//! layer now folds the norm into its product instead ([`mod@super::wn_linear`]), never
//! forming `w`.
//!
//! With `n = ||v||` and `s_o = g_o / n`, for the gradient `dw` of `w`:
//! - `a_o = Σ_{i in channel o} dw_i · v_i`;
//! - `dg_o = a_o / n`;
//! - `dv_i = s_{o(i)} · dw_i - v_i · (Σ_o g_o · a_o) / n³`.
//!
//! Thread mapping (CPU): `v` is cut into runs of `CHUNK` values, one task each; a run
//! walks its channels with a counter, so any `out_dim` (first, middle or last) is one loop.
//! The norm and the dot products are summed in `f64` per run, then across runs.
//!
//! Backends: flex and ndarray run both passes here; burn's cubecl backend (wgpu) composes
//! burn's own tensor ops (the trait's default bodies, the formula before this op). The
//! reference twin is that composition with burn's autodiff; the tests compare values and
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
use crate::host::{HostIo, floats};

/// Values of `v` per task (64 K floats, 256 KiB).
const CHUNK: usize = 1 << 16;

/// A weight-normalised layer's parameters.
///
/// # Shapes
/// - `v`: any rank, `C_out` along the op's `out_dim`; `g`: `[C_out]`
#[derive(ExtensionType, Debug, Clone)]
pub struct VG<B: Backend> {
    pub v: FloatTensor<B>,
    pub g: FloatTensor<B>,
}

/// Backends with the fused weight norm of this module.
#[backend_extension(NdArray, Flex, Cube, Autodiff)]
pub trait WeightNormBackend: Backend {
    /// `g · v / ||v||`, `g` along `out_dim` of `v`. Default: burn's tensor ops.
    fn weight_norm(#[extension_type] vg: VG<Self>, out_dim: usize) -> FloatTensor<Self> {
        composed_forward::<Self>(vg, out_dim)
    }

    /// Backward from `v`, `g` and the gradient of `w` → the gradients of `v` and `g`.
    /// Default: burn's tensor ops (the formula in the module docs).
    fn weight_norm_backward(
        #[extension_type] vg: VG<Self>,
        grad: FloatTensor<Self>,
        out_dim: usize,
    ) -> VG<Self> {
        composed_backward::<Self>(vg, grad, out_dim)
    }
}

/// The forward from burn's tensor ops (the trait's default body).
pub(super) fn composed_forward<B: Backend>(VG { v, g }: VG<B>, out_dim: usize) -> FloatTensor<B> {
    let norm = B::float_sqrt(B::float_sum(B::float_powi_scalar(v.clone(), 2.into())));
    let scale = B::float_div(g, norm);
    let shape = v.shape().to_vec();
    B::float_mul(v, B::float_reshape(scale, along(&shape, out_dim)))
}

/// The backward from burn's tensor ops (the trait's default body).
pub(super) fn composed_backward<B: Backend>(
    VG { v, g }: VG<B>,
    grad: FloatTensor<B>,
    out_dim: usize,
) -> VG<B> {
    let shape = v.shape().to_vec();
    let c = shape[out_dim];
    let sq = B::float_sum(B::float_powi_scalar(v.clone(), 2.into()));
    let n = B::float_sqrt(sq.clone());
    // a_o: the dot products per channel, summed over every other dimension to [C].
    let mut a = B::float_mul(grad.clone(), v.clone());
    for d in (0..shape.len()).rev().filter(|&d| d != out_dim) {
        a = B::float_sum_dim(a, d);
    }
    let a = B::float_reshape(a, Shape::from(vec![c]));
    let dg = B::float_div(a.clone(), n.clone());
    let scale = B::float_div(g.clone(), n.clone());
    let total = B::float_sum(B::float_mul(g, a));
    let k = B::float_div(total, B::float_mul(sq, n));
    let dv = B::float_sub(
        B::float_mul(grad, B::float_reshape(scale, along(&shape, out_dim))),
        B::float_mul(v, B::float_reshape(k, Shape::from(vec![1; shape.len()]))),
    );
    VG { v: dv, g: dg }
}

/// `[C]` broadcast along `out_dim` of `shape`: all ones but `C` there.
fn along(shape: &[usize], out_dim: usize) -> Shape {
    let mut s = vec![1usize; shape.len()];
    s[out_dim] = shape[out_dim];
    Shape::from(s)
}

/// `w = g · v / ||v||`: one norm over all of `v`, `g` broadcast along `out_dim`, on any
/// backend (see the module docs).
///
/// # Shapes
/// - `v`: any rank `D`, with `v.dims()[out_dim] == C_out`
/// - `g`: `[C_out]`
/// - returns the shape of `v`
///
/// # Panics
/// When `g` does not have `v.dims()[out_dim]` values (the layers build them together).
pub fn weight_norm<const D: usize>(v: Tensor<D>, g: Tensor<1>, out_dim: usize) -> Tensor<D> {
    assert!(
        out_dim < D && g.dims()[0] == v.dims()[out_dim],
        "weight_norm: g {:?} along dimension {out_dim} of v {:?}",
        g.dims(),
        v.dims()
    );
    let vg = VG {
        v: v.into_dispatch(),
        g: g.into_dispatch(),
    };
    Tensor::from_dispatch(<burn::backend::Dispatch as WeightNormBackend>::weight_norm(
        vg, out_dim,
    ))
}

// ---------------------------------------------------------------------------------------------
// Host implementation.

/// Channels and the run of values per channel: `v` is `[outer, C, inner]`.
fn layout(shape: &[usize], out_dim: usize) -> (usize, usize) {
    (shape[out_dim], shape[out_dim + 1..].iter().product())
}

/// Calls `f(channel, values)` for the runs of one channel inside the chunk of `len` values
/// starting at flat index `start`.
fn runs(
    start: usize,
    len: usize,
    (c, inner): (usize, usize),
    mut f: impl FnMut(usize, usize, usize),
) {
    let inner = inner.max(1);
    let mut i = start;
    let end = start + len;
    while i < end {
        let o = (i / inner) % c;
        let run_end = ((i / inner + 1) * inner).min(end);
        f(o, i - start, run_end - i);
        i = run_end;
    }
}

/// Independent `f64` partial sums of [`dot`]: eight lanes, so the adds neither wait on one
/// another nor stop the compiler from vectorising (one running sum is one add per latency).
const LANES: usize = 8;

/// `Σ a_i · b_i` in `f64`, over `LANES` interleaved partial sums.
pub(super) fn dot(a: &[f32], b: &[f32]) -> f64 {
    let mut acc = [0.0f64; LANES];
    let (a8, b8) = (a.chunks_exact(LANES), b.chunks_exact(LANES));
    let tail: f64 = a8
        .remainder()
        .iter()
        .zip(b8.remainder())
        .map(|(x, y)| *x as f64 * *y as f64)
        .sum();
    for (x, y) in a8.zip(b8) {
        for l in 0..LANES {
            acc[l] += x[l] as f64 * y[l] as f64;
        }
    }
    acc.iter().sum::<f64>() + tail
}

/// `||v||` in `f64`.
fn norm(v: &[f32]) -> f64 {
    v.par_chunks(CHUNK).map(|r| dot(r, r)).sum::<f64>().sqrt()
}

fn host_forward(v: &[f32], g: &[f32], lay: (usize, usize)) -> Vec<f32> {
    let n = norm(v);
    let scale: Vec<f32> = g.iter().map(|g| (*g as f64 / n) as f32).collect();
    let mut w = vec![0.0f32; v.len()];
    w.par_chunks_mut(CHUNK)
        .zip(v.par_chunks(CHUNK))
        .enumerate()
        .for_each(|(k, (w, v))| {
            runs(k * CHUNK, v.len(), lay, |o, at, len| {
                let s = scale[o];
                w[at..at + len]
                    .iter_mut()
                    .zip(&v[at..at + len])
                    .for_each(|(w, v)| *w = s * v);
            });
        });
    w
}

/// `dw` becomes `dv` in place; returns `dg`.
fn host_backward(v: &[f32], g: &[f32], dw: &mut [f32], lay: (usize, usize)) -> Vec<f32> {
    let c = lay.0;
    // One pass for both the squared norm and the per-channel dot products.
    let (sq, a) = v
        .par_chunks(CHUNK)
        .zip(dw.par_chunks(CHUNK))
        .enumerate()
        .map(|(k, (v, dw))| {
            let mut a = vec![0.0f64; c];
            runs(k * CHUNK, v.len(), lay, |o, at, len| {
                a[o] += dot(&v[at..at + len], &dw[at..at + len]);
            });
            (dot(v, v), a)
        })
        .reduce(
            || (0.0, vec![0.0f64; c]),
            |(sx, mut x), (sy, y)| {
                x.iter_mut().zip(&y).for_each(|(x, y)| *x += y);
                (sx + sy, x)
            },
        );
    let n = sq.sqrt();
    let total: f64 = g.iter().zip(&a).map(|(g, a)| *g as f64 * a).sum();
    let k = (total / (n * n * n)) as f32;
    let scale: Vec<f32> = g.iter().map(|g| (*g as f64 / n) as f32).collect();
    dw.par_chunks_mut(CHUNK)
        .zip(v.par_chunks(CHUNK))
        .enumerate()
        .for_each(|(j, (d, v))| {
            runs(j * CHUNK, v.len(), lay, |o, at, len| {
                let s = scale[o];
                d[at..at + len]
                    .iter_mut()
                    .zip(&v[at..at + len])
                    .for_each(|(d, v)| *d = s * *d - k * v);
            });
        });
    a.iter().map(|a| (a / n) as f32).collect()
}

impl<H: HostIo> WeightNormBackend for H {
    fn weight_norm(VG { v, g }: VG<Self>, out_dim: usize) -> FloatTensor<Self> {
        let device = v.device();
        let shape = v.shape().to_vec();
        let w = host_forward(&H::read(v), &H::read(g), layout(&shape, out_dim));
        floats::<H>(w, &shape, &device)
    }

    fn weight_norm_backward(
        VG { v, g }: VG<Self>,
        grad: FloatTensor<Self>,
        out_dim: usize,
    ) -> VG<Self> {
        let device = v.device();
        let shape = v.shape().to_vec();
        let c = shape[out_dim];
        let mut d = H::floats(grad);
        let dg = host_backward(&H::read(v), &H::read(g), &mut d, layout(&shape, out_dim));
        VG {
            v: floats::<H>(d, &shape, &device),
            g: floats::<H>(dg, &[c], &device),
        }
    }
}

/// The GPU backend composes burn's tensor ops (the trait's default bodies).
impl WeightNormBackend for Cube {}

// ---------------------------------------------------------------------------------------------
// Autodiff: the handwritten backward.

crate::backward_op!(
    WeightNormBackwardOp<2>: WeightNormBackend,
    (VG<B>, usize),
    |(vg, out_dim), grad| {
        let d = B::weight_norm_backward(vg, grad, out_dim);
        [d.v, d.g]
    }
);

impl<B: Backend + WeightNormBackend, C: CheckpointStrategy> WeightNormBackend for Autodiff<B, C> {
    fn weight_norm(VG { v, g }: VG<Self>, out_dim: usize) -> FloatTensor<Self> {
        let nodes = [v.node(), g.node()];
        let inner: VG<B> = VG {
            v: v.into_primitive(),
            g: g.into_primitive(),
        };
        let run = |vg| B::weight_norm(vg, out_dim);
        let keep = |vg, _: &FloatTensor<B>| (vg, out_dim);
        autodiff::forward::<B, C, _, _, 2>(WeightNormBackwardOp, nodes, inner, run, keep)
    }

    fn weight_norm_backward(
        VG { v, g }: VG<Self>,
        grad: FloatTensor<Self>,
        out_dim: usize,
    ) -> VG<Self> {
        let inner = VG {
            v: v.into_primitive(),
            g: g.into_primitive(),
        };
        let d = B::weight_norm_backward(inner, grad.into_primitive(), out_dim);
        VG {
            v: Self::from_inner(d.v),
            g: Self::from_inner(d.g),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::check::on_cpu_backends;
    use burn::tensor::{Device, Distribution, TensorData};

    use crate::check::{check_finite_differences, host, output_and_gradients};

    fn max_rel(a: &[f32], b: &[f32]) -> f32 {
        crate::check::max_rel(a, b, 1e-6)
    }

    /// The reference twin: the composition of burn's ops (the layers' formula before this
    /// op) under burn's autodiff.
    fn reference<const D: usize>(v: Tensor<D>, g: Tensor<1>, out_dim: usize) -> Tensor<D> {
        let norm = v.clone().powi_scalar(2).sum().sqrt();
        let mut shape = [1usize; D];
        shape[out_dim] = g.dims()[0];
        v * (g / norm).reshape(shape)
    }

    fn check<const D: usize>(device: &Device, shape: [usize; D], out_dim: usize) {
        device.seed((D * 10 + out_dim) as u64);
        let v = Tensor::<D>::random(shape, Distribution::Normal(0.0, 1.0), device);
        let g = Tensor::<1>::random([shape[out_dim]], Distribution::Uniform(0.5, 2.0), device);
        let dw = Tensor::<D>::random(shape, Distribution::Normal(0.0, 1.0), device);
        let [w, dv, dg] = output_and_gradients(&v, &g, &dw, |v, g| weight_norm(v, g, out_dim));
        let [w_ref, dv_ref, dg_ref] =
            output_and_gradients(&v, &g, &dw, |v, g| reference(v, g, out_dim));
        let what = format!("v {shape:?}, out_dim {out_dim}");
        assert!(max_rel(&w, &w_ref) < 1e-5, "{what}: forward");
        assert!(max_rel(&dv, &dv_ref) < 1e-4, "{what}: grad v");
        assert!(max_rel(&dg, &dg_ref) < 1e-4, "{what}: grad g");
    }

    /// The layers' shapes: linear `[in, out]` (out last), transposed convolution
    /// `[C_in, C_out, k, k]` (out in the middle), convolution `[C_out, C_in, k, k]` (out
    /// first); the large one spans several runs of [`CHUNK`] values.
    fn check_all(device: Device) {
        check(&device, [7, 5], 1);
        check(&device, [3, 4, 2, 2], 1);
        check(&device, [4, 3, 3, 3], 0);
        check(&device, [300, 500], 1);
    }

    on_cpu_backends!(check_all: matches_burn_on_flex, matches_burn_on_ndarray);

    /// The trait's default bodies (what wgpu runs) against the host passes, values and
    /// gradients, on flex without autodiff.
    #[test]
    fn default_bodies_match_the_host_passes() {
        type F = burn::backend::Flex;
        let t = crate::check::flex_pattern;
        let shape = [3usize, 4, 2, 2];
        let (v, dw) = (t(&shape, 0, 0.0), t(&shape, 5, 0.0));
        let g = t(&[4], 9, 3.0);
        let vg = || VG::<F> {
            v: v.clone(),
            g: g.clone(),
        };
        let fused_w = F::floats(<F as WeightNormBackend>::weight_norm(vg(), 1));
        let composed_w = F::floats(composed_forward::<F>(vg(), 1));
        assert!(max_rel(&fused_w, &composed_w) < 1e-5, "forward");
        let fused = <F as WeightNormBackend>::weight_norm_backward(vg(), dw.clone(), 1);
        let composed = composed_backward::<F>(vg(), dw, 1);
        assert!(
            max_rel(&F::floats(fused.v), &F::floats(composed.v)) < 1e-5,
            "grad v"
        );
        assert!(
            max_rel(&F::floats(fused.g), &F::floats(composed.g)) < 1e-5,
            "grad g"
        );
    }

    /// Central finite differences of `sum(weight_norm(v, g) * dw)`.
    #[test]
    fn finite_differences() {
        let device = Device::flex().autodiff();
        let shape = [2usize, 3, 2];
        let len = 12;
        let vs: Vec<f32> = (0..len).map(|i| ((i * 5 % 7) as f32 - 3.0) * 0.3).collect();
        let gs = vec![0.7f32, 1.3, 2.1];
        let ds: Vec<f32> = (0..len).map(|i| ((i * 3 % 5) as f32 - 2.0) * 0.5).collect();
        let f = |vv: &[f32], gv: &[f32]| -> f64 {
            let v = Tensor::<3>::from_data(TensorData::new(vv.to_vec(), shape), &device);
            let g = Tensor::<1>::from_data(TensorData::new(gv.to_vec(), [3]), &device);
            host(weight_norm(v, g, 1))
                .iter()
                .zip(&ds)
                .map(|(w, d)| *w as f64 * *d as f64)
                .sum()
        };
        let v = Tensor::<3>::from_data(TensorData::new(vs.clone(), shape), &device).require_grad();
        let g = Tensor::<1>::from_data(TensorData::new(gs.clone(), [3]), &device).require_grad();
        let dw = Tensor::<3>::from_data(TensorData::new(ds.clone(), shape), &device);
        let grads = (weight_norm(v.clone(), g.clone(), 1) * dw).sum().backward();
        let dv = host(v.grad(&grads).expect("v grad"));
        let dg = host(g.grad(&grads).expect("g grad"));
        check_finite_differences([&vs, &gs], [&dv, &dg], f, 1e-2, 1e-3);
    }
}
