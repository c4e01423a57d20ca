//! GaussianAvatars' regularisers on the stored Gaussians (`train.py`, `losses['xyz']` and
//! `losses['scale']` with `metric_xyz = metric_scale = False`), over the Gaussians visible
//! in the view (`visibility_filter`, radius above 0). The image terms are texavatars' L1 and
//! D-SSIM ([`crate::metrics`]) weighted by [`super::constants::LAMBDA_DSSIM`].

use burn::tensor::Tensor;
use burn::tensor::activation::relu;

use super::constants::{LAMBDA_SCALE, LAMBDA_XYZ, THRESHOLD_SCALE, THRESHOLD_XYZ};

/// Mean of `v` [N] over the rows where `visible` [N] is 1; 0 when none is (GaussianAvatars'
/// `x[visibility_filter].mean()` would be NaN there).
fn visible_mean(v: Tensor<1>, visible: Tensor<1>) -> Tensor<1> {
    let count = visible.clone().sum().clamp_min(1.0);
    (v * visible).sum() / count
}

/// `lambda_xyz * mean(relu(|mu_l| - threshold_xyz))`: local positions (in units of the
/// triangle's scale) kept within one unit of the centroid.
///
/// # Shapes
/// - `xyz`: [N, 3]; `visible`: `[N]` (0 or 1); returns `[1]`
pub fn position_loss(xyz: Tensor<2>, visible: Tensor<1>) -> Tensor<1> {
    let n = xyz.dims()[0];
    // The epsilon keeps the gradient finite at mu_l = 0 (GaussianAvatars' initialisation),
    // where torch's `norm` takes the subgradient 0.
    let norm = (xyz.powi_scalar(2).sum_dim(1) + 1e-30).sqrt().reshape([n]);
    visible_mean(relu(norm - THRESHOLD_XYZ), visible) * LAMBDA_XYZ
}

/// `lambda_scale * mean(|relu(exp(s_l) - threshold_scale)|)`: local scales (before the
/// triangle's `k`) kept below 0.6.
///
/// # Shapes
/// - `log_scales`: [N, 3]; `visible`: `[N]` (0 or 1); returns `[1]`
pub fn scale_loss(log_scales: Tensor<2>, visible: Tensor<1>) -> Tensor<1> {
    let n = log_scales.dims()[0];
    let over = relu(log_scales.exp() - THRESHOLD_SCALE);
    let norm = (over.powi_scalar(2).sum_dim(1) + 1e-30).sqrt().reshape([n]);
    visible_mean(norm, visible) * LAMBDA_SCALE
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::{Device, TensorData};

    fn t2(v: Vec<f32>, n: usize, device: &Device) -> Tensor<2> {
        Tensor::from_data(TensorData::new(v, [n, 3]), device)
    }
    fn value(t: Tensor<1>) -> f32 {
        t.into_data().iter::<f32>().next().unwrap_or(f32::NAN)
    }

    /// Hand values of GaussianAvatars' formulas.
    #[test]
    fn regularisers_match_hand_values() {
        let d = Device::flex();
        let vis = Tensor::<1>::from_data(TensorData::new(vec![1.0f32, 1.0, 1.0, 0.0], [4]), &d);
        // |mu| = 1, 5, 2 and an invisible 10: relu(|mu| - 1) = 0, 4, 1; mean 5/3.
        let xyz = t2(
            vec![0.6, 0.8, 0.0, 3.0, 4.0, 0.0, 0.0, 0.0, 2.0, 10.0, 0.0, 0.0],
            4,
            &d,
        );
        let got = value(position_loss(xyz, vis.clone()));
        assert!((got - 0.01 * 5.0 / 3.0).abs() < 1e-6, "{got}");
        // exp(s) = (0.5, 0.6, 1.6) -> relu(. - 0.6) = (0, 0, 1), norm 1; (0.9, 0.9, 0.9) ->
        // 0.3 each, norm 0.3 sqrt(3); (0.1, 0.1, 0.1) -> 0; invisible large. Mean over 3.
        let s = |v: f32| v.ln();
        let ls = t2(
            vec![
                s(0.5),
                s(0.6),
                s(1.6),
                s(0.9),
                s(0.9),
                s(0.9),
                s(0.1),
                s(0.1),
                s(0.1),
                3.0,
                3.0,
                3.0,
            ],
            4,
            &d,
        );
        let got = value(scale_loss(ls, vis));
        let want = (1.0 + 0.3 * 3f32.sqrt()) / 3.0;
        assert!((got - want).abs() < 1e-5, "{got} vs {want}");
        // Nothing visible: 0, not NaN.
        let none = Tensor::<1>::zeros([1], &d);
        assert_eq!(
            value(position_loss(t2(vec![5.0, 0.0, 0.0], 1, &d), none)),
            0.0
        );
    }
}
