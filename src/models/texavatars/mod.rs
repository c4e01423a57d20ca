//! The networks of method §3: weight-normalised layers ([`layers`]), Exp2Code, the view
//! encoder and the two decoders ([`decoders`]), the Pluecker maps the view encoder reads
//! ([`pluecker`]) and [`TexAvatarNet`], which bundles them and maps (condition, camera) to
//! the local attribute maps of the lifting operator; [`Avatar`] adds the lifting set-up and
//! the rasterizer (condition, camera, posed mesh -> image).
//!
//! Sizes come from a [`NetConfig`] (`configs/paper.json`, `cpu.json`, `tiny.json`); the
//! constants that are not sizes are in [`constants`].

pub mod avatar;
pub mod constants;
pub mod decoders;
pub mod drivable;
pub mod files;
pub mod layers;
pub mod net;
pub mod pluecker;

pub use avatar::{Ablations, Avatar, AvatarConfig, AvatarOutput, LiftSetup};
pub use decoders::{
    AppearanceDecoder, AppearanceDecoderConfig, Exp2Code, Exp2CodeConfig, GeometryDecoder,
    GeometryDecoderConfig, ViewEncoder, ViewEncoderConfig,
};
pub use layers::{
    Bias, WnConv2d, WnConv2dConfig, WnConvTranspose2d, WnConvTranspose2dConfig, WnLinear,
    WnLinearConfig, leaky_relu, weight_norm,
};
pub use net::{AppearancePlan, ConditionConfig, LocalMaps, NetConfig, TexAvatarNet, ViewPlan};
pub use pluecker::{PlueckerMap, view_input, view_input_batch};
