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

use burn::config::Config;
use burn::module::{Module, Param};
use burn::tensor::module::{conv2d, linear};
use burn::tensor::ops::ConvOptions;
use burn::tensor::{Device, Distribution, Tensor};

use super::constants::LEAKY_RELU_SLOPE;
use super::conv_transpose::{ConvTParams, conv_transpose2d};

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

/// `w = g * v / ||v||`: one norm over all of `v`, `g` `[C_out]` broadcast along `out_dim`.
///
/// # Shapes
/// - `v`: any rank `D`, with `v.dims()[out_dim] == C_out`
/// - `g`: `[C_out]`
/// - returns the shape of `v`
pub fn weight_norm<const D: usize>(v: Tensor<D>, g: Tensor<1>, out_dim: usize) -> Tensor<D> {
    let norm = v.clone().powi_scalar(2).sum().sqrt();
    let mut shape = [1usize; D];
    shape[out_dim] = g.dims()[0];
    v * (g / norm).reshape(shape)
}

/// `(v, g)` that hold the effective weight `w` itself: `v = w` and `g_o = ||w||` for every
/// output channel, so that `g * v / ||v||` is `w` again (a folded layer saved and loaded as
/// an ordinary one computes the same function).
fn fold_v_g<const D: usize>(w: Tensor<D>, out_dim: usize) -> (Param<Tensor<D>>, Param<Tensor<1>>) {
    let w = w.detach();
    let c_out = w.dims()[out_dim];
    let norm = w.clone().powi_scalar(2).sum().sqrt();
    let g = Tensor::<1>::ones([c_out], &w.device()) * norm;
    (Param::from_tensor(w), Param::from_tensor(g))
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

/// Adds an untied bias [C, H, W] to `y` [N, C, H, W].
fn add_untied(y: Tensor<4>, bias: &Option<Param<Tensor<3>>>, layer: &str) -> Tensor<4> {
    match bias {
        None => y,
        Some(b) => {
            let b = b.val();
            let [_, c, h, w] = y.dims();
            assert_eq!(
                b.dims(),
                [c, h, w],
                "{layer}: the untied bias is {:?} but the output is [N, {c}, {h}, {w}]; the layer \
                 only runs at the resolution it was built for",
                b.dims()
            );
            y + b.unsqueeze::<4>()
        }
    }
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
        let (v, g) = init_v_g([self.d_output, self.d_input], 0, self.d_input, device);
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
    /// The effective weight `g * v / ||v||`, [d_output, d_input].
    pub fn effective_weight(&self) -> Tensor<2> {
        if self.folded {
            return self.v.val();
        }
        weight_norm(self.v.val(), self.g.val(), 0)
    }

    /// For inference: stores the effective weight in `v` so that forward passes skip the
    /// norm (training would then move the weight itself, without the norm: train unfolded).
    pub fn fold(self) -> Self {
        let (v, g) = fold_v_g(self.effective_weight(), 0);
        Self {
            v,
            g,
            folded: true,
            ..self
        }
    }

    /// `y = x w^T + b`.
    ///
    /// # Shapes
    /// - `x`: [..., d_input]
    /// - returns [..., d_output]
    pub fn forward<const D: usize>(&self, x: Tensor<D>) -> Tensor<D> {
        linear(
            x,
            self.effective_weight().transpose(),
            self.bias.as_ref().map(|b| b.val()),
        )
    }
}

// ---------------------------------------------------------------------------------------------

/// Configuration of a [`WnConv2d`].
#[derive(Config, Debug)]
pub struct WnConv2dConfig {
    /// Input and output channels.
    pub channels: [usize; 2],
    /// Kernel height and width.
    pub kernel_size: [usize; 2],
    /// Stride.
    #[config(default = "[1, 1]")]
    pub stride: [usize; 2],
    /// Zero padding on each side.
    #[config(default = "[0, 0]")]
    pub padding: [usize; 2],
    /// The bias.
    #[config(default = "Bias::PerChannel")]
    pub bias: Bias,
}

/// Weight-normalised 2D convolution.
#[derive(Module, Debug)]
pub struct WnConv2d {
    /// Direction `v`, [C_out, C_in, k_h, k_w].
    pub v: Param<Tensor<4>>,
    /// Magnitude per output channel, `[C_out]`.
    pub g: Param<Tensor<1>>,
    /// Whether `v` already holds the effective weight ([`Self::fold`]); not saved.
    pub folded: bool,
    /// Per-channel bias, `[C_out]`.
    pub bias: Option<Param<Tensor<1>>>,
    /// Untied bias, [C_out, H_out, W_out].
    pub untied_bias: Option<Param<Tensor<3>>>,
    /// Stride.
    pub stride: [usize; 2],
    /// Zero padding on each side.
    pub padding: [usize; 2],
}

impl WnConv2dConfig {
    /// Initialises the layer (see the module docs for the distributions).
    pub fn init(&self, device: &Device) -> WnConv2d {
        let [c_in, c_out] = self.channels;
        let [kh, kw] = self.kernel_size;
        let fan_in = c_in * kh * kw;
        let (v, g) = init_v_g([c_out, c_in, kh, kw], 0, fan_in, device);
        let (bias, untied_bias) = init_bias(&self.bias, c_out, fan_in, device);
        WnConv2d {
            v,
            g,
            folded: false,
            bias,
            untied_bias,
            stride: self.stride,
            padding: self.padding,
        }
    }
}

impl WnConv2d {
    /// The effective weight `g * v / ||v||`, [C_out, C_in, k_h, k_w].
    pub fn effective_weight(&self) -> Tensor<4> {
        if self.folded {
            return self.v.val();
        }
        weight_norm(self.v.val(), self.g.val(), 0)
    }

    /// For inference: stores the effective weight in `v` so that forward passes skip the
    /// norm (training would then move the weight itself, without the norm: train unfolded).
    pub fn fold(self) -> Self {
        let (v, g) = fold_v_g(self.effective_weight(), 0);
        Self {
            v,
            g,
            folded: true,
            ..self
        }
    }

    /// Convolution with the effective weight, plus the bias.
    ///
    /// # Shapes
    /// - `x`: [N, C_in, H, W]
    /// - returns [N, C_out, H_out, W_out] with `H_out = (H + 2 p - k) / s + 1`
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let y = conv2d(
            x,
            self.effective_weight(),
            self.bias.as_ref().map(|b| b.val()),
            ConvOptions::new(self.stride, self.padding, [1, 1], 1),
        );
        add_untied(y, &self.untied_bias, "WnConv2d")
    }
}

// ---------------------------------------------------------------------------------------------

/// Configuration of a [`WnConvTranspose2d`].
#[derive(Config, Debug)]
pub struct WnConvTranspose2dConfig {
    /// Input and output channels.
    pub channels: [usize; 2],
    /// Kernel height and width.
    pub kernel_size: [usize; 2],
    /// Stride.
    #[config(default = "[1, 1]")]
    pub stride: [usize; 2],
    /// Padding (removed from each side of the full output).
    #[config(default = "[0, 0]")]
    pub padding: [usize; 2],
    /// The bias.
    #[config(default = "Bias::PerChannel")]
    pub bias: Bias,
}

/// Weight-normalised 2D transposed convolution.
#[derive(Module, Debug)]
pub struct WnConvTranspose2d {
    /// Direction `v`, [C_in, C_out, k_h, k_w] (PyTorch's layout for transposed convolutions).
    pub v: Param<Tensor<4>>,
    /// Magnitude per output channel, `[C_out]` (broadcast along dimension 1 of `v`).
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
}

impl WnConvTranspose2dConfig {
    /// Initialises the layer (see the module docs for the distributions).
    pub fn init(&self, device: &Device) -> WnConvTranspose2d {
        let [c_in, c_out] = self.channels;
        let [kh, kw] = self.kernel_size;
        let fan_in = c_out * kh * kw;
        let (v, g) = init_v_g([c_in, c_out, kh, kw], 1, fan_in, device);
        let (bias, untied_bias) = init_bias(&self.bias, c_out, fan_in, device);
        WnConvTranspose2d {
            v,
            g,
            folded: false,
            bias,
            untied_bias,
            stride: self.stride,
            padding: self.padding,
        }
    }
}

impl WnConvTranspose2d {
    /// The effective weight `g * v / ||v||`, [C_in, C_out, k_h, k_w].
    pub fn effective_weight(&self) -> Tensor<4> {
        if self.folded {
            return self.v.val();
        }
        weight_norm(self.v.val(), self.g.val(), 1)
    }

    /// For inference: stores the effective weight in `v` so that forward passes skip the
    /// norm (training would then move the weight itself, without the norm: train unfolded).
    pub fn fold(self) -> Self {
        let (v, g) = fold_v_g(self.effective_weight(), 1);
        Self {
            v,
            g,
            folded: true,
            ..self
        }
    }

    /// Transposed convolution with the effective weight, plus the bias.
    ///
    /// # Shapes
    /// - `x`: [N, C_in, H, W]
    /// - returns [N, C_out, H_out, W_out] with `H_out = (H - 1) s - 2 p + k`
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let p = ConvTParams {
            stride: self.stride,
            padding: self.padding,
        };
        let mut y = conv_transpose2d(x, self.effective_weight(), p);
        if let Some(b) = &self.bias {
            y = y + b.val().reshape([1, -1, 1, 1]);
        }
        add_untied(y, &self.untied_bias, "WnConvTranspose2d")
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::TensorData;

    fn host<const D: usize>(t: Tensor<D>) -> Vec<f32> {
        t.into_data().iter::<f32>().collect()
    }

    fn max_diff(a: &[f32], b: &[f32]) -> f32 {
        assert_eq!(a.len(), b.len());
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max)
    }

    #[allow(deprecated)]
    fn device() -> Device {
        let d = Device::ndarray();
        d.seed(11);
        d
    }

    fn input(shape: [usize; 4], device: &Device) -> Tensor<4> {
        Tensor::random(shape, Distribution::Uniform(-1.0, 1.0), device)
    }

    /// Random magnitudes in [0.5, 2] (so that per-channel behaviour is visible).
    fn random_g(n: usize, device: &Device) -> Param<Tensor<1>> {
        Param::from_tensor(Tensor::random([n], Distribution::Uniform(0.5, 2.0), device))
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
        let mut conv = WnConv2dConfig::new([3, 4], [3, 3])
            .with_padding([1, 1])
            .init(&d);
        conv.g = random_g(4, &d);
        let y0 = host(conv.forward(x.clone()));
        conv.v = Param::from_tensor(conv.v.val() * 7.5);
        assert!(max_diff(&y0, &host(conv.forward(x.clone()))) < 1e-5);

        let mut up = WnConvTranspose2dConfig::new([3, 2], [4, 4])
            .with_stride([2, 2])
            .with_padding([1, 1])
            .with_bias(Bias::Untied {
                height: 10,
                width: 10,
            })
            .init(&d);
        up.g = random_g(2, &d);
        let y0 = host(up.forward(x.clone()));
        up.v = Param::from_tensor(up.v.val() * 0.03);
        assert!(max_diff(&y0, &host(up.forward(x))) < 1e-5);

        let mut lin = WnLinearConfig::new(6, 5).init(&d);
        lin.g = random_g(5, &d);
        let xl = Tensor::<2>::random([3, 6], Distribution::Uniform(-1.0, 1.0), &d);
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
        let mut conv = WnConv2dConfig::new([3, 4], [3, 3])
            .with_padding([1, 1])
            .init(&d);
        conv.g = random_g(4, &d);
        let mut up = WnConvTranspose2dConfig::new([3, 2], [4, 4])
            .with_stride([2, 2])
            .with_padding([1, 1])
            .init(&d);
        up.g = random_g(2, &d);
        let mut lin = WnLinearConfig::new(6, 5).init(&d);
        lin.g = random_g(5, &d);
        let xl = Tensor::<2>::random([3, 6], Distribution::Uniform(-1.0, 1.0), &d);
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

    #[test]
    fn untied_and_per_channel_biases_broadcast() {
        let d = device();
        let x = input([3, 2, 4, 4], &d);
        // With g = 0 the output is the bias alone.
        let mut up = WnConvTranspose2dConfig::new([2, 2], [4, 4])
            .with_stride([2, 2])
            .with_padding([1, 1])
            .with_bias(Bias::Untied {
                height: 8,
                width: 8,
            })
            .init(&d);
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
        let up = WnConvTranspose2dConfig::new([2, 2], [4, 4])
            .with_stride([2, 2])
            .with_padding([1, 1])
            .with_bias(Bias::Untied {
                height: 8,
                width: 8,
            })
            .init(&d);
        let _ = up.forward(input([1, 2, 8, 8], &d));
    }
}
