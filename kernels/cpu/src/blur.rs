//! SSIM's Gaussian blur as one op with a handwritten backward: every `[H, W]` plane
//! correlated with the separable 11-tap window ([`gaussian_window`]) along the rows, then
//! along the columns, zero padding, same size.
//!
//! Why: composed from burn's `conv2d` (a 1x11 and an 11x1 convolution with one channel),
//! the backward runs burn's transposed convolution, a direct loop on the CPU backends that
//! was a large share of a `cpu`-configuration training step. Here both directions are two
//! 11-tap passes per plane.

//! The backward is the forward applied to the gradient: a correlation with zero padding is
//! adjoint to the correlation with the mirrored kernel, and the Gaussian window is
//! symmetric. `blur_is_self_adjoint` checks `<blur(x), y> = <x, blur(y)>`.
//!
//! Thread mapping (CPU): one task per plane (batch item x channel); each task does the row
//! pass into a scratch plane, then the column pass.
//!
//! Backends: flex and ndarray run the passes here; burn's cubecl backend (wgpu) composes
//! burn's `conv2d` (the trait's default body, the formula before this op). The reference
//! twin is that composition with burn's autodiff.

// burn-ndarray is deprecated in burn 0.22; the design keeps it alongside flex.
#![allow(deprecated)]

use burn::backend::autodiff::{
    Autodiff,
    checkpoint::{base::Checkpointer, strategy::CheckpointStrategy},
    grads::Gradients,
    ops::{Backward, Ops},
};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, Cube, TensorMetadata, backend_extension};
use burn::tensor::module::conv2d;
use burn::tensor::ops::ConvOptions;
use burn::tensor::{Shape, Tensor, TensorData};
use rayon::prelude::*;

use crate::autodiff;
use crate::host::{HostIo, floats};

/// The window's side (pixels): SSIM's 11x11 Gaussian window in 3DGS / GaussianAvatars
/// (`utils/loss_utils.py`, `ssim()`, after Wang et al. 2004).
pub const SSIM_WINDOW: usize = 11;

/// The window's standard deviation (pixels), as in 3DGS / GaussianAvatars (`create_window`'s
/// `gaussian(window_size, 1.5)`).
pub const SSIM_SIGMA: f64 = 1.5;

/// The normalised 1D Gaussian window (the 2D window is its outer product).
pub fn gaussian_window() -> Vec<f32> {
    let c = (SSIM_WINDOW / 2) as f64;
    let g: Vec<f64> = (0..SSIM_WINDOW)
        .map(|x| (-(x as f64 - c).powi(2) / (2.0 * SSIM_SIGMA * SSIM_SIGMA)).exp())
        .collect();
    let s: f64 = g.iter().sum();
    g.iter().map(|v| (v / s) as f32).collect()
}

/// Backends with the Gaussian blur of this module.
#[backend_extension(NdArray, Flex, Cube, Autodiff)]
pub trait BlurBackend: Backend {
    /// Every plane of `x` `[N, C, H, W]` blurred. Default: burn's `conv2d`.
    fn gaussian_blur(x: FloatTensor<Self>) -> FloatTensor<Self> {
        composed_primitive::<Self>(x)
    }
}

/// The trait's default body: burn's `conv2d` on primitives, a 1x11 then an 11x1
/// convolution per plane.
fn composed_primitive<B: Backend>(x: FloatTensor<B>) -> FloatTensor<B> {
    let shape = x.shape().to_vec();
    let [n, c, h, w] = [shape[0], shape[1], shape[2], shape[3]];
    let device = x.device();
    let g = gaussian_window();
    let r = SSIM_WINDOW / 2;
    let kernel = |s: [usize; 4]| B::float_from_data(TensorData::new(g.clone(), s), &device);
    let x = B::float_reshape(x, Shape::from(vec![n * c, 1, h, w]));
    let x = B::conv2d(
        x,
        kernel([1, 1, 1, SSIM_WINDOW]),
        None,
        ConvOptions::new([1, 1], [0, r], [1, 1], 1),
    );
    let x = B::conv2d(
        x,
        kernel([1, 1, SSIM_WINDOW, 1]),
        None,
        ConvOptions::new([1, 1], [r, 0], [1, 1], 1),
    );
    B::float_reshape(x, Shape::from(shape))
}

/// The blur from burn's `conv2d` on tensors (the reference twin; the trait's default body
/// is the same on primitives): a 1x11 then an 11x1 convolution per plane.
///
/// # Shapes
/// - `x`: [N, C, H, W]
/// - returns [N, C, H, W]
pub fn composed(x: Tensor<4>) -> Tensor<4> {
    let [n, c, h, w] = x.dims();
    let device = x.device();
    let g = gaussian_window();
    let r = SSIM_WINDOW / 2;
    let kx = Tensor::<4>::from_data(TensorData::new(g.clone(), [1, 1, 1, SSIM_WINDOW]), &device);
    let ky = Tensor::<4>::from_data(TensorData::new(g, [1, 1, SSIM_WINDOW, 1]), &device);
    let x = x.reshape([n * c, 1, h, w]);
    let x = conv2d(x, kx, None, ConvOptions::new([1, 1], [0, r], [1, 1], 1));
    let x = conv2d(x, ky, None, ConvOptions::new([1, 1], [r, 0], [1, 1], 1));
    x.reshape([n, c, h, w])
}

/// Blurs every channel of `x` with the Gaussian window, zero padding, same size, on any
/// backend (see the module docs).
///
/// # Shapes
/// - `x`: [N, C, H, W]
/// - returns [N, C, H, W]
pub fn gaussian_blur(x: Tensor<4>) -> Tensor<4> {
    Tensor::from_dispatch(<burn::backend::Dispatch as BlurBackend>::gaussian_blur(
        x.into_dispatch(),
    ))
}

// ---------------------------------------------------------------------------------------------
// Host implementation.

/// Blurs the `[h, w]` planes of `x` in place.
fn host_blur(x: &mut [f32], [h, w]: [usize; 2]) {
    let p = h * w;
    if p == 0 {
        return;
    }
    let g = gaussian_window();
    let r = SSIM_WINDOW / 2;
    x.par_chunks_mut(p)
        .for_each_init(Vec::new, |tmp: &mut Vec<f32>, plane| {
            tmp.resize(p, 0.0);
            // Rows: tmp[y, x] = Σ_k g[k] · plane[y, x + k - r], one tap at a time over the
            // pixels it reaches (element-wise, so in SIMD lanes).
            for (src, dst) in plane.chunks_exact(w).zip(tmp.chunks_exact_mut(w)) {
                dst.fill(0.0);
                for (k, gk) in g.iter().enumerate() {
                    // Output x reads input x + k - r; both inside [0, w).
                    let (x0, s0) = if k < r { (r - k, 0) } else { (0, k - r) };
                    let len = w.saturating_sub(x0.max(s0));
                    if len == 0 {
                        continue;
                    }
                    dst[x0..x0 + len]
                        .iter_mut()
                        .zip(&src[s0..s0 + len])
                        .for_each(|(d, s)| *d += gk * s);
                }
            }
            // Columns: plane[y, x] = Σ_k g[k] · tmp[y + k - r, x], a row of the output at a time.
            for (y0, dst) in plane.chunks_exact_mut(w).enumerate() {
                dst.fill(0.0);
                let lo = y0.saturating_sub(r);
                let hi = (y0 + r + 1).min(h);
                for (y, gk) in (lo..hi).zip(&g[lo + r - y0..]) {
                    let src = &tmp[y * w..][..w];
                    dst.iter_mut().zip(src).for_each(|(d, s)| *d += gk * s);
                }
            }
        });
}

impl<H: HostIo> BlurBackend for H {
    fn gaussian_blur(x: FloatTensor<Self>) -> FloatTensor<Self> {
        let device = x.device();
        let shape = x.shape().to_vec();
        assert_eq!(
            shape.len(),
            4,
            "gaussian_blur: x is {shape:?}, not [N, C, H, W]"
        );
        let mut v = H::floats(x);
        host_blur(&mut v, [shape[2], shape[3]]);
        floats::<H>(v, &shape, &device)
    }
}

/// The GPU backend composes burn's `conv2d` (the trait's default body).
impl BlurBackend for Cube {}

// ---------------------------------------------------------------------------------------------
// Autodiff: the backward is the blur of the gradient (see the module docs).

#[derive(Debug)]
struct BlurBackwardOp;

impl<B: Backend + BlurBackend> Backward<B, 1> for BlurBackwardOp {
    type State = ();

    fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _: &mut Checkpointer) {
        autodiff::backward::<B, _, 1>(ops, grads, |(), grad| [B::gaussian_blur(grad)]);
    }
}

impl<B: Backend + BlurBackend, C: CheckpointStrategy> BlurBackend for Autodiff<B, C> {
    fn gaussian_blur(x: FloatTensor<Self>) -> FloatTensor<Self> {
        let nodes = [x.node()];
        let inner = x.into_primitive();
        BlurBackwardOp
            .prepare::<C>(nodes)
            .compute_bound()
            .stateless(B::gaussian_blur(inner))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::check::on_cpu_backends;
    use burn::tensor::{Device, Distribution};

    fn host<const D: usize>(t: Tensor<D>) -> Vec<f32> {
        t.into_data().iter::<f32>().collect()
    }

    fn max_abs(a: &[f32], b: &[f32]) -> f32 {
        assert_eq!(a.len(), b.len());
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max)
    }

    /// Values and gradients against the `conv2d` composition (the reference twin), with
    /// planes smaller than the window (every tap hits the padding) and larger ones.
    fn check(device: Device) {
        for shape in [[2, 3, 13, 17], [1, 2, 4, 5], [1, 1, 1, 1], [1, 1, 30, 12]] {
            device.seed(shape.iter().sum::<usize>() as u64);
            let x = Tensor::<4>::random(shape, Distribution::Uniform(0.0, 1.0), &device);
            let dy = Tensor::<4>::random(shape, Distribution::Normal(0.0, 1.0), &device);
            let run = |ours: bool| {
                let xa = x.clone().require_grad();
                let y = if ours {
                    gaussian_blur(xa.clone())
                } else {
                    composed(xa.clone())
                };
                let grads = (y.clone() * dy.clone()).sum().backward();
                (host(y), host(xa.grad(&grads).expect("x grad")))
            };
            let ((y, dx), (y_ref, dx_ref)) = (run(true), run(false));
            assert!(max_abs(&y, &y_ref) < 1e-6, "{shape:?}: forward");
            assert!(max_abs(&dx, &dx_ref) < 1e-5, "{shape:?}: gradient");
        }
    }

    on_cpu_backends!(check: matches_conv2d_on_flex, matches_conv2d_on_ndarray);

    /// The trait's default body (what wgpu runs) against the host passes, on flex.
    #[test]
    fn default_body_matches_the_host_passes() {
        use burn::backend::ops::FloatTensorOps;
        type F = burn::backend::Flex;
        let shape = [2usize, 1, 12, 7];
        let v: Vec<f32> = (0..168).map(|i| (i as f32 * 0.61).sin()).collect();
        let x = || F::float_from_data(TensorData::new(v.clone(), shape), &Default::default());
        let fused = F::floats(<F as BlurBackend>::gaussian_blur(x()));
        let composed = F::floats(composed_primitive::<F>(x()));
        assert!(max_abs(&fused, &composed) < 1e-6);
    }

    /// `<blur(x), y> = <x, blur(y)>`: what the backward relies on.
    #[test]
    fn blur_is_self_adjoint() {
        let (h, w) = (9, 14);
        let x: Vec<f32> = (0..h * w).map(|i| ((i * 37 % 19) as f32) / 19.0).collect();
        let y: Vec<f32> = (0..h * w)
            .map(|i| ((i * 11 % 23) as f32) / 23.0 - 0.5)
            .collect();
        let (mut bx, mut by) = (x.clone(), y.clone());
        host_blur(&mut bx, [h, w]);
        host_blur(&mut by, [h, w]);
        let dot = |a: &[f32], b: &[f32]| {
            a.iter()
                .zip(b)
                .map(|(a, b)| *a as f64 * *b as f64)
                .sum::<f64>()
        };
        assert!((dot(&bx, &y) - dot(&x, &by)).abs() < 1e-5);
    }

    /// Central finite differences of `sum(blur(x) * dy)` (linear, so exact up to rounding).
    #[test]
    fn finite_differences() {
        let device = Device::flex().autodiff();
        let shape = [1usize, 1, 5, 6];
        let xs: Vec<f32> = (0..30).map(|i| (i as f32 * 0.37).sin()).collect();
        let ds: Vec<f32> = (0..30).map(|i| (i as f32 * 0.73).cos()).collect();
        let f = |xv: &[f32]| -> f64 {
            let x = Tensor::<4>::from_data(TensorData::new(xv.to_vec(), shape), &device);
            host(gaussian_blur(x))
                .iter()
                .zip(&ds)
                .map(|(y, d)| *y as f64 * *d as f64)
                .sum()
        };
        let x = Tensor::<4>::from_data(TensorData::new(xs.clone(), shape), &device).require_grad();
        let dy = Tensor::<4>::from_data(TensorData::new(ds.clone(), shape), &device);
        let grads = (gaussian_blur(x.clone()) * dy).sum().backward();
        let dx = host(x.grad(&grads).expect("x grad"));
        let eps = 1e-2f32;
        for (i, a) in dx.iter().enumerate() {
            let (mut p, mut m) = (xs.clone(), xs.clone());
            p[i] += eps;
            m[i] -= eps;
            let fd = (f(&p) - f(&m)) / (2.0 * eps as f64);
            assert!((fd - *a as f64).abs() < 1e-4, "[{i}]: {fd} vs {a}");
        }
    }
}
