//! texavatars: hybrid texel-3D Gaussian head avatars (TexAvatars, 3DV 2026) on burn.
//!
//! The modules follow the data flow:
//!
//! 1. Input: [`data`] (VHAP / GaussianAvatars exports as a burn dataset, one identity per
//!    subject) → [`head`] (FLAME-compatible model, skinning, VHAP's teeth, the default head)
//!    → [`synth`] (the synthetic benchmark, written in the same export format) → [`mesh`]
//!    (OBJ with UVs) and [`camera`] (one pinhole convention).
//! 2. The avatar: [`texel`] (UV layout maps, sample grid, per-face frames) → [`lift`] (local
//!    texel attributes to 3D Gaussians) → [`splat`] (the differentiable Gaussian
//!    rasterizer) → [`models`] (TexAvatars' networks and GaussianAvatars' bound Gaussians,
//!    side by side, both offering [`models::Drivable`]); [`eta`] (the image expression code
//!    computed from a capture's own images).
//! 3. Learning and judging: [`metrics`] (losses and image metrics, with the pretrained VGG16
//!    / AlexNet weights) → [`train`] (both models' objectives and training through burn's
//!    learner) → [`eval`] (the paper's evaluation protocol, tables, panels, curves).
//! 4. Use: [`drive`] (motions, cameras, rendering, PLY export, frame-rate benchmark),
//!    [`view`] (driving an avatar live in a web browser), [`study`] (ablations over subjects
//!    and seeds) and [`demo`] (the whole pipeline as one command).
//!
//! Around them: [`cli`] (the `texavatars` commands, thin wrappers), [`device`] (backend
//! choice), `fusion` (the custom ops on burn's kernel-fusion backend), [`gpu`] (launching
//! the CubeCL kernels), [`io`] (npy / npz / PNG / pickle files), [`util`] (random numbers,
//! file helpers), [`limits`] (memory and size checks) and [`error`] (errors that name the
//! file and field). The host ops (fused layers, gemm, Winograd, pooling, blur, Adam, host
//! I/O, rayon's pool) are the `texavatars-cpu` crate ([`cpu`]); the GPU kernels are the
//! `texavatars-kernels` crate ([`kernels`]).
//!
//! # Layers
//!
//! Lowest first. A module uses modules of lower layers only, never one of its own layer or a
//! higher one (`tests/cpu/layers.rs` checks every `crate::` path in `src/`):
//!
//! 1. [`error`], [`cpu`], [`kernels`], [`alloc`], [`device`], `fusion`, [`gpu`]
//! 2. [`io`], [`limits`], [`util`], [`camera`]
//! 3. [`mesh`]
//! 4. [`head`], [`texel`]
//! 5. [`data`], [`lift`]
//! 6. [`splat`], [`metrics`], [`synth`]
//! 7. [`models`], [`eta`]
//! 8. [`train`], [`drive`]
//! 9. [`eval`]
//! 10. [`study`], [`demo`], [`view`]
//! 11. [`cli`]

pub mod alloc;
pub mod camera;
pub mod cli;
pub mod data;
pub mod demo;
pub mod device;
pub mod drive;
pub mod error;
pub mod eta;
pub mod eval;
#[cfg(feature = "fusion")]
pub mod fusion;
pub mod gpu;
pub mod head;
pub mod io;
pub mod lift;
pub mod limits;
pub mod mesh;
pub mod metrics;
pub mod models;
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
