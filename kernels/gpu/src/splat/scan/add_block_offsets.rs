//! Adds the scanned block totals back: element `i` of block `b` gets `block_offsets[b]`.
//! One workgroup of `SCAN_THREADS` threads per block of `SCAN_BLOCK` elements,
//! `SCAN_ITEMS` consecutive elements per thread (the mapping of `blocks`).
//!
//! # Shapes
//! - `output`: `[n]` u32, `block_offsets`: `[ceil(n / SCAN_BLOCK)]` u32.

use cubecl::prelude::*;

use super::{SCAN_BLOCK, SCAN_ITEMS};

/// See the module documentation.
#[cube(launch_unchecked)]
pub fn scan_add_block_offsets(output: &mut [u32], block_offsets: &[u32], n: u32, num_blocks: u32) {
    let block = CUBE_POS as u32;
    if block >= num_blocks {
        terminate!();
    }
    let offset = block_offsets[block as usize];
    let base = block * SCAN_BLOCK + UNIT_POS * SCAN_ITEMS;
    for j in 0..SCAN_ITEMS {
        let idx = base + j;
        if idx < n {
            output[idx as usize] += offset;
        }
    }
}
