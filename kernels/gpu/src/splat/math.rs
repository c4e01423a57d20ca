//! Device helpers shared by the splat kernels: NaN-safe tests and the per-Gaussian EWA
//! projection, written once so the forward and backward kernels evaluate bit-identical
//! expressions.
//!
//! Conventions (see `tests/fixtures/splat/README.md`): a world mean `m` maps to camera space
//! as `p = R m + t`; `u = fx x / z + cx`; the Jacobian of the projection is evaluated at the
//! tangents clamped to the widened field of view; `Sigma2D = J R Sigma R^T J^T + LOW_PASS I`;
//! the conic is `inverse(Sigma2D) = [[a, b], [b, c]]`.

use cubecl::prelude::*;

use super::camera::{
    CAM_CX, CAM_CY, CAM_FX, CAM_FY, CAM_LIM_X_NEG, CAM_LIM_X_POS, CAM_LIM_Y_NEG, CAM_LIM_Y_POS,
    CAM_R, CAM_T,
};
use super::constants::{ALPHA_MAX, LOW_PASS, MIN_DET, NEAR_PLANE};

/// Bits of the f32 exponent field: all ones means infinity or NaN.
pub const F32_EXPONENT_MASK: u32 = 0x7f80_0000;

/// True when `x` is neither NaN nor infinite. Bitwise, so no compiler fast-math assumption
/// can fold it away.
#[cube]
pub fn is_finite(x: f32) -> bool {
    let bits = u32::reinterpret(x);
    (bits & F32_EXPONENT_MASK) != F32_EXPONENT_MASK
}

/// Everything the projection of one Gaussian computes, kept for the backward pass.
#[derive(CubeType, Clone, Copy)]
#[expand(derive(Clone, Copy))]
pub struct Projection {
    /// False when the Gaussian is culled: a non-finite input, depth at or before the near
    /// plane, or a 2D covariance that is not positive definite (`det > 0` and `a > 0`) or
    /// not finite.
    pub valid: bool,
    /// Camera-space mean.
    pub x: f32,
    /// Camera-space mean.
    pub y: f32,
    /// Camera-space depth.
    pub z: f32,
    /// Camera-space covariance `V = R Sigma R^T`, upper triangle.
    pub v00: f32,
    /// See `v00`.
    pub v01: f32,
    /// See `v00`.
    pub v02: f32,
    /// See `v00`.
    pub v11: f32,
    /// See `v00`.
    pub v12: f32,
    /// See `v00`.
    pub v22: f32,
    /// `z * clamp(x / z, -lim_neg, lim_pos)`.
    pub tx: f32,
    /// `z * clamp(y / z, -lim_neg, lim_pos)`.
    pub ty: f32,
    /// True when `x / z` lies within its clamp range (the clamp passes the gradient).
    pub x_free: bool,
    /// True when `y / z` lies within its clamp range.
    pub y_free: bool,
    /// Jacobian entry `fx / z`.
    pub j00: f32,
    /// Jacobian entry `-fx tx / z^2`.
    pub j02: f32,
    /// Jacobian entry `fy / z`.
    pub j11: f32,
    /// Jacobian entry `-fy ty / z^2`.
    pub j12: f32,
    /// `Sigma2D[0][0]`, low-pass included.
    pub cov_a: f32,
    /// `Sigma2D[0][1]`.
    pub cov_b: f32,
    /// `Sigma2D[1][1]`, low-pass included.
    pub cov_c: f32,
    /// `det(Sigma2D)`.
    pub det: f32,
    /// Conic `a` (inverse covariance `[0][0]`).
    pub conic_a: f32,
    /// Conic `b` (inverse covariance `[0][1]`).
    pub conic_b: f32,
    /// Conic `c` (inverse covariance `[1][1]`).
    pub conic_c: f32,
    /// Projected mean, pixels.
    pub u: f32,
    /// Projected mean, pixels.
    pub v: f32,
}

/// Projects Gaussian `g` (rows of `means` `[N, 3]` and `cov6` `[N, 6]`) with the camera
/// buffer `cam` (see [`crate::splat::camera`]). The opacity test is the caller's.
#[cube]
pub fn project_gaussian(cam: &[f32], means: &[f32], cov6: &[f32], g: usize) -> Projection {
    let mx = means[g * 3];
    let my = means[g * 3 + 1];
    let mz = means[g * 3 + 2];
    let s00 = cov6[g * 6];
    let s01 = cov6[g * 6 + 1];
    let s02 = cov6[g * 6 + 2];
    let s11 = cov6[g * 6 + 3];
    let s12 = cov6[g * 6 + 4];
    let s22 = cov6[g * 6 + 5];
    let inputs_finite = is_finite(mx)
        && is_finite(my)
        && is_finite(mz)
        && is_finite(s00)
        && is_finite(s01)
        && is_finite(s02)
        && is_finite(s11)
        && is_finite(s12)
        && is_finite(s22);

    let r00 = cam[CAM_R];
    let r01 = cam[CAM_R + 1];
    let r02 = cam[CAM_R + 2];
    let r10 = cam[CAM_R + 3];
    let r11 = cam[CAM_R + 4];
    let r12 = cam[CAM_R + 5];
    let r20 = cam[CAM_R + 6];
    let r21 = cam[CAM_R + 7];
    let r22 = cam[CAM_R + 8];
    let fx = cam[CAM_FX];
    let fy = cam[CAM_FY];

    let x = r00 * mx + r01 * my + r02 * mz + cam[CAM_T];
    let y = r10 * mx + r11 * my + r12 * mz + cam[CAM_T + 1];
    let z = r20 * mx + r21 * my + r22 * mz + cam[CAM_T + 2];

    // V = R S R^T: with w_i = S r_i (S symmetric), V_il = w_i . r_l.
    let w00 = s00 * r00 + s01 * r01 + s02 * r02;
    let w01 = s01 * r00 + s11 * r01 + s12 * r02;
    let w02 = s02 * r00 + s12 * r01 + s22 * r02;
    let w10 = s00 * r10 + s01 * r11 + s02 * r12;
    let w11 = s01 * r10 + s11 * r11 + s12 * r12;
    let w12 = s02 * r10 + s12 * r11 + s22 * r12;
    let w20 = s00 * r20 + s01 * r21 + s02 * r22;
    let w21 = s01 * r20 + s11 * r21 + s12 * r22;
    let w22 = s02 * r20 + s12 * r21 + s22 * r22;
    let v00 = w00 * r00 + w01 * r01 + w02 * r02;
    let v01 = w00 * r10 + w01 * r11 + w02 * r12;
    let v02 = w00 * r20 + w01 * r21 + w02 * r22;
    let v11 = w10 * r10 + w11 * r11 + w12 * r12;
    let v12 = w10 * r20 + w11 * r21 + w12 * r22;
    let v22 = w20 * r20 + w21 * r21 + w22 * r22;

    // A safe depth for the arithmetic below; culled Gaussians never use the results.
    let in_front = z > NEAR_PLANE;
    let zs = select(in_front, z, 1.0f32);
    let rz = 1.0f32 / zs;
    let rz2 = rz * rz;

    let lim_x_pos = cam[CAM_LIM_X_POS];
    let lim_x_neg = cam[CAM_LIM_X_NEG];
    let lim_y_pos = cam[CAM_LIM_Y_POS];
    let lim_y_neg = cam[CAM_LIM_Y_NEG];
    let tan_x = x * rz;
    let tan_y = y * rz;
    let x_free = tan_x >= -lim_x_neg && tan_x <= lim_x_pos;
    let y_free = tan_y >= -lim_y_neg && tan_y <= lim_y_pos;
    let tx = zs * clamp(tan_x, -lim_x_neg, lim_x_pos);
    let ty = zs * clamp(tan_y, -lim_y_neg, lim_y_pos);

    let j00 = fx * rz;
    let j02 = -fx * tx * rz2;
    let j11 = fy * rz;
    let j12 = -fy * ty * rz2;

    // M = J V (2x3), Sigma2D = M J^T.
    let m00 = j00 * v00 + j02 * v02;
    let m02 = j00 * v02 + j02 * v22;
    let m11 = j11 * v11 + j12 * v12;
    let m12 = j11 * v12 + j12 * v22;
    let m01 = j00 * v01 + j02 * v12;
    let cov_a = m00 * j00 + m02 * j02 + LOW_PASS;
    let cov_b = m01 * j11 + m02 * j12;
    let cov_c = m11 * j11 + m12 * j12 + LOW_PASS;
    let det = cov_a * cov_c - cov_b * cov_b;
    let det_ok = det > MIN_DET && is_finite(det);
    let inv_det = 1.0f32 / select(det_ok, det, 1.0f32);
    let conic_a = cov_c * inv_det;
    let conic_b = -cov_b * inv_det;
    let conic_c = cov_a * inv_det;

    let u = fx * x * rz + cam[CAM_CX];
    let v = fy * y * rz + cam[CAM_CY];

    let valid = inputs_finite
        && in_front
        && det_ok
        && cov_a > 0.0f32
        && is_finite(cov_a)
        && is_finite(cov_c)
        && is_finite(conic_a)
        && is_finite(conic_b)
        && is_finite(conic_c)
        && is_finite(u)
        && is_finite(v);

    Projection {
        valid,
        x,
        y,
        z,
        v00,
        v01,
        v02,
        v11,
        v12,
        v22,
        tx,
        ty,
        x_free,
        y_free,
        j00,
        j02,
        j11,
        j12,
        cov_a,
        cov_b,
        cov_c,
        det,
        conic_a,
        conic_b,
        conic_c,
        u,
        v,
    }
}

/// The Gaussian exponent `sigma = 0.5 (a dx^2 + c dy^2) + b dx dy` at offset
/// `(dx, dy) = mean - pixel centre`.
#[cube]
pub fn gaussian_sigma(conic_a: f32, conic_b: f32, conic_c: f32, dx: f32, dy: f32) -> f32 {
    0.5f32 * (conic_a * dx * dx + conic_c * dy * dy) + conic_b * dx * dy
}

/// Unclamped alpha `opacity * exp(-sigma)` and its visibility factor `exp(-sigma)`.
#[cube]
pub fn raw_alpha(opacity: f32, sigma: f32) -> (f32, f32) {
    let vis = (-sigma).exp();
    (opacity * vis, vis)
}

/// Alpha as composited: the raw alpha clamped at [`ALPHA_MAX`].
#[cube]
pub fn clamp_alpha(alpha_raw: f32) -> f32 {
    min(alpha_raw, ALPHA_MAX)
}
