//! LPIPS v0.1 on VGG16 ([`crate::metrics::Lpips::distance`] with [`Net::Vgg16`]) on the
//! host, through the perceptual loss's CPU network ([`VggCpu`]: Winograd convolutions on
//! channels-last maps). `eval` scores every image with it on the CPU backends: through
//! burn's generic convolutions, LPIPS-vgg took most of an evaluation's time at 550 x 802.
//!
//! The input scaling is LPIPS's own (`lpips.pretrained_networks.ScalingLayer`: images
//! mapped to [-1, 1], then `(x - shift) / scale`); each tap is unit-normalised over its
//! channels (`lpips.normalize_tensor`, eps 1e-10), the squared difference weighted by the
//! tap's linear layer, averaged over the tap's pixels and summed over the five taps.
//!
//! Thread mapping: the network's, as [`VggCpu`]'s; each tap's distance is a parallel sum
//! over blocks of pixels.
//!
//! The reference twin is [`crate::metrics::Lpips`] on burn's ops, itself checked against
//! the `lpips` package's outputs; `tests/cpu/metrics.rs` compares this path with both.

use rayon::prelude::*;
use texavatars_cpu::map::Map;

use crate::error::Result;
use crate::metrics::constants::{LPIPS_EPS, LPIPS_SCALE, LPIPS_SHIFT};
use crate::metrics::nets::Net;
use crate::metrics::vgg_cpu::VggCpu;
use crate::metrics::weights::{self, HostWeights};

/// Pixels per parallel block of a tap's distance.
const PIXELS_PER_BLOCK: usize = 512;

/// LPIPS-vgg on the host (see the module docs).
#[derive(Debug)]
pub struct LpipsVggCpu {
    net: VggCpu,
    /// The five taps' linear weights, `C_k` each.
    lins: Vec<Vec<f32>>,
}

impl LpipsVggCpu {
    /// Loads the installed VGG16 LPIPS weights.
    ///
    /// Errors name the missing file and say that `texavatars weights install` installs it.
    pub fn load() -> Result<Self> {
        let host = weights::read(&weights::weights_file(Net::Vgg16)?, Net::Vgg16)?;
        Ok(Self::from_host(&host))
    }

    /// Builds the metric from VGG16 weights already read into memory.
    ///
    /// # Panics
    /// If `host` is not VGG16 or lacks a linear layer per tap.
    pub fn from_host(host: &HostWeights) -> Self {
        assert_eq!(host.net, Net::Vgg16, "LPIPS-vgg needs VGG16 weights");
        let channels = Net::Vgg16.tap_channels();
        assert_eq!(host.lins.len(), channels.len(), "one linear layer per tap");
        for (lin, &c) in host.lins.iter().zip(&channels) {
            assert_eq!(lin.data.len(), c, "linear layer of a {c}-channel tap");
        }
        LpipsVggCpu {
            net: VggCpu::new(host),
            lins: host.lins.iter().map(|l| l.data.clone()).collect(),
        }
    }

    /// LPIPS between two images, as [`crate::metrics::Lpips::distance`]: inputs in [0, 1].
    ///
    /// # Shapes
    /// - `a`, `b`: `[H, W, 3]` row-major (the rasterizer's layout), H and W at least 16
    pub fn distance(&self, a: &[f32], b: &[f32], height: usize, width: usize) -> f64 {
        assert_eq!(a.len(), height * width * 3, "LPIPS-vgg: image a");
        assert_eq!(b.len(), height * width * 3, "LPIPS-vgg: image b");
        let taps = self
            .net
            .taps(vec![scaled(a, height, width), scaled(b, height, width)]);
        let [ta, tb]: [Vec<Map>; 2] = taps.try_into().expect("taps of two images");
        ta.iter()
            .zip(&tb)
            .zip(&self.lins)
            .map(|((x, y), lin)| tap_distance(&x.data, &y.data, lin))
            .sum()
    }
}

/// An `[H, W, 3]` image in [0, 1] as the network's input: `(2x - 1 - shift) / scale`.
fn scaled(img: &[f32], h: usize, w: usize) -> Map {
    let data = img
        .chunks_exact(3)
        .flat_map(|p| (0..3).map(move |c| (2.0 * p[c] - 1.0 - LPIPS_SHIFT[c]) / LPIPS_SCALE[c]))
        .collect();
    Map { data, h, w }
}

/// One tap's term: the mean over pixels of `sum_c lin_c (x_c / |x| - y_c / |y|)^2`, with
/// `|.|` the channel L2 norm plus [`LPIPS_EPS`].
fn tap_distance(x: &[f32], y: &[f32], lin: &[f32]) -> f64 {
    let c = lin.len();
    let pixels = x.len() / c;
    let unit = |p: &[f32]| 1.0 / (p.iter().map(|v| v * v).sum::<f32>().sqrt() + LPIPS_EPS);
    let sum: f64 = x
        .par_chunks(c * PIXELS_PER_BLOCK)
        .zip(y.par_chunks(c * PIXELS_PER_BLOCK))
        .map(|(xs, ys)| {
            xs.chunks_exact(c)
                .zip(ys.chunks_exact(c))
                .map(|(px, py)| {
                    let (ix, iy) = (unit(px), unit(py));
                    px.iter()
                        .zip(py)
                        .zip(lin)
                        .map(|((&u, &v), &l)| {
                            let d = u * ix - v * iy;
                            l * d * d
                        })
                        .sum::<f32>() as f64
                })
                .sum::<f64>()
        })
        .sum();
    sum / pixels.max(1) as f64
}
