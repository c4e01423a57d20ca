//! GPU kernels of texavatars, written in CubeCL.
pub mod splat;
