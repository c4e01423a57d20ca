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
//!
//! Two implementations of the same loss: on the CPU backends (flex, ndarray) a backend
//! extension with a handwritten backward runs the whole loss on host memory
//! ([`crate::metrics::vgg_cpu`], the faster of the two there); on wgpu the loss is burn's
//! own `Conv2d` / `max_pool2d` / `relu` stack ([`Features`]) differentiated by autodiff, which
//! is also the CPU path's reference twin in the tests.

// burn-ndarray is deprecated in burn 0.22; the design keeps it alongside flex.
#![allow(deprecated)]

use std::sync::Arc;

use burn::backend::autodiff::{
    Autodiff,
    checkpoint::{base::Checkpointer, strategy::CheckpointStrategy},
    grads::Gradients,
    ops::{Backward, Ops},
};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, ExtensionType, Flex, NdArray, TensorMetadata, backend_extension};
use burn::module::Module;
use burn::tensor::{Device, Tensor};

use crate::error::Result;
use crate::metrics::constants::{IMAGENET_MEAN, IMAGENET_STD};
use crate::metrics::lpips::channel_constant;
use crate::metrics::nets::{Features, Net};
use crate::metrics::on_cpu;
use crate::metrics::vgg_cpu::{Saved, VggCpu};
use crate::metrics::weights::{self, HostWeights};
use texavatars_cpu::autodiff;
use texavatars_cpu::host::{HostIo, floats};

/// VGG16 perceptual loss (frozen backbone, gradients reach the images).
#[derive(Module, Debug)]
pub struct VggPerceptual {
    features: Features,
    /// The same weights prepared for the CPU extension.
    #[module(skip)]
    cpu: CpuVgg,
}

/// The CPU network handed to the extension op (shared, never copied).
#[derive(Clone, Debug)]
pub struct CpuVgg(Arc<VggCpu>);

/// The two images of one loss evaluation.
///
/// # Shapes
/// - `a`, `b`: [N, 3, H, W]
#[derive(ExtensionType, Debug, Clone)]
pub struct ImagePair<B: Backend> {
    pub a: FloatTensor<B>,
    pub b: FloatTensor<B>,
}

/// Backends with the CPU perceptual loss (flex, ndarray, and autodiff over them).
#[backend_extension(NdArray, Flex, Autodiff)]
pub trait PerceptualBackend: Backend {
    /// The loss of [`VggPerceptual::forward`] → `[1]`.
    fn vgg_l1(#[extension_type] ab: ImagePair<Self>, net: CpuVgg) -> FloatTensor<Self>;
}

/// `[N, 3, H, W]` of a tensor primitive.
fn nhw<B: Backend>(t: &FloatTensor<B>) -> [usize; 3] {
    let s = t.shape().to_vec();
    [s[0], s[2], s[3]]
}

/// The loss on host memory, without a backward: the CPU backends' [`PerceptualBackend`].
fn host_vgg_l1<H: HostIo>(ImagePair { a, b }: ImagePair<H>, net: CpuVgg) -> FloatTensor<H> {
    let device = a.device();
    let dims = nhw::<H>(&a);
    let (loss, _) = net.0.loss(&H::read(a), &H::read(b), dims, [false; 2]);
    floats::<H>(vec![loss as f32], &[1], &device)
}

impl PerceptualBackend for Flex {
    fn vgg_l1(ab: ImagePair<Self>, net: CpuVgg) -> FloatTensor<Self> {
        host_vgg_l1(ab, net)
    }
}

impl PerceptualBackend for NdArray {
    fn vgg_l1(ab: ImagePair<Self>, net: CpuVgg) -> FloatTensor<Self> {
        host_vgg_l1(ab, net)
    }
}

#[derive(Debug)]
struct VggBackwardOp;

impl<B: Backend> Backward<B, 2> for VggBackwardOp {
    type State = (Arc<Saved>, CpuVgg, [usize; 3], B::Device);

    fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, _: &mut Checkpointer) {
        // Only the images whose gradient was kept (the tracked ones) get one: the reference
        // image's would be a full-size zero tensor every step.
        let grad = grads.consume::<B>(&ops.node);
        let g = read_scalar::<B>(grad);
        let (saved, net, [n, h, w], device) = ops.state;
        for (k, node) in ops.parents.into_iter().enumerate() {
            if let Some(node) = node
                && let Some(d) = net.0.backward(&saved, k, g)
            {
                grads.register::<B>(node.id, floats::<B>(d, &[n, 3, h, w], &device));
            }
        }
    }
}

/// The value of a one-element float tensor.
fn read_scalar<B: Backend>(t: FloatTensor<B>) -> f32 {
    texavatars_cpu::host::read_floats::<B>(t)
        .first()
        .copied()
        .unwrap_or(0.0)
}

impl<B: HostIo + PerceptualBackend, C: CheckpointStrategy> PerceptualBackend for Autodiff<B, C> {
    fn vgg_l1(ImagePair { a, b }: ImagePair<Self>, net: CpuVgg) -> FloatTensor<Self> {
        let keep = [a.is_tracked(), b.is_tracked()];
        let nodes = [a.node(), b.node()];
        let (a, b) = (a.into_primitive(), b.into_primitive());
        let device = a.device();
        let dims = nhw::<B>(&a);
        let scalar = |loss: f64| floats::<B>(vec![loss as f32], &[1], &device);
        // Untracked, `keep` is `[false; 2]`: the pass is `B::vgg_l1`'s (nothing saved).
        let run = |(a, b)| net.0.loss(&B::read(a), &B::read(b), dims, keep);
        let state = |_, (loss, saved)| {
            (
                (Arc::new(saved), net.clone(), dims, device.clone()),
                scalar(loss),
            )
        };
        let output = |(loss, _)| scalar(loss);
        autodiff::forward_with::<B, C, _, _, _, 2>(VggBackwardOp, nodes, (a, b), run, state, output)
    }
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
            cpu: CpuVgg(Arc::new(VggCpu::new(host))),
        }
    }

    /// Sum over the five taps of the mean absolute feature difference.
    ///
    /// # Shapes
    /// - `a`, `b`: [N, 3, H, W], values in [0, 1] (H, W at least 16)
    /// - returns `[1]`
    pub fn forward(&self, a: Tensor<4>, b: Tensor<4>) -> Tensor<1> {
        if on_cpu(&a.device()) {
            let ab = ImagePair {
                a: a.into_dispatch(),
                b: b.into_dispatch(),
            };
            return Tensor::from_dispatch(<burn::backend::Dispatch as PerceptualBackend>::vgg_l1(
                ab,
                self.cpu.clone(),
            ));
        }
        self.forward_burn(a, b)
    }

    /// The same loss through burn's tensor ops (the path on wgpu, and the reference twin of
    /// the CPU extension).
    ///
    /// # Shapes
    /// As [`VggPerceptual::forward`].
    pub fn forward_burn(&self, a: Tensor<4>, b: Tensor<4>) -> Tensor<1> {
        let n = a.dims()[0];
        let device = a.device();
        let mean = channel_constant(IMAGENET_MEAN, &device);
        let std = channel_constant(IMAGENET_STD, &device);
        // Two passes rather than one over the concatenated pair: a reference image that
        // needs no gradient (a ground truth) then stays off the autodiff graph, and the
        // backward pass runs through the VGG for `a` alone, which makes a training step with
        // the VGG loss on noticeably cheaper.
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::npy::Array;
    use burn::tensor::TensorData;

    /// VGG16 weights with He-scaled pseudo-random values and small biases.
    fn weights(seed: u64) -> HostWeights {
        let mut state = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 40) as f32 / (1u64 << 24) as f32 - 0.5
        };
        let convs = Net::Vgg16
            .convs()
            .iter()
            .map(|c| {
                let n = c.out_channels * c.in_channels * 9;
                let s = (24.0 / (c.in_channels * 9) as f32).sqrt();
                (
                    Array {
                        shape: vec![c.out_channels, c.in_channels, 3, 3],
                        data: (0..n).map(|_| next() * s).collect(),
                    },
                    Array {
                        shape: vec![c.out_channels],
                        data: (0..c.out_channels).map(|_| next() * 0.1).collect(),
                    },
                )
            })
            .collect();
        HostWeights {
            net: Net::Vgg16,
            convs,
            lins: Vec::new(),
        }
    }

    fn image(seed: usize, [n, h, w]: [usize; 3]) -> Vec<f32> {
        (0..n * 3 * h * w)
            .map(|i| (((i * 7919 + seed * 104_729) % 1009) as f32) / 1009.0)
            .collect()
    }

    fn host<const D: usize>(t: Tensor<D>) -> Vec<f32> {
        t.into_data().iter::<f32>().collect()
    }

    fn max_rel(a: &[f32], b: &[f32]) -> f32 {
        assert_eq!(a.len(), b.len());
        let scale = b.iter().fold(1e-12f32, |m, v| m.max(v.abs()));
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs() / scale)
            .fold(0.0, f32::max)
    }

    /// Loss and both images' gradients from the CPU extension and from burn's ops (the
    /// reference twin), on one CPU backend. Odd sizes exercise the pools' dropped edges.
    fn check_against_burn(device: Device) {
        let dims = [2, 37, 21];
        let [n, h, w] = dims;
        let vgg = VggPerceptual::from_host(&weights(3), &device);
        let t = |v: Vec<f32>| Tensor::<4>::from_data(TensorData::new(v, [n, 3, h, w]), &device);
        let run = |cpu: bool| {
            let a = t(image(1, dims)).require_grad();
            let b = t(image(2, dims)).require_grad();
            let loss = if cpu {
                vgg.forward(a.clone(), b.clone())
            } else {
                vgg.forward_burn(a.clone(), b.clone())
            };
            let value = host(loss.clone())[0];
            let grads = loss.backward();
            (
                value,
                host(a.grad(&grads).expect("a grad")),
                host(b.grad(&grads).expect("b grad")),
            )
        };
        let (l, da, db) = run(true);
        let (l_ref, da_ref, db_ref) = run(false);
        assert!(l > 0.0 && l.is_finite(), "loss {l}");
        assert!(
            ((l - l_ref) / l_ref).abs() < 1e-5,
            "loss {l} vs burn's {l_ref}"
        );
        assert!(da.iter().any(|v| *v != 0.0));
        assert!(max_rel(&da, &da_ref) < 1e-4, "gradient of a");
        assert!(max_rel(&db, &db_ref) < 1e-4, "gradient of b");
        // The same loss without autodiff (the extension's plain backend path).
        let plain = device.clone().without_autodiff();
        let vgg = VggPerceptual::from_host(&weights(3), &plain);
        let tp = |v: Vec<f32>| Tensor::<4>::from_data(TensorData::new(v, [n, 3, h, w]), &plain);
        let l_plain = host(vgg.forward(tp(image(1, dims)), tp(image(2, dims))))[0];
        assert!(((l_plain - l_ref) / l_ref).abs() < 1e-5);
    }

    #[test]
    fn matches_burn_on_flex() {
        check_against_burn(Device::flex().autodiff());
    }

    #[test]
    fn matches_burn_on_ndarray() {
        check_against_burn(Device::ndarray().autodiff());
    }

    /// Only the image that requires a gradient gets one; a constant reference is skipped.
    #[test]
    fn constant_reference_gets_no_gradient() {
        let device = Device::flex().autodiff();
        let dims = [1, 16, 16];
        let vgg = VggPerceptual::from_host(&weights(4), &device);
        let t = |v: Vec<f32>| Tensor::<4>::from_data(TensorData::new(v, [1, 3, 16, 16]), &device);
        let a = t(image(5, dims)).require_grad();
        let b = t(image(6, dims));
        let grads = vgg.forward(a.clone(), b.clone()).backward();
        assert!(a.grad(&grads).is_some());
        assert!(b.grad(&grads).is_none());
        assert_eq!(host(vgg.forward(a.clone(), a)), [0.0]);
    }

    /// Central finite differences of the host loss (accumulated in float64) along sparse
    /// directions, against the analytic gradient of both images.
    #[test]
    fn finite_differences() {
        let net = VggCpu::new(&weights(7));
        let dims = [1, 18, 17];
        let a = image(8, dims);
        let b = image(9, dims);
        let (_, saved) = net.loss(&a, &b, dims, [true, true]);
        let grads = [
            net.backward(&saved, 0, 1.0).expect("a kept"),
            net.backward(&saved, 1, 1.0).expect("b kept"),
        ];
        // The loss is piecewise smooth (ReLU, max-pool, |.|): a step on a few pixels still
        // crosses some kinks, and float32 rounding in the features is about 1% of the change
        // at this step (about 1e-4 absolute), so the tolerance is 5% plus 1e-3. The exact
        // check is the comparison with
        // burn's autodiff (`matches_burn_on_*`, 1e-4).
        let eps = 1e-3f32;
        for (k, g) in grads.iter().enumerate() {
            for trial in 0..3 {
                // A sparse direction (a few pixels), so that the step crosses few ReLU and
                // |.| kinks.
                let dir: Vec<f32> = (0..a.len())
                    .map(|i| match (i * 31 + trial * 17 + k) % 101 {
                        0 => 1.0,
                        50 => -1.0,
                        _ => 0.0,
                    })
                    .collect();
                let shifted = |s: f32| {
                    let mut x = if k == 0 { a.clone() } else { b.clone() };
                    x.iter_mut().zip(&dir).for_each(|(v, d)| *v += s * d);
                    let (l, _) = if k == 0 {
                        net.loss(&x, &b, dims, [false; 2])
                    } else {
                        net.loss(&a, &x, dims, [false; 2])
                    };
                    l
                };
                let fd = (shifted(eps) - shifted(-eps)) / (2.0 * eps as f64);
                let analytic: f64 = g.iter().zip(&dir).map(|(g, d)| (g * d) as f64).sum();
                assert!(
                    (fd - analytic).abs() < 5e-2 * analytic.abs() + 1e-3,
                    "input {k}, direction {trial}: {fd} vs {analytic}"
                );
            }
        }
    }
}
