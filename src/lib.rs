//! texavatars: hybrid texel-3D Gaussian head avatars (TexAvatars, 3DV 2026) on burn.
//!
//! The modules follow the data flow: [`data`] (VHAP export, dataset) → [`head`]
//! (FLAME-compatible model, skinning, the default head) → [`synth`] (the synthetic
//! benchmark) → [`mesh`] (OBJ with UVs) → [`texel`] (UV layout maps, sample grid, per-face
//! frames) → [`model`] (the networks: condition and camera to local texel attributes) →
//! [`lift`] (local texel attributes to 3D Gaussians) → [`camera`] → [`splat`] (the
//! differentiable Gaussian rasterizer) → [`metrics`] (losses and image metrics, with the
//! pretrained VGG16 / AlexNet weights) → [`train`] (the objective and training through
//! burn's learner).

pub mod camera;
pub mod cli;
pub mod data;
pub mod demo;
pub mod device;
pub mod drive;
pub mod error;
pub mod eval;
pub mod head;
pub mod io;
pub mod lift;
pub mod mesh;
pub mod metrics;
pub mod model;
pub mod splat;
pub mod synth;
pub mod texel;
pub mod train;

pub use burn;
pub use texavatars_kernels as kernels;
