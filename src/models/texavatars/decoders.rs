//! The four networks of method §3: Exp2Code, the view encoder (Pluecker2Code), the geometry
//! decoder D_g and the appearance decoder D_a. All layers are weight-normalised
//! ([`super::layers`]); a LeakyReLU (0.2) follows every layer except the last of each
//! decoder (Exp2Code and the view encoder end with one, as in the authors' code).
//!
//! Biases follow the authors' code: every transposed convolution of the decoders has an
//! untied (per-pixel) bias when `untied_bias` is set (the paper's configuration), the 3x3
//! convolutions, the view encoder and Exp2Code have per-channel biases.

use burn::config::Config;
use burn::module::Module;
use burn::tensor::{Device, Tensor};

use super::constants::*;
use super::layers::{
    Bias, WnConv2d, WnConv2dConfig, WnConvTranspose2d, WnConvTranspose2dConfig, WnLinear,
    WnLinearConfig, leaky_relu,
};

/// Square weight-normalised convolutions of `shape`, one per entry of `channels` (their
/// output channels), chained from `c_in` (left at the last output's channels).
fn convs(channels: &[usize], c_in: &mut usize, shape: ConvShape, device: &Device) -> Vec<WnConv2d> {
    channels
        .iter()
        .map(|&c_out| {
            let conv = WnConv2dConfig::new([*c_in, c_out], [shape.kernel; 2])
                .with_stride([shape.stride; 2])
                .with_padding([shape.padding; 2])
                .init(device);
            *c_in = c_out;
            conv
        })
        .collect()
}

/// Side of the output of upsampling stage `i` (0-based): `BASE_RES * 2^(i + 1)`.
fn stage_res(i: usize) -> usize {
    BASE_RES << (i + 1)
}

/// A stride-2 transposed convolution (k4 s2 p1) to side `res`.
fn up(
    c_in: usize,
    c_out: usize,
    res: usize,
    untied_bias: bool,
    device: &Device,
) -> WnConvTranspose2d {
    let bias = if untied_bias {
        Bias::Untied {
            height: res,
            width: res,
        }
    } else {
        Bias::PerChannel
    };
    WnConvTranspose2dConfig::new([c_in, c_out], [UP.kernel; 2])
        .with_stride([UP.stride; 2])
        .with_padding([UP.padding; 2])
        .with_bias(bias)
        .init(device)
}

/// Runs `layers` in order with a LeakyReLU after each, except after the last one when
/// `last_linear`.
fn chain(layers: &[WnConvTranspose2d], mut x: Tensor<4>, last_linear: bool) -> Tensor<4> {
    let n = layers.len();
    for (i, layer) in layers.iter().enumerate() {
        x = layer.forward_act(x, !(last_linear && i + 1 == n));
    }
    x
}

fn fold_all(layers: Vec<WnConvTranspose2d>) -> Vec<WnConvTranspose2d> {
    layers.into_iter().map(WnConvTranspose2d::fold).collect()
}

// ---------------------------------------------------------------------------------------------

/// Configuration of [`Exp2Code`].
#[derive(Config, Debug)]
pub struct Exp2CodeConfig {
    /// Size of the condition vector (FLAME: 100 + 15 + 128 = 243).
    pub cond_dim: usize,
    /// Channels of the 8 x 8 code (paper: 256).
    pub channels: usize,
}

/// Exp2Code: the condition vector to a `C0 x 8 x 8` code, shared by both decoders.
#[derive(Module, Debug)]
pub struct Exp2Code {
    /// Linear `cond_dim -> C0 * 64`.
    pub linear: WnLinear,
    /// C0.
    pub channels: usize,
}

impl Exp2CodeConfig {
    /// Initialises the network.
    pub fn init(&self, device: &Device) -> Exp2Code {
        Exp2Code {
            linear: WnLinearConfig::new(self.cond_dim, self.channels * BASE_RES * BASE_RES)
                .init(device),
            channels: self.channels,
        }
    }
}

impl Exp2Code {
    /// Linear layer, LeakyReLU, reshape (channel-major, as PyTorch's `view(-1, C0, 8, 8)`).
    ///
    /// # Shapes
    /// - `condition`: [N, cond_dim]
    /// - returns [N, C0, 8, 8]
    pub fn forward(&self, condition: Tensor<2>) -> Tensor<4> {
        let n = condition.dims()[0];
        leaky_relu(self.linear.forward(condition)).reshape([n, self.channels, BASE_RES, BASE_RES])
    }

    /// Folds the weight norm for inference ([`WnLinear::fold`]).
    pub fn fold(self) -> Self {
        Self {
            linear: self.linear.fold(),
            ..self
        }
    }
}

// ---------------------------------------------------------------------------------------------

/// Configuration of [`ViewEncoder`].
#[derive(Config, Debug)]
pub struct ViewEncoderConfig {
    /// Output channels of the stride-2 convolutions (paper: [16, 32]); the last is the width
    /// of the view embedding.
    pub channels: Vec<usize>,
}

/// The view encoder (Pluecker2Code): 3x3 stride-2 convolutions, each followed by a
/// LeakyReLU, from the Pluecker map to the view embedding.
#[derive(Module, Debug)]
pub struct ViewEncoder {
    /// The convolutions.
    pub convs: Vec<WnConv2d>,
}

impl ViewEncoderConfig {
    /// Initialises the network.
    pub fn init(&self, device: &Device) -> ViewEncoder {
        let mut c_in = PLUECKER_CHANNELS;
        let convs = convs(&self.channels, &mut c_in, VIEW, device);
        ViewEncoder { convs }
    }
}

impl ViewEncoder {
    /// Encodes Pluecker maps ([`super::pluecker::view_input_batch`]).
    ///
    /// # Shapes
    /// - `pluecker`: [N, 6, S, S]
    /// - returns [N, C_view, S / 2^L, S / 2^L] for L convolutions
    pub fn forward(&self, pluecker: Tensor<4>) -> Tensor<4> {
        self.convs
            .iter()
            .fold(pluecker, |x, conv| conv.forward_act(x, true))
    }

    /// Folds the weight norms for inference ([`WnConv2d::fold`]).
    pub fn fold(self) -> Self {
        Self {
            convs: self.convs.into_iter().map(WnConv2d::fold).collect(),
        }
    }
}

// ---------------------------------------------------------------------------------------------

/// The geometry decoder D_g: transposed convolutions from the 8 x 8 code to the local
/// geometry maps (offset 3, quaternion 4, log-scale 3, opacity logit 1).
#[derive(Module, Debug)]
pub struct GeometryDecoder {
    /// The transposed convolutions.
    pub layers: Vec<WnConvTranspose2d>,
}

/// Configuration of [`GeometryDecoder`].
#[derive(Config, Debug)]
pub struct GeometryDecoderConfig {
    /// Channels of the code (input).
    pub code_channels: usize,
    /// Output channels of each transposed convolution; the last must be 11 (paper:
    /// [256, 128, 128, 64, 32, 11]). Their number k sets the output side `8 * 2^k`.
    pub channels: Vec<usize>,
    /// Untied (per-pixel) biases (the paper) instead of per-channel ones.
    #[config(default = true)]
    pub untied_bias: bool,
}

impl GeometryDecoderConfig {
    /// Initialises the network.
    pub fn init(&self, device: &Device) -> GeometryDecoder {
        let mut c_in = self.code_channels;
        let layers = self
            .channels
            .iter()
            .enumerate()
            .map(|(i, &c_out)| {
                let layer = up(c_in, c_out, stage_res(i), self.untied_bias, device);
                c_in = c_out;
                layer
            })
            .collect();
        GeometryDecoder { layers }
    }
}

impl GeometryDecoder {
    /// Decodes the code; no activation on the output.
    ///
    /// # Shapes
    /// - `code`: [N, C0, 8, 8]
    /// - returns [N, 11, R, R] with `R = 8 * 2^k`
    pub fn forward(&self, code: Tensor<4>) -> Tensor<4> {
        chain(&self.layers, code, true)
    }

    /// Folds the weight norms for inference ([`WnConvTranspose2d::fold`]).
    pub fn fold(self) -> Self {
        Self {
            layers: fold_all(self.layers),
        }
    }
}

// ---------------------------------------------------------------------------------------------

/// Configuration of [`AppearanceDecoder`].
#[derive(Config, Debug)]
pub struct AppearanceDecoderConfig {
    /// Channels of the code (input).
    pub code_channels: usize,
    /// Channels of the view embedding concatenated after `before_view`.
    pub view_channels: usize,
    /// Output channels of the transposed convolutions before the view injection (paper:
    /// [256, 128], to 16^2 and 32^2).
    pub before_view: Vec<usize>,
    /// Output channels of the 3x3 convolutions right after the injection (paper: [128, 128]).
    pub mid: Vec<usize>,
    /// Output channels of the transposed convolutions after those; the last must be 3
    /// (paper: [64, 64, 3, 3], to 64^2 ... 512^2).
    pub after_view: Vec<usize>,
    /// Untied (per-pixel) biases on the transposed convolutions (the paper).
    #[config(default = true)]
    pub untied_bias: bool,
}

/// The appearance decoder D_a: transposed convolutions from the code, concatenation of the
/// view embedding, 3x3 convolutions, transposed convolutions to RGB (no activation).
#[derive(Module, Debug)]
pub struct AppearanceDecoder {
    /// Transposed convolutions before the view injection.
    pub before_view: Vec<WnConvTranspose2d>,
    /// 3x3 convolutions after the injection.
    pub mid: Vec<WnConv2d>,
    /// Transposed convolutions after the 3x3 convolutions.
    pub after_view: Vec<WnConvTranspose2d>,
}

impl AppearanceDecoderConfig {
    /// Initialises the network.
    pub fn init(&self, device: &Device) -> AppearanceDecoder {
        let mut c_in = self.code_channels;
        let mut stage = 0;
        let mut ups = |list: &[usize], c_in: &mut usize| -> Vec<WnConvTranspose2d> {
            list.iter()
                .map(|&c_out| {
                    let layer = up(*c_in, c_out, stage_res(stage), self.untied_bias, device);
                    stage += 1;
                    *c_in = c_out;
                    layer
                })
                .collect()
        };
        let before_view = ups(&self.before_view, &mut c_in);
        c_in += self.view_channels;
        let mid = convs(&self.mid, &mut c_in, MID, device);
        let after_view = ups(&self.after_view, &mut c_in);
        AppearanceDecoder {
            before_view,
            mid,
            after_view,
        }
    }
}

impl AppearanceDecoder {
    /// Decodes the code with the view embedding; no activation on the output.
    ///
    /// # Shapes
    /// - `code`: [N, C0, 8, 8]
    /// - `view`: [N, C_view, V, V] with `V = 8 * 2^len(before_view)` (paper: 32)
    /// - returns [N, 3, R, R]
    pub fn forward(&self, code: Tensor<4>, view: Tensor<4>) -> Tensor<4> {
        let x = chain(&self.before_view, code, false);
        let x = Tensor::cat(vec![x, view], 1);
        let x = self.mid.iter().fold(x, |x, conv| conv.forward_act(x, true));
        chain(&self.after_view, x, true)
    }

    /// Folds the weight norms for inference (see [`WnConvTranspose2d::fold`]).
    pub fn fold(self) -> Self {
        Self {
            before_view: fold_all(self.before_view),
            mid: self.mid.into_iter().map(WnConv2d::fold).collect(),
            after_view: fold_all(self.after_view),
        }
    }
}
