//! The pretrained feature extractors: torchvision's VGG16 and AlexNet convolution stacks,
//! as LPIPS v0.1 and the VGG perceptual loss use them (five ReLU taps each).
//!
//! Weights are frozen (they never require gradients) but the networks are ordinary burn
//! tensor ops, so gradients flow to the input images on an autodiff device.

use burn::module::{Module, Param};
use burn::nn::PaddingConfig2d;
use burn::nn::conv::Conv2d;
use burn::tensor::activation::relu;
use burn::tensor::module::max_pool2d;
use burn::tensor::ops::MaxPoolOptions;
use burn::tensor::{Device, Tensor};

use crate::error::Result;
use crate::metrics::weights::{self, HostWeights};

/// The two pretrained backbones.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
pub enum Net {
    /// torchvision `vgg16().features[:30]` (taps relu1_2, relu2_2, relu3_3, relu4_3, relu5_3).
    Vgg16,
    /// torchvision `alexnet().features[:12]` (taps relu1 .. relu5).
    AlexNet,
}

/// One convolution of a backbone and what surrounds it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ConvSpec {
    /// Input channels.
    pub in_channels: usize,
    /// Output channels.
    pub out_channels: usize,
    /// Square kernel side.
    pub kernel: usize,
    /// Stride.
    pub stride: usize,
    /// Zero padding on every side.
    pub padding: usize,
    /// Max-pool (kernel, stride) applied to the input of this convolution, if any.
    pub pool_before: Option<(usize, usize)>,
    /// Whether the ReLU after this convolution is one of the five taps.
    pub tap: bool,
}

const fn conv(
    in_channels: usize,
    out_channels: usize,
    kernel: usize,
    stride: usize,
    padding: usize,
    pool_before: Option<(usize, usize)>,
    tap: bool,
) -> ConvSpec {
    ConvSpec {
        in_channels,
        out_channels,
        kernel,
        stride,
        padding,
        pool_before,
        tap,
    }
}

/// torchvision VGG16 `features.{0,2,5,7,10,12,14,17,19,21,24,26,28}`: 3x3 convolutions with
/// padding 1, 2x2 max-pools (stride 2) before convs 2, 4, 7 and 10.
const VGG16: [ConvSpec; 13] = [
    conv(3, 64, 3, 1, 1, None, false),
    conv(64, 64, 3, 1, 1, None, true),
    conv(64, 128, 3, 1, 1, Some((2, 2)), false),
    conv(128, 128, 3, 1, 1, None, true),
    conv(128, 256, 3, 1, 1, Some((2, 2)), false),
    conv(256, 256, 3, 1, 1, None, false),
    conv(256, 256, 3, 1, 1, None, true),
    conv(256, 512, 3, 1, 1, Some((2, 2)), false),
    conv(512, 512, 3, 1, 1, None, false),
    conv(512, 512, 3, 1, 1, None, true),
    conv(512, 512, 3, 1, 1, Some((2, 2)), false),
    conv(512, 512, 3, 1, 1, None, false),
    conv(512, 512, 3, 1, 1, None, true),
];

/// torchvision AlexNet `features.{0,3,6,8,10}`: 11x11 stride 4 padding 2; 5x5 padding 2;
/// three 3x3 padding 1; 3x3 stride-2 max-pools before convs 1 and 2.
const ALEXNET: [ConvSpec; 5] = [
    conv(3, 64, 11, 4, 2, None, true),
    conv(64, 192, 5, 1, 2, Some((3, 2)), true),
    conv(192, 384, 3, 1, 1, Some((3, 2)), true),
    conv(384, 256, 3, 1, 1, None, true),
    conv(256, 256, 3, 1, 1, None, true),
];

impl Net {
    /// Both backbones.
    pub const ALL: [Net; 2] = [Net::Vgg16, Net::AlexNet];

    /// Short name (`vgg16`, `alexnet`), also the stem of the weight files.
    pub fn name(self) -> &'static str {
        match self {
            Net::Vgg16 => "vgg16",
            Net::AlexNet => "alexnet",
        }
    }

    /// The convolutions in order.
    pub fn convs(self) -> &'static [ConvSpec] {
        match self {
            Net::Vgg16 => &VGG16,
            Net::AlexNet => &ALEXNET,
        }
    }

    /// Channels of the five taps.
    pub fn tap_channels(self) -> Vec<usize> {
        self.convs()
            .iter()
            .filter(|c| c.tap)
            .map(|c| c.out_channels)
            .collect()
    }
}

/// A frozen backbone that returns its five ReLU taps.
#[derive(Module, Debug)]
pub struct Features {
    convs: Vec<Conv2d>,
    #[module(skip)]
    net: Net,
}

/// A frozen parameter (pretrained weights never require gradients).
pub(crate) fn frozen<const D: usize>(t: Tensor<D>) -> Param<Tensor<D>> {
    Param::from_tensor(t).set_require_grad(false)
}

impl Features {
    /// Loads `net` from the installed weights (see [`weights::weights_dir`]).
    ///
    /// Errors name the missing file and say that `texavatars weights install` installs it.
    pub fn load(net: Net, device: &Device) -> Result<Self> {
        let host = weights::read(&weights::weights_file(net)?, net)?;
        Ok(Self::from_host(&host, device))
    }

    /// Builds the backbone from weights already read into memory.
    pub fn from_host(host: &HostWeights, device: &Device) -> Self {
        let convs = host
            .net
            .convs()
            .iter()
            .zip(&host.convs)
            .map(|(spec, (w, b))| {
                let p = spec.padding;
                Conv2d {
                    weight: frozen(weights::tensor::<4>(w, device)),
                    bias: Some(frozen(weights::tensor::<1>(b, device))),
                    stride: [spec.stride; 2],
                    kernel_size: [spec.kernel; 2],
                    dilation: [1, 1],
                    groups: 1,
                    padding: PaddingConfig2d::Explicit(p, p, p, p),
                }
            })
            .collect();
        Features {
            convs,
            net: host.net,
        }
    }

    /// Which backbone this is.
    pub fn net(&self) -> Net {
        self.net
    }

    /// The five ReLU taps.
    ///
    /// # Shapes
    /// - `x`: [N, 3, H, W], already normalised as the caller's metric requires
    /// - returns five [N, C_k, H_k, W_k] (C_k = [`Net::tap_channels`]; VGG16: H, H/2, H/4,
    ///   H/8, H/16; AlexNet: about H/4, H/8, H/16, H/16, H/16)
    pub fn forward(&self, x: Tensor<4>) -> Vec<Tensor<4>> {
        let mut taps = Vec::with_capacity(5);
        let mut x = x;
        for (conv, spec) in self.convs.iter().zip(self.net.convs()) {
            if let Some((k, s)) = spec.pool_before {
                x = max_pool2d(x, MaxPoolOptions::new([k, k]).with_stride([s, s]));
            }
            x = relu(conv.forward(x));
            if spec.tap {
                taps.push(x.clone());
            }
        }
        taps
    }
}
