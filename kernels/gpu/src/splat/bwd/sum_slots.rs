//! Per-Gaussian sum of the per-intersection gradient slots (backward without float
//! atomics): one thread per Gaussian.
//!
//! The host sorts the intersection indices by Gaussian (stable radix sort of
//! `gaussian_from_isect`, values = intersection index) and builds every Gaussian's range in
//! that list with `tile_ranges::segment_ranges`. Each thread then adds its Gaussian's slots
//! serially, in ascending intersection order, so the result is deterministic.
//!
//! # Shapes
//! - `grad_slots`: `[M, GRAD2D_STRIDE]` (see `bwd::rasterize`).
//! - `isect_from_gaussian_rank`: `[M]` u32: intersection indices sorted by Gaussian.
//! - `gaussian_ranges`: `[N, 2]` u32: `[start, end)` into `isect_from_gaussian_rank`.
//! - `grad2d`: `[N, GRAD2D_STRIDE]`.

use cubecl::prelude::*;

use crate::splat::constants::GRAD2D_STRIDE;

/// See the module documentation.
#[cube(launch_unchecked)]
pub fn sum_slots(
    grad_slots: &[f32],
    isect_from_gaussian_rank: &[u32],
    gaussian_ranges: &[u32],
    grad2d: &mut [f32],
    num_gaussians: u32,
) {
    let gaussian = ABSOLUTE_POS as u32;
    if gaussian >= num_gaussians {
        terminate!();
    }
    let g = gaussian as usize;
    let start = gaussian_ranges[g * 2];
    let end = gaussian_ranges[g * 2 + 1];
    let stride = GRAD2D_STRIDE as usize;
    let mut sums = Array::<f32>::new(GRAD2D_STRIDE as usize);
    for q in 0..stride {
        sums[q] = 0.0f32;
    }
    for k in start..end {
        let slot = isect_from_gaussian_rank[k as usize] as usize * stride;
        for q in 0..stride {
            sums[q] += grad_slots[slot + q];
        }
    }
    for q in 0..stride {
        grad2d[g * stride + q] = sums[q];
    }
}
