//! Constants of the networks (method §3), each with its reason, in one place.
//!
//! The channel plans of the paper's networks live here too; [`super::NetConfig::paper`] and
//! [`super::NetConfig::scaled`] build configurations from them.

use crate::kernels::lift::constants::{LOCAL_CHANNELS, LOCAL_RGB};
pub use texavatars_cpu::constants::LEAKY_RELU_SLOPE;

/// Side of the square grid Exp2Code reshapes its output to (256 x 8 x 8 in the paper). Every
/// upsampling stage doubles it, so `R_uv = BASE_RES * 2^k` for `k` stages.
pub const BASE_RES: usize = 8;

/// Kernel side, stride and padding of a square convolution.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ConvShape {
    pub kernel: usize,
    pub stride: usize,
    pub padding: usize,
}

/// Transposed convolutions: kernel 4, stride 2, padding 1, so that the output side is
/// exactly twice the input side (`(n - 1) * 2 - 2 + 4 = 2n`).
pub const UP: ConvShape = ConvShape {
    kernel: 4,
    stride: 2,
    padding: 1,
};

/// The appearance decoder's 3x3 convolutions after the view injection keep the resolution
/// (stride 1, padding 1).
pub const MID: ConvShape = ConvShape {
    kernel: 3,
    stride: 1,
    padding: 1,
};

/// The view encoder's convolutions: 3x3, stride 2, padding 1, each halving the side
/// (`floor((n + 2 - 3) / 2) + 1 = n / 2` for even `n`).
pub const VIEW: ConvShape = ConvShape {
    kernel: 3,
    stride: 2,
    padding: 1,
};

/// Channels of a Pluecker map: moment `o x d` (3) then direction `d` (3).
pub const PLUECKER_CHANNELS: usize = 6;

/// Side of the square the Pluecker map of the full camera image is first resized to, before
/// it is halved down to the view encoder's input. The authors' code resizes to 512 x 512 for
/// every configuration (it does not follow R_uv).
pub const PLUECKER_SQUARE_RES: usize = 512;

/// Output channels of the geometry decoder: position offset 3, rotation quaternion 4
/// (w, x, y, z), log-scale 3, opacity logit 1, in the lifting operator's channel order.
pub const GEOMETRY_CHANNELS: usize = LOCAL_RGB;

/// Output channels of the appearance decoder: RGB, used directly as the Gaussian colour.
pub const RGB_CHANNELS: usize = LOCAL_CHANNELS - LOCAL_RGB;

/// Scaled-down configurations never make a layer narrower than this: the paper's appearance
/// decoder has a 3-channel stage at 256^2 (convT 64->3, then 3->3) that must stay 3 wide, and
/// 1- or 2-channel layers make the tiny test networks degenerate.
pub const MIN_SCALED_WIDTH: usize = RGB_CHANNELS;

/// Condition sizes: FLAME's expression coefficients (method §1).
pub const FLAME_EXPRESSION_DIM: usize = 100;
/// The shipped default head's expression coefficients (52 ARKit-style blendshapes).
pub const DEFAULT_HEAD_EXPRESSION_DIM: usize = 52;
/// Pose: global rotation 3, neck 3, jaw 3, eyes 6 (axis-angle); the data loader's value.
pub const POSE_DIM: usize = crate::data::dataset::POSE_DIM;
/// The image-derived expression embedding eta (EMOPortraits in the paper); the data
/// loader's value.
pub const ETA_DIM: usize = crate::data::vhap::ETA_DIM;

/// The paper's Exp2Code output channels (243 -> 256 x 8 x 8).
pub const PAPER_CODE_CHANNELS: usize = 256;
/// The paper's geometry decoder: output channels of its six transposed convolutions, at
/// 16, 32, 64, 128, 256 and 512.
pub const PAPER_GEOMETRY: [usize; 6] = [256, 128, 128, 64, 32, GEOMETRY_CHANNELS];
/// The paper's appearance decoder before the view injection: transposed convolutions to 16
/// and 32.
pub const PAPER_APPEARANCE_BEFORE_VIEW: [usize; 2] = [256, 128];
/// The paper's appearance decoder right after the view injection: two 3x3 convolutions at 32.
pub const PAPER_APPEARANCE_MID: [usize; 2] = [128, 128];
/// The paper's appearance decoder after the 3x3 convolutions: transposed convolutions to 64,
/// 128, 256 and 512.
pub const PAPER_APPEARANCE_AFTER_VIEW: [usize; 4] = [64, 64, RGB_CHANNELS, RGB_CHANNELS];
/// The paper's view encoder (Pluecker2Code): two stride-2 convolutions 6 -> 16 -> 32.
pub const PAPER_VIEW: [usize; 2] = [16, 32];

/// The background the avatar is rendered on: the data's ([`crate::data::BACKGROUND`]).
pub const BACKGROUND: [f32; 3] = crate::data::BACKGROUND;
