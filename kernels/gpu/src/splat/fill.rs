//! Fill: `output[i] = value`, one thread per element.
//!
//! Also zero-fills `f32` buffers (the bit pattern of `0.0` is `0`).
//!
//! # Shapes
//! - `output`: `[n]` u32.

use cubecl::prelude::*;

/// See the module documentation.
#[cube(launch_unchecked)]
pub fn fill_u32(output: &mut [u32], value: u32, n: u32) {
    let i = ABSOLUTE_POS as u32;
    if i >= n {
        terminate!();
    }
    output[i as usize] = value;
}
