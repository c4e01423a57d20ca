//! Bilinear blend at the kept samples: one thread per sample.
//!
//! `out[k, c] = sum_q weights[k, q] * src[taps[k, q] * src_row + c * src_ch]`, with a
//! sigmoid on the last channel when `sigmoid_last` (the opacity logit). Strides let the
//! source be texel-major (`[R*R, C]`) or channel-major (`[C, R*R]`).
//!
//! # Shapes
//! - `taps`, `weights`: `[N, 4]`, `out`: `[N, channels]`.

use cubecl::prelude::*;

/// See the module documentation.
#[allow(clippy::too_many_arguments)]
#[cube(launch_unchecked)]
pub fn blend(
    src: &[f32],
    src_row: u32,
    src_ch: u32,
    taps: &[u32],
    weights: &[f32],
    out: &mut [f32],
    num_samples: u32,
    channels: u32,
    #[comptime] sigmoid_last: bool,
) {
    let k = ABSOLUTE_POS as u32;
    if k >= num_samples {
        terminate!();
    }
    let ki = k as usize;
    for c in 0..channels {
        let mut acc = 0.0f32;
        for q in 0..4usize {
            let t = taps[ki * 4 + q];
            acc += weights[ki * 4 + q] * src[(t * src_row + c * src_ch) as usize];
        }
        if sigmoid_last && c == channels - 1 {
            acc = 1.0f32 / (1.0f32 + (-acc).exp());
        }
        out[(k * channels + c) as usize] = acc;
    }
}
