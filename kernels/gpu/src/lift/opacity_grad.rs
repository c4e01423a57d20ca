//! The sigmoid's derivative on the opacity channel: one thread per sample.
//!
//! `out = dout` except `out[k, 12] = dout[k, 12] * s (1 - s)`, `s = sigmoid(logit[k, 12])`.
//!
//! # Shapes
//! - `dout`, `logit`, `out`: `[N, 13]`.

use cubecl::prelude::*;

use super::constants::{OUT_CHANNELS, OUT_OPACITY};

/// See the module documentation.
#[allow(clippy::manual_memcpy)] // a device loop, not a slice copy
#[cube(launch_unchecked)]
pub fn opacity_grad(dout: &[f32], logit: &[f32], out: &mut [f32], num_samples: u32) {
    let k = ABSOLUTE_POS as u32;
    if k >= num_samples {
        terminate!();
    }
    let base = k as usize * OUT_CHANNELS;
    for c in 0..OUT_CHANNELS {
        out[base + c] = dout[base + c];
    }
    let s = 1.0f32 / (1.0f32 + (-logit[base + OUT_OPACITY]).exp());
    out[base + OUT_OPACITY] = dout[base + OUT_OPACITY] * s * (1.0f32 - s);
}
