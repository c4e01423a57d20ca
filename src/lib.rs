//! texavatars: hybrid texel-3D Gaussian head avatars (TexAvatars, 3DV 2026) on burn.
//!
//! The modules follow the data flow:
//!
//! 1. Input: [`data`] (VHAP / GaussianAvatars exports as a burn dataset, one identity per
//!    subject) → [`head`] (FLAME-compatible model, skinning, VHAP's teeth, the default head)
//!    → [`synth`] (the synthetic benchmark, written in the same export format) → [`mesh`]
//!    (OBJ with UVs) and [`camera`] (one pinhole convention).
//! 2. The avatar: [`texel`] (UV layout maps, sample grid, per-face frames) → [`model`] (the
//!    networks: condition and camera to local texel attributes) → [`lift`] (local texel
//!    attributes to 3D Gaussians) → [`splat`] (the differentiable Gaussian rasterizer).
//!    [`gaussianavatars`], a sibling of [`model`], is the GaussianAvatars baseline (Gaussians
//!    bound to mesh triangles); both models offer [`drivable::Drivable`].
//! 3. Learning and judging: [`metrics`] (losses and image metrics, with the pretrained VGG16
//!    / AlexNet weights) → [`train`] (the objective and training through burn's learner) →
//!    [`eval`] (the paper's evaluation protocol, tables, panels, curves).
//! 4. Use: [`drive`] (motions, cameras, rendering, PLY export, frame-rate benchmark),
//!    [`view`] (driving an avatar live in a web browser) and [`demo`] (the whole pipeline
//!    as one command).
//!
//! Around them: [`cli`] (the `texavatars` commands, thin wrappers), [`threads`] (commands
//! run on rayon's pool), [`device`] (backend choice), `fusion` (the custom ops on burn's
//! kernel-fusion backend), [`io`] (npy / npz / PNG / pickle files) and [`error`] (errors
//! that name the file and field). The GPU kernels are the `texavatars-kernels` crate
//! ([`kernels`]).

pub mod alloc;
pub mod camera;
pub mod cli;
pub mod data;
pub mod demo;
pub mod device;
pub mod drivable;
pub mod drive;
pub mod error;
pub mod eval;
#[cfg(feature = "fusion")]
pub mod fusion;
pub mod gaussianavatars;
pub mod gpu;
pub mod head;
pub mod io;
pub mod lift;
pub mod limits;
pub mod mesh;
pub mod metrics;
pub mod model;
pub mod splat;
pub mod study;
pub mod synth;
pub mod texel;
pub mod train;
pub mod util;
pub mod view;

pub use burn;
pub use texavatars_cpu as cpu;
pub use texavatars_kernels as kernels;
