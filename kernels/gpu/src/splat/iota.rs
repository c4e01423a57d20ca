//! Iota: `output[i] = i`, one thread per element; the identity permutation, the initial
//! values of an index sort.
//!
//! # Shapes
//! - `output`: `[n]` u32.

use cubecl::prelude::*;

/// See the module documentation.
#[cube(launch_unchecked)]
pub fn iota_u32(output: &mut [u32], n: u32) {
    let i = ABSOLUTE_POS as u32;
    if i >= n {
        terminate!();
    }
    output[i as usize] = i;
}
