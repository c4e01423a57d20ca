//! The training objective of method §6:
//!
//! `L = 0.8 L1 + 0.2 (1 - SSIM) + lambda_vgg L_VGG + 0.01 L_pos + 1.0 L_scale`
//!
//! - L1 and SSIM ([`crate::metrics::l1`], [`crate::metrics::ssim_loss`]: 11x11 Gaussian
//!   window, sigma 1.5) between the render and the ground truth on the white background,
//!   over the full image;
//! - L_VGG ([`crate::metrics::VggPerceptual`]), weight 0.01, only once the iteration has
//!   reached the configured fraction of the run (default one half);
//! - L_pos = mean over texels of `relu(|mu^l| - 1)` and L_scale = mean over texels of
//!   `|relu(exp(s^l) - 0.6)|`, on the decoders' local maps (all texels of all frames).
//!
//! The paper writes `|.|` for the two regularizers without saying which norm. They are
//! GaussianAvatars' (same thresholds 1.0 and 0.6 and weights 0.01 and 1.0), whose code takes
//! the Euclidean norm of the 3-vector per Gaussian (`_xyz.norm(dim=1)`,
//! `relu(exp(_scaling) - 0.6).norm(dim=1)`) and then the mean; this implementation does the
//! same per texel (with the safe norm of [`NORM_EPS`]).

use burn::tensor::Tensor;
use serde::{Deserialize, Serialize};

use super::constants::*;
use crate::metrics::{self, VggPerceptual};
use crate::models::texavatars::LocalMaps;

/// Weights and thresholds of the objective (defaults: the paper's, [`super::constants`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LossWeights {
    /// L1 weight (0.8).
    pub l1: f64,
    /// `1 - SSIM` weight (0.2).
    pub dssim: f64,
    /// VGG weight once on (0.01).
    pub vgg: f64,
    /// L_pos weight (0.01).
    pub position: f64,
    /// L_pos threshold on `|mu^l|` (1.0).
    pub position_threshold: f64,
    /// L_scale weight (1.0).
    pub scale: f64,
    /// L_scale threshold on `exp(s^l)` (0.6).
    pub scale_threshold: f64,
}

impl Default for LossWeights {
    fn default() -> Self {
        LossWeights {
            l1: L1_WEIGHT,
            dssim: DSSIM_WEIGHT,
            vgg: VGG_WEIGHT,
            position: POSITION_WEIGHT,
            position_threshold: POSITION_THRESHOLD,
            scale: SCALE_WEIGHT,
            scale_threshold: SCALE_THRESHOLD,
        }
    }
}

/// The objective and each of its terms, unweighted (`total` is the weighted sum).
///
/// # Shapes
/// - every field: `[1]`
#[derive(Clone, Debug)]
pub struct LossTerms {
    /// The weighted sum that is minimised.
    pub total: Tensor<1>,
    /// Mean absolute error.
    pub l1: Tensor<1>,
    /// `1 - SSIM`.
    pub dssim: Tensor<1>,
    /// The VGG perceptual loss; `None` while it is off.
    pub vgg: Option<Tensor<1>>,
    /// L_pos.
    pub position: Tensor<1>,
    /// L_scale.
    pub scale: Tensor<1>,
}

/// Per-texel safe Euclidean norm over the channel axis.
///
/// # Shapes
/// - `x`: [N, 3, R, R]
/// - returns [N, 1, R, R]
fn channel_norm(x: Tensor<4>) -> Tensor<4> {
    (x.clone() * x)
        .sum_dim(1)
        .add_scalar(NORM_EPS * NORM_EPS)
        .sqrt()
}

/// The mean of a [N, 1, R, R] map, as [1].
fn mean_all(x: Tensor<4>) -> Tensor<1> {
    let [n, c, h, w] = x.dims();
    x.reshape([n * c * h * w]).mean()
}

/// L_pos = mean over texels of `relu(|mu^l| - threshold)`.
///
/// # Shapes
/// - returns `[1]`
pub fn position_loss(maps: &LocalMaps, threshold: f64) -> Tensor<1> {
    let excess = channel_norm(maps.offset()).sub_scalar(threshold);
    mean_all(burn::tensor::activation::relu(excess))
}

/// L_scale = mean over texels of `|relu(exp(s^l) - threshold)|`.
///
/// # Shapes
/// - returns `[1]`
pub fn scale_loss(maps: &LocalMaps, threshold: f64) -> Tensor<1> {
    let excess = burn::tensor::activation::relu(maps.log_scale().exp().sub_scalar(threshold));
    mean_all(channel_norm(excess))
}

/// The objective for renders against ground-truth images. `vgg` is the perceptual loss to
/// add (pass `None` while it is off, or in the "w/o VGG" ablation).
///
/// # Shapes
/// - `renders`, `images`: [N, H, W, 3], RGB (the ground truth in [0, 1])
/// - `maps`: the decoders' outputs that produced `renders`
pub fn objective(
    renders: Tensor<4>,
    images: Tensor<4>,
    maps: &LocalMaps,
    vgg: Option<&VggPerceptual>,
    weights: &LossWeights,
) -> LossTerms {
    let a = renders.permute([0, 3, 1, 2]);
    let b = images.permute([0, 3, 1, 2]);
    let l1 = metrics::l1(a.clone(), b.clone());
    let dssim = metrics::ssim_loss(a.clone(), b.clone());
    let position = position_loss(maps, weights.position_threshold);
    let scale = scale_loss(maps, weights.scale_threshold);
    let mut total = l1.clone().mul_scalar(weights.l1)
        + dssim.clone().mul_scalar(weights.dssim)
        + position.clone().mul_scalar(weights.position)
        + scale.clone().mul_scalar(weights.scale);
    let vgg = vgg.map(|net| net.forward(a, b));
    if let Some(v) = &vgg {
        total = total + v.clone().mul_scalar(weights.vgg);
    }
    LossTerms {
        total,
        l1,
        dssim,
        vgg,
        position,
        scale,
    }
}
