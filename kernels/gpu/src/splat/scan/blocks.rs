//! Block-local exclusive scan: one workgroup of `SCAN_THREADS` threads per block of
//! `SCAN_BLOCK` consecutive elements, `SCAN_ITEMS` consecutive elements per thread.
//!
//! Each thread scans its items serially, the per-thread totals are scanned across the
//! workgroup in shared memory (Hillis–Steele), and the block total goes to `block_sums`.
//!
//! # Shapes
//! - `input`, `output`: `[n]` u32 (distinct buffers).
//! - `block_sums`: `[ceil(n / SCAN_BLOCK)]` u32.

use cubecl::prelude::*;

use super::{SCAN_BLOCK, SCAN_ITEMS, SCAN_THREADS};

/// See the module documentation.
#[cube(launch_unchecked)]
pub fn scan_blocks(
    input: &[u32],
    output: &mut [u32],
    block_sums: &mut [u32],
    n: u32,
    num_blocks: u32,
) {
    let block = CUBE_POS as u32;
    if block >= num_blocks {
        terminate!();
    }
    let tid = UNIT_POS;
    let base = block * SCAN_BLOCK + tid * SCAN_ITEMS;

    let mut exclusive = Array::<u32>::new(SCAN_ITEMS as usize);
    let mut thread_total = 0u32;
    for j in 0..SCAN_ITEMS {
        let idx = base + j;
        let mut value = 0u32;
        if idx < n {
            value = input[idx as usize];
        }
        exclusive[j as usize] = thread_total;
        thread_total += value;
    }

    let mut partial = Shared::<[u32]>::new_slice(SCAN_THREADS as usize);
    partial[tid as usize] = thread_total;
    sync_cube();
    let mut offset = 1u32;
    while offset < SCAN_THREADS {
        let mut add = 0u32;
        if tid >= offset {
            add = partial[(tid - offset) as usize];
        }
        sync_cube();
        partial[tid as usize] += add;
        sync_cube();
        offset *= 2u32;
    }
    let inclusive = partial[tid as usize];
    let thread_offset = inclusive - thread_total;

    for j in 0..SCAN_ITEMS {
        let idx = base + j;
        if idx < n {
            output[idx as usize] = exclusive[j as usize] + thread_offset;
        }
    }
    if tid == SCAN_THREADS - 1 {
        block_sums[block as usize] = inclusive;
    }
}
