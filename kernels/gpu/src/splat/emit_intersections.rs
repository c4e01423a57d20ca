//! Emit the tile intersections: one thread per Gaussian, in depth order.
//!
//! The thread at depth rank `r` handles Gaussian `g = gaussian_from_depth_rank[r]` and writes
//! one `(tile id, g)` pair per tile of its rectangle (row-major) at
//! `isect_offsets[r] .. isect_offsets[r] + tile_counts[g]`. The offsets are the exclusive scan
//! of the tile counts in depth order, so the emitted list is ordered by depth and every
//! Gaussian's intersections are contiguous. A stable sort by tile id then yields the
//! per-tile lists in depth order.
//!
//! # Shapes
//! - `gaussian_from_depth_rank`: `[N]` u32, `isect_offsets`: `[N]` u32 (depth order).
//! - `tile_rects`: `[N, 4]` u32, `tile_counts`: `[N]` u32 (Gaussian order, see `project`).
//! - `tile_from_isect`, `gaussian_from_isect`: `[M]` u32 with `M` the total tile count.

use cubecl::prelude::*;

/// See the module documentation.
#[allow(clippy::too_many_arguments)]
#[cube(launch_unchecked)]
pub fn emit_intersections(
    gaussian_from_depth_rank: &[u32],
    isect_offsets: &[u32],
    tile_rects: &[u32],
    tile_counts: &[u32],
    tile_from_isect: &mut [u32],
    gaussian_from_isect: &mut [u32],
    num_gaussians: u32,
    tiles_x: u32,
) {
    let rank = ABSOLUTE_POS as u32;
    if rank >= num_gaussians {
        terminate!();
    }
    let g = gaussian_from_depth_rank[rank as usize];
    let gi = g as usize;
    if tile_counts[gi] == 0 {
        terminate!();
    }
    let x0 = tile_rects[gi * 4];
    let y0 = tile_rects[gi * 4 + 1];
    let x1 = tile_rects[gi * 4 + 2];
    let y1 = tile_rects[gi * 4 + 3];
    let mut isect = isect_offsets[rank as usize];
    for ty in y0..y1 {
        for tx in x0..x1 {
            tile_from_isect[isect as usize] = ty * tiles_x + tx;
            gaussian_from_isect[isect as usize] = g;
            isect += 1u32;
        }
    }
}
