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

use cubecl::prelude::*;

use super::constants::{
    ALPHA_MIN, BOUNDS_ABS_MARGIN, BOUNDS_REL_MARGIN, PROJECTED_STRIDE, TILE_SIZE,
};
use super::math::{is_finite, project_gaussian};

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
    num_gaussians: u32,
    width: u32,
    height: u32,
) {
    let gaussian = ABSOLUTE_POS as u32;
    if gaussian >= num_gaussians {
        terminate!();
    }
    let g = gaussian as usize;
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
    if count > 0 {
        projected[row] = p.u;
        projected[row + 1] = p.v;
        projected[row + 2] = p.conic_a;
        projected[row + 3] = p.conic_b;
        projected[row + 4] = p.conic_c;
        projected[row + 5] = p.z;
        projected[row + 6] = opacity;
        projected[row + 7] = f32::cast_from(count);
        depth_keys[g] = u32::reinterpret(p.z);
    } else {
        for k in 0..PROJECTED_STRIDE as usize {
            projected[row + k] = 0.0f32;
        }
        depth_keys[g] = u32::MAX;
    }
    tile_rects[g * 4] = tile_x0;
    tile_rects[g * 4 + 1] = tile_y0;
    tile_rects[g * 4 + 2] = tile_x1;
    tile_rects[g * 4 + 3] = tile_y1;
    tile_counts[g] = count;
}
