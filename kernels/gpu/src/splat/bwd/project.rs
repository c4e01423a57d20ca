//! Backward projection: one thread per Gaussian.
//!
//! Maps the accumulated screen-space gradient of a Gaussian (2D mean, conic, colour,
//! opacity) back to its world mean and covariance by the exact chain rule of the forward
//! projection (`math::project_gaussian`):
//! - conic = inverse(Sigma2D): `dL/dSigma2D = -Q G Q` with `Q` the conic and `G` the
//!   symmetric matrix gradient of the conic (`b` appears twice in `sigma`'s quadratic form
//!   `0.5 d^T Q d`, so its matrix entries get half of `dL/db` each).
//! - `Sigma2D = J V J^T + LOW_PASS I`: `dL/dV = J^T G2 J`, `dL/dJ = 2 G2 J V`.
//! - `V = R Sigma R^T`: `dL/dSigma = R^T (dL/dV) R`; an off-diagonal `cov6` entry appears
//!   twice in `Sigma`, so its gradient is twice the matrix entry.
//! - `J = [[fx/z, 0, -fx tx/z^2], [0, fy/z, -fy ty/z^2]]` with `tx = z clamp(x/z, ...)`:
//!   where the clamp is active `tx = z lim` (no `x` dependence, `dtx/dz = lim`), otherwise
//!   `tx = x`. `u = fx x/z + cx`, `v = fy y/z + cy`. `dL/dmean = R^T dL/dp_camera`.
//!
//! Culled Gaussians (zero tile count in `projected`) get zero gradients everywhere. The
//! colour and opacity gradients are copied from the accumulated screen-space gradient.
//!
//! # Shapes
//! - `means`: `[N, 3]`, `cov6`: `[N, 6]`, `cam`: `[CAMERA_LEN]`.
//! - `projected`: `[N, PROJECTED_STRIDE]` (forward), `grad2d`: `[N, GRAD2D_STRIDE]`.
//! - `grad_means`: `[N, 3]`, `grad_cov6`: `[N, 6]`, `grad_colors`: `[N, 3]`,
//!   `grad_opacities`: `[N]`.

use cubecl::prelude::*;

use crate::splat::camera::{CAM_FX, CAM_FY, CAM_R};
use crate::splat::constants::{GRAD2D_STRIDE, PROJECTED_STRIDE};
use crate::splat::math::project_gaussian;

/// See the module documentation.
#[allow(clippy::too_many_arguments)]
#[cube(launch_unchecked)]
pub fn project_backward(
    means: &[f32],
    cov6: &[f32],
    cam: &[f32],
    projected: &[f32],
    grad2d: &[f32],
    grad_means: &mut [f32],
    grad_cov6: &mut [f32],
    grad_colors: &mut [f32],
    grad_opacities: &mut [f32],
    num_gaussians: u32,
) {
    let gaussian = ABSOLUTE_POS as u32;
    if gaussian >= num_gaussians {
        terminate!();
    }
    let g = gaussian as usize;
    let listed = projected[g * PROJECTED_STRIDE as usize + 7] > 0.0f32;
    let p = project_gaussian(cam, means, cov6, g);

    if !(listed && p.valid) {
        for k in 0..3usize {
            grad_means[g * 3 + k] = 0.0f32;
            grad_colors[g * 3 + k] = 0.0f32;
        }
        for k in 0..6usize {
            grad_cov6[g * 6 + k] = 0.0f32;
        }
        grad_opacities[g] = 0.0f32;
        terminate!();
    }

    let row = g * GRAD2D_STRIDE as usize;
    let d_u = grad2d[row];
    let d_v = grad2d[row + 1];
    let d_qa = grad2d[row + 2];
    let d_qb = grad2d[row + 3];
    let d_qc = grad2d[row + 4];
    grad_colors[g * 3] = grad2d[row + 5];
    grad_colors[g * 3 + 1] = grad2d[row + 6];
    grad_colors[g * 3 + 2] = grad2d[row + 7];
    grad_opacities[g] = grad2d[row + 8];

    // Conic -> Sigma2D: G2 = -Q G Q, G = [[d_qa, d_qb / 2], [d_qb / 2, d_qc]].
    let qa = p.conic_a;
    let qb = p.conic_b;
    let qc = p.conic_c;
    let half_b = 0.5f32 * d_qb;
    let qg00 = qa * d_qa + qb * half_b;
    let qg01 = qa * half_b + qb * d_qc;
    let qg10 = qb * d_qa + qc * half_b;
    let qg11 = qb * half_b + qc * d_qc;
    let g00 = -(qg00 * qa + qg01 * qb);
    let g01 = -(qg00 * qb + qg01 * qc);
    let g11 = -(qg10 * qb + qg11 * qc);

    // Sigma2D = J V J^T: dL/dJ = 2 G2 M with M = J V; dL/dV = J^T G2 J.
    let j00 = p.j00;
    let j02 = p.j02;
    let j11 = p.j11;
    let j12 = p.j12;
    let m00 = j00 * p.v00 + j02 * p.v02;
    let m01 = j00 * p.v01 + j02 * p.v12;
    let m02 = j00 * p.v02 + j02 * p.v22;
    let m10 = j11 * p.v01 + j12 * p.v02;
    let m11 = j11 * p.v11 + j12 * p.v12;
    let m12 = j11 * p.v12 + j12 * p.v22;
    let dj00 = 2.0f32 * (g00 * m00 + g01 * m10);
    let dj02 = 2.0f32 * (g00 * m02 + g01 * m12);
    let dj11 = 2.0f32 * (g01 * m01 + g11 * m11);
    let dj12 = 2.0f32 * (g01 * m02 + g11 * m12);

    let p00 = g00 * j00;
    let p01 = g01 * j11;
    let p02 = g00 * j02 + g01 * j12;
    let p11 = g11 * j11;
    let p12 = g01 * j02 + g11 * j12;
    let gv00 = j00 * p00;
    let gv01 = j00 * p01;
    let gv02 = j00 * p02;
    let gv11 = j11 * p11;
    let gv12 = j11 * p12;
    let gv22 = j02 * p02 + j12 * p12;

    // V = R S R^T: dL/dS = R^T GV R, via B = GV R.
    let r00 = cam[CAM_R];
    let r01 = cam[CAM_R + 1];
    let r02 = cam[CAM_R + 2];
    let r10 = cam[CAM_R + 3];
    let r11 = cam[CAM_R + 4];
    let r12 = cam[CAM_R + 5];
    let r20 = cam[CAM_R + 6];
    let r21 = cam[CAM_R + 7];
    let r22 = cam[CAM_R + 8];
    let b00 = gv00 * r00 + gv01 * r10 + gv02 * r20;
    let b01 = gv00 * r01 + gv01 * r11 + gv02 * r21;
    let b02 = gv00 * r02 + gv01 * r12 + gv02 * r22;
    let b10 = gv01 * r00 + gv11 * r10 + gv12 * r20;
    let b11 = gv01 * r01 + gv11 * r11 + gv12 * r21;
    let b12 = gv01 * r02 + gv11 * r12 + gv12 * r22;
    let b20 = gv02 * r00 + gv12 * r10 + gv22 * r20;
    let b21 = gv02 * r01 + gv12 * r11 + gv22 * r21;
    let b22 = gv02 * r02 + gv12 * r12 + gv22 * r22;
    let gs00 = r00 * b00 + r10 * b10 + r20 * b20;
    let gs01 = r00 * b01 + r10 * b11 + r20 * b21;
    let gs02 = r00 * b02 + r10 * b12 + r20 * b22;
    let gs11 = r01 * b01 + r11 * b11 + r21 * b21;
    let gs12 = r01 * b02 + r11 * b12 + r21 * b22;
    let gs22 = r02 * b02 + r12 * b12 + r22 * b22;
    grad_cov6[g * 6] = gs00;
    grad_cov6[g * 6 + 1] = 2.0f32 * gs01;
    grad_cov6[g * 6 + 2] = 2.0f32 * gs02;
    grad_cov6[g * 6 + 3] = gs11;
    grad_cov6[g * 6 + 4] = 2.0f32 * gs12;
    grad_cov6[g * 6 + 5] = gs22;

    // Camera-space mean: through (u, v) and through J.
    let fx = cam[CAM_FX];
    let fy = cam[CAM_FY];
    let rz = 1.0f32 / p.z;
    let rz2 = rz * rz;
    let rz3 = rz2 * rz;
    let x_gate = select(p.x_free, 1.0f32, 0.0f32);
    let y_gate = select(p.y_free, 1.0f32, 0.0f32);
    let dtx_dz = select(p.x_free, 0.0f32, p.tx * rz);
    let dty_dz = select(p.y_free, 0.0f32, p.ty * rz);
    let d_x = d_u * fx * rz - dj02 * fx * rz2 * x_gate;
    let d_y = d_v * fy * rz - dj12 * fy * rz2 * y_gate;
    let d_z = -(d_u * fx * p.x + d_v * fy * p.y) * rz2 - dj00 * fx * rz2 - dj11 * fy * rz2
        + dj02 * (2.0f32 * fx * p.tx * rz3 - fx * rz2 * dtx_dz)
        + dj12 * (2.0f32 * fy * p.ty * rz3 - fy * rz2 * dty_dz);

    grad_means[g * 3] = r00 * d_x + r10 * d_y + r20 * d_z;
    grad_means[g * 3 + 1] = r01 * d_x + r11 * d_y + r21 * d_z;
    grad_means[g * 3 + 2] = r02 * d_x + r12 * d_y + r22 * d_z;
}
