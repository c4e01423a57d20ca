//! Forward rasterization: one workgroup of `TILE_SIZE x TILE_SIZE` threads per tile, one
//! thread per pixel.
//!
//! The workgroup walks its tile's intersections (depth order) in batches of
//! [`RASTER_BATCH`]: every thread loads one Gaussian's screen data into shared memory, then
//! every pixel composites the batch front to back:
//! `sigma = 0.5 (a dx^2 + c dy^2) + b dx dy` with `(dx, dy) = mean - pixel centre`,
//! `alpha = min(ALPHA_MAX, opacity exp(-sigma))`, skipped when `sigma < 0` or
//! `alpha < ALPHA_MIN`; a pixel stops before a Gaussian that would bring its transmittance
//! below `TRANSMITTANCE_MIN` (that Gaussian is not added). The workgroup stops once every
//! pixel has stopped. Pixels outside the image (partial tiles) only help loading.
//!
//! # Shapes
//! - `projected`: `[N, PROJECTED_STRIDE]` (see `project`), `colors`: `[N, 3]`.
//! - `gaussian_from_isect`: `[M]` u32 (tile-major, depth order within a tile).
//! - `tile_ranges`: `[tiles_y * tiles_x, 2]` u32.
//! - `cam`: `[CAMERA_LEN]` (the background colour is read from it).
//! - `out`: `[H, W, 4]` f32: composited RGB plus background, and final transmittance.
//! - `last`: `[H, W]` u32: end (exclusive, relative to the tile's range start) of the
//!   intersections the pixel composited, for the backward pass.

use cubecl::prelude::*;

use super::camera::CAM_BG;
use super::constants::{ALPHA_MIN, PROJECTED_STRIDE, TILE_PIXELS, TILE_SIZE, TRANSMITTANCE_MIN};
use super::math::{clamp_alpha, gaussian_sigma, raw_alpha};

/// Gaussians loaded into shared memory per batch (one per thread).
pub const RASTER_BATCH: u32 = TILE_PIXELS;

/// See the module documentation. Launch with a `(tiles_x, tiles_y)` grid of
/// `(TILE_SIZE, TILE_SIZE)` workgroups.
#[allow(clippy::too_many_arguments)]
#[cube(launch_unchecked)]
pub fn rasterize(
    projected: &[f32],
    colors: &[f32],
    gaussian_from_isect: &[u32],
    tile_ranges: &[u32],
    cam: &[f32],
    out: &mut [f32],
    last: &mut [u32],
    width: u32,
    height: u32,
    tiles_x: u32,
) {
    let tid = UNIT_POS;
    let px = CUBE_POS_X * TILE_SIZE + UNIT_POS_X;
    let py = CUBE_POS_Y * TILE_SIZE + UNIT_POS_Y;
    let tile = CUBE_POS_Y * tiles_x + CUBE_POS_X;
    let inside = px < width && py < height;
    let pixel_x = f32::cast_from(px) + 0.5f32;
    let pixel_y = f32::cast_from(py) + 0.5f32;

    let range_start = tile_ranges[(tile * 2) as usize];
    let range_end = tile_ranges[(tile * 2 + 1) as usize];
    let num_batches = (range_end - range_start).div_ceil(RASTER_BATCH);

    let mut s_mean = Shared::<[f32]>::new_slice((RASTER_BATCH * 2) as usize);
    let mut s_conic = Shared::<[f32]>::new_slice((RASTER_BATCH * 3) as usize);
    let mut s_opacity = Shared::<[f32]>::new_slice(RASTER_BATCH as usize);
    let mut s_color = Shared::<[f32]>::new_slice((RASTER_BATCH * 3) as usize);
    // Two alternating counters of finished pixels (one is reset while the other is read).
    let done_count = Shared::<[Atomic<u32>]>::new_slice(2usize);
    if tid == 0 {
        done_count[0].store(0u32);
    }

    let mut transmittance = 1.0f32;
    let mut red = 0.0f32;
    let mut green = 0.0f32;
    let mut blue = 0.0f32;
    let mut done = !inside;
    let mut end = 0u32;

    for batch in 0..num_batches {
        sync_cube();
        let batch_start = range_start + batch * RASTER_BATCH;
        let isect = batch_start + tid;
        if isect < range_end {
            let g = gaussian_from_isect[isect as usize] as usize;
            let row = g * PROJECTED_STRIDE as usize;
            let t = tid as usize;
            s_mean[t * 2] = projected[row];
            s_mean[t * 2 + 1] = projected[row + 1];
            s_conic[t * 3] = projected[row + 2];
            s_conic[t * 3 + 1] = projected[row + 3];
            s_conic[t * 3 + 2] = projected[row + 4];
            s_opacity[t] = projected[row + 6];
            s_color[t * 3] = colors[g * 3];
            s_color[t * 3 + 1] = colors[g * 3 + 1];
            s_color[t * 3 + 2] = colors[g * 3 + 2];
        }
        if tid == 0 {
            done_count[((batch + 1) % 2) as usize].store(0u32);
        }
        if done {
            done_count[(batch % 2) as usize].fetch_add(1u32);
        }
        sync_cube();
        if done_count[(batch % 2) as usize].load() == TILE_PIXELS {
            break;
        }

        let batch_len = min(RASTER_BATCH, range_end - batch_start);
        if !done {
            for j in 0..batch_len {
                let t = j as usize;
                let dx = s_mean[t * 2] - pixel_x;
                let dy = s_mean[t * 2 + 1] - pixel_y;
                let sigma = gaussian_sigma(
                    s_conic[t * 3],
                    s_conic[t * 3 + 1],
                    s_conic[t * 3 + 2],
                    dx,
                    dy,
                );
                let (alpha_raw, _vis) = raw_alpha(s_opacity[t], sigma);
                let alpha = clamp_alpha(alpha_raw);
                if sigma >= 0.0f32 && alpha >= ALPHA_MIN {
                    let next_t = transmittance * (1.0f32 - alpha);
                    if next_t < TRANSMITTANCE_MIN {
                        done = true;
                        break;
                    }
                    let weight = alpha * transmittance;
                    red += weight * s_color[t * 3];
                    green += weight * s_color[t * 3 + 1];
                    blue += weight * s_color[t * 3 + 2];
                    transmittance = next_t;
                    end = batch * RASTER_BATCH + j + 1;
                }
            }
        }
    }

    if inside {
        let pixel = (py * width + px) as usize;
        out[pixel * 4] = red + transmittance * cam[CAM_BG];
        out[pixel * 4 + 1] = green + transmittance * cam[CAM_BG + 1];
        out[pixel * 4 + 2] = blue + transmittance * cam[CAM_BG + 2];
        out[pixel * 4 + 3] = transmittance;
        last[pixel] = end;
    }
}
