//! GPU kernels of texavatars, written in CubeCL.
//!
//! One kernel per file; `bwd/` folders mirror the forward ones. The constants every
//! implementation shares (reference, CPU, GPU) live in [`splat::constants`] and
//! [`lift::constants`].

pub mod lift;
pub mod splat;
