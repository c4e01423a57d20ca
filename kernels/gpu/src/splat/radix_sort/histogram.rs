//! Radix sort pass, step 1: per-block digit histogram. One workgroup of `RADIX_THREADS`
//! threads per block of `RADIX_BLOCK` keys, `RADIX_ITEMS` consecutive keys per thread,
//! counting into shared atomics.
//!
//! # Shapes
//! - `keys`: `[n]` u32.
//! - `histogram`: `[RADIX_BUCKETS * num_blocks]` u32, digit-major (`digit * num_blocks +
//!   block`), so its exclusive scan is the global offset of every (digit, block).

use cubecl::prelude::*;

use super::{RADIX_BLOCK, RADIX_BUCKETS, RADIX_ITEMS};

/// Counts, per block, how many keys have each digit `(key >> shift) & digit_mask`
/// (`digit_mask < RADIX_BUCKETS`).
#[cube(launch_unchecked)]
pub fn radix_histogram(
    keys: &[u32],
    histogram: &mut [u32],
    n: u32,
    shift: u32,
    digit_mask: u32,
    num_blocks: u32,
) {
    let block = CUBE_POS as u32;
    if block >= num_blocks {
        terminate!();
    }
    let tid = UNIT_POS;
    let counts = Shared::<[Atomic<u32>]>::new_slice(RADIX_BUCKETS as usize);
    // One digit per thread (RADIX_THREADS >= RADIX_BUCKETS, asserted in the module).
    if tid < RADIX_BUCKETS {
        counts[tid as usize].store(0u32);
    }
    sync_cube();
    let base = block * RADIX_BLOCK + tid * RADIX_ITEMS;
    for j in 0..RADIX_ITEMS {
        let idx = base + j;
        if idx < n {
            let digit = (keys[idx as usize] >> shift) & digit_mask;
            counts[digit as usize].fetch_add(1u32);
        }
    }
    sync_cube();
    if tid < RADIX_BUCKETS {
        histogram[(tid * num_blocks + block) as usize] = counts[tid as usize].load();
    }
}
