//! LPIPS v0.1 (Zhang et al. 2018, the `lpips` package) on the AlexNet or VGG16 backbone.
//!
//! `d(x, y) = sum_k mean_{h,w} w_k . (u_k(x) - u_k(y))^2` where `u_k` is tap k of the
//! backbone fed `(x - shift) / scale`, unit-normalised over channels (eps 1e-10), and `w_k`
//! the 1x1 linear layer of tap k (no bias).
//!
//! The definition takes images in [-1, 1]. [`Lpips::distance`] takes [0, 1] images and maps
//! them (`normalize=True` in the `lpips` package); [`Lpips::distance_raw`] feeds its inputs
//! as they are, which with [0, 1] images is what GaussianAvatars' evaluation reports (their
//! issue #100: smaller numbers, not comparable with LPIPS proper).
//!
//! Gradients reach the images on an autodiff device, but the channel norm's square root has
//! an infinite derivative where a tap is all zero (as in the reference implementation); use
//! [`crate::metrics::VggPerceptual`] as a training loss.

use burn::module::{Module, Param};
use burn::tensor::module::conv2d;
use burn::tensor::ops::ConvOptions;
use burn::tensor::{Device, Tensor, TensorData};

use crate::error::{Error, Result};
use crate::metrics::constants::{LPIPS_EPS, LPIPS_SCALE, LPIPS_SHIFT};
use crate::metrics::nets::{Features, Net, frozen};
use crate::metrics::weights::{self, HostWeights};

/// The smallest image side LPIPS can score. AlexNet's fifth tap needs one pixel after its
/// second max pool: conv1 (kernel 11, stride 4, padding 2) gives `(n - 7) / 4 + 1`, each pool
/// (kernel 3, stride 2) `(m - 3) / 2 + 1`, and the 5x5 / 3x3 convolutions keep the size, so
/// `n >= 31` (VGG16's four 2x2 pools need only 16).
pub const MIN_SIDE: usize = 31;

/// Fails, naming `what`, when a `height` x `width` image is too small for LPIPS
/// ([`MIN_SIDE`]) instead of letting the convolutions panic.
pub fn check_size(height: usize, width: usize, what: &str) -> Result<()> {
    if height.min(width) < MIN_SIDE {
        return Err(Error::invalid(
            what,
            "size",
            format!(
                "{width}x{height} pixels: LPIPS needs at least {MIN_SIDE} on each side \
                 (score without it: --no-lpips)"
            ),
        ));
    }
    Ok(())
}

/// LPIPS v0.1 with its backbone and linear layers.
#[derive(Module, Debug)]
pub struct Lpips {
    features: Features,
    /// [1, C_k, 1, 1] per tap.
    lins: Vec<Param<Tensor<4>>>,
}

/// A per-channel constant as [1, 3, 1, 1].
pub(crate) fn channel_constant(v: [f32; 3], device: &Device) -> Tensor<4> {
    Tensor::from_data(TensorData::new(v.to_vec(), [1, 3, 1, 1]), device)
}

/// Divides by the channel L2 norm (plus eps), as `lpips.normalize_tensor`.
///
/// # Shapes
/// - `x`: [N, C, H, W]; returns the same
fn unit_normalise(x: Tensor<4>) -> Tensor<4> {
    let norm = (x.clone() * x.clone()).sum_dim(1).sqrt() + LPIPS_EPS;
    x / norm
}

impl Lpips {
    /// Loads LPIPS on `net` from the installed weights (see
    /// [`crate::metrics::weights::weights_dir`]).
    ///
    /// Errors name the missing file and say that `texavatars weights install` installs it.
    pub fn load(net: Net, device: &Device) -> Result<Self> {
        let host = weights::read(&weights::weights_file(net)?, net)?;
        Ok(Self::from_host(&host, device))
    }

    /// Builds LPIPS from weights already read into memory.
    pub fn from_host(host: &HostWeights, device: &Device) -> Self {
        Lpips {
            features: Features::from_host(host, device),
            lins: host
                .lins
                .iter()
                .map(|l| frozen(weights::tensor::<4>(l, device)))
                .collect(),
        }
    }

    /// Which backbone this is.
    pub fn net(&self) -> Net {
        self.features.net()
    }

    /// LPIPS between images in [0, 1] (mapped to [-1, 1] first, as the definition requires).
    ///
    /// # Shapes
    /// - `a`, `b`: [N, 3, H, W]
    /// - returns `[N]`
    pub fn distance(&self, a: Tensor<4>, b: Tensor<4>) -> Tensor<1> {
        self.distance_raw(a * 2.0 - 1.0, b * 2.0 - 1.0)
    }

    /// LPIPS of the inputs exactly as given (the network expects [-1, 1]; [0, 1] images
    /// here give GaussianAvatars' variant).
    ///
    /// # Shapes
    /// - `a`, `b`: [N, 3, H, W]
    /// - returns `[N]`
    pub fn distance_raw(&self, a: Tensor<4>, b: Tensor<4>) -> Tensor<1> {
        let n = a.dims()[0];
        let device = a.device();
        let shift = channel_constant(LPIPS_SHIFT, &device);
        let scale = channel_constant(LPIPS_SCALE, &device);
        // Both images through the backbone as one batch.
        let x = (Tensor::cat(vec![a, b], 0) - shift) / scale;
        let taps = self.features.forward(x);
        let mut total: Option<Tensor<1>> = None;
        for (f, lin) in taps.into_iter().zip(&self.lins) {
            let u = unit_normalise(f);
            let d = u.clone().narrow(0, 0, n) - u.narrow(0, n, n);
            let d = d.clone() * d;
            let l = conv2d(
                d,
                lin.val(),
                None,
                ConvOptions::new([1, 1], [0, 0], [1, 1], 1),
            );
            let [_, _, h, w] = l.dims();
            let m = l.reshape([n, h * w]).mean_dim(1).reshape([n]);
            total = Some(match total {
                Some(t) => t + m,
                None => m,
            });
        }
        total.unwrap_or_else(|| Tensor::zeros([n], &device))
    }
}
