//! Tile-based 3D Gaussian splatting.
//!
//! The forward pipeline, in launch order (the host side lives in the main crate's
//! `splat::gpu`):
//!
//! 1. [`project`]: one thread per Gaussian: camera-space mean, EWA 2D covariance, conic,
//!    opacity-aware screen rectangle of tiles, depth sort key; per workgroup, then
//!    globally, the smallest and largest visible key and the total tile count, which the
//!    host reads back.
//! 2. [`iota`], [`radix_sort`] (with [`scan`]): stable LSD radix sort of the Gaussians by
//!    depth, over the low key bits in which the visible keys differ.
//! 3. [`gather`] and [`scan`]: tile counts in depth order and their exclusive prefix sum,
//!    the first index of each Gaussian's intersections.
//! 4. [`emit_intersections`]: one thread per Gaussian (in depth order) writes a
//!    `(tile id, Gaussian)` pair per tile it touches.
//! 5. [`radix_sort`] by tile id (stable, so depth order survives within a tile).
//! 6. [`tile_ranges`]: `[start, end)` of every tile in the sorted intersections.
//! 7. [`rasterize`]: one 16x16 workgroup per tile composites front to back.
//!
//! The backward pipeline is in [`bwd`]: [`bwd::rasterize`] (per tile, back to front; float
//! atomics, optionally after a subgroup sum, or per-intersection slots) then
//! [`bwd::sum_slots`] (only without float atomics) and [`bwd::project`].
//!
//! Every kernel reads camera values from one small `f32` buffer laid out as described in
//! [`camera`].

pub mod bwd;
pub mod camera;
pub mod constants;
pub mod emit_intersections;
pub mod fill;
pub mod gather;
pub mod iota;
pub mod math;
pub mod project;
pub mod radix_sort;
pub mod rasterize;
pub mod scan;
pub mod tile_ranges;
