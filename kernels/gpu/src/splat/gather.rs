//! Gather: `output[i] = source[index[i]]`, one thread per output element.
//!
//! Used to list the Gaussians' tile counts in depth order before scanning them.
//!
//! # Shapes
//! - `source`: `[S]` u32, `index`: `[n]` u32 (values `< S`), `output`: `[n]` u32.

use cubecl::prelude::*;

/// See the module documentation.
#[cube(launch_unchecked)]
pub fn gather_u32(source: &[u32], index: &[u32], output: &mut [u32], n: u32) {
    let i = ABSOLUTE_POS as u32;
    if i >= n {
        terminate!();
    }
    output[i as usize] = source[index[i as usize] as usize];
}
