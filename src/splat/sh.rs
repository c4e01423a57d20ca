//! Real spherical harmonics (degrees 0-3) as in 3DGS, evaluated with burn tensor ops so that
//! colours stay differentiable w.r.t. the coefficients and the Gaussian positions.

use burn::tensor::{Tensor, TensorData};

/// Band 0.
pub const C0: f32 = 0.282_094_8;
/// Band 1.
pub const C1: f32 = 0.488_602_52;
/// Band 2.
pub const C2: [f32; 5] = [
    1.092_548_4,
    -1.092_548_4,
    0.315_391_57,
    -1.092_548_4,
    0.546_274_2,
];
/// Band 3.
pub const C3: [f32; 7] = [
    -0.590_043_6,
    2.890_611_4,
    -0.457_045_8,
    0.373_176_34,
    -0.457_045_8,
    1.445_305_7,
    -0.590_043_6,
];

/// Evaluates SH of `degree` for view directions from `camera_position` to each mean, then
/// applies the 3DGS offset: `rgb = max(sh(dir) + 0.5, 0)`.
///
/// # Shapes
/// - `coeffs`: [N, K, 3] with K = (degree + 1)^2
/// - `means`: [N, 3]
/// - returns [N, 3]
pub fn colors(
    coeffs: Tensor<3>,
    degree: usize,
    means: Tensor<2>,
    camera_position: [f32; 3],
) -> Tensor<2> {
    let device = means.device();
    let [n, k, _] = coeffs.dims();
    assert_eq!(
        k,
        (degree + 1) * (degree + 1),
        "coeffs must be [N, (degree+1)^2, 3]"
    );
    let cam = Tensor::<2>::from_data(TensorData::new(camera_position.to_vec(), [1, 3]), &device);
    let d = means - cam;
    let norm = (d.clone() * d.clone()).sum_dim(1).sqrt().clamp_min(1e-12);
    let d = d / norm;
    let basis = basis(d, degree);
    // [N, K, 1] * [N, K, 3] summed over K.
    let rgb = (basis.unsqueeze_dim::<3>(2) * coeffs)
        .sum_dim(1)
        .reshape([n, 3]);
    (rgb + 0.5).clamp_min(0.0)
}

/// The SH basis values [N, K] for unit directions [N, 3].
pub fn basis(d: Tensor<2>, degree: usize) -> Tensor<2> {
    let n = d.dims()[0];
    let c = |i: usize| d.clone().narrow(1, i, 1);
    let (x, y, z) = (c(0), c(1), c(2));
    let mut cols: Vec<Tensor<2>> = vec![x.ones_like() * C0];
    if degree > 0 {
        cols.push(-y.clone() * C1);
        cols.push(z.clone() * C1);
        cols.push(-x.clone() * C1);
    }
    if degree > 1 {
        let (xx, yy, zz) = (
            x.clone() * x.clone(),
            y.clone() * y.clone(),
            z.clone() * z.clone(),
        );
        let (xy, yz, xz) = (
            x.clone() * y.clone(),
            y.clone() * z.clone(),
            x.clone() * z.clone(),
        );
        cols.push(xy.clone() * C2[0]);
        cols.push(yz * C2[1]);
        cols.push((zz.clone() * 2.0 - xx.clone() - yy.clone()) * C2[2]);
        cols.push(xz * C2[3]);
        cols.push((xx.clone() - yy.clone()) * C2[4]);
        if degree > 2 {
            cols.push(y.clone() * (xx.clone() * 3.0 - yy.clone()) * C3[0]);
            cols.push(xy * z.clone() * C3[1]);
            cols.push(y.clone() * (zz.clone() * 4.0 - xx.clone() - yy.clone()) * C3[2]);
            cols.push(z.clone() * (zz.clone() * 2.0 - xx.clone() * 3.0 - yy.clone() * 3.0) * C3[3]);
            cols.push(x.clone() * (zz * 4.0 - xx.clone() - yy.clone()) * C3[4]);
            cols.push(z * (xx.clone() - yy.clone()) * C3[5]);
            cols.push(x * (xx - yy * 3.0) * C3[6]);
        }
    }
    let out = Tensor::cat(cols, 1);
    debug_assert_eq!(out.dims(), [n, (degree + 1) * (degree + 1)]);
    out
}
