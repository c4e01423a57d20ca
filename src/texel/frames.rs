//! Per-frame geometry from posed vertices: the position map and the per-face frames, with
//! their handwritten backward passes (used by the fused CPU lifting).
//!
//! Matrices are `[[f32; 3]; 3]`, row-major: `m[r][c]`. A frame's *columns* are its axes.

use crate::kernels::lift::constants::NORM_EPS;
use crate::texel::layout::UvLayout;

pub type Vec3 = [f32; 3];
pub type Mat3 = [[f32; 3]; 3];

/// Which per-face frame lifts local attributes to 3D.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FrameKind {
    /// The paper's `J_F = [e1 | e2 | n / sqrt(|n|)]`.
    #[default]
    Jacobian,
    /// GaussianAvatars' `k R` (the "w/o Jacobian" ablation).
    ScaledRotation,
}

pub const IDENTITY: Mat3 = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

#[inline]
pub fn sub(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
#[inline]
pub fn add(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}
#[inline]
pub fn scale(a: Vec3, s: f32) -> Vec3 {
    [a[0] * s, a[1] * s, a[2] * s]
}
#[inline]
pub fn dot(a: Vec3, b: Vec3) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
#[inline]
pub fn cross(a: Vec3, b: Vec3) -> Vec3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
/// `sqrt(a . a + NORM_EPS^2)`.
#[inline]
pub fn safe_norm(a: Vec3) -> f32 {
    (dot(a, a) + NORM_EPS * NORM_EPS).sqrt()
}
/// Backward of `y = x / safe_norm(x)`: `dx = (dy - x (x . dy) / m^2) / m`.
#[inline]
fn normalize_backward(x: Vec3, dy: Vec3) -> Vec3 {
    let m = safe_norm(x);
    let s = dot(x, dy) / (m * m);
    scale(sub(dy, scale(x, s)), 1.0 / m)
}
/// Matrix with columns `a, b, c`.
#[inline]
pub fn from_cols(a: Vec3, b: Vec3, c: Vec3) -> Mat3 {
    [[a[0], b[0], c[0]], [a[1], b[1], c[1]], [a[2], b[2], c[2]]]
}
#[inline]
pub fn col(m: &Mat3, c: usize) -> Vec3 {
    [m[0][c], m[1][c], m[2][c]]
}

/// The frame of the triangle `(v0, v1, v2)`.
pub fn face_frame(kind: FrameKind, v: [Vec3; 3]) -> Mat3 {
    let e1 = sub(v[1], v[0]);
    let e2 = sub(v[2], v[0]);
    match kind {
        FrameKind::Jacobian => {
            let n = cross(e1, e2);
            from_cols(e1, e2, scale(n, 1.0 / safe_norm(n).sqrt()))
        }
        FrameKind::ScaledRotation => {
            let (r, k) = scaled_rotation(v);
            r.map(|row| row.map(|x| x * k))
        }
    }
}

/// GaussianAvatars' frame of the triangle `(v0, v1, v2)`: the rotation `R = [a0 | a1 | a2]`
/// (columns) and the scale `k`, as GaussianAvatars' `compute_face_orientation`
/// (`utils/graphics_utils.py`, `return_scale=True`) computes them for its binding and as the
/// lift's [`FrameKind::ScaledRotation`] uses them. `R` is a proper rotation (`a2 = a0 x a1`).
pub fn scaled_rotation(v: [Vec3; 3]) -> (Mat3, f32) {
    let (a, k) = scaled_rotation_parts(sub(v[1], v[0]), sub(v[2], v[0]));
    (from_cols(a[0], a[1], a[2]), k)
}

/// GaussianAvatars' frame: `a0 = norm(e1)`, `a1 = norm(a0 x e2)`, `a2 = -norm(a1 x a0)`,
/// `k = (|e1| + |a2 . e2|) / 2`.
fn scaled_rotation_parts(e1: Vec3, e2: Vec3) -> ([Vec3; 3], f32) {
    let a0 = scale(e1, 1.0 / safe_norm(e1));
    let c = cross(a0, e2);
    let a1 = scale(c, 1.0 / safe_norm(c));
    let d = cross(a1, a0);
    let a2 = scale(d, -1.0 / safe_norm(d));
    let k = 0.5 * (safe_norm(e1) + dot(a2, e2).abs());
    ([a0, a1, a2], k)
}

/// Backward of [`face_frame`]: gradients of the three vertices given `dm = dL/dM`.
pub fn face_frame_backward(kind: FrameKind, v: [Vec3; 3], dm: &Mat3) -> [Vec3; 3] {
    let e1 = sub(v[1], v[0]);
    let e2 = sub(v[2], v[0]);
    let (de1, de2) = match kind {
        FrameKind::Jacobian => {
            let n = cross(e1, e2);
            let m = safe_norm(n);
            let dj3 = col(dm, 2);
            // J3 = n m^(-1/2), dm/dn = n / m.
            let dn = sub(
                scale(dj3, 1.0 / m.sqrt()),
                scale(n, 0.5 * dot(dj3, n) / (m * m * m.sqrt())),
            );
            (
                add(col(dm, 0), cross(e2, dn)),
                add(col(dm, 1), cross(dn, e1)),
            )
        }
        FrameKind::ScaledRotation => {
            let ([a0, a1, a2], k) = scaled_rotation_parts(e1, e2);
            let (d0, d1, d2) = (col(dm, 0), col(dm, 1), col(dm, 2));
            let dk = dot(d0, a0) + dot(d1, a1) + dot(d2, a2);
            let (mut da0, mut da1, mut da2) = (scale(d0, k), scale(d1, k), scale(d2, k));
            // k = (|e1| + |s|) / 2, s = a2 . e2.
            let s = dot(a2, e2);
            let ds = 0.5
                * dk
                * if s > 0.0 {
                    1.0
                } else if s < 0.0 {
                    -1.0
                } else {
                    0.0
                };
            da2 = add(da2, scale(e2, ds));
            let mut de2 = scale(a2, ds);
            let mut de1 = scale(e1, 0.5 * dk / safe_norm(e1));
            // a2 = -norm(d), d = a1 x a0.
            let d = cross(a1, a0);
            let dd = normalize_backward(d, scale(da2, -1.0));
            da1 = add(da1, cross(a0, dd));
            da0 = add(da0, cross(dd, a1));
            // a1 = norm(c), c = a0 x e2.
            let c = cross(a0, e2);
            let dc = normalize_backward(c, da1);
            da0 = add(da0, cross(e2, dc));
            de2 = add(de2, cross(dc, a0));
            // a0 = norm(e1).
            de1 = add(de1, normalize_backward(e1, da0));
            (de1, de2)
        }
    };
    [scale(add(de1, de2), -1.0), de1, de2]
}

/// Per-face frames of the posed mesh.
///
/// # Shapes
/// - `faces`: `[F]`; `vertices`: `[V]`; returns `[F]`
pub fn face_frames(kind: FrameKind, faces: &[[u32; 3]], vertices: &[Vec3]) -> Vec<Mat3> {
    faces
        .iter()
        .map(|f| face_frame(kind, f.map(|i| vertices[i as usize])))
        .collect()
}

/// The position map: per texel, the barycentric interpolation of its face's posed vertices
/// (zero where no face covers it).
///
/// # Shapes
/// - `vertices`: `[V]`; returns [R * R]
pub fn position_map(layout: &UvLayout, vertices: &[Vec3]) -> Vec<Vec3> {
    layout
        .face
        .iter()
        .zip(&layout.verts)
        .zip(&layout.bary)
        .map(|((f, vs), b)| match f {
            Some(_) => interpolate(vs, b, vertices),
            None => [0.0; 3],
        })
        .collect()
}

/// `sum_k b_k v[vs_k]`.
#[inline]
pub fn interpolate(vs: &[u32; 3], b: &[f32; 3], vertices: &[Vec3]) -> Vec3 {
    let mut p = [0.0; 3];
    for k in 0..3 {
        p = add(p, scale(vertices[vs[k] as usize], b[k]));
    }
    p
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame_loss(kind: FrameKind, v: [Vec3; 3], w: &Mat3) -> f64 {
        let m = face_frame(kind, v);
        (0..3)
            .flat_map(|r| (0..3).map(move |c| (r, c)))
            .map(|(r, c)| m[r][c] as f64 * w[r][c] as f64)
            .sum()
    }

    /// Central differences (in f64 around f32 values) against the handwritten backward.
    #[test]
    fn frame_backward_matches_finite_differences() {
        let v = [[0.1, -0.2, 0.3], [0.9, 0.1, 0.2], [0.2, 0.8, -0.1]];
        let w = [[0.3, -1.1, 0.7], [0.2, 0.5, -0.4], [-0.9, 0.6, 1.3]];
        for kind in [FrameKind::Jacobian, FrameKind::ScaledRotation] {
            let g = face_frame_backward(kind, v, &w);
            for i in 0..3 {
                for c in 0..3 {
                    let h = 1e-3f32;
                    let (mut p, mut m) = (v, v);
                    p[i][c] += h;
                    m[i][c] -= h;
                    let fd = (frame_loss(kind, p, &w) - frame_loss(kind, m, &w)) / (2.0 * h as f64);
                    let err = (fd - g[i][c] as f64).abs();
                    assert!(
                        err < 2e-3 * (1.0 + fd.abs()),
                        "{kind:?} v{i}[{c}]: fd {fd} vs {}",
                        g[i][c]
                    );
                }
            }
        }
    }

    /// A flat mesh whose positions equal its UVs (z = 0): the position map at a covered
    /// texel is the texel centre's UV, and zero elsewhere.
    #[test]
    fn position_map_interpolates_the_face() {
        use crate::mesh::UvMesh;
        use crate::texel::UvLayout;
        let uvs = [[0.1f32, 0.1], [0.9, 0.2], [0.3, 0.8]];
        let m = UvMesh {
            uvs: uvs.to_vec(),
            positions: uvs.iter().map(|t| [t[0], t[1], 0.0]).collect(),
            faces: vec![[0, 1, 2]],
            uv_faces: vec![[0, 1, 2]],
        };
        let r = 16;
        let layout = UvLayout::new(&m, r).expect("layout");
        let p = position_map(&layout, &m.positions);
        let mut covered = 0;
        for j in 0..r {
            for i in 0..r {
                let t = j * r + i;
                if layout.face[t].is_some() {
                    covered += 1;
                    let want = [
                        (i as f32 + 0.5) / r as f32,
                        (j as f32 + 0.5) / r as f32,
                        0.0,
                    ];
                    for c in 0..3 {
                        assert!(
                            (p[t][c] - want[c]).abs() < 1e-6,
                            "texel ({i}, {j}): {:?}",
                            p[t]
                        );
                    }
                } else {
                    assert_eq!(p[t], [0.0; 3]);
                }
            }
        }
        assert!(covered > 30);
    }

    #[test]
    fn degenerate_faces_are_finite() {
        for v in [
            [[0.0; 3]; 3],
            [[1.0, 0.0, 0.0], [2.0, 0.0, 0.0], [3.0, 0.0, 0.0]],
        ] {
            for kind in [FrameKind::Jacobian, FrameKind::ScaledRotation] {
                let m = face_frame(kind, v);
                let g = face_frame_backward(kind, v, &IDENTITY);
                assert!(m.iter().flatten().all(|x| x.is_finite()), "{kind:?} {m:?}");
                assert!(g.iter().flatten().all(|x| x.is_finite()), "{kind:?} {g:?}");
            }
        }
    }

    #[test]
    fn scaled_rotation_is_a_scaled_rotation() {
        let v = [[0.1, -0.2, 0.3], [0.9, 0.1, 0.2], [0.2, 0.8, -0.1]];
        let m = face_frame(FrameKind::ScaledRotation, v);
        let k = safe_norm(col(&m, 0));
        for a in 0..3 {
            for b in 0..3 {
                let d = dot(col(&m, a), col(&m, b)) / (k * k);
                assert!((d - f32::from(u8::from(a == b))).abs() < 1e-5);
            }
        }
        // Right-handed: det > 0.
        let det = dot(col(&m, 0), cross(col(&m, 1), col(&m, 2)));
        assert!(det > 0.0);
    }
}
