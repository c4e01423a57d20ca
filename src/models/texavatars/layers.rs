//! Weight-normalised layers in the form of RGCA (and of the authors' code, which takes its
//! layers from RGCA): `w = g * v / ||v||`, with ONE Frobenius norm over the whole weight
//! tensor `v` and one learned magnitude `g_o` per output channel.
//!
//! Unlike `torch.nn.utils.weight_norm` (one norm per output channel), the whole-tensor norm
//! couples the channels: `sum_o (||w_o|| / g_o)^2 = 1`, and when all `g_o` are equal to `c`,
//! `||w|| = c`. The output is invariant to any positive scaling of `v`; the gradient w.r.t.
//! `v` is orthogonal to `v` (so plain gradient descent never shrinks `||v||`, and `||v||`
//! cannot reach zero in training).
//!
//! # Initialisation (as the authors' code, i.e. PyTorch's defaults plus RGCA's wrapper)
//! - `v ~ U(-b, b)` with `b = 1 / sqrt(fan_in)` (PyTorch's default `kaiming_uniform_(a = √5)`):
//!   `fan_in = d_input` for [`WnLinear`], `(C_in) * k_h * k_w` for [`WnConv2d`] and
//!   `(C_out) * k_h * k_w` for [`WnConvTranspose2d`] (PyTorch's convention: dimension 1 of the
//!   stored weight);
//! - `g_o = ||v||` for every output channel, so the initial effective weight is exactly `v`;
//! - per-channel biases `~ U(-b, b)` (PyTorch's default), untied biases zero (RGCA).
//!
//! Seed the device (`device.seed(s)`) before `init` for reproducible weights.

use std::fmt;
use std::marker::PhantomData;

use burn::config::{Config, config_to_json};
use burn::module::{Module, Param};
use burn::tensor::module::linear;
use burn::tensor::{Device, Distribution, Tensor};
use serde::{Deserialize, Serialize};

use super::constants::LEAKY_RELU_SLOPE;
use texavatars_cpu::conv::{self as ops, ConvParams, conv};
use texavatars_cpu::conv_bias_act::conv_bias_act;
pub use texavatars_cpu::weight_norm::weight_norm;
use texavatars_cpu::wn_linear::wn_linear;

/// LeakyReLU with the networks' slope ([`LEAKY_RELU_SLOPE`] = 0.2).
pub fn leaky_relu<const D: usize>(x: Tensor<D>) -> Tensor<D> {
    burn::tensor::activation::leaky_relu(x, LEAKY_RELU_SLOPE)
}

/// The bias of a convolution.
#[derive(Config, Debug, PartialEq, Eq)]
pub enum Bias {
    /// No bias.
    None,
    /// One bias per output channel, shape `[C_out]`.
    PerChannel,
    /// One bias per output channel and pixel ("untied"), shape [C_out, height, width]; the
    /// layer then only runs at that output resolution.
    Untied {
        /// Output height.
        height: usize,
        /// Output width.
        width: usize,
    },
}

/// `v ~ U(-b, b)`, `b = 1 / sqrt(fan_in)`, and `g` = `||v||` per output channel.
fn init_v_g<const D: usize>(
    shape: [usize; D],
    out_dim: usize,
    fan_in: usize,
    device: &Device,
) -> (Param<Tensor<D>>, Param<Tensor<1>>) {
    let b = 1.0 / (fan_in.max(1) as f64).sqrt();
    let v = Tensor::<D>::random(shape, Distribution::Uniform(-b, b), device).detach();
    let norm = v.clone().powi_scalar(2).sum().sqrt();
    let g = (Tensor::<1>::ones([shape[out_dim]], device) * norm).detach();
    (Param::from_tensor(v), Param::from_tensor(g))
}

// The weight-norm building block of the three layers. Each layer keeps `v`, `g` and `folded`
// as fields of its own rather than in a nested module, because saved records (`avatar.bpk`)
// are keyed by field paths (`linear.v`, not `linear.wn.v`) and records written before this
// block existed must keep loading (the test `records_saved_by_earlier_code_load`); the layers'
// `effective_weight` and `fold` are these two functions on those fields.

/// The effective weight `g * v / ||v||` ([`weight_norm`], `g` along dimension `out_dim` of
/// `v`), or `v` itself once folded.
fn effective_weight<const D: usize>(
    v: &Param<Tensor<D>>,
    g: &Param<Tensor<1>>,
    folded: bool,
    out_dim: usize,
) -> Tensor<D> {
    if folded {
        return v.val();
    }
    weight_norm(v.val(), g.val(), out_dim)
}

/// Folds in place: `v = w` (the effective weight) and `g_o = ||w||` for every output
/// channel, so that `g * v / ||v||` is `w` again (a folded layer saved and loaded as an
/// ordinary one computes the same function), and `folded` tells forward passes to skip the
/// norm.
fn fold<const D: usize>(
    v: &mut Param<Tensor<D>>,
    g: &mut Param<Tensor<1>>,
    folded: &mut bool,
    out_dim: usize,
) {
    let w = effective_weight(v, g, *folded, out_dim).detach();
    let norm = w.clone().powi_scalar(2).sum().sqrt();
    *g = Param::from_tensor(Tensor::<1>::ones([w.dims()[out_dim]], &w.device()) * norm);
    *v = Param::from_tensor(w);
    *folded = true;
}

fn uniform_bias(n: usize, fan_in: usize, device: &Device) -> Param<Tensor<1>> {
    let b = 1.0 / (fan_in.max(1) as f64).sqrt();
    Param::from_tensor(Tensor::random([n], Distribution::Uniform(-b, b), device))
}

/// The two bias parameters of a convolution from its [`Bias`] kind.
type Biases = (Option<Param<Tensor<1>>>, Option<Param<Tensor<3>>>);

fn init_bias(kind: &Bias, c_out: usize, fan_in: usize, device: &Device) -> Biases {
    match *kind {
        Bias::None => (None, None),
        Bias::PerChannel => (Some(uniform_bias(c_out, fan_in, device)), None),
        Bias::Untied { height, width } => (
            None,
            Some(Param::from_tensor(Tensor::zeros(
                [c_out, height, width],
                device,
            ))),
        ),
    }
}

/// Checks that an untied bias [C, H, W] matches the layer's output [N, C, H, W] (`out` is
/// its [C, H, W]).
fn check_untied(out: [usize; 3], bias: &Param<Tensor<3>>, layer: &str) {
    let dims = bias.dims();
    let [c, h, w] = out;
    assert_eq!(
        dims,
        [c, h, w],
        "{layer}: the untied bias is {dims:?} but the output is [N, {c}, {h}, {w}]; the layer \
         only runs at the resolution it was built for",
    );
}

// ---------------------------------------------------------------------------------------------

/// Configuration of a [`WnLinear`].
#[derive(Config, Debug)]
pub struct WnLinearConfig {
    /// Input features.
    pub d_input: usize,
    /// Output features.
    pub d_output: usize,
    /// Whether to add a per-feature bias.
    #[config(default = true)]
    pub bias: bool,
}

/// Weight-normalised linear layer.
#[derive(Module, Debug)]
pub struct WnLinear {
    /// Direction `v`, [d_output, d_input] (PyTorch's layout).
    pub v: Param<Tensor<2>>,
    /// Magnitude per output feature, `[d_output]`.
    pub g: Param<Tensor<1>>,
    /// Whether `v` already holds the effective weight ([`Self::fold`]); not saved.
    pub folded: bool,
    /// Bias, `[d_output]`.
    pub bias: Option<Param<Tensor<1>>>,
}

impl WnLinearConfig {
    /// Initialises the layer (see the module docs for the distributions).
    pub fn init(&self, device: &Device) -> WnLinear {
        let (v, g) = init_v_g(
            [self.d_output, self.d_input],
            WnLinear::OUT_DIM,
            self.d_input,
            device,
        );
        let bias = self
            .bias
            .then(|| uniform_bias(self.d_output, self.d_input, device));
        WnLinear {
            v,
            g,
            folded: false,
            bias,
        }
    }
}

impl WnLinear {
    /// The dimension of `v` that indexes the output features.
    const OUT_DIM: usize = 0;

    /// The effective weight `g * v / ||v||`, [d_output, d_input].
    pub fn effective_weight(&self) -> Tensor<2> {
        effective_weight(&self.v, &self.g, self.folded, Self::OUT_DIM)
    }

    /// `y = x w^T + b`.
    ///
    /// # Shapes
    /// - `x`: [..., d_input]
    /// - returns [..., d_output]
    pub fn forward<const D: usize>(&self, x: Tensor<D>) -> Tensor<D> {
        let bias = self.bias.as_ref().map(|b| b.val());
        if self.folded {
            return linear(x, self.v.val().transpose(), bias);
        }
        // The fused op ([`wn_linear`]) takes `[B, d_input]`: the leading dimensions are
        // flattened and restored.
        let dims = x.dims();
        let [o, i] = self.v.dims();
        let rows = dims[..D - 1].iter().product::<usize>();
        let y = wn_linear(x.reshape([rows, i]), self.v.val(), self.g.val());
        let y = match bias {
            Some(b) => y + b.unsqueeze::<2>(),
            None => y,
        };
        let mut out = dims;
        out[D - 1] = o;
        y.reshape(out)
    }

    /// For inference: stores the effective weight in `v` so that forward passes skip the
    /// norm (training would then move the weight itself, without the norm: train unfolded).
    pub fn fold(mut self) -> Self {
        fold(&mut self.v, &mut self.g, &mut self.folded, Self::OUT_DIM);
        self
    }
}

// ---------------------------------------------------------------------------------------------

/// What sets a transposed convolution ([`Transposed`]) apart from a plain one ([`Plain`]): the
/// op's kind, which fixes the layout of the weight and the operation.
pub trait ConvKind: Clone + Copy + fmt::Debug + Send + Sync + 'static {
    /// The layer's name, for messages.
    const NAME: &'static str;

    /// The ops' convolution kind.
    const KIND: ops::ConvKind;

    /// The dimension of `v` [_, _, k_h, k_w] that indexes the output channels, in PyTorch's
    /// layouts: 0 for a convolution ([C_out, C_in, k_h, k_w]), 1 for a transposed one
    /// ([C_in, C_out, k_h, k_w]). `fan_in` is the other one times `k_h k_w`.
    const OUT_DIM: usize = match Self::KIND {
        ops::ConvKind::Plain => 0,
        ops::ConvKind::Transposed => 1,
    };

    /// The layer's kind, stride and padding, as the ops take them.
    fn params(layer: &WnConv<Self>) -> ConvParams {
        ConvParams {
            kind: Self::KIND,
            stride: layer.stride,
            padding: layer.padding,
        }
    }

    /// The layer's operation, before its bias ([`conv`]).
    ///
    /// # Shapes
    /// - `x`: [N, C_in, H, W]
    /// - returns [N, C_out, H_out, W_out]
    fn apply(x: Tensor<4>, layer: &WnConv<Self>) -> Tensor<4> {
        conv(x, layer.effective_weight(), Self::params(layer))
    }

    /// `[H_out, W_out]` for an input `[H, W]`, or `None` when the layer leaves no output.
    fn output_size(layer: &WnConv<Self>, input: [usize; 2]) -> Option<[usize; 2]> {
        let [_, _, kh, kw] = layer.v.dims();
        Self::params(layer).output_size(input, [kh, kw])
    }

    /// The operation, the bias (`[C_out]` or [C_out, H_out, W_out]) and, with `act`, the
    /// networks' LeakyReLU, as one op ([`conv_bias_act`]).
    ///
    /// # Shapes
    /// As [`Self::apply`].
    fn apply_bias_act<const D: usize>(
        x: Tensor<4>,
        layer: &WnConv<Self>,
        bias: Tensor<D>,
        act: bool,
    ) -> Tensor<4> {
        conv_bias_act(x, layer.effective_weight(), bias, Self::params(layer), act)
    }
}

/// A plain convolution: `H_out = (H + 2 p - k) / s + 1`.
#[derive(Clone, Copy, Debug)]
pub struct Plain;

/// A transposed convolution: `H_out = (H - 1) s - 2 p + k` (the padding is removed from each
/// side of the full output).
#[derive(Clone, Copy, Debug)]
pub struct Transposed;

impl ConvKind for Plain {
    const NAME: &'static str = "WnConv2d";
    const KIND: ops::ConvKind = ops::ConvKind::Plain;
}

impl ConvKind for Transposed {
    const NAME: &'static str = "WnConvTranspose2d";
    const KIND: ops::ConvKind = ops::ConvKind::Transposed;
}

/// Configuration of a [`WnConv2d`].
pub type WnConv2dConfig = WnConvConfig<Plain>;
/// Configuration of a [`WnConvTranspose2d`].
pub type WnConvTranspose2dConfig = WnConvConfig<Transposed>;
/// Weight-normalised 2D convolution.
pub type WnConv2d = WnConv<Plain>;
/// Weight-normalised 2D transposed convolution.
pub type WnConvTranspose2d = WnConv<Transposed>;

fn unit_stride() -> [usize; 2] {
    [1, 1]
}

fn per_channel() -> Bias {
    Bias::PerChannel
}

/// Configuration of a [`WnConv`] ([`WnConv2dConfig`], [`WnConvTranspose2dConfig`]); written
/// out rather than derived, as `#[derive(Config)]` takes no type parameters.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(bound = "")]
pub struct WnConvConfig<K: ConvKind> {
    /// Input and output channels.
    pub channels: [usize; 2],
    /// Kernel height and width.
    pub kernel_size: [usize; 2],
    /// Stride; `[1, 1]` unless set.
    #[serde(default = "unit_stride")]
    pub stride: [usize; 2],
    /// Zero padding on each side (a transposed convolution removes it from each side of the
    /// full output); `[0, 0]` unless set.
    #[serde(default)]
    pub padding: [usize; 2],
    /// The bias; [`Bias::PerChannel`] unless set.
    #[serde(default = "per_channel")]
    pub bias: Bias,
    /// Plain or transposed.
    #[serde(skip)]
    pub kind: PhantomData<K>,
}

impl<K: ConvKind> Config for WnConvConfig<K> {}

impl<K: ConvKind> fmt::Display for WnConvConfig<K> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&config_to_json(self))
    }
}

impl<K: ConvKind> WnConvConfig<K> {
    /// Stride 1, no padding, a per-channel bias.
    pub fn new(channels: [usize; 2], kernel_size: [usize; 2]) -> Self {
        Self {
            channels,
            kernel_size,
            stride: unit_stride(),
            padding: [0, 0],
            bias: per_channel(),
            kind: PhantomData,
        }
    }

    /// Sets the stride.
    pub fn with_stride(self, stride: [usize; 2]) -> Self {
        Self { stride, ..self }
    }

    /// Sets the padding.
    pub fn with_padding(self, padding: [usize; 2]) -> Self {
        Self { padding, ..self }
    }

    /// Sets the bias.
    pub fn with_bias(self, bias: Bias) -> Self {
        Self { bias, ..self }
    }

    /// Initialises the layer (see the module docs for the distributions).
    pub fn init(&self, device: &Device) -> WnConv<K> {
        let [c_in, c_out] = self.channels;
        let [kh, kw] = self.kernel_size;
        let shape = match K::OUT_DIM {
            0 => [c_out, c_in, kh, kw],
            _ => [c_in, c_out, kh, kw],
        };
        let fan_in = shape[1] * kh * kw;
        let (v, g) = init_v_g(shape, K::OUT_DIM, fan_in, device);
        let (bias, untied_bias) = init_bias(&self.bias, c_out, fan_in, device);
        WnConv {
            v,
            g,
            folded: false,
            bias,
            untied_bias,
            stride: self.stride,
            padding: self.padding,
            kind: PhantomData,
        }
    }
}

/// Weight-normalised 2D convolution, plain ([`WnConv2d`]) or transposed
/// ([`WnConvTranspose2d`]).
#[derive(Module, Debug)]
pub struct WnConv<K: ConvKind> {
    /// Direction `v`: [C_out, C_in, k_h, k_w], or [C_in, C_out, k_h, k_w] for a transposed
    /// convolution (PyTorch's layouts; see [`ConvKind::OUT_DIM`]).
    pub v: Param<Tensor<4>>,
    /// Magnitude per output channel, `[C_out]` (broadcast along dimension
    /// [`ConvKind::OUT_DIM`] of `v`).
    pub g: Param<Tensor<1>>,
    /// Whether `v` already holds the effective weight ([`Self::fold`]); not saved.
    pub folded: bool,
    /// Per-channel bias, `[C_out]`.
    pub bias: Option<Param<Tensor<1>>>,
    /// Untied bias, [C_out, H_out, W_out].
    pub untied_bias: Option<Param<Tensor<3>>>,
    /// Stride.
    pub stride: [usize; 2],
    /// Padding.
    pub padding: [usize; 2],
    /// Plain or transposed; not saved.
    #[module(skip)]
    pub kind: PhantomData<K>,
}

impl<K: ConvKind> WnConv<K> {
    /// The dimension of `v` that indexes the output channels.
    const OUT_DIM: usize = K::OUT_DIM;

    /// The effective weight `g * v / ||v||`, in the layout of `v`.
    pub fn effective_weight(&self) -> Tensor<4> {
        effective_weight(&self.v, &self.g, self.folded, Self::OUT_DIM)
    }

    /// For inference: stores the effective weight in `v` so that forward passes skip the
    /// norm (training would then move the weight itself, without the norm: train unfolded).
    pub fn fold(mut self) -> Self {
        fold(&mut self.v, &mut self.g, &mut self.folded, Self::OUT_DIM);
        self
    }

    /// The convolution with the effective weight, plus the bias.
    ///
    /// # Shapes
    /// - `x`: [N, C_in, H, W]
    /// - returns [N, C_out, H_out, W_out] ([`Plain`] and [`Transposed`] give `H_out`)
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        self.forward_act(x, false)
    }

    /// [`Self::forward`] followed by the networks' LeakyReLU when `act`: with a bias, the
    /// whole layer is one op ([`conv_bias_act`], for either kind).
    ///
    /// # Shapes
    /// As [`Self::forward`].
    ///
    /// # Panics
    /// When an untied bias does not match the output's resolution.
    pub fn forward_act(&self, x: Tensor<4>, act: bool) -> Tensor<4> {
        match (&self.bias, &self.untied_bias) {
            (_, Some(b)) => {
                let [_, _, h, w] = x.dims();
                if let Some([ho, wo]) = K::output_size(self, [h, w]) {
                    check_untied([self.g.dims()[0], ho, wo], b, K::NAME);
                }
                K::apply_bias_act(x, self, b.val(), act)
            }
            (Some(b), None) => K::apply_bias_act(x, self, b.val(), act),
            (None, None) if act => leaky_relu(K::apply(x, self)),
            (None, None) => K::apply(x, self),
        }
    }
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use super::*;
    use crate::io::npz::Npz;
    use burn::tensor::TensorData;

    #[allow(deprecated)]
    fn device() -> Device {
        let d = Device::ndarray();
        d.seed(11);
        d
    }

    fn host<const D: usize>(t: Tensor<D>) -> Vec<f32> {
        t.into_data().iter::<f32>().collect()
    }

    fn max_diff(a: &[f32], b: &[f32]) -> f32 {
        assert_eq!(a.len(), b.len());
        a.iter().zip(b).fold(0.0, |m, (x, y)| m.max((x - y).abs()))
    }

    fn input(shape: [usize; 4], device: &Device) -> Tensor<4> {
        Tensor::random(shape, Distribution::Uniform(-1.0, 1.0), device)
    }

    /// Random magnitudes in [0.5, 2] (so that per-channel behaviour is visible).
    fn random_g(n: usize, device: &Device) -> Param<Tensor<1>> {
        Param::from_tensor(Tensor::random([n], Distribution::Uniform(0.5, 2.0), device))
    }

    /// A transposed convolution k4 s2 p1 with an untied bias [C_out, H_out, W_out].
    fn upsampler(
        channels: [usize; 2],
        [height, width]: [usize; 2],
        d: &Device,
    ) -> WnConvTranspose2d {
        WnConvTranspose2dConfig::new(channels, [4, 4])
            .with_stride([2, 2])
            .with_padding([1, 1])
            .with_bias(Bias::Untied { height, width })
            .init(d)
    }

    /// One layer of each type with random magnitudes: a convolution 3 -> 4 (k3 p1), a
    /// transposed convolution 3 -> 2 (k4 s2 p1, an untied bias for 5 x 5 inputs) and a linear
    /// layer 6 -> 5, with an input [3, 6] for the linear layer.
    fn random_layers(d: &Device) -> (WnConv2d, WnConvTranspose2d, WnLinear, Tensor<2>) {
        let mut conv = WnConv2dConfig::new([3, 4], [3, 3])
            .with_padding([1, 1])
            .init(d);
        conv.g = random_g(4, d);
        let mut up = upsampler([3, 2], [10, 10], d);
        up.g = random_g(2, d);
        let mut lin = WnLinearConfig::new(6, 5).init(d);
        lin.g = random_g(5, d);
        let xl = Tensor::<2>::random([3, 6], Distribution::Uniform(-1.0, 1.0), d);
        (conv, up, lin, xl)
    }

    #[test]
    fn initial_effective_weight_is_v() {
        let d = device();
        let conv = WnConvTranspose2dConfig::new([5, 4], [4, 4]).init(&d);
        let diff = max_diff(&host(conv.effective_weight()), &host(conv.v.val()));
        assert!(diff < 1e-6, "{diff}");
        let lin = WnLinearConfig::new(7, 3).init(&d);
        assert!(max_diff(&host(lin.effective_weight()), &host(lin.v.val())) < 1e-6);
        // v ~ U(-1/sqrt(fan_in), 1/sqrt(fan_in)): fan_in = C_out * 16 for the transposed conv.
        let b = 1.0 / ((4 * 16) as f32).sqrt();
        assert!(host(conv.v.val()).iter().all(|x| x.abs() <= b));
        let untied = WnConv2dConfig::new([2, 3], [3, 3])
            .with_bias(Bias::Untied {
                height: 4,
                width: 5,
            })
            .init(&d);
        let bias = untied.untied_bias.as_ref().expect("untied bias").val();
        assert_eq!(bias.dims(), [3, 4, 5]);
        assert!(host(bias).iter().all(|&x| x == 0.0));
        assert!(untied.bias.is_none());
    }

    #[test]
    fn scaling_v_leaves_outputs_unchanged() {
        let d = device();
        let x = input([2, 3, 5, 5], &d);
        let (mut conv, mut up, mut lin, xl) = random_layers(&d);
        let y0 = host(conv.forward(x.clone()));
        conv.v = Param::from_tensor(conv.v.val() * 7.5);
        assert!(max_diff(&y0, &host(conv.forward(x.clone()))) < 1e-5);

        let y0 = host(up.forward(x.clone()));
        up.v = Param::from_tensor(up.v.val() * 0.03);
        assert!(max_diff(&y0, &host(up.forward(x))) < 1e-5);

        let y0 = host(lin.forward(xl.clone()));
        lin.v = Param::from_tensor(lin.v.val() * 123.0);
        assert!(max_diff(&y0, &host(lin.forward(xl))) < 1e-4);
    }

    /// One norm over the whole tensor: `sum_o (||w_o|| / g_o)^2 = 1`, and `||w|| = c` when all
    /// `g_o = c`; `||w_o||` follows `g_o` times the channel's share of `||v||`.
    #[test]
    fn effective_weight_norms_per_output_channel() {
        let d = device();
        let mut up = WnConvTranspose2dConfig::new([3, 4], [4, 4]).init(&d);
        let g = [0.5f32, 1.0, 2.0, 3.0];
        up.g = Param::from_tensor(Tensor::from_data(TensorData::new(g.to_vec(), [4]), &d));
        let w = host(up.effective_weight()); // [C_in, C_out, 4, 4]
        let v = host(up.v.val());
        let v_norm: f32 = v.iter().map(|x| x * x).sum::<f32>().sqrt();
        let channel_norm = |t: &[f32], o: usize| -> f32 {
            let mut s = 0.0;
            for i in 0..3 {
                for k in 0..16 {
                    s += t[(i * 4 + o) * 16 + k].powi(2);
                }
            }
            s.sqrt()
        };
        let mut total = 0.0;
        for (o, &go) in g.iter().enumerate() {
            let expected = go * channel_norm(&v, o) / v_norm;
            assert!((channel_norm(&w, o) - expected).abs() < 1e-5);
            total += (channel_norm(&w, o) / go).powi(2);
        }
        assert!((total - 1.0).abs() < 1e-5, "{total}");
        // Equal magnitudes c: ||w|| = c.
        up.g = Param::from_tensor(Tensor::ones([4], &d) * 1.7);
        let w_norm: f32 = host(up.effective_weight())
            .iter()
            .map(|x| x * x)
            .sum::<f32>()
            .sqrt();
        assert!((w_norm - 1.7).abs() < 1e-5, "{w_norm}");
    }

    /// A folded layer computes the same outputs, and so does its record read as an
    /// ordinary layer (`folded` is not saved).
    #[test]
    fn folding_keeps_the_function() {
        let d = device();
        let x = input([2, 3, 5, 5], &d);
        let (conv, up, lin, xl) = random_layers(&d);
        let before = [
            host(conv.forward(x.clone())),
            host(up.forward(x.clone())),
            host(lin.forward(xl.clone())),
        ];
        let (conv, up, lin) = (conv.fold(), up.fold(), lin.fold());
        assert!(conv.folded && up.folded && lin.folded);
        let folded = [
            host(conv.forward(x.clone())),
            host(up.forward(x.clone())),
            host(lin.forward(xl.clone())),
        ];
        let (conv, up, lin) = (
            WnConv2d {
                folded: false,
                ..conv
            },
            WnConvTranspose2d {
                folded: false,
                ..up
            },
            WnLinear {
                folded: false,
                ..lin
            },
        );
        let reloaded = [
            host(conv.forward(x.clone())),
            host(up.forward(x)),
            host(lin.forward(xl)),
        ];
        for ((b, f), r) in before.iter().zip(&folded).zip(&reloaded) {
            assert!(max_diff(b, f) < 1e-6, "{}", max_diff(b, f));
            assert!(max_diff(b, r) < 1e-5, "{}", max_diff(b, r));
        }
    }

    /// Records written by the layers before they shared their weight-norm code load into these
    /// layers and give the outputs saved with them (within 1e-6).
    ///
    /// `tests/fixtures/wn_layers` was written by the code of commit c5ec0bb ("Real captures
    /// read as VHAP and GaussianAvatars mean them"), on ndarray with seed 11, saving each layer
    /// with `Module::save_file` as `avatar.bpk` is saved (and read here with
    /// `Module::try_load_file`, as `load_avatar` reads it): a linear layer 4 -> 3 with a bias, a
    /// convolution 2 -> 3 (k3 p1, per-channel bias) and a transposed convolution 2 -> 3 (k4 s2
    /// p1, a random untied bias [3, 6, 6]), all with random `g`. `outputs.npz` holds their
    /// inputs (`x_linear` [2, 4], `x_conv` [2, 2, 3, 3]) and outputs.
    #[test]
    fn records_saved_by_earlier_code_load() {
        let d = device();
        d.seed(5); // not the writer's seed: the layers start from other values
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/wn_layers");
        assert!(
            dir.is_dir(),
            "fixture missing: {} (see tests/fixtures/README.md)",
            dir.display()
        );
        let mut npz = Npz::open(&dir.join("outputs.npz")).expect("outputs.npz");
        let mut array = |name: &str| npz.floats(name).expect(name);
        let tensor = |a: crate::io::npy::Array| TensorData::new(a.data, a.shape);
        let xl = Tensor::<2>::from_data(tensor(array("x_linear")), &d);
        let x = Tensor::<4>::from_data(tensor(array("x_conv")), &d);
        // Fresh layers (other random values) of the saved sizes, then the saved records.
        let load = |file: &str| dir.join(file);
        let lin = WnLinearConfig::new(4, 3)
            .init(&d)
            .try_load_file(load("linear.bpk"))
            .expect("linear.bpk");
        let conv = WnConv2dConfig::new([2, 3], [3, 3])
            .with_padding([1, 1])
            .init(&d)
            .try_load_file(load("conv2d.bpk"))
            .expect("conv2d.bpk");
        let up = upsampler([2, 3], [6, 6], &d)
            .try_load_file(load("conv_transpose2d.bpk"))
            .expect("conv_transpose2d.bpk");
        assert!(!lin.folded && !conv.folded && !up.folded);
        let outputs = [
            ("linear", host(lin.forward(xl))),
            ("conv2d", host(conv.forward(x.clone()))),
            ("conv_transpose2d", host(up.forward(x))),
        ];
        for (name, y) in outputs {
            let expected = array(name).data;
            let diff = max_diff(&y, &expected);
            assert!(diff < 1e-6, "{name}: {diff}");
        }
    }

    #[test]
    fn untied_and_per_channel_biases_broadcast() {
        let d = device();
        let x = input([3, 2, 4, 4], &d);
        // With g = 0 the output is the bias alone.
        let mut up = upsampler([2, 2], [8, 8], &d);
        up.g = Param::from_tensor(Tensor::zeros([2], &d));
        let bias: Vec<f32> = (0..2 * 8 * 8).map(|k| k as f32 * 0.01 - 0.3).collect();
        up.untied_bias = Some(Param::from_tensor(Tensor::from_data(
            TensorData::new(bias.clone(), [2, 8, 8]),
            &d,
        )));
        let y = up.forward(x.clone());
        assert_eq!(y.dims(), [3, 2, 8, 8]);
        let y = host(y);
        for n in 0..3 {
            assert!(max_diff(&y[n * 128..(n + 1) * 128], &bias) < 1e-7);
        }
        let mut conv = WnConv2dConfig::new([2, 2], [3, 3])
            .with_padding([1, 1])
            .init(&d);
        conv.g = Param::from_tensor(Tensor::zeros([2], &d));
        conv.bias = Some(Param::from_tensor(Tensor::from_data(
            TensorData::new(vec![0.25f32, -1.5], [2]),
            &d,
        )));
        let y = host(conv.forward(x));
        for (k, value) in y.iter().enumerate() {
            let c = (k / 16) % 2;
            assert_eq!(*value, [0.25, -1.5][c]);
        }
    }

    #[test]
    #[should_panic(expected = "only runs at the resolution")]
    fn untied_bias_rejects_another_resolution() {
        let d = device();
        let up = upsampler([2, 2], [8, 8], &d);
        let _ = up.forward(input([1, 2, 8, 8], &d));
    }
}
