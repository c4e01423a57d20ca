//! Image metrics and losses: L1, PSNR, SSIM, LPIPS v0.1 (AlexNet, VGG16) and the VGG16
//! perceptual loss, with the pretrained weights they need ([`weights`]).
//!
//! All take images as [N, 3, H, W] float tensors (see [`image_tensor`] and [`hwc_to_nchw`])
//! on any device; on an autodiff device every metric is differentiable with respect to the
//! images. The numbers are defined as GaussianAvatars / TexAvatars evaluate: full images,
//! clamped to [0, 1] for PSNR.

pub mod constants;
pub mod lpips;
pub mod lpips_cpu;
pub mod nets;
pub mod perceptual;
pub mod ssim;
pub mod vgg_cpu;
pub mod weights;

use burn::tensor::{Device, Tensor, TensorData};

pub use lpips::Lpips;
pub use lpips_cpu::LpipsVggCpu;
pub use nets::{Features, Net};
pub use perceptual::VggPerceptual;
pub use ssim::{ssim, ssim_loss};

use crate::io::image::RgbImage;

/// Whether `device` is one of the CPU backends (`flex`, `ndarray`), where the host paths
/// of the VGG16 loss and LPIPS ([`vgg_cpu`], [`lpips_cpu`]) run instead of burn's ops.
pub(crate) fn on_cpu(device: &Device) -> bool {
    matches!(
        device.clone().without_autodiff().as_dispatch(),
        burn::backend::DispatchDevice::Flex(_) | burn::backend::DispatchDevice::NdArray(_)
    )
}

/// A host RGB image as a [1, 3, H, W] tensor on `device`.
pub fn image_tensor(img: &RgbImage, device: &Device) -> Tensor<4> {
    let t = Tensor::<3>::from_data(
        TensorData::new(img.rgb.clone(), [img.height, img.width, 3]),
        device,
    );
    hwc_to_nchw(t)
}

/// An [H, W, 3] image (as the rasterizer's RGB output) as [1, 3, H, W].
///
/// # Shapes
/// - `t`: [H, W, 3]
/// - returns [1, 3, H, W]
pub fn hwc_to_nchw(t: Tensor<3>) -> Tensor<4> {
    t.permute([2, 0, 1]).unsqueeze_dim::<4>(0)
}

/// Mean absolute difference over everything (the L1 photometric loss).
///
/// # Shapes
/// - `a`, `b`: [N, C, H, W]
/// - returns `[1]`
pub fn l1(a: Tensor<4>, b: Tensor<4>) -> Tensor<1> {
    let [n, c, h, w] = a.dims();
    (a - b).abs().reshape([n * c * h * w]).mean()
}

/// Mean squared difference per image, over pixels and channels.
///
/// # Shapes
/// - `a`, `b`: [N, C, H, W]
/// - returns `[N]`
pub fn mse(a: Tensor<4>, b: Tensor<4>) -> Tensor<1> {
    let [n, c, h, w] = a.dims();
    let d = a - b;
    mean_per_image(d.clone() * d, [n, c, h, w])
}

/// The mean over channels and pixels per image, in two stages (per row, then over rows): a
/// single f32 reduction over a whole image loses digits on some backends.
///
/// # Shapes
/// - `x`: [N, C, H, W]
/// - returns [N]
pub(crate) fn mean_per_image(x: Tensor<4>, [n, c, h, w]: [usize; 4]) -> Tensor<1> {
    x.reshape([n, c * h, w])
        .mean_dim(2)
        .mean_dim(1)
        .reshape([n])
}

/// PSNR in dB per image, `-10 log10(MSE)`, both images clamped to [0, 1] first (the peak is
/// 1). Identical images give `+inf` (serialised as JSON `null`).
///
/// # Shapes
/// - `a`, `b`: [N, C, H, W]
/// - returns `[N]`
pub fn psnr(a: Tensor<4>, b: Tensor<4>) -> Tensor<1> {
    let m = mse(a.clamp(0.0, 1.0), b.clamp(0.0, 1.0));
    m.log() * (-10.0 / std::f32::consts::LN_10)
}

/// The values of a 1D tensor on the host, as f64.
pub fn to_host(t: Tensor<1>) -> Vec<f64> {
    t.into_data().iter::<f32>().map(|v| v as f64).collect()
}
