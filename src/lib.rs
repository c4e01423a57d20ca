//! texavatars: hybrid texel-3D Gaussian head avatars (TexAvatars, 3DV 2026) on burn.
//!
//! The modules follow the data flow: [`camera`] → [`splat`] (the differentiable Gaussian
//! rasterizer).

pub mod camera;
pub mod cli;
pub mod device;
pub mod error;
pub mod io;
pub mod splat;

pub use burn;
pub use texavatars_kernels as kernels;
