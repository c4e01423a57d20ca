//! The per-Gaussian lift: one thread per row (a texel in `global` mode, a sample in `local`
//! mode).
//!
//! `mean = J mu_l + P`, `Sigma = A A^T` with `A = J R(q) diag(exp(s))`, `q` normalised
//! (safe norm); RGB passes through; the opacity logit passes through, or gets its sigmoid
//! when `sigmoid_opacity`. `J` is `frames[frame_of_row[r]]` (the identity where that is
//! [`NO_FRAME`]), `P = sum_k bary[r, k] vertices[corners[r, k]]`.
//!
//! # Shapes
//! - `local`: 14 channels per row at `local[r * local_row + c * local_ch]`
//! - `frames`: `[F, 9]`, `frame_of_row`: `[M]`, `vertices`: `[V, 3]`,
//!   `corners`: `[M, 3]` u32, `bary`: `[M, 3]`, `out`: `[M, 13]` (mean, cov6, RGB, opacity).

use cubecl::prelude::*;

use super::constants::{
    LOCAL_LOG_SCALE, LOCAL_MEAN, LOCAL_OPACITY, LOCAL_QUAT, LOCAL_RGB, OUT_CHANNELS, OUT_COV,
    OUT_MEAN, OUT_OPACITY, OUT_RGB,
};
use super::math::{
    M3, Q4, V3, add, dot, identity, load_m3, load3, mat_mul, mat_vec, rotation, row0, row1, row2,
    scale, scale_cols, v3,
};

/// `frame_of_row` value for rows without a face (their frame is the identity).
pub const NO_FRAME: u32 = u32::MAX;

/// Channel `c` of row `r` of the local attributes.
#[cube]
pub fn local_at(local: &[f32], r: u32, c: u32, local_row: u32, local_ch: u32) -> f32 {
    local[(r * local_row + c * local_ch) as usize]
}

/// Channels `c0..c0 + 3` of row `r` as a vector.
#[cube]
pub fn local_v3(local: &[f32], r: u32, c0: u32, local_row: u32, local_ch: u32) -> V3 {
    v3(
        local_at(local, r, c0, local_row, local_ch),
        local_at(local, r, c0 + 1, local_row, local_ch),
        local_at(local, r, c0 + 2, local_row, local_ch),
    )
}

/// The three vertices of face `fi`.
#[derive(CubeType, Clone, Copy)]
#[expand(derive(Clone, Copy))]
pub struct Tri {
    pub v0: V3,
    pub v1: V3,
    pub v2: V3,
}

/// Loads face `fi`'s vertices.
#[cube]
pub fn face_vertices(vertices: &[f32], faces: &[u32], fi: usize) -> Tri {
    Tri {
        v0: load3(vertices, faces[fi * 3] as usize * 3),
        v1: load3(vertices, faces[fi * 3 + 1] as usize * 3),
        v2: load3(vertices, faces[fi * 3 + 2] as usize * 3),
    }
}

/// The frame of row `r`.
#[cube]
pub fn row_frame(frames: &[f32], frame_of_row: &[u32], r: u32) -> M3 {
    let f = frame_of_row[r as usize];
    let has = f != NO_FRAME;
    // Rows without a face read face 0's slot (there is at least one face) and discard it.
    let m = load_m3(frames, select(has, f, 0u32) as usize * 9);
    let i = identity();
    M3 {
        m00: select(has, m.m00, i.m00),
        m01: select(has, m.m01, i.m01),
        m02: select(has, m.m02, i.m02),
        m10: select(has, m.m10, i.m10),
        m11: select(has, m.m11, i.m11),
        m12: select(has, m.m12, i.m12),
        m20: select(has, m.m20, i.m20),
        m21: select(has, m.m21, i.m21),
        m22: select(has, m.m22, i.m22),
    }
}

/// `A = J R(q) diag(exp(s))` and its parts.
#[derive(CubeType, Clone, Copy)]
#[expand(derive(Clone, Copy))]
pub struct Factor {
    pub a: M3,
    pub r: M3,
    pub s: V3,
    pub q: Q4,
}

/// The covariance factor of row `r`.
#[cube]
pub fn factor(local: &[f32], r: u32, local_row: u32, local_ch: u32, j: M3) -> Factor {
    let q = Q4 {
        w: local_at(local, r, LOCAL_QUAT as u32, local_row, local_ch),
        x: local_at(local, r, LOCAL_QUAT as u32 + 1, local_row, local_ch),
        y: local_at(local, r, LOCAL_QUAT as u32 + 2, local_row, local_ch),
        z: local_at(local, r, LOCAL_QUAT as u32 + 3, local_row, local_ch),
    };
    let ls = local_v3(local, r, LOCAL_LOG_SCALE as u32, local_row, local_ch);
    let s = v3(ls.x.exp(), ls.y.exp(), ls.z.exp());
    let rot = rotation(q);
    Factor {
        a: scale_cols(mat_mul(j, rot), s),
        r: rot,
        s,
        q,
    }
}

/// See the module documentation.
#[allow(clippy::too_many_arguments)]
#[cube(launch_unchecked)]
pub fn lift_rows(
    local: &[f32],
    local_row: u32,
    local_ch: u32,
    frames: &[f32],
    frame_of_row: &[u32],
    vertices: &[f32],
    corners: &[u32],
    bary: &[f32],
    out: &mut [f32],
    num_rows: u32,
    #[comptime] sigmoid_opacity: bool,
) {
    let r = ABSOLUTE_POS as u32;
    if r >= num_rows {
        terminate!();
    }
    let ri = r as usize;
    let j = row_frame(frames, frame_of_row, r);
    let p0 = scale(load3(vertices, corners[ri * 3] as usize * 3), bary[ri * 3]);
    let p1 = scale(
        load3(vertices, corners[ri * 3 + 1] as usize * 3),
        bary[ri * 3 + 1],
    );
    let p2 = scale(
        load3(vertices, corners[ri * 3 + 2] as usize * 3),
        bary[ri * 3 + 2],
    );
    let anchor = add(add(p0, p1), p2);
    let mu = local_v3(local, r, LOCAL_MEAN as u32, local_row, local_ch);
    let mean = add(mat_vec(j, mu), anchor);
    let f = factor(local, r, local_row, local_ch, j);
    let a0 = row0(f.a);
    let a1 = row1(f.a);
    let a2 = row2(f.a);
    let base = ri * OUT_CHANNELS;
    out[base + OUT_MEAN] = mean.x;
    out[base + OUT_MEAN + 1] = mean.y;
    out[base + OUT_MEAN + 2] = mean.z;
    out[base + OUT_COV] = dot(a0, a0);
    out[base + OUT_COV + 1] = dot(a0, a1);
    out[base + OUT_COV + 2] = dot(a0, a2);
    out[base + OUT_COV + 3] = dot(a1, a1);
    out[base + OUT_COV + 4] = dot(a1, a2);
    out[base + OUT_COV + 5] = dot(a2, a2);
    for c in 0..3usize {
        out[base + OUT_RGB + c] = local_at(local, r, (LOCAL_RGB + c) as u32, local_row, local_ch);
    }
    let mut o = local_at(local, r, LOCAL_OPACITY as u32, local_row, local_ch);
    if sigmoid_opacity {
        o = 1.0f32 / (1.0f32 + (-o).exp());
    }
    out[base + OUT_OPACITY] = o;
}
