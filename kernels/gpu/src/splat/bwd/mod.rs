//! Backward kernels of the rasterizer, mirroring the forward ones.

pub mod project;
pub mod rasterize;
pub mod sum_slots;
