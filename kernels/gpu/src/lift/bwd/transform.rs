//! Backward of the per-Gaussian lift: one thread per row.
//!
//! From `dout` (mean 3, cov6 6, RGB 3, opacity 1) per row: the gradient of the 14 local
//! channels (written with strides, so texel rows can land channel-major) and of the row's
//! frame `[M, 9]`. The anchor's gradient is `dout`'s mean part, used directly by the caller.
//! `Sigma = A A^T`: `dA = 2 G A` with `G` the symmetric matrix of `dcov6` (off-diagonals
//! halved); `A = J B`, `B = R diag(s)`: `dJ = dmean mu^T + dA B^T`, `dB = J^T dA`,
//! `dR = dB diag(s)`, `ds_c = s_c sum_k dB_kc R_kc`, `dq` by the rotation's backward.
//! When `sigmoid_opacity`, the opacity gradient gets the sigmoid's derivative at the row's
//! own logit (local mode).
//!
//! # Shapes
//! - as `lift_rows`; `dout`: `[M, 13]`; `dlocal` at `dlocal[r * dl_row + c * dl_ch]`;
//!   `dframes`: `[M, 9]`.

use cubecl::prelude::*;

use crate::lift::constants::{
    LOCAL_LOG_SCALE, LOCAL_MEAN, LOCAL_OPACITY, LOCAL_QUAT, LOCAL_RGB, OUT_CHANNELS, OUT_COV,
    OUT_MEAN, OUT_OPACITY, OUT_RGB,
};
use crate::lift::math::{
    col0, col1, col2, dot, from_cols, mat_add, mat_mul, mat_vec, rotation_backward, scale,
    scale_cols, store_m3, transpose, v3,
};
use crate::lift::transform::{factor, local_at, local_v3, row_frame};

#[cube]
fn write_local(dlocal: &mut [f32], r: u32, c: u32, dl_row: u32, dl_ch: u32, v: f32) {
    dlocal[(r * dl_row + c * dl_ch) as usize] = v;
}

/// See the module documentation.
#[allow(clippy::too_many_arguments)]
#[cube(launch_unchecked)]
pub fn lift_rows_backward(
    local: &[f32],
    local_row: u32,
    local_ch: u32,
    frames: &[f32],
    frame_of_row: &[u32],
    dout: &[f32],
    dlocal: &mut [f32],
    dl_row: u32,
    dl_ch: u32,
    dframes: &mut [f32],
    num_rows: u32,
    #[comptime] sigmoid_opacity: bool,
) {
    let r = ABSOLUTE_POS as u32;
    if r >= num_rows {
        terminate!();
    }
    let ri = r as usize;
    let base = ri * OUT_CHANNELS;
    let j = row_frame(frames, frame_of_row, r);
    let f = factor(local, r, local_row, local_ch, j);
    let mu = local_v3(local, r, LOCAL_MEAN as u32, local_row, local_ch);
    let dmean = v3(
        dout[base + OUT_MEAN],
        dout[base + OUT_MEAN + 1],
        dout[base + OUT_MEAN + 2],
    );
    let d0 = dout[base + OUT_COV];
    let d1 = 0.5f32 * dout[base + OUT_COV + 1];
    let d2 = 0.5f32 * dout[base + OUT_COV + 2];
    let d3 = dout[base + OUT_COV + 3];
    let d4 = 0.5f32 * dout[base + OUT_COV + 4];
    let d5 = dout[base + OUT_COV + 5];
    let g = from_cols(v3(d0, d1, d2), v3(d1, d3, d4), v3(d2, d4, d5));
    let ga = mat_mul(g, f.a);
    let da = from_cols(
        scale(col0(ga), 2.0f32),
        scale(col1(ga), 2.0f32),
        scale(col2(ga), 2.0f32),
    );
    // B = R diag(s).
    let b = scale_cols(f.r, f.s);
    // dJ = dmean mu^T + dA B^T.
    let outer = from_cols(scale(dmean, mu.x), scale(dmean, mu.y), scale(dmean, mu.z));
    let dj = mat_add(outer, mat_mul(da, transpose(b)));
    store_m3(dframes, ri * 9, dj);
    // dmu = J^T dmean.
    let dmu = mat_vec(transpose(j), dmean);
    let db = mat_mul(transpose(j), da);
    let dr = scale_cols(db, f.s);
    let dls = v3(
        dot(col0(db), col0(f.r)) * f.s.x,
        dot(col1(db), col1(f.r)) * f.s.y,
        dot(col2(db), col2(f.r)) * f.s.z,
    );
    let dq = rotation_backward(f.q, dr);
    write_local(dlocal, r, LOCAL_MEAN as u32, dl_row, dl_ch, dmu.x);
    write_local(dlocal, r, LOCAL_MEAN as u32 + 1, dl_row, dl_ch, dmu.y);
    write_local(dlocal, r, LOCAL_MEAN as u32 + 2, dl_row, dl_ch, dmu.z);
    write_local(dlocal, r, LOCAL_QUAT as u32, dl_row, dl_ch, dq.w);
    write_local(dlocal, r, LOCAL_QUAT as u32 + 1, dl_row, dl_ch, dq.x);
    write_local(dlocal, r, LOCAL_QUAT as u32 + 2, dl_row, dl_ch, dq.y);
    write_local(dlocal, r, LOCAL_QUAT as u32 + 3, dl_row, dl_ch, dq.z);
    write_local(dlocal, r, LOCAL_LOG_SCALE as u32, dl_row, dl_ch, dls.x);
    write_local(dlocal, r, LOCAL_LOG_SCALE as u32 + 1, dl_row, dl_ch, dls.y);
    write_local(dlocal, r, LOCAL_LOG_SCALE as u32 + 2, dl_row, dl_ch, dls.z);
    for c in 0..3usize {
        write_local(
            dlocal,
            r,
            (LOCAL_RGB + c) as u32,
            dl_row,
            dl_ch,
            dout[base + OUT_RGB + c],
        );
    }
    let mut dop = dout[base + OUT_OPACITY];
    if sigmoid_opacity {
        let s = 1.0f32
            / (1.0f32 + (-local_at(local, r, LOCAL_OPACITY as u32, local_row, local_ch)).exp());
        dop *= s * (1.0f32 - s);
    }
    write_local(dlocal, r, LOCAL_OPACITY as u32, dl_row, dl_ch, dop);
}
