//! One Gaussian's lift from local attributes to 3D, and its backward pass.
//!
//! `mu = J mu_l + P`, `Sigma = J R(q) diag(exp(s))^2 R(q)^T J^T` with `q` normalised
//! (safe norm, see [`NORM_EPS`]) and `w`-first. Written once and used by the fused CPU code
//! for texels (`global` mode) and for samples (`local` mode).

use crate::kernels::lift::constants::NORM_EPS;
use crate::texel::frames::{Mat3, Vec3};

/// Local geometric attributes of one Gaussian.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LocalGeom {
    pub mean: Vec3,
    /// `(w, x, y, z)`, not necessarily normalised.
    pub quat: [f32; 4],
    pub log_scale: Vec3,
}

/// Gradients of [`LocalGeom`], of the frame and of the anchor position.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LiftGrads {
    pub local: LocalGeom,
    pub frame: Mat3,
    pub anchor: Vec3,
}

fn quat_norm(q: &[f32; 4]) -> f32 {
    (q.iter().map(|v| v * v).sum::<f32>() + NORM_EPS * NORM_EPS).sqrt()
}

/// Rotation matrix of the normalised `q`.
pub fn rotation(q: &[f32; 4]) -> Mat3 {
    let m = quat_norm(q);
    let [w, x, y, z] = q.map(|v| v / m);
    [
        [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y - w * z),
            2.0 * (x * z + w * y),
        ],
        [
            2.0 * (x * y + w * z),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z - w * x),
        ],
        [
            2.0 * (x * z - w * y),
            2.0 * (y * z + w * x),
            1.0 - 2.0 * (x * x + y * y),
        ],
    ]
}

/// Backward of [`rotation`]: `dq` from `dr = dL/dR`.
fn rotation_backward(q: &[f32; 4], dr: &Mat3) -> [f32; 4] {
    let m = quat_norm(q);
    let [w, x, y, z] = q.map(|v| v / m);
    let g = dr;
    let dw =
        2.0 * (-z * g[0][1] + y * g[0][2] + z * g[1][0] - x * g[1][2] - y * g[2][0] + x * g[2][1]);
    let dx = 2.0
        * (y * g[0][1] + z * g[0][2] + y * g[1][0] - 2.0 * x * g[1][1] - w * g[1][2]
            + z * g[2][0]
            + w * g[2][1]
            - 2.0 * x * g[2][2]);
    let dy = 2.0
        * (-2.0 * y * g[0][0] + x * g[0][1] + w * g[0][2] + x * g[1][0] + z * g[1][2]
            - w * g[2][0]
            + z * g[2][1]
            - 2.0 * y * g[2][2]);
    let dz = 2.0
        * (-2.0 * z * g[0][0] - w * g[0][1] + x * g[0][2] + w * g[1][0] - 2.0 * z * g[1][1]
            + y * g[1][2]
            + x * g[2][0]
            + y * g[2][1]);
    let dn = [dw, dx, dy, dz];
    // q_hat = q / m: dq = dn / m - q (q . dn) / m^3.
    let qdn: f32 = q.iter().zip(&dn).map(|(a, b)| a * b).sum();
    std::array::from_fn(|k| dn[k] / m - q[k] * qdn / (m * m * m))
}

/// `A = J R diag(exp(s))`, so that `Sigma = A A^T`.
fn factor(frame: &Mat3, l: &LocalGeom) -> (Mat3, Mat3, Vec3) {
    let r = rotation(&l.quat);
    let s = l.log_scale.map(f32::exp);
    let mut a = [[0.0f32; 3]; 3];
    for i in 0..3 {
        for c in 0..3 {
            a[i][c] = (0..3).map(|k| frame[i][k] * r[k][c]).sum::<f32>() * s[c];
        }
    }
    (a, r, s)
}

/// Lifts one Gaussian: returns `(mean, cov6)` with cov6 = `(xx, xy, xz, yy, yz, zz)`.
pub fn lift(frame: &Mat3, anchor: Vec3, l: &LocalGeom) -> (Vec3, [f32; 6]) {
    let mut mean = anchor;
    for (i, m) in mean.iter_mut().enumerate() {
        *m += (0..3).map(|k| frame[i][k] * l.mean[k]).sum::<f32>();
    }
    let (a, _, _) = factor(frame, l);
    let row = |i: usize, j: usize| (0..3).map(|c| a[i][c] * a[j][c]).sum::<f32>();
    (
        mean,
        [
            row(0, 0),
            row(0, 1),
            row(0, 2),
            row(1, 1),
            row(1, 2),
            row(2, 2),
        ],
    )
}

/// Backward of [`lift`] given `dmean` and `dcov6`.
pub fn lift_backward(frame: &Mat3, l: &LocalGeom, dmean: Vec3, dcov: &[f32; 6]) -> LiftGrads {
    let mut g = LiftGrads {
        anchor: dmean,
        ..Default::default()
    };
    // mean = J mu_l + P.
    for (i, (gf, f)) in g.frame.iter_mut().zip(frame).enumerate() {
        for (k, (gfk, fk)) in gf.iter_mut().zip(f).enumerate() {
            *gfk += dmean[i] * l.mean[k];
            g.local.mean[k] += fk * dmean[i];
        }
    }
    // Sigma = A A^T: dA = 2 G A with G the symmetric matrix of dcov (off-diagonals halved).
    let gm = [
        [dcov[0], 0.5 * dcov[1], 0.5 * dcov[2]],
        [0.5 * dcov[1], dcov[3], 0.5 * dcov[4]],
        [0.5 * dcov[2], 0.5 * dcov[4], dcov[5]],
    ];
    let (a, r, s) = factor(frame, l);
    let mut da = [[0.0f32; 3]; 3];
    for i in 0..3 {
        for c in 0..3 {
            da[i][c] = 2.0 * (0..3).map(|j| gm[i][j] * a[j][c]).sum::<f32>();
        }
    }
    // A = J B, B = R D: dJ = dA B^T, dB = J^T dA.
    let b: Mat3 = std::array::from_fn(|k| std::array::from_fn(|c| r[k][c] * s[c]));
    let mut db = [[0.0f32; 3]; 3];
    for i in 0..3 {
        for k in 0..3 {
            g.frame[i][k] += (0..3).map(|c| da[i][c] * b[k][c]).sum::<f32>();
            db[i][k] = (0..3).map(|j| frame[j][i] * da[j][k]).sum::<f32>();
        }
    }
    // B = R diag(s), s = exp(log_scale).
    let dr: Mat3 = std::array::from_fn(|k| std::array::from_fn(|c| db[k][c] * s[c]));
    for c in 0..3 {
        let ds: f32 = (0..3).map(|k| db[k][c] * r[k][c]).sum();
        g.local.log_scale[c] = ds * s[c];
    }
    g.local.quat = rotation_backward(&l.quat, &dr);
    g
}

#[cfg(test)]
mod tests {
    use super::*;

    fn loss(frame: &Mat3, anchor: Vec3, l: &LocalGeom, wm: Vec3, wc: &[f32; 6]) -> f64 {
        let (m, c) = lift(frame, anchor, l);
        m.iter().zip(wm).map(|(a, b)| (a * b) as f64).sum::<f64>()
            + c.iter().zip(wc).map(|(a, b)| (a * b) as f64).sum::<f64>()
    }

    #[test]
    fn backward_matches_finite_differences() {
        let frame = [[0.8, -0.3, 0.2], [0.1, 0.9, -0.4], [0.3, 0.2, 0.7]];
        let anchor = [0.1, 0.2, 0.3];
        let l = LocalGeom {
            mean: [0.2, -0.5, 0.3],
            quat: [0.9, 0.2, -0.3, 0.4],
            log_scale: [-0.5, 0.1, -1.0],
        };
        let wm = [0.7, -0.2, 0.4];
        let wc = [0.3, -0.6, 0.9, 0.5, -0.2, 0.8];
        let g = lift_backward(&frame, &l, wm, &wc);
        let h = 1e-3f32;
        let check = |fd: f64, an: f32, what: &str| {
            assert!(
                (fd - an as f64).abs() < 3e-3 * (1.0 + fd.abs()),
                "{what}: fd {fd} vs {an}"
            );
        };
        for k in 0..3 {
            let (mut p, mut m) = (l, l);
            p.mean[k] += h;
            m.mean[k] -= h;
            let fd = (loss(&frame, anchor, &p, wm, &wc) - loss(&frame, anchor, &m, wm, &wc))
                / (2.0 * h as f64);
            check(fd, g.local.mean[k], "mean");
            let (mut p, mut m) = (l, l);
            p.log_scale[k] += h;
            m.log_scale[k] -= h;
            let fd = (loss(&frame, anchor, &p, wm, &wc) - loss(&frame, anchor, &m, wm, &wc))
                / (2.0 * h as f64);
            check(fd, g.local.log_scale[k], "log_scale");
        }
        for k in 0..4 {
            let (mut p, mut m) = (l, l);
            p.quat[k] += h;
            m.quat[k] -= h;
            let fd = (loss(&frame, anchor, &p, wm, &wc) - loss(&frame, anchor, &m, wm, &wc))
                / (2.0 * h as f64);
            check(fd, g.local.quat[k], "quat");
        }
        for i in 0..3 {
            for k in 0..3 {
                let (mut p, mut m) = (frame, frame);
                p[i][k] += h;
                m[i][k] -= h;
                let fd = (loss(&p, anchor, &l, wm, &wc) - loss(&m, anchor, &l, wm, &wc))
                    / (2.0 * h as f64);
                check(fd, g.frame[i][k], "frame");
            }
        }
        assert_eq!(g.anchor, wm);
    }
}
