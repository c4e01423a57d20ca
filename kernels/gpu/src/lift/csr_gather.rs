//! Weighted gather over a CSR list: one thread per target. The deterministic (atomic-free)
//! form of every scatter-add of the lifting backward (samples to texels, texels or samples
//! to faces, corners and anchors to vertices).
//!
//! `out[t * out_row + c * out_ch] (+)= sum_{e in offsets[t]..offsets[t+1]}
//! weights[e] * values[entries[e] * val_row + val_offset + c]` for `c < channels`.
//!
//! # Shapes
//! - `offsets`: `[T + 1]`, `entries`, `weights`: `[E]`.

use cubecl::prelude::*;

/// See the module documentation.
#[allow(clippy::too_many_arguments)]
#[cube(launch_unchecked)]
pub fn csr_gather(
    values: &[f32],
    val_row: u32,
    val_offset: u32,
    offsets: &[u32],
    entries: &[u32],
    weights: &[f32],
    out: &mut [f32],
    out_row: u32,
    out_ch: u32,
    num_targets: u32,
    channels: u32,
    #[comptime] accumulate: bool,
) {
    let t = ABSOLUTE_POS as u32;
    if t >= num_targets {
        terminate!();
    }
    let start = offsets[t as usize];
    let end = offsets[t as usize + 1];
    for c in 0..channels {
        let mut acc = 0.0f32;
        for e in start..end {
            let src = entries[e as usize] * val_row + val_offset + c;
            acc += weights[e as usize] * values[src as usize];
        }
        let o = (t * out_row + c * out_ch) as usize;
        if accumulate {
            out[o] += acc;
        } else {
            out[o] = acc;
        }
    }
}
