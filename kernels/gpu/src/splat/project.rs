//! Forward projection: one thread per Gaussian.
//!
//! Computes the screen-space footprint of every Gaussian (projected mean, conic), its
//! depth sort key and the rectangle of tiles its `alpha >= ALPHA_MIN` region can reach.
//!
//! Culled Gaussians (non-finite mean/covariance/colour/opacity, depth at or before the near
//! plane, 2D covariance not positive definite, opacity below `ALPHA_MIN`, or no tile hit)
//! get a zero tile count, an all-zero projection row and the sort key `u32::MAX`.
//!
//! Tile bounds are opacity aware: with `sigma_max = ln(255 opacity)` the set
//! `alpha >= 1/255` is the ellipse `d^T conic d <= 2 sigma_max`, whose axis-aligned half
//! extents are `sqrt(2 sigma_max Sigma2D_xx)` and `sqrt(2 sigma_max Sigma2D_yy)`. A tile is
//! listed when one of its pixel centres lies in that box (widened by the margins of
//! `constants`), clipped to the image.
//!
//! # Shapes
//! - `means`: `[N, 3]`, `cov6`: `[N, 6]` (`xx, xy, xz, yy, yz, zz`), `colors`: `[N, 3]`,
//!   `opacities`: `[N]`.
//! - `cam`: `[CAMERA_LEN]` (see `camera`).
//! - `projected`: `[N, PROJECTED_STRIDE]`: `u, v, conic a, conic b, conic c, z, opacity,
//!   tiles touched` (the count as f32, exact below 2^24).
//! - `tile_rects`: `[N, 4]` u32: first tile x, first tile y, end tile x, end tile y
//!   (exclusive ends).
//! - `tile_counts`: `[N]` u32: tiles touched.
//! - `depth_keys`: `[N]` u32: bit pattern of the (positive) depth, which sorts like the
//!   float; `u32::MAX` when culled.
//! - `key_stats`: `[KEY_STATS_LEN]` u32 atomics, set by the host to `[u32::MAX, 0, 0]`:
//!   the smallest and the largest depth key of the Gaussians that touch a tile, and their
//!   total tile count (`KEY_MIN`, `KEY_MAX`, `TOTAL_TILES`). Each workgroup reduces its
//!   Gaussians in shared memory first, so the global atomics are one set per workgroup. The
//!   host reads the three words back (the forward's one round trip): the total sizes the
//!   intersection buffers, and the depth sort only sorts the low bits in which the smallest
//!   and largest key differ (every visible key shares the bits above; culled Gaussians touch
//!   no tile, so where they land in depth order does not matter).

use cubecl::prelude::*;

use super::constants::{
    ALPHA_MIN, BOUNDS_ABS_MARGIN, BOUNDS_REL_MARGIN, PROJECTED_STRIDE, TILE_SIZE,
};
use super::math::{is_finite, project_gaussian};

/// Length of `key_stats`.
pub const KEY_STATS_LEN: usize = 3;
/// `key_stats[KEY_MIN]`: the smallest depth key of a visible Gaussian.
pub const KEY_MIN: usize = 0;
/// `key_stats[KEY_MAX]`: the largest depth key of a visible Gaussian.
pub const KEY_MAX: usize = 1;
/// `key_stats[TOTAL_TILES]`: tiles touched, summed over the Gaussians (wraps above
/// `u32::MAX`; the host checks scenes that could get there exactly).
pub const TOTAL_TILES: usize = 2;

/// See the module documentation.
#[allow(clippy::too_many_arguments)]
#[cube(launch_unchecked)]
pub fn project(
    means: &[f32],
    cov6: &[f32],
    colors: &[f32],
    opacities: &[f32],
    cam: &[f32],
    projected: &mut [f32],
    tile_rects: &mut [u32],
    tile_counts: &mut [u32],
    depth_keys: &mut [u32],
    key_stats: &mut [Atomic<u32>],
    num_gaussians: u32,
    width: u32,
    height: u32,
) {
    let gaussian = ABSOLUTE_POS as u32;
    let mut count = 0u32;
    let mut key = 0xFFFF_FFFFu32;
    // No early return: every unit reaches the workgroup barriers below.
    if gaussian < num_gaussians {
        let (c, k) = project_one(
            means,
            cov6,
            colors,
            opacities,
            cam,
            projected,
            tile_rects,
            tile_counts,
            depth_keys,
            gaussian as usize,
            width,
            height,
        );
        count = c;
        key = k;
    }

    let stats = Shared::<[Atomic<u32>]>::new_slice(KEY_STATS_LEN);
    if UNIT_POS == 0 {
        stats[KEY_MIN].store(u32::MAX);
        stats[KEY_MAX].store(0u32);
        stats[TOTAL_TILES].store(0u32);
    }
    sync_cube();
    if count > 0 {
        stats[KEY_MIN].fetch_min(key);
        stats[KEY_MAX].fetch_max(key);
        stats[TOTAL_TILES].fetch_add(count);
    }
    sync_cube();
    if UNIT_POS == 0 {
        let total = stats[TOTAL_TILES].load();
        if total > 0 {
            key_stats[KEY_MIN].fetch_min(stats[KEY_MIN].load());
            key_stats[KEY_MAX].fetch_max(stats[KEY_MAX].load());
            key_stats[TOTAL_TILES].fetch_add(total);
        }
    }
}

/// One Gaussian of [`project`]: writes its rows and returns its tile count and depth key.
#[allow(clippy::too_many_arguments)]
#[cube]
fn project_one(
    means: &[f32],
    cov6: &[f32],
    colors: &[f32],
    opacities: &[f32],
    cam: &[f32],
    projected: &mut [f32],
    tile_rects: &mut [u32],
    tile_counts: &mut [u32],
    depth_keys: &mut [u32],
    g: usize,
    width: u32,
    height: u32,
) -> (u32, u32) {
    let p = project_gaussian(cam, means, cov6, g);
    let opacity = opacities[g];
    let opacity_ok = is_finite(opacity) && opacity >= ALPHA_MIN;
    let color_ok =
        is_finite(colors[g * 3]) && is_finite(colors[g * 3 + 1]) && is_finite(colors[g * 3 + 2]);

    let mut count = 0u32;
    let mut tile_x0 = 0u32;
    let mut tile_y0 = 0u32;
    let mut tile_x1 = 0u32;
    let mut tile_y1 = 0u32;
    if p.valid && opacity_ok && color_ok {
        let sigma_max = max((255.0f32 * opacity).ln(), 0.0f32);
        let scale = 1.0f32 + BOUNDS_REL_MARGIN;
        let extent_x = (2.0f32 * sigma_max * p.cov_a).sqrt() * scale + BOUNDS_ABS_MARGIN;
        let extent_y = (2.0f32 * sigma_max * p.cov_c).sqrt() * scale + BOUNDS_ABS_MARGIN;
        // Pixel i has its centre at i + 0.5: it lies in [u - e, u + e] iff
        // u - e - 0.5 <= i <= u + e - 0.5.
        let lo_x = max((p.u - extent_x - 0.5f32).ceil(), 0.0f32);
        let hi_x = min((p.u + extent_x - 0.5f32).floor(), f32::cast_from(width - 1));
        let lo_y = max((p.v - extent_y - 0.5f32).ceil(), 0.0f32);
        let hi_y = min(
            (p.v + extent_y - 0.5f32).floor(),
            f32::cast_from(height - 1),
        );
        if lo_x <= hi_x && lo_y <= hi_y {
            tile_x0 = u32::cast_from(lo_x) / TILE_SIZE;
            tile_x1 = u32::cast_from(hi_x) / TILE_SIZE + 1;
            tile_y0 = u32::cast_from(lo_y) / TILE_SIZE;
            tile_y1 = u32::cast_from(hi_y) / TILE_SIZE + 1;
            count = (tile_x1 - tile_x0) * (tile_y1 - tile_y0);
        }
    }

    let row = g * PROJECTED_STRIDE as usize;
    let mut key = 0xFFFF_FFFFu32;
    if count > 0 {
        projected[row] = p.u;
        projected[row + 1] = p.v;
        projected[row + 2] = p.conic_a;
        projected[row + 3] = p.conic_b;
        projected[row + 4] = p.conic_c;
        projected[row + 5] = p.z;
        projected[row + 6] = opacity;
        projected[row + 7] = f32::cast_from(count);
        key = u32::reinterpret(p.z);
    } else {
        for k in 0..PROJECTED_STRIDE as usize {
            projected[row + k] = 0.0f32;
        }
    }
    depth_keys[g] = key;
    tile_rects[g * 4] = tile_x0;
    tile_rects[g * 4 + 1] = tile_y0;
    tile_rects[g * 4 + 2] = tile_x1;
    tile_rects[g * 4 + 3] = tile_y1;
    tile_counts[g] = count;
    (count, key)
}
