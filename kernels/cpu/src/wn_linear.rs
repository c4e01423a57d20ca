//! A weight-normalised linear map, `y = x · wᵀ` with `w = g · v / ||v||` (the layers' form:
//! one norm over all of `v`, `g` per output feature), as one op with a handwritten backward.
//! The bias stays a plain add outside it (the app's `WnLinear` layer).
//!
//! Why: Exp2Code's linear layer is the decoders' largest weight (`64·C_code x C_cond`:
//! 16,384 x 243 = 4.0 M values in the `paper` configuration) and sees one condition vector per
//! frame, so its cost is passes over memory, not arithmetic. Composed ([`mod@super::weight_norm`]
//! then burn's `linear`), the forward wrote `w` and read it again, and the backward formed
//! `dw = dyᵀ · x`, a transposed copy, `dx = dy · w`, then the weight norm's three passes, so
//! this one layer was a large share of the `paper` decoders' step. Here `w` is never formed:
//!
//! - forward, one pass over `v`: per output row `o`, `||v_o||²` and `u_bo = v_o · x_b`; then
//!   `n = ||v||` and `y_bo = s_o · u_bo` with `s_o = g_o / n`;
//! - backward, two passes: the first as the forward (`u` and `n` again, rather than a saved
//!   copy), giving `a_o = Σ_b dy_bo · u_bo` (`= Σ_i dw_oi · v_oi`, the weight norm's dot
//!   product, without `dw`), `dg_o = a_o / n` and `k = Σ_o g_o · a_o / n³`; the second writes
//!   `dv_o = Σ_b e_bo · x_b - k · v_o` and sums `dx_b = Σ_o e_bo · v_o`, with
//!   `e_bo = s_o · dy_bo`. The weight norm's formula is [`mod@super::weight_norm`]'s.
//!
//! Thread mapping (CPU): `v` is cut into runs of `ROWS_PER_TASK` output rows, one task
//! each; `dx` is summed per task and the partial sums added. Norms and dot products are summed
//! in `f64`.
//!
//! Backends: flex and ndarray run both passes here; burn's cubecl backend (wgpu) composes the
//! weight norm's default bodies and burn's matrix products (the trait's default bodies). The
//! reference twin is that composition, [`super::weight_norm::weight_norm`] then `linear`,
//! under burn's autodiff; the tests compare values and gradients and check finite
//! differences.

// burn-ndarray is deprecated in burn 0.22; the design keeps it alongside flex.
#![allow(deprecated)]

use burn::backend::autodiff::{Autodiff, checkpoint::strategy::CheckpointStrategy};
use burn::backend::tensor::FloatTensor;
use burn::backend::{
    AutodiffBackend, Backend, Cube, ExtensionType, TensorMetadata, backend_extension,
};
use burn::tensor::Tensor;
use rayon::prelude::*;

use super::weight_norm::{self, VG, dot};
use crate::autodiff;
use crate::host::{HostIo, floats};

/// Output rows of `v` per task: 256 rows of the `paper` layer's 243 inputs are about 250 KB.
const ROWS_PER_TASK: usize = 256;

/// The op's inputs.
///
/// # Shapes
/// - `x`: `[B, I]`; `v`: `[O, I]` (PyTorch's layout); `g`: `[O]`
#[derive(ExtensionType, Debug, Clone)]
pub struct XVG<B: Backend> {
    pub x: FloatTensor<B>,
    pub v: FloatTensor<B>,
    pub g: FloatTensor<B>,
}

/// Backends with the fused weight-normalised linear map of this module.
#[backend_extension(NdArray, Flex, Cube, Autodiff)]
pub trait WnLinearBackend: Backend {
    /// `x · (g · v / ||v||)ᵀ` → `[B, O]`. Default: the weight norm's default body, then
    /// burn's matrix product.
    fn wn_linear(#[extension_type] xvg: XVG<Self>) -> FloatTensor<Self> {
        composed_forward::<Self>(xvg)
    }

    /// Backward from the inputs and the gradient of `y` → the gradients of `x`, `v` and `g`.
    /// Default: burn's matrix products, then the weight norm's default backward body.
    fn wn_linear_backward(#[extension_type] xvg: XVG<Self>, grad: FloatTensor<Self>) -> XVG<Self> {
        composed_backward::<Self>(xvg, grad)
    }
}

/// The forward from burn's tensor ops (the trait's default body).
fn composed_forward<B: Backend>(XVG { x, v, g }: XVG<B>) -> FloatTensor<B> {
    let w = weight_norm::composed_forward::<B>(VG { v, g }, 0);
    B::float_matmul(x, B::float_transpose(w))
}

/// The backward from burn's tensor ops (the trait's default body).
fn composed_backward<B: Backend>(XVG { x, v, g }: XVG<B>, grad: FloatTensor<B>) -> XVG<B> {
    let w = weight_norm::composed_forward::<B>(
        VG {
            v: v.clone(),
            g: g.clone(),
        },
        0,
    );
    let dx = B::float_matmul(grad.clone(), w);
    let dw = B::float_matmul(B::float_transpose(grad), x);
    let d = weight_norm::composed_backward::<B>(VG { v, g }, dw, 0);
    XVG {
        x: dx,
        v: d.v,
        g: d.g,
    }
}

/// `x · (g · v / ||v||)ᵀ` on any backend (see the module docs).
///
/// # Shapes
/// - `x`: `[B, I]`; `v`: `[O, I]`; `g`: `[O]`
/// - returns `[B, O]`
///
/// # Panics
/// When the sizes disagree (the layer builds `v` and `g` together and checks `x`).
pub fn wn_linear(x: Tensor<2>, v: Tensor<2>, g: Tensor<1>) -> Tensor<2> {
    let ([_, i], [o, vi], [go]) = (x.dims(), v.dims(), g.dims());
    assert!(
        i == vi && o == go,
        "wn_linear: x {:?}, v {:?}, g {:?}",
        x.dims(),
        v.dims(),
        g.dims()
    );
    let xvg = XVG {
        x: x.into_dispatch(),
        v: v.into_dispatch(),
        g: g.into_dispatch(),
    };
    Tensor::from_dispatch(<burn::backend::Dispatch as WnLinearBackend>::wn_linear(xvg))
}

// ---------------------------------------------------------------------------------------------
// Host implementation.

/// Sizes: batch `b`, inputs `i`, outputs `o`.
#[derive(Clone, Copy, Debug)]
struct Dims {
    b: usize,
    i: usize,
    o: usize,
}

/// One pass over `v`: `uᵀ` `[O, B]` (`u_bo = v_o · x_b`, in `f64`) and `||v||`.
fn host_products(x: &[f32], v: &[f32], d: Dims) -> (Vec<f64>, f64) {
    let mut ut = vec![0.0f64; d.o * d.b];
    if d.i == 0 {
        return (ut, 0.0);
    }
    if d.b == 0 {
        // No products: the norm alone (the zip below would stop at the empty `uᵀ`).
        let sq: f64 = v.par_chunks(ROWS_PER_TASK * d.i).map(|r| dot(r, r)).sum();
        return (ut, sq.sqrt());
    }
    let sq: f64 = ut
        .par_chunks_mut(ROWS_PER_TASK * d.b.max(1))
        .zip(v.par_chunks(ROWS_PER_TASK * d.i))
        .map(|(ut, v)| {
            let mut sq = 0.0;
            for (row, vo) in v.chunks_exact(d.i).enumerate() {
                sq += dot(vo, vo);
                for (b, xb) in x.chunks_exact(d.i).enumerate() {
                    ut[row * d.b + b] = dot(vo, xb);
                }
            }
            sq
        })
        .sum();
    (ut, sq.sqrt())
}

fn host_forward(x: &[f32], v: &[f32], g: &[f32], d: Dims) -> Vec<f32> {
    let mut y = vec![0.0f32; d.b * d.o];
    if d.i == 0 {
        // Empty products are zero (and `||v||` is zero: no `0 / 0`).
        return y;
    }
    let (ut, n) = host_products(x, v, d);
    for (b, yb) in y.chunks_exact_mut(d.o.max(1)).enumerate() {
        for (o, y) in yb.iter_mut().enumerate() {
            *y = (g[o] as f64 / n * ut[o * d.b + b]) as f32;
        }
    }
    y
}

/// → (dx `[B, I]`, dv `[O, I]`, dg `[O]`).
fn host_backward(
    x: &[f32],
    v: &[f32],
    g: &[f32],
    dy: &[f32],
    d: Dims,
) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let (ut, n) = host_products(x, v, d);
    // a_o = Σ_b dy_bo · u_bo.
    let a: Vec<f64> = (0..d.o)
        .map(|o| {
            (0..d.b)
                .map(|b| dy[b * d.o + o] as f64 * ut[o * d.b + b])
                .sum()
        })
        .collect();
    let total: f64 = g.iter().zip(&a).map(|(g, a)| *g as f64 * a).sum();
    let k = (total / (n * n * n)) as f32;
    // eᵀ [O, B]: e_bo = s_o · dy_bo.
    let et: Vec<f32> = (0..d.o * d.b)
        .map(|t| (g[t / d.b] as f64 / n * dy[(t % d.b) * d.o + t / d.b] as f64) as f32)
        .collect();
    let mut dv = vec![0.0f32; d.o * d.i];
    let dx = if d.i == 0 {
        Vec::new()
    } else {
        dv.par_chunks_mut(ROWS_PER_TASK * d.i)
            .zip(v.par_chunks(ROWS_PER_TASK * d.i))
            .zip(et.par_chunks(ROWS_PER_TASK * d.b.max(1)))
            .fold(
                || vec![0.0f32; d.b * d.i],
                |mut dx, ((dv, v), et)| {
                    for ((dvo, vo), eo) in dv
                        .chunks_exact_mut(d.i)
                        .zip(v.chunks_exact(d.i))
                        .zip(et.chunks(d.b.max(1)))
                    {
                        dvo.iter_mut().zip(vo).for_each(|(dv, v)| *dv = -k * v);
                        for ((e, xb), dxb) in eo
                            .iter()
                            .zip(x.chunks_exact(d.i))
                            .zip(dx.chunks_exact_mut(d.i))
                        {
                            dvo.iter_mut().zip(xb).for_each(|(dv, x)| *dv += e * x);
                            dxb.iter_mut().zip(vo).for_each(|(dx, v)| *dx += e * v);
                        }
                    }
                    dx
                },
            )
            .reduce(
                || vec![0.0f32; d.b * d.i],
                |mut a, b| {
                    a.iter_mut().zip(&b).for_each(|(a, b)| *a += b);
                    a
                },
            )
    };
    let dg = a.iter().map(|a| (a / n) as f32).collect();
    (dx, dv, dg)
}

fn dims<B: Backend>(x: &FloatTensor<B>, v: &FloatTensor<B>) -> Dims {
    let (xs, vs) = (x.shape().to_vec(), v.shape().to_vec());
    Dims {
        b: xs[0],
        i: xs[1],
        o: vs[0],
    }
}

impl<H: HostIo> WnLinearBackend for H {
    fn wn_linear(XVG { x, v, g }: XVG<Self>) -> FloatTensor<Self> {
        let device = x.device();
        let d = dims::<H>(&x, &v);
        let y = host_forward(&H::read(x), &H::read(v), &H::read(g), d);
        floats::<H>(y, &[d.b, d.o], &device)
    }

    fn wn_linear_backward(XVG { x, v, g }: XVG<Self>, grad: FloatTensor<Self>) -> XVG<Self> {
        let device = x.device();
        let d = dims::<H>(&x, &v);
        let (dx, dv, dg) = host_backward(&H::read(x), &H::read(v), &H::read(g), &H::read(grad), d);
        XVG {
            x: floats::<H>(dx, &[d.b, d.i], &device),
            v: floats::<H>(dv, &[d.o, d.i], &device),
            g: floats::<H>(dg, &[d.o], &device),
        }
    }
}

/// The GPU backend composes burn's ops (the trait's default bodies).
impl WnLinearBackend for Cube {}

// ---------------------------------------------------------------------------------------------
// Autodiff: the handwritten backward.

crate::backward_op!(
    WnLinearBackwardOp<3>: WnLinearBackend,
    XVG<B>,
    |xvg, grad| {
        let d = B::wn_linear_backward(xvg, grad);
        [d.x, d.v, d.g]
    }
);

impl<B: Backend + WnLinearBackend, C: CheckpointStrategy> WnLinearBackend for Autodiff<B, C> {
    fn wn_linear(XVG { x, v, g }: XVG<Self>) -> FloatTensor<Self> {
        let nodes = [x.node(), v.node(), g.node()];
        let inner: XVG<B> = XVG {
            x: x.into_primitive(),
            v: v.into_primitive(),
            g: g.into_primitive(),
        };
        let keep = |xvg, _: &FloatTensor<B>| xvg;
        autodiff::forward::<B, C, _, _, 3>(WnLinearBackwardOp, nodes, inner, B::wn_linear, keep)
    }

    fn wn_linear_backward(XVG { x, v, g }: XVG<Self>, grad: FloatTensor<Self>) -> XVG<Self> {
        let inner = XVG {
            x: x.into_primitive(),
            v: v.into_primitive(),
            g: g.into_primitive(),
        };
        let d = B::wn_linear_backward(inner, grad.into_primitive());
        XVG {
            x: Self::from_inner(d.x),
            v: Self::from_inner(d.v),
            g: Self::from_inner(d.g),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::check::on_cpu_backends;
    use burn::tensor::module::linear;
    use burn::tensor::{Device, Distribution, TensorData};

    use crate::check::{
        check_finite_differences, compare_outputs, host, layer_output_and_gradients,
    };

    /// The reference twin: the layer's formula before this op, the weight norm then burn's
    /// `linear`, under burn's autodiff.
    fn reference(x: Tensor<2>, v: Tensor<2>, g: Tensor<1>) -> Tensor<2> {
        linear(x, weight_norm::weight_norm(v, g, 0).transpose(), None)
    }

    fn check(device: &Device, [b, i, o]: [usize; 3]) {
        device.seed((b * 100 + i * 10 + o) as u64);
        let x = Tensor::<2>::random([b, i], Distribution::Normal(0.0, 1.0), device);
        let v = Tensor::<2>::random([o, i], Distribution::Normal(0.0, 1.0), device);
        let g = Tensor::<1>::random([o], Distribution::Uniform(0.5, 2.0), device);
        let up = Tensor::<2>::random([b, o], Distribution::Normal(0.0, 1.0), device);
        let ours = layer_output_and_gradients([&x, &v], &g, &up, wn_linear);
        let want = layer_output_and_gradients([&x, &v], &g, &up, reference);
        compare_outputs(&ours, &want, &format!("B {b}, I {i}, O {o}"));
    }

    /// Batches of one and several, a single output, and more rows than one task holds.
    fn check_all(device: Device) {
        check(&device, [1, 7, 5]);
        check(&device, [3, 4, 1]);
        check(&device, [2, 9, 2 * ROWS_PER_TASK + 3]);
    }

    on_cpu_backends!(check_all: matches_the_composition_on_flex, matches_the_composition_on_ndarray);

    /// The trait's default bodies (what wgpu runs) against the host passes, values and
    /// gradients, on flex without autodiff.
    #[test]
    fn default_bodies_match_the_host_passes() {
        type F = burn::backend::Flex;
        let t = crate::check::flex_pattern;
        let (x, v, g, dy) = (
            t(&[2, 5], 0, 0.0),
            t(&[3, 5], 3, 0.0),
            t(&[3], 9, 3.0),
            t(&[2, 3], 5, 0.0),
        );
        let xvg = || XVG::<F> {
            x: x.clone(),
            v: v.clone(),
            g: g.clone(),
        };
        let max_rel = |a: FloatTensor<F>, b: FloatTensor<F>| {
            crate::check::max_rel(&F::floats(a), &F::floats(b), 1e-6)
        };
        let fused = <F as WnLinearBackend>::wn_linear(xvg());
        assert!(
            max_rel(fused, composed_forward::<F>(xvg())) < 1e-5,
            "forward"
        );
        let fused = <F as WnLinearBackend>::wn_linear_backward(xvg(), dy.clone());
        let composed = composed_backward::<F>(xvg(), dy);
        assert!(max_rel(fused.x, composed.x) < 1e-5, "grad x");
        assert!(max_rel(fused.v, composed.v) < 1e-5, "grad v");
        assert!(max_rel(fused.g, composed.g) < 1e-5, "grad g");
    }

    /// Degenerate sizes stay finite: an empty batch gives zero gradients of `v` and `g` (not
    /// `0 / 0` from a norm summed over no rows), no inputs give a zero output.
    #[test]
    fn empty_batch_and_inputs() {
        let d = Dims { b: 0, i: 3, o: 2 };
        let v = [1.0f32, -2.0, 0.5, 3.0, 0.0, -1.0];
        let (dx, dv, dg) = host_backward(&[], &v, &[1.0, 2.0], &[], d);
        assert!(dx.is_empty());
        assert_eq!(dv, vec![0.0; 6]);
        assert_eq!(dg, vec![0.0; 2]);
        let (_, n) = host_products(&[], &v, d);
        let want = v.iter().map(|v| (*v as f64).powi(2)).sum::<f64>().sqrt();
        assert!((n - want).abs() < 1e-12, "{n} vs {want}");
        let y = host_forward(&[], &[], &[1.0, 2.0], Dims { b: 2, i: 0, o: 2 });
        assert_eq!(y, vec![0.0; 4]);
    }

    /// Central finite differences of `sum(wn_linear(x, v, g) · up)`, every entry of `x` and
    /// `v` (as one input) and of `g`.
    #[test]
    fn finite_differences() {
        let device = Device::flex().autodiff();
        let [b, i, o] = [2usize, 3, 4];
        let xs: Vec<f32> = (0..b * i)
            .map(|k| ((k * 5 % 7) as f32 - 3.0) * 0.3)
            .collect();
        let vs: Vec<f32> = (0..o * i)
            .map(|k| ((k * 3 % 11) as f32 - 5.0) * 0.2)
            .collect();
        let gs = vec![0.7f32, 1.3, 2.1, 0.9];
        let up: Vec<f32> = (0..b * o)
            .map(|k| ((k * 3 % 5) as f32 - 2.0) * 0.5)
            .collect();
        let xv: Vec<f32> = xs.iter().chain(&vs).copied().collect();
        let f = |xv: &[f32], gv: &[f32]| -> f64 {
            let x = Tensor::<2>::from_data(TensorData::new(xv[..b * i].to_vec(), [b, i]), &device);
            let v = Tensor::<2>::from_data(TensorData::new(xv[b * i..].to_vec(), [o, i]), &device);
            let g = Tensor::<1>::from_data(TensorData::new(gv.to_vec(), [o]), &device);
            host(wn_linear(x, v, g))
                .iter()
                .zip(&up)
                .map(|(y, u)| *y as f64 * *u as f64)
                .sum()
        };
        let x = Tensor::<2>::from_data(TensorData::new(xs.clone(), [b, i]), &device).require_grad();
        let v = Tensor::<2>::from_data(TensorData::new(vs.clone(), [o, i]), &device).require_grad();
        let g = Tensor::<1>::from_data(TensorData::new(gs.clone(), [o]), &device).require_grad();
        let upt = Tensor::<2>::from_data(TensorData::new(up.clone(), [b, o]), &device);
        let grads = (wn_linear(x.clone(), v.clone(), g.clone()) * upt)
            .sum()
            .backward();
        let dxv: Vec<f32> = host(x.grad(&grads).expect("x grad"))
            .into_iter()
            .chain(host(v.grad(&grads).expect("v grad")))
            .collect();
        let dg = host(g.grad(&grads).expect("g grad"));
        check_finite_differences([&xv, &gs], [&dxv, &dg], f, 1e-2, 1e-3);
    }
}
