//! The GPU splat on wgpu (lavapipe when the machine has no GPU), one test binary: the
//! kernels ([`gpu_kernels`]), the public differentiable renderer ([`splat_gpu`]) and the
//! kernels' WGSL validated with naga without a device ([`wgsl`]). `benches/gpu.sh` runs this
//! binary as its parity tests.

#[path = "../common/mod.rs"]
mod common;

mod gpu_kernels;
mod splat_gpu;
mod wgsl;
