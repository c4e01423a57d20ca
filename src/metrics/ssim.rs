//! SSIM in the form 3DGS and GaussianAvatars train and evaluate with: an 11x11 Gaussian
//! window (sigma 1.5) applied per channel as a "same"-size convolution with zero padding,
//! C1 = 0.01^2, C2 = 0.03^2, the SSIM map averaged over all pixels and channels.
//!
//! The window is separable, so it is applied as a 1x11 then an 11x1 convolution (exactly the
//! 2D window, zero padding included), as one op with a handwritten backward
//! ([`texavatars_cpu::blur`]); the rest is plain tensor ops, differentiable on an autodiff
//! device.

use burn::tensor::Tensor;

use crate::metrics::constants::{SSIM_C1, SSIM_C2};
pub use texavatars_cpu::blur::{gaussian_blur, gaussian_window};

/// The SSIM map.
///
/// # Shapes
/// - `a`, `b`: [N, C, H, W], values in [0, 1]
/// - returns [N, C, H, W]
pub fn ssim_map(a: Tensor<4>, b: Tensor<4>) -> Tensor<4> {
    let [n, c, h, w] = a.dims();
    // Five blurs rather than one of the five maps stacked: splitting the blurred stack into
    // tracked channel slices made autodiff build a zero-filled gradient of the whole stack
    // per slice and add the five (the largest of a `cpu` training step's slice gradients,
    // docs/performance.md). Each plane is blurred alone either way, so the values are the
    // same.
    let (mu1, mu2) = (gaussian_blur(a.clone()), gaussian_blur(b.clone()));
    let (e11, e22) = (
        gaussian_blur(a.clone() * a.clone()),
        gaussian_blur(b.clone() * b.clone()),
    );
    let e12 = gaussian_blur(a * b);
    let mu11 = mu1.clone() * mu1.clone();
    let mu22 = mu2.clone() * mu2.clone();
    let mu12 = mu1 * mu2;
    let s11 = e11 - mu11.clone();
    let s22 = e22 - mu22.clone();
    let s12 = e12 - mu12.clone();
    let num = (mu12 * 2.0 + SSIM_C1) * (s12 * 2.0 + SSIM_C2);
    let den = (mu11 + mu22 + SSIM_C1) * (s11 + s22 + SSIM_C2);
    let map = num / den;
    debug_assert_eq!(map.dims(), [n, c, h, w]);
    map
}

/// SSIM per image: the map's mean over channels and pixels.
///
/// # Shapes
/// - `a`, `b`: [N, C, H, W], values in [0, 1]
/// - returns `[N]`
pub fn ssim(a: Tensor<4>, b: Tensor<4>) -> Tensor<1> {
    let dims = a.dims();
    crate::metrics::mean_per_image(ssim_map(a, b), dims)
}

/// The SSIM training loss `1 - SSIM`, averaged over the batch.
///
/// # Shapes
/// - `a`, `b`: [N, C, H, W], values in [0, 1]
/// - returns `[1]`
pub fn ssim_loss(a: Tensor<4>, b: Tensor<4>) -> Tensor<1> {
    ssim(a, b).mean().neg() + 1.0
}
