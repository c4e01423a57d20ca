//! texavatars-cpu: the host ops of texavatars as burn backend extensions.
//!
//! Each op runs on host memory for burn's CPU backends (flex and ndarray), composes burn's
//! own tensor ops on its cubecl backend (the trait's default body), and has a handwritten
//! backward under burn's autodiff. Every op has a reference twin (the composition of burn's
//! ops, or plain loops) and tests that compare values and gradients with it and check
//! finite differences; they build and run without the texavatars app
//! (`cargo test -p texavatars-cpu`).
//!
//! - Layers of the networks: [`bias_act`] (bias and LeakyReLU), [`conv`] (2D convolutions,
//!   plain and transposed, whose host passes are [`conv2d`] and [`conv_transpose`]),
//!   [`conv_bias_act`] (a convolution of either kind, its bias and its activation as one
//!   op), [`weight_norm`] and [`wn_linear`] (weight normalisation, and a
//!   linear layer with the norm folded into its product); `check` holds their tests'
//!   comparisons.
//! - The perceptual loss's convolutions, on channels-last maps ([`map`]): [`conv3x3`] (3x3
//!   convolutions in the column formulation), [`winograd`] (the same as Winograd's minimal
//!   filtering) and [`pool`] (2x2 max-pooling and its backward through the ReLU).
//! - [`blur`] (SSIM's Gaussian blur) and [`adam`] (Adam as one pass per parameter).
//! - Below them: [`autodiff`] (what every op's autodiff implementation shares), [`gemm`] (matrix products), [`host`] (tensors to host vectors and back),
//!   [`threads`] (running work on rayon's pool) and [`constants`].

pub mod adam;
pub mod autodiff;
pub mod bias_act;
pub mod blur;
#[cfg(test)]
mod check;
pub mod constants;
pub mod conv;
pub mod conv2d;
pub mod conv3x3;
pub mod conv_bias_act;
pub mod conv_transpose;
pub mod gemm;
pub mod host;
pub mod map;
pub mod pool;
mod simd;
pub mod threads;
pub mod weight_norm;
pub mod winograd;
pub mod wn_linear;
