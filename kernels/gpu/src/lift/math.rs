//! Device helpers shared by the lifting kernels: 3-vectors, 3x3 matrices (row-major; a
//! frame's columns are its axes), the per-face frames and the per-Gaussian lift, each with
//! its backward. Written once so forward and backward kernels evaluate the same expressions
//! as the CPU code in `src/lift/transform.rs` and `src/texel/frames.rs`.

use cubecl::prelude::*;

use super::constants::NORM_EPS;

/// A 3-vector.
#[derive(CubeType, Clone, Copy)]
#[expand(derive(Clone, Copy))]
pub struct V3 {
    pub x: f32,
    pub y: f32,
    pub z: f32,
}

/// A 3x3 matrix, `mRC` = row R, column C.
#[derive(CubeType, Clone, Copy)]
#[expand(derive(Clone, Copy))]
pub struct M3 {
    pub m00: f32,
    pub m01: f32,
    pub m02: f32,
    pub m10: f32,
    pub m11: f32,
    pub m12: f32,
    pub m20: f32,
    pub m21: f32,
    pub m22: f32,
}

/// A quaternion `(w, x, y, z)`.
#[derive(CubeType, Clone, Copy)]
#[expand(derive(Clone, Copy))]
pub struct Q4 {
    pub w: f32,
    pub x: f32,
    pub y: f32,
    pub z: f32,
}

/// Gradients of a frame's three vertices.
#[derive(CubeType, Clone, Copy)]
#[expand(derive(Clone, Copy))]
pub struct Corners {
    pub d0: V3,
    pub d1: V3,
    pub d2: V3,
}

#[cube]
pub fn v3(x: f32, y: f32, z: f32) -> V3 {
    V3 { x, y, z }
}

#[cube]
pub fn load3(buf: &[f32], base: usize) -> V3 {
    V3 {
        x: buf[base],
        y: buf[base + 1],
        z: buf[base + 2],
    }
}

#[cube]
pub fn add(a: V3, b: V3) -> V3 {
    V3 {
        x: a.x + b.x,
        y: a.y + b.y,
        z: a.z + b.z,
    }
}

#[cube]
pub fn sub(a: V3, b: V3) -> V3 {
    V3 {
        x: a.x - b.x,
        y: a.y - b.y,
        z: a.z - b.z,
    }
}

#[cube]
pub fn scale(a: V3, s: f32) -> V3 {
    V3 {
        x: a.x * s,
        y: a.y * s,
        z: a.z * s,
    }
}

#[cube]
pub fn dot(a: V3, b: V3) -> f32 {
    a.x * b.x + a.y * b.y + a.z * b.z
}

#[cube]
pub fn cross(a: V3, b: V3) -> V3 {
    V3 {
        x: a.y * b.z - a.z * b.y,
        y: a.z * b.x - a.x * b.z,
        z: a.x * b.y - a.y * b.x,
    }
}

/// `sqrt(a . a + NORM_EPS^2)`.
#[cube]
pub fn safe_norm(a: V3) -> f32 {
    (dot(a, a) + NORM_EPS * NORM_EPS).sqrt()
}

/// Backward of `y = x / safe_norm(x)`.
#[cube]
pub fn normalize_backward(x: V3, dy: V3) -> V3 {
    let m = safe_norm(x);
    let s = dot(x, dy) / (m * m);
    scale(sub(dy, scale(x, s)), 1.0f32 / m)
}

#[cube]
pub fn from_cols(a: V3, b: V3, c: V3) -> M3 {
    M3 {
        m00: a.x,
        m01: b.x,
        m02: c.x,
        m10: a.y,
        m11: b.y,
        m12: c.y,
        m20: a.z,
        m21: b.z,
        m22: c.z,
    }
}

#[cube]
pub fn col0(m: M3) -> V3 {
    v3(m.m00, m.m10, m.m20)
}

#[cube]
pub fn col1(m: M3) -> V3 {
    v3(m.m01, m.m11, m.m21)
}

#[cube]
pub fn col2(m: M3) -> V3 {
    v3(m.m02, m.m12, m.m22)
}

#[cube]
pub fn identity() -> M3 {
    from_cols(
        v3(1.0f32, 0.0f32, 0.0f32),
        v3(0.0f32, 1.0f32, 0.0f32),
        v3(0.0f32, 0.0f32, 1.0f32),
    )
}

#[cube]
pub fn load_m3(buf: &[f32], base: usize) -> M3 {
    M3 {
        m00: buf[base],
        m01: buf[base + 1],
        m02: buf[base + 2],
        m10: buf[base + 3],
        m11: buf[base + 4],
        m12: buf[base + 5],
        m20: buf[base + 6],
        m21: buf[base + 7],
        m22: buf[base + 8],
    }
}

#[cube]
pub fn store_m3(buf: &mut [f32], base: usize, m: M3) {
    buf[base] = m.m00;
    buf[base + 1] = m.m01;
    buf[base + 2] = m.m02;
    buf[base + 3] = m.m10;
    buf[base + 4] = m.m11;
    buf[base + 5] = m.m12;
    buf[base + 6] = m.m20;
    buf[base + 7] = m.m21;
    buf[base + 8] = m.m22;
}

#[cube]
pub fn row0(m: M3) -> V3 {
    v3(m.m00, m.m01, m.m02)
}

#[cube]
pub fn row1(m: M3) -> V3 {
    v3(m.m10, m.m11, m.m12)
}

#[cube]
pub fn row2(m: M3) -> V3 {
    v3(m.m20, m.m21, m.m22)
}

/// `a b`.
#[cube]
pub fn mat_mul(a: M3, b: M3) -> M3 {
    let c0 = col0(b);
    let c1 = col1(b);
    let c2 = col2(b);
    let r0 = row0(a);
    let r1 = row1(a);
    let r2 = row2(a);
    M3 {
        m00: dot(r0, c0),
        m01: dot(r0, c1),
        m02: dot(r0, c2),
        m10: dot(r1, c0),
        m11: dot(r1, c1),
        m12: dot(r1, c2),
        m20: dot(r2, c0),
        m21: dot(r2, c1),
        m22: dot(r2, c2),
    }
}

#[cube]
pub fn transpose(a: M3) -> M3 {
    from_cols(row0(a), row1(a), row2(a))
}

#[cube]
pub fn mat_vec(a: M3, v: V3) -> V3 {
    v3(dot(row0(a), v), dot(row1(a), v), dot(row2(a), v))
}

/// `a diag(s)`: column c scaled by `s_c`.
#[cube]
pub fn scale_cols(a: M3, s: V3) -> M3 {
    from_cols(
        scale(col0(a), s.x),
        scale(col1(a), s.y),
        scale(col2(a), s.z),
    )
}

#[cube]
pub fn mat_add(a: M3, b: M3) -> M3 {
    from_cols(
        add(col0(a), col0(b)),
        add(col1(a), col1(b)),
        add(col2(a), col2(b)),
    )
}

/// `GaussianAvatars`' frame parts: axes `a0, a1, a2` and scale `k`.
#[cube]
fn scaled_rotation(e1: V3, e2: V3) -> M3 {
    let a0 = scale(e1, 1.0f32 / safe_norm(e1));
    let c = cross(a0, e2);
    let a1 = scale(c, 1.0f32 / safe_norm(c));
    let d = cross(a1, a0);
    let a2 = scale(d, -1.0f32 / safe_norm(d));
    from_cols(a0, a1, a2)
}

#[cube]
fn jacobian_frame(v0: V3, v1: V3, v2: V3) -> M3 {
    let e1 = sub(v1, v0);
    let e2 = sub(v2, v0);
    let n = cross(e1, e2);
    from_cols(e1, e2, scale(n, 1.0f32 / safe_norm(n).sqrt()))
}

#[cube]
fn scaled_rotation_frame(v0: V3, v1: V3, v2: V3) -> M3 {
    let e1 = sub(v1, v0);
    let e2 = sub(v2, v0);
    let r = scaled_rotation(e1, e2);
    let k = 0.5f32 * (safe_norm(e1) + dot(col2(r), e2).abs());
    from_cols(scale(col0(r), k), scale(col1(r), k), scale(col2(r), k))
}

/// The frame of triangle `(v0, v1, v2)`: `[e1 | e2 | n / sqrt(|n|)]`, or `k R` when
/// `scaled_rotation`.
#[cube]
pub fn face_frame(v0: V3, v1: V3, v2: V3, #[comptime] scaled_rotation: bool) -> M3 {
    if scaled_rotation {
        scaled_rotation_frame(v0, v1, v2)
    } else {
        jacobian_frame(v0, v1, v2)
    }
}

#[cube]
fn jacobian_frame_backward(v0: V3, v1: V3, v2: V3, dm: M3) -> Corners {
    let e1 = sub(v1, v0);
    let e2 = sub(v2, v0);
    let n = cross(e1, e2);
    let m = safe_norm(n);
    let dj3 = col2(dm);
    let dn = sub(
        scale(dj3, 1.0f32 / m.sqrt()),
        scale(n, 0.5f32 * dot(dj3, n) / (m * m * m.sqrt())),
    );
    let de1 = add(col0(dm), cross(e2, dn));
    let de2 = add(col1(dm), cross(dn, e1));
    Corners {
        d0: scale(add(de1, de2), -1.0f32),
        d1: de1,
        d2: de2,
    }
}

#[cube]
fn scaled_rotation_frame_backward(v0: V3, v1: V3, v2: V3, dm: M3) -> Corners {
    let e1 = sub(v1, v0);
    let e2 = sub(v2, v0);
    let r = scaled_rotation(e1, e2);
    let a0 = col0(r);
    let a1 = col1(r);
    let a2 = col2(r);
    let k = 0.5f32 * (safe_norm(e1) + dot(a2, e2).abs());
    let d0 = col0(dm);
    let d1 = col1(dm);
    let d2 = col2(dm);
    let dk = dot(d0, a0) + dot(d1, a1) + dot(d2, a2);
    let s = dot(a2, e2);
    let sign = select(s > 0.0f32, 1.0f32, select(s < 0.0f32, -1.0f32, 0.0f32));
    let ds = 0.5f32 * dk * sign;
    let da2 = add(scale(d2, k), scale(e2, ds));
    let d = cross(a1, a0);
    let dd = normalize_backward(d, scale(da2, -1.0f32));
    let da1 = add(scale(d1, k), cross(a0, dd));
    let da0 = add(scale(d0, k), cross(dd, a1));
    let c = cross(a0, e2);
    let dc = normalize_backward(c, da1);
    let da0 = add(da0, cross(e2, dc));
    let de2 = add(scale(a2, ds), cross(dc, a0));
    let de1 = add(
        scale(e1, 0.5f32 * dk / safe_norm(e1)),
        normalize_backward(e1, da0),
    );
    Corners {
        d0: scale(add(de1, de2), -1.0f32),
        d1: de1,
        d2: de2,
    }
}

/// Backward of [`face_frame()`] given `dm = dL/dM`.
#[cube]
pub fn face_frame_backward(
    v0: V3,
    v1: V3,
    v2: V3,
    dm: M3,
    #[comptime] scaled_rotation: bool,
) -> Corners {
    if scaled_rotation {
        scaled_rotation_frame_backward(v0, v1, v2, dm)
    } else {
        jacobian_frame_backward(v0, v1, v2, dm)
    }
}

#[cube]
fn quat_norm(q: Q4) -> f32 {
    (q.w * q.w + q.x * q.x + q.y * q.y + q.z * q.z + NORM_EPS * NORM_EPS).sqrt()
}

/// Rotation of the normalised `q`.
#[cube]
pub fn rotation(q: Q4) -> M3 {
    let m = quat_norm(q);
    let w = q.w / m;
    let x = q.x / m;
    let y = q.y / m;
    let z = q.z / m;
    M3 {
        m00: 1.0f32 - 2.0f32 * (y * y + z * z),
        m01: 2.0f32 * (x * y - w * z),
        m02: 2.0f32 * (x * z + w * y),
        m10: 2.0f32 * (x * y + w * z),
        m11: 1.0f32 - 2.0f32 * (x * x + z * z),
        m12: 2.0f32 * (y * z - w * x),
        m20: 2.0f32 * (x * z - w * y),
        m21: 2.0f32 * (y * z + w * x),
        m22: 1.0f32 - 2.0f32 * (x * x + y * y),
    }
}

/// Backward of [`rotation()`]: `dq` from `g = dL/dR`.
#[cube]
pub fn rotation_backward(q: Q4, g: M3) -> Q4 {
    let m = quat_norm(q);
    let w = q.w / m;
    let x = q.x / m;
    let y = q.y / m;
    let z = q.z / m;
    let dw = 2.0f32 * (-z * g.m01 + y * g.m02 + z * g.m10 - x * g.m12 - y * g.m20 + x * g.m21);
    let dx = 2.0f32
        * (y * g.m01 + z * g.m02 + y * g.m10 - 2.0f32 * x * g.m11 - w * g.m12
            + z * g.m20
            + w * g.m21
            - 2.0f32 * x * g.m22);
    let dy = 2.0f32
        * (-2.0f32 * y * g.m00 + x * g.m01 + w * g.m02 + x * g.m10 + z * g.m12 - w * g.m20
            + z * g.m21
            - 2.0f32 * y * g.m22);
    let dz = 2.0f32
        * (-2.0f32 * z * g.m00 - w * g.m01 + x * g.m02 + w * g.m10 - 2.0f32 * z * g.m11
            + y * g.m12
            + x * g.m20
            + y * g.m21);
    let qdn = q.w * dw + q.x * dx + q.y * dy + q.z * dz;
    let m3 = m * m * m;
    Q4 {
        w: dw / m - q.w * qdn / m3,
        x: dx / m - q.x * qdn / m3,
        y: dy / m - q.y * qdn / m3,
        z: dz / m - q.z * qdn / m3,
    }
}
