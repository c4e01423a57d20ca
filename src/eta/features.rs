//! The image features an eta code is reduced from: torchvision's VGG16 (the weights
//! `texavatars weights install` provides) on the face crop, three ReLU taps average-pooled
//! to a grid.
//!
//! A crop ([`super::crop`], RGB in [0, 1]) is normalised with ImageNet's mean and standard
//! deviation (torchvision's convention for these weights) and run through
//! `vgg16().features`; the taps `relu2_2`, `relu3_3` and `relu4_3` are each average-pooled
//! to [`GRID`] x [`GRID`] cells (PyTorch's `adaptive_avg_pool2d`) and concatenated, tap by
//! tap, channel-major then row-major: `(128 + 256 + 512) x 16 = 14,336` values per image.
//! The grid keeps where on the face a pattern is (the crop follows the tracked head, so a
//! cell covers about the same part of the face in every frame); the three depths see
//! fine texture (wrinkles, shading) to parts of the face.

use burn::tensor::module::adaptive_avg_pool2d;
use burn::tensor::{Device, Tensor, TensorData};

use crate::error::Result;
use crate::metrics::constants::{IMAGENET_MEAN, IMAGENET_STD};
use crate::metrics::nets::{Features, Net};
use crate::metrics::weights::HostWeights;

/// Cells per side of the pooling grid.
pub const GRID: usize = 4;

/// Which of VGG16's five taps (0-based: relu1_2, relu2_2, relu3_3, relu4_3, relu5_3) the
/// code reads.
pub const TAPS: [usize; 3] = [1, 2, 3];

/// The taps' names, for records.
pub const NETWORK: &str = "vgg16 relu2_2+relu3_3+relu4_3, 4x4 average grid";

/// Values per image of each tap, in order (the projection scales each block as a whole).
pub fn blocks() -> Vec<usize> {
    let channels = Net::Vgg16.tap_channels();
    TAPS.iter().map(|&t| channels[t] * GRID * GRID).collect()
}

/// Values per image.
pub fn dims() -> usize {
    blocks().iter().sum()
}

/// VGG16 as a feature extractor for eta.
pub struct Extractor {
    features: Features,
    device: Device,
}

impl Extractor {
    /// Loads the installed VGG16 weights (errors say `texavatars weights install`).
    pub fn load(device: &Device) -> Result<Self> {
        Ok(Extractor {
            features: Features::load(Net::Vgg16, device)?,
            device: device.clone(),
        })
    }

    /// From VGG16 weights in memory (tests use weights of their own).
    pub fn from_host(host: &HostWeights, device: &Device) -> Self {
        Extractor {
            features: Features::from_host(host, device),
            device: device.clone(),
        }
    }

    /// The features of `crops`, one vector of [`dims`] values each.
    ///
    /// # Shapes
    /// - `crops`: N x [size, size, 3] row-major RGB in [0, 1]
    /// - returns N x [`dims`]
    pub fn features(&self, crops: &[Vec<f32>], size: usize) -> Vec<Vec<f32>> {
        if crops.is_empty() {
            return Vec::new();
        }
        let n = crops.len();
        let data: Vec<f32> = crops.iter().flatten().copied().collect();
        let x = Tensor::<4>::from_data(TensorData::new(data, [n, size, size, 3]), &self.device)
            .permute([0, 3, 1, 2]);
        let stat = |v: [f32; 3]| {
            Tensor::<1>::from_data(TensorData::new(v.to_vec(), [3]), &self.device)
                .reshape([1, 3, 1, 1])
        };
        let x = (x - stat(IMAGENET_MEAN)) / stat(IMAGENET_STD);
        let taps = self.features.forward(x);
        let pooled: Vec<Tensor<2>> = TAPS
            .iter()
            .map(|&t| {
                let p = adaptive_avg_pool2d(taps[t].clone(), [GRID, GRID]);
                let [n, c, g, h] = p.dims();
                p.reshape([n, c * g * h])
            })
            .collect();
        let all = Tensor::cat(pooled, 1);
        let d = all.dims()[1];
        let flat: Vec<f32> = all.into_data().iter::<f32>().collect();
        flat.chunks_exact(d).map(<[f32]>::to_vec).collect()
    }
}
