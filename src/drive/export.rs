//! A driven avatar's Gaussians as a standard 3DGS PLY (the INRIA layout of
//! [`crate::splat::ply`]), which 3DGS viewers open.
//!
//! Per Gaussian: the world-space mean; `f_dc = (rgb - 0.5) / C0` (SH degree 0, so a viewer's
//! `max(0.5 + C0 f_dc, 0)` gives the avatar's colour back); the opacity's logit; and log
//! scales and a rotation from the eigen-decomposition `Σ = R diag(λ) Rᵀ` (cyclic Jacobi in
//! float64; `R` made a proper rotation, `scale = sqrt(λ)`). For loaders that insist on a
//! higher SH degree, [`PlyGaussians::pad_sh_degree`] adds zero `f_rest_*` coefficients (the
//! same colours).
//!
//! Two things a PLY cannot hold exactly are clamped and counted in [`ExportStats`]: colour
//! channels below 0 (the method's colours have no activation; every 3DGS viewer clamps them
//! at 0), and eigenvalues below [`MIN_VARIANCE`] (a covariance blended across triangle
//! borders is positive semi-definite but may be singular; a log scale needs a positive
//! variance). Opacities are clamped into `[OPACITY_EPS, 1 - OPACITY_EPS]` before the logit.

use glam::{DMat3, DQuat, DVec3};

use crate::data::Conditioning;
use crate::error::{Error, Result};
use crate::models::Drivable;
use crate::splat::Gaussians;
use crate::splat::ply::PlyGaussians;
use crate::splat::sh::C0;

/// Smallest variance written, in squared world units: a standard deviation of 0.1 µm for a
/// head in metres, far below what a pixel resolves (the rasterizer adds 0.3 px² to every
/// projected covariance).
pub const MIN_VARIANCE: f64 = 1e-14;

/// Opacities are kept this far from 0 and 1 so that their logit is finite.
pub const OPACITY_EPS: f32 = 1e-6;

/// What an export had to clamp.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ExportStats {
    /// Gaussians.
    pub gaussians: usize,
    /// Gaussians with a colour channel below 0.
    pub negative_colors: usize,
    /// Gaussians with an eigenvalue below [`MIN_VARIANCE`].
    pub degenerate_covariances: usize,
}

/// Host copies of Gaussians (the fields of [`crate::splat::Gaussians`]).
///
/// # Shapes
/// - `means`: [N, 3]; `cov6`: [N, 6] (xx, xy, xz, yy, yz, zz); `colors`: [N, 3];
///   `opacities`: `[N]` (after the sigmoid)
pub struct HostGaussians<'a> {
    pub means: &'a [f32],
    pub cov6: &'a [f32],
    pub colors: &'a [f32],
    pub opacities: &'a [f32],
}

/// Frame `c`'s world-space Gaussians as a PLY: the model's own ([`Drivable::frame_ply`],
/// e.g. GaussianAvatars' SH coefficients), else `g` (the frame's Gaussians from
/// [`Drivable::frame_gaussians`], colours baked for its camera) through [`to_ply`].
pub fn frame_ply(
    avatar: &dyn Drivable,
    c: &Conditioning,
    g: Gaussians,
) -> Result<(PlyGaussians, ExportStats)> {
    if let Some(p) = avatar.frame_ply(c) {
        let p = p?;
        let stats = ExportStats {
            gaussians: p.len(),
            ..Default::default()
        };
        return Ok((p, stats));
    }
    let host = |t: burn::tensor::Tensor<2>| -> Vec<f32> { t.into_data().iter::<f32>().collect() };
    let means = host(g.means);
    let cov6 = host(g.cov6);
    let colors = host(g.colors);
    let opacities: Vec<f32> = g.opacities.into_data().iter::<f32>().collect();
    to_ply(&HostGaussians {
        means: &means,
        cov6: &cov6,
        colors: &colors,
        opacities: &opacities,
    })
}

/// Converts Gaussians to a degree-0 PLY; fails on wrong lengths or non-finite values.
pub fn to_ply(g: &HostGaussians) -> Result<(PlyGaussians, ExportStats)> {
    let n = g.opacities.len();
    for (name, len, per) in [
        ("means", g.means.len(), 3),
        ("cov6", g.cov6.len(), 6),
        ("colors", g.colors.len(), 3),
    ] {
        if len != per * n {
            return Err(Error::invalid(
                "gaussians",
                name,
                format!("{len} values for {n} Gaussians"),
            ));
        }
    }
    let mut stats = ExportStats {
        gaussians: n,
        ..Default::default()
    };
    let mut ply = PlyGaussians {
        means: g.means.to_vec(),
        sh: Vec::with_capacity(3 * n),
        sh_degree: 0,
        opacity_logits: Vec::with_capacity(n),
        log_scales: Vec::with_capacity(3 * n),
        quats: Vec::with_capacity(4 * n),
    };
    for i in 0..n {
        let c = &g.cov6[6 * i..6 * i + 6];
        let rgb = &g.colors[3 * i..3 * i + 3];
        let o = g.opacities[i];
        if c.iter()
            .chain(rgb)
            .chain(&g.means[3 * i..3 * i + 3])
            .any(|v| !v.is_finite())
            || !o.is_finite()
        {
            return Err(Error::invalid(
                "gaussians",
                format!("gaussian {i}"),
                "not finite",
            ));
        }
        if rgb.iter().any(|&v| v < 0.0) {
            stats.negative_colors += 1;
        }
        ply.sh.extend(rgb.iter().map(|&v| (v - 0.5) / C0));
        let o = o.clamp(OPACITY_EPS, 1.0 - OPACITY_EPS);
        ply.opacity_logits.push((o / (1.0 - o)).ln());
        let (q, var) = decompose(c);
        if var.iter().any(|&v| v < MIN_VARIANCE) {
            stats.degenerate_covariances += 1;
        }
        ply.log_scales
            .extend(var.map(|v| (0.5 * v.max(MIN_VARIANCE).ln()) as f32));
        ply.quats
            .extend([q.w as f32, q.x as f32, q.y as f32, q.z as f32]);
    }
    Ok((ply, stats))
}

/// `Σ = R diag(λ) Rᵀ` for a covariance (xx, xy, xz, yy, yz, zz): the rotation as a unit
/// quaternion and the eigenvalues (in `R`'s column order).
pub fn decompose(c: &[f32]) -> (DQuat, [f64; 3]) {
    let c: Vec<f64> = c.iter().map(|&v| v as f64).collect();
    let mut a = [[c[0], c[1], c[2]], [c[1], c[3], c[4]], [c[2], c[4], c[5]]];
    let mut v = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    let scale = a.iter().flatten().fold(0.0f64, |m, x| m.max(x.abs()));
    if scale > 0.0 {
        // Cyclic Jacobi: each rotation zeroes one off-diagonal entry; quadratic convergence,
        // a handful of sweeps reach float64 precision for 3 x 3.
        for _ in 0..32 {
            let off = a[0][1].abs() + a[0][2].abs() + a[1][2].abs();
            if off <= 1e-15 * scale {
                break;
            }
            for (p, q) in [(0, 1), (0, 2), (1, 2)] {
                if a[p][q].abs() <= 1e-300 {
                    continue;
                }
                let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let t = if theta == 0.0 { 1.0 } else { t };
                let cs = 1.0 / (t * t + 1.0).sqrt();
                let sn = t * cs;
                // A ← Jᵀ A J with J the rotation in the (p, q) plane: columns, then rows.
                for row in &mut a {
                    let (akp, akq) = (row[p], row[q]);
                    row[p] = cs * akp - sn * akq;
                    row[q] = sn * akp + cs * akq;
                }
                let (row_p, row_q) = (a[p], a[q]);
                for k in 0..3 {
                    a[p][k] = cs * row_p[k] - sn * row_q[k];
                    a[q][k] = sn * row_p[k] + cs * row_q[k];
                }
                for row in &mut v {
                    let (vp, vq) = (row[p], row[q]);
                    row[p] = cs * vp - sn * vq;
                    row[q] = sn * vp + cs * vq;
                }
            }
        }
    }
    let cols = [0, 1, 2].map(|j| DVec3::new(v[0][j], v[1][j], v[2][j]));
    let mut r = DMat3::from_cols(cols[0], cols[1], cols[2]);
    if r.determinant() < 0.0 {
        r.z_axis = -r.z_axis;
    }
    let q = DQuat::from_mat3(&r).normalize();
    (q, [a[0][0], a[1][1], a[2][2]])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::splat::ply::cov6_from_quat_scale;

    fn rebuilt(c: &[f32]) -> [f32; 6] {
        let (q, var) = decompose(c);
        let s = var.map(|v| (v.max(MIN_VARIANCE).sqrt()) as f32);
        cov6_from_quat_scale([q.w as f32, q.x as f32, q.y as f32, q.z as f32], s)
    }

    #[test]
    fn decomposition_rebuilds_covariances() {
        let cases: [[f32; 6]; 5] = [
            [1.0, 0.0, 0.0, 2.0, 0.0, 3.0],
            [2.0, 0.5, -0.3, 1.5, 0.2, 1.0],
            [1e-6, 2e-7, 0.0, 3e-6, -1e-7, 2e-6],
            [1.0, 1.0, 0.0, 1.0, 0.0, 0.5], // singular: eigenvalue 0
            [2.0, 0.0, 0.0, 2.0, 0.0, 2.0], // isotropic
        ];
        for c in cases {
            let r = rebuilt(&c);
            let scale = c.iter().fold(0.0f32, |m, v| m.max(v.abs()));
            for k in 0..6 {
                assert!(
                    (r[k] - c[k]).abs() <= 1e-5 * scale,
                    "{c:?} -> {r:?} (entry {k})"
                );
            }
        }
    }

    #[test]
    fn colours_opacities_and_counts() {
        let g = HostGaussians {
            means: &[0.0, 0.0, 1.0, 1.0, 2.0, 3.0],
            cov6: &[1.0, 0.0, 0.0, 1.0, 0.0, 1.0, 1.0, 1.0, 0.0, 1.0, 0.0, 1.0],
            colors: &[0.5, 1.0, 0.0, -0.2, 0.3, 0.9],
            opacities: &[0.5, 1.0],
        };
        let (ply, stats) = to_ply(&g).expect("valid");
        assert_eq!(stats.negative_colors, 1);
        assert_eq!(stats.degenerate_covariances, 1);
        assert!((ply.sh[0]).abs() < 1e-7);
        assert!((0.5 + C0 * ply.sh[1] - 1.0).abs() < 1e-6);
        assert!(ply.opacity_logits[0].abs() < 1e-7);
        assert!(ply.opacity_logits[1].is_finite());
        let bad = HostGaussians {
            opacities: &[0.5, f32::NAN],
            ..g
        };
        assert!(to_ply(&bad).is_err());
    }

    /// `export ply --sh-degree 3`: 45 `f_rest_*` properties (3DGS's `GaussianModel.save_ply`
    /// order, `_features_rest.transpose(1, 2).flatten(start_dim=1)`: channel-major), all zero,
    /// between `f_dc_2` and `opacity`; the file reads back at degree 3 with everything else
    /// unchanged.
    #[test]
    fn degree_3_export_pads_zero_f_rest_and_reads_back() {
        use crate::splat::ply;
        let g = HostGaussians {
            means: &[0.0, 0.0, 1.0, 1.0, 2.0, 3.0],
            cov6: &[
                1.0, 0.2, 0.0, 2.0, 0.1, 0.5, 1e-4, 0.0, 0.0, 4e-4, 0.0, 9e-4,
            ],
            colors: &[0.5, 1.0, 0.25, 0.1, 0.3, 0.9],
            opacities: &[0.5, 0.9],
        };
        let (deg0, _) = to_ply(&g).expect("valid");
        let mut deg3 = deg0.clone();
        deg3.pad_sh_degree(3).expect("pad");
        let dir = std::env::temp_dir().join(format!("texavatars-exp3-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("00000.ply");
        ply::write(&p, &deg3).unwrap();
        let (names, rows) = ply::raw_float_rows(&std::fs::read(&p).unwrap());
        let rest: Vec<usize> = (0..names.len())
            .filter(|&j| names[j].starts_with("f_rest_"))
            .collect();
        assert_eq!(rest.len(), 45);
        let dc2 = names.iter().position(|n| n == "f_dc_2").unwrap();
        for (i, &j) in rest.iter().enumerate() {
            assert_eq!(
                (j, names[j].as_str()),
                (dc2 + 1 + i, format!("f_rest_{i}").as_str())
            );
        }
        assert_eq!(names[dc2 + 46], "opacity");
        assert!(rows.iter().all(|r| rest.iter().all(|&j| r[j] == 0.0)));
        let back = ply::read(&p).unwrap();
        assert_eq!(back, deg3);
        assert_eq!(back.sh_degree, 3);
        for i in 0..2 {
            assert_eq!(&back.sh[48 * i..48 * i + 3], &deg0.sh[3 * i..3 * i + 3]);
        }
        assert_eq!(back.means, deg0.means);
        assert_eq!(back.opacity_logits, deg0.opacity_logits);
        assert_eq!(back.log_scales, deg0.log_scales);
        assert_eq!(back.quats, deg0.quats);
    }
}
