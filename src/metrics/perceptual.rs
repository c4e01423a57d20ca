//! The VGG perceptual loss of TexAvatars' training objective (method §6, weight 0.01,
//! switched on after half of the iterations).
//!
//! The paper says only "perceptual loss on VGG features". This implementation follows the
//! form of the widely copied `VGGPerceptualLoss` (a per-block L1 distance of VGG16 features,
//! summed over blocks), with all five taps: images in [0, 1] are normalised with the ImageNet
//! mean and standard deviation (what torchvision's VGG16 was trained on), passed through the
//! frozen VGG16, and the loss is the sum over relu1_2, relu2_2, relu3_3, relu4_3 and relu5_3
//! of the **mean absolute difference (L1)** of the features. L1 rather than L2 keeps the
//! deep taps (large activations) from dominating the sum quadratically and is robust to the
//! early, far-from-converged renders. No resizing, no per-tap weights.

use burn::module::Module;
use burn::tensor::{Device, Tensor};

use crate::error::Result;
use crate::metrics::constants::{IMAGENET_MEAN, IMAGENET_STD};
use crate::metrics::lpips::channel_constant;
use crate::metrics::nets::{Features, Net};
use crate::metrics::weights::{self, HostWeights};

/// VGG16 perceptual loss (frozen backbone, gradients reach the images).
#[derive(Module, Debug)]
pub struct VggPerceptual {
    features: Features,
}

impl VggPerceptual {
    /// Loads VGG16 from the installed weights.
    ///
    /// Errors name the missing file and say that `texavatars weights install` installs it.
    pub fn load(device: &Device) -> Result<Self> {
        let host = weights::read(&weights::weights_file(Net::Vgg16)?, Net::Vgg16)?;
        Ok(Self::from_host(&host, device))
    }

    /// Builds the loss from VGG16 weights already read into memory.
    ///
    /// # Panics
    /// If `host` is not VGG16.
    pub fn from_host(host: &HostWeights, device: &Device) -> Self {
        assert_eq!(host.net, Net::Vgg16, "the perceptual loss uses VGG16");
        VggPerceptual {
            features: Features::from_host(host, device),
        }
    }

    /// Sum over the five taps of the mean absolute feature difference.
    ///
    /// # Shapes
    /// - `a`, `b`: [N, 3, H, W], values in [0, 1] (H, W at least 16)
    /// - returns `[1]`
    pub fn forward(&self, a: Tensor<4>, b: Tensor<4>) -> Tensor<1> {
        let n = a.dims()[0];
        let device = a.device();
        let mean = channel_constant(IMAGENET_MEAN, &device);
        let std = channel_constant(IMAGENET_STD, &device);
        // Two passes rather than one over the concatenated pair: a reference image that
        // needs no gradient (a ground truth) then stays off the autodiff graph, and the
        // backward pass runs through the VGG for `a` alone (measured: a fifth less time per
        // training step with the VGG loss on, at 138 x 200 on 2 CPU cores).
        let fa = self.features.forward((a - mean.clone()) / std.clone());
        let fb = self.features.forward((b - mean) / std);
        let mut total: Option<Tensor<1>> = None;
        for (fa, fb) in fa.into_iter().zip(fb) {
            let d = (fa - fb).abs();
            let [_, c, h, w] = d.dims();
            let m = d.reshape([n * c * h * w]).mean();
            total = Some(match total {
                Some(t) => t + m,
                None => m,
            });
        }
        total.unwrap_or_else(|| Tensor::zeros([1], &device))
    }
}
