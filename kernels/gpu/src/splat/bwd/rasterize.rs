//! Backward rasterization: one workgroup of `TILE_SIZE x TILE_SIZE` threads per tile, one
//! thread per pixel, walking the tile's intersections back to front.
//!
//! Every pixel starts from its final transmittance `T_final` (the forward output) and its
//! `last` (how far the forward pass composited), recomputes each contributing Gaussian's
//! alpha exactly as the forward pass did, and recovers the transmittance in front of it by
//! division, `T_i = T_{i+1} / (1 - alpha_i)`. With `S_i = sum_{j > i} alpha_j T_j c_j` (the
//! colour composited behind `i`), the loss gradient of `alpha_i` is
//! `g . (T_i c_i - S_i / (1 - alpha_i)) - (g . bg + g_T) T_final / (1 - alpha_i)`, where
//! `g` is dL/dRGB and `g_T` dL/dT of the pixel. The colour gradient is `alpha_i T_i g`.
//! Where `opacity exp(-sigma)` exceeds `ALPHA_MAX` the clamp is active and opacity and
//! sigma get no gradient; otherwise `dalpha/dopacity = exp(-sigma)` and
//! `dalpha/dsigma = -alpha`, and sigma's gradient flows to the conic and the 2D mean.
//!
//! Batches of [`BWD_BATCH`] Gaussians are loaded into shared memory, the last batch first;
//! the workgroup only walks up to the largest `last` of its pixels.
//!
//! Per-Gaussian accumulation of the nine screen-space gradients has two variants, chosen at
//! compile time by `float_atomics` together with the element type `G` of `grad2d`:
//! - `true`, `G = Atomic<f32>`: every contributing pixel adds into `grad2d[g]` with
//!   `Atomic<f32>::fetch_add`. With `plane_reduce` (adapters with subgroup operations) the
//!   pixels of a plane (subgroup) first sum their nine values with `plane_sum`, and only one
//!   unit of the plane (its smallest index) adds them: one set of atomics per plane and Gaussian instead of one
//!   per pixel (8 instead of up to 256 per tile for 32-wide planes), as gsplat reduces per
//!   warp before its atomics.
//! - `false`, `G = f32` (devices without float atomics): `grad2d` is a plain one-entry dummy,
//!   so the generated shader declares no `atomic<f32>` at all (CubeCL binds every argument,
//!   used or not, and WGSL validation rejects an `atomic<f32>` binding on adapters without
//!   float atomics; `tests/gpu/wgsl.rs` validates both variants with naga). For every
//!   intersection the workgroup sums its
//!   pixels' contributions in shared memory (fixed order, deterministic) and one thread
//!   writes the sum to the intersection's own slot `grad_slots[isect]` (every
//!   `(tile, Gaussian)` pair is unique, so no two workgroups write the same slot). Slots of
//!   intersections no pixel reached are left untouched (zero-filled by the host);
//!   `sum_slots` then adds each Gaussian's slots.
//!
//! # Shapes
//! - `projected`: `[N, PROJECTED_STRIDE]`, `colors`: `[N, 3]`.
//! - `gaussian_from_isect`: `[M]` u32, `tile_ranges`: `[tiles, 2]` u32.
//! - `cam`: `[CAMERA_LEN]`.
//! - `out`: `[H, W, 4]` (forward output), `last`: `[H, W]` u32, `grad_out`: `[H, W, 4]`.
//! - `grad2d`: `[N, GRAD2D_STRIDE]` (atomic variant; a one-entry dummy otherwise).
//! - `grad_slots`: `[M, GRAD2D_STRIDE]` (slot variant; a dummy otherwise).

use cubecl::prelude::*;

use crate::splat::camera::CAM_BG;
use crate::splat::constants::{
    ALPHA_MAX, ALPHA_MIN, GRAD2D_STRIDE, PROJECTED_STRIDE, TILE_PIXELS, TILE_SIZE,
};
use crate::splat::math::{clamp_alpha, gaussian_sigma, raw_alpha};

/// Gaussians loaded into shared memory per batch (half the workgroup), which keeps the
/// slot variant's shared memory below 16 KiB.
pub const BWD_BATCH: u32 = 128;

/// Segments of the shared-memory reduction over the tile's pixels (slot variant).
const REDUCE_SEGMENTS: u32 = 16;
/// Pixels summed serially per segment.
const REDUCE_SEGMENT_LEN: u32 = TILE_PIXELS / REDUCE_SEGMENTS;

/// An element of `rasterize_backward`'s `grad2d`: `Atomic<f32>` adds into it (the
/// float-atomic variant); `f32` is the slot variant's dummy, never added to.
#[cube]
pub trait GradCell: CubePrimitive {
    /// Adds `value` to `cells[index]`.
    fn add_grad(cells: &mut [Self], index: usize, value: f32);
}

#[cube]
impl GradCell for Atomic<f32> {
    fn add_grad(cells: &mut [Self], index: usize, value: f32) {
        cells[index].fetch_add(value);
    }
}

#[cube]
impl GradCell for f32 {
    fn add_grad(cells: &mut [Self], index: usize, value: f32) {
        // Never emitted: `G = f32` is launched only with `float_atomics` false, which
        // compiles the calls away; a plain add keeps the function total.
        cells[index] += value;
    }
}

/// See the module documentation. Launch with a `(tiles_x, tiles_y)` grid of
/// `(TILE_SIZE, TILE_SIZE)` workgroups; `G = Atomic<f32>` with `float_atomics`, `G = f32`
/// without. `plane_reduce` (only with `float_atomics`) needs plane operations.
#[allow(clippy::too_many_arguments)]
#[cube(launch_unchecked)]
pub fn rasterize_backward<G: GradCell>(
    projected: &[f32],
    colors: &[f32],
    gaussian_from_isect: &[u32],
    tile_ranges: &[u32],
    cam: &[f32],
    out: &[f32],
    last: &[u32],
    grad_out: &[f32],
    grad2d: &mut [G],
    grad_slots: &mut [f32],
    width: u32,
    height: u32,
    tiles_x: u32,
    #[comptime] float_atomics: bool,
    #[comptime] plane_reduce: bool,
) {
    let tid = UNIT_POS;
    let px = CUBE_POS_X * TILE_SIZE + UNIT_POS_X;
    let py = CUBE_POS_Y * TILE_SIZE + UNIT_POS_Y;
    let tile = CUBE_POS_Y * tiles_x + CUBE_POS_X;
    let inside = px < width && py < height;
    let pixel_x = f32::cast_from(px) + 0.5f32;
    let pixel_y = f32::cast_from(py) + 0.5f32;

    let mut t_final = 1.0f32;
    let mut g_red = 0.0f32;
    let mut g_green = 0.0f32;
    let mut g_blue = 0.0f32;
    let mut g_trans = 0.0f32;
    let mut pixel_end = 0u32;
    if inside {
        let pixel = (py * width + px) as usize;
        t_final = out[pixel * 4 + 3];
        g_red = grad_out[pixel * 4];
        g_green = grad_out[pixel * 4 + 1];
        g_blue = grad_out[pixel * 4 + 2];
        g_trans = grad_out[pixel * 4 + 3];
        pixel_end = last[pixel];
    }
    // dL/dT_final through the background and the transmittance output.
    let final_term =
        (g_red * cam[CAM_BG] + g_green * cam[CAM_BG + 1] + g_blue * cam[CAM_BG + 2] + g_trans)
            * t_final;

    let range_start = tile_ranges[(tile * 2) as usize];
    // The unit of its plane that adds the plane's sums: the one with the smallest index in
    // the workgroup. Not `UNIT_POS_PLANE == 0` or `plane_elect()`: both read the subgroup
    // invocation id, which WGSL does not offer for multi-dimensional workgroups.
    let mut plane_leader = false;
    if plane_reduce {
        plane_leader = plane_min(tid) == tid;
    }

    // The workgroup walks up to the largest `last` of its pixels.
    let max_end = Shared::<[Atomic<u32>]>::new_slice(1usize);
    if tid == 0 {
        max_end[0].store(0u32);
    }
    sync_cube();
    max_end[0].fetch_max(pixel_end);
    sync_cube();
    let range_len = max_end[0].load();
    let num_batches = range_len.div_ceil(BWD_BATCH);

    let mut s_gaussian = Shared::<[u32]>::new_slice(BWD_BATCH as usize);
    let mut s_mean = Shared::<[f32]>::new_slice((BWD_BATCH * 2) as usize);
    let mut s_conic = Shared::<[f32]>::new_slice((BWD_BATCH * 3) as usize);
    let mut s_opacity = Shared::<[f32]>::new_slice(BWD_BATCH as usize);
    let mut s_color = Shared::<[f32]>::new_slice((BWD_BATCH * 3) as usize);
    let mut s_reduce = Shared::<[f32]>::new_slice(if float_atomics {
        1usize
    } else {
        (GRAD2D_STRIDE * TILE_PIXELS) as usize
    });
    let mut s_partial = Shared::<[f32]>::new_slice(if float_atomics {
        1usize
    } else {
        (GRAD2D_STRIDE * REDUCE_SEGMENTS) as usize
    });

    let mut transmittance = t_final;
    let mut behind_red = 0.0f32;
    let mut behind_green = 0.0f32;
    let mut behind_blue = 0.0f32;

    for batch in 0..num_batches {
        let batch_end = range_len - batch * BWD_BATCH;
        let batch_start = select(batch_end > BWD_BATCH, batch_end - BWD_BATCH, 0u32);
        let batch_len = batch_end - batch_start;
        sync_cube();
        if tid < batch_len {
            let g = gaussian_from_isect[(range_start + batch_start + tid) as usize];
            let gi = g as usize;
            let row = gi * PROJECTED_STRIDE as usize;
            let t = tid as usize;
            s_gaussian[t] = g;
            s_mean[t * 2] = projected[row];
            s_mean[t * 2 + 1] = projected[row + 1];
            s_conic[t * 3] = projected[row + 2];
            s_conic[t * 3 + 1] = projected[row + 3];
            s_conic[t * 3 + 2] = projected[row + 4];
            s_opacity[t] = projected[row + 6];
            s_color[t * 3] = colors[gi * 3];
            s_color[t * 3 + 1] = colors[gi * 3 + 1];
            s_color[t * 3 + 2] = colors[gi * 3 + 2];
        }
        sync_cube();

        for step in 0..batch_len {
            let j = batch_len - 1 - step;
            let rel = batch_start + j;
            let t = j as usize;

            let mut contributes = false;
            let mut d_u = 0.0f32;
            let mut d_v = 0.0f32;
            let mut d_a = 0.0f32;
            let mut d_b = 0.0f32;
            let mut d_c = 0.0f32;
            let mut d_red = 0.0f32;
            let mut d_green = 0.0f32;
            let mut d_blue = 0.0f32;
            let mut d_opacity = 0.0f32;
            if rel < pixel_end {
                let conic_a = s_conic[t * 3];
                let conic_b = s_conic[t * 3 + 1];
                let conic_c = s_conic[t * 3 + 2];
                let dx = s_mean[t * 2] - pixel_x;
                let dy = s_mean[t * 2 + 1] - pixel_y;
                let sigma = gaussian_sigma(conic_a, conic_b, conic_c, dx, dy);
                let (alpha_raw, vis) = raw_alpha(s_opacity[t], sigma);
                let alpha = clamp_alpha(alpha_raw);
                if sigma >= 0.0f32 && alpha >= ALPHA_MIN {
                    contributes = true;
                    let inv_one_minus = 1.0f32 / (1.0f32 - alpha);
                    let t_here = transmittance * inv_one_minus;
                    let weight = alpha * t_here;
                    let c_red = s_color[t * 3];
                    let c_green = s_color[t * 3 + 1];
                    let c_blue = s_color[t * 3 + 2];
                    d_red = weight * g_red;
                    d_green = weight * g_green;
                    d_blue = weight * g_blue;
                    let d_alpha = g_red * (c_red * t_here - behind_red * inv_one_minus)
                        + g_green * (c_green * t_here - behind_green * inv_one_minus)
                        + g_blue * (c_blue * t_here - behind_blue * inv_one_minus)
                        - final_term * inv_one_minus;
                    behind_red += weight * c_red;
                    behind_green += weight * c_green;
                    behind_blue += weight * c_blue;
                    transmittance = t_here;
                    if alpha_raw <= ALPHA_MAX {
                        d_opacity = d_alpha * vis;
                        let d_sigma = -d_alpha * alpha;
                        d_a = 0.5f32 * d_sigma * dx * dx;
                        d_b = d_sigma * dx * dy;
                        d_c = 0.5f32 * d_sigma * dy * dy;
                        d_u = d_sigma * (conic_a * dx + conic_b * dy);
                        d_v = d_sigma * (conic_b * dx + conic_c * dy);
                    }
                }
            }

            if float_atomics {
                let mut add = contributes;
                if plane_reduce {
                    // Every unit of the workgroup is at the same step (the loop bounds are
                    // uniform), so the plane operations run in uniform control flow.
                    add = false;
                    if plane_any(contributes) {
                        d_u = plane_sum(d_u);
                        d_v = plane_sum(d_v);
                        d_a = plane_sum(d_a);
                        d_b = plane_sum(d_b);
                        d_c = plane_sum(d_c);
                        d_red = plane_sum(d_red);
                        d_green = plane_sum(d_green);
                        d_blue = plane_sum(d_blue);
                        d_opacity = plane_sum(d_opacity);
                        add = plane_leader;
                    }
                }
                if add {
                    let base = (s_gaussian[t] * GRAD2D_STRIDE) as usize;
                    G::add_grad(grad2d, base, d_u);
                    G::add_grad(grad2d, base + 1, d_v);
                    G::add_grad(grad2d, base + 2, d_a);
                    G::add_grad(grad2d, base + 3, d_b);
                    G::add_grad(grad2d, base + 4, d_c);
                    G::add_grad(grad2d, base + 5, d_red);
                    G::add_grad(grad2d, base + 6, d_green);
                    G::add_grad(grad2d, base + 7, d_blue);
                    G::add_grad(grad2d, base + 8, d_opacity);
                }
            } else {
                let p = tid as usize;
                let stride = TILE_PIXELS as usize;
                s_reduce[p] = d_u;
                s_reduce[stride + p] = d_v;
                s_reduce[2 * stride + p] = d_a;
                s_reduce[3 * stride + p] = d_b;
                s_reduce[4 * stride + p] = d_c;
                s_reduce[5 * stride + p] = d_red;
                s_reduce[6 * stride + p] = d_green;
                s_reduce[7 * stride + p] = d_blue;
                s_reduce[8 * stride + p] = d_opacity;
                sync_cube();
                if tid < GRAD2D_STRIDE * REDUCE_SEGMENTS {
                    let quantity = tid / REDUCE_SEGMENTS;
                    let segment = tid % REDUCE_SEGMENTS;
                    let first = quantity * TILE_PIXELS + segment * REDUCE_SEGMENT_LEN;
                    let mut sum = 0.0f32;
                    for i in 0..REDUCE_SEGMENT_LEN {
                        sum += s_reduce[(first + i) as usize];
                    }
                    s_partial[tid as usize] = sum;
                }
                sync_cube();
                if tid < GRAD2D_STRIDE {
                    let mut sum = 0.0f32;
                    for i in 0..REDUCE_SEGMENTS {
                        sum += s_partial[(tid * REDUCE_SEGMENTS + i) as usize];
                    }
                    let isect = range_start + rel;
                    grad_slots[(isect * GRAD2D_STRIDE + tid) as usize] = sum;
                }
            }
        }
    }
}
