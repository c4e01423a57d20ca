//! GaussianAvatars' training settings, each with where it comes from. Files are in
//! GaussianAvatars' repository (`ShenhanQian/GaussianAvatars`).
//!
//! Its schedule is for 600,000 iterations (`arguments/__init__.py`, `OptimizationParams`);
//! the original 3DGS values are in its comments. Interval settings are counted in
//! iterations of that schedule ([`REFERENCE_ITERATIONS`]).

/// `OptimizationParams.iterations`.
pub const REFERENCE_ITERATIONS: usize = 600_000;

/// `position_lr_init`, `position_lr_final`, `position_lr_delay_mult`
/// (`position_lr_max_steps` is the run's length): the exponential decay of the local
/// positions' learning rate (`utils/general_utils.py`, `get_expon_lr_func`).
pub const POSITION_LR_INIT: f64 = 0.005;
pub const POSITION_LR_FINAL: f64 = 0.000_05;
pub const POSITION_LR_DELAY_MULT: f64 = 0.01;
/// `feature_lr` for the DC term; the higher SH bands train at a twentieth of it
/// (`scene/gaussian_model.py`, `training_setup`: `feature_lr / 20.0` for `f_rest`).
pub const FEATURE_LR: f64 = 0.0025;
pub const FEATURE_REST_LR_DIVISOR: f64 = 20.0;
/// `opacity_lr`, `scaling_lr`, `rotation_lr`.
pub const OPACITY_LR: f64 = 0.05;
pub const SCALING_LR: f64 = 0.017;
pub const ROTATION_LR: f64 = 0.001;
/// FLAME refinement's learning rates (`arguments/__init__.py`, `flame_expr_lr`,
/// `flame_pose_lr` for the four rotations, `flame_trans_lr`), one parameter group each in
/// `FlameGaussianModel.training_setup`; on unless `--not_finetune_flame_params`.
pub const FLAME_EXPR_LR: f64 = 1e-3;
pub const FLAME_POSE_LR: f64 = 1e-5;
pub const FLAME_TRANS_LR: f64 = 1e-6;
/// Adam's epsilon (`training_setup`: `torch.optim.Adam(l, lr=0.0, eps=1e-15)`).
pub const ADAM_EPS: f32 = 1e-15;

/// `lambda_dssim`: the image loss is `(1 - 0.2) L1 + 0.2 (1 - SSIM)` (`train.py`).
pub const LAMBDA_DSSIM: f32 = 0.2;
/// `lambda_xyz`, `threshold_xyz` (`metric_xyz = False`): `relu(|mu_l| - 1)`, the local
/// position in units of the triangle's scale `k` (`train.py`, `losses['xyz']`).
pub const LAMBDA_XYZ: f32 = 0.01;
pub const THRESHOLD_XYZ: f32 = 1.0;
/// `lambda_scale`, `threshold_scale` (`metric_scale = False`): `|relu(exp(s_l) - 0.6)|`
/// (`train.py`, `losses['scale']`).
pub const LAMBDA_SCALE: f32 = 1.0;
pub const THRESHOLD_SCALE: f32 = 0.6;

/// `densification_interval`, `opacity_reset_interval`, `densify_from_iter`,
/// `densify_until_iter` (reference iterations).
pub const DENSIFICATION_INTERVAL: usize = 2_000;
pub const OPACITY_RESET_INTERVAL: usize = 60_000;
pub const DENSIFY_FROM_ITER: usize = 10_000;
pub const DENSIFY_UNTIL_ITER: usize = 600_000;
/// `densify_grad_threshold`: the mean view-space positional gradient above which a
/// Gaussian is cloned or split.
pub const DENSIFY_GRAD_THRESHOLD: f32 = 0.0002;
/// `percent_dense`: clone below, split above this fraction of the scene extent.
pub const PERCENT_DENSE: f32 = 0.01;
/// `densify_and_prune(..., 0.005, ...)` in `train.py`: prune below this opacity.
pub const PRUNE_MIN_OPACITY: f32 = 0.005;
/// `size_threshold = 20` (pixels of screen radius) after the first opacity reset.
pub const PRUNE_SCREEN_SIZE: f32 = 20.0;

/// `lr_init * ... ` of `get_expon_lr_func` at `step` of `max_steps`, with its delay (here
/// `lr_delay_steps = 0`, as GaussianAvatars calls it, so the delay factor is 1 and
/// `lr_delay_mult` has no effect): `exp(ln(init) (1 - t) + ln(final) t)`, `t = step /
/// max_steps` clamped to [0, 1].
pub fn expon_lr(init: f64, last: f64, step: usize, max_steps: usize) -> f64 {
    let t = (step as f64 / max_steps.max(1) as f64).clamp(0.0, 1.0);
    (init.ln() * (1.0 - t) + last.ln() * t).exp()
}

/// An interval of GaussianAvatars' 600,000-iteration schedule scaled to a run of
/// `iterations`: `max(1, round(interval * iterations / 600,000))`. The rule keeps every event
/// at the same fraction of training (densification starts at 1/60 of the run, the opacity
/// resets every tenth).
pub fn scaled(interval: usize, iterations: usize) -> usize {
    ((interval as f64 * iterations as f64 / REFERENCE_ITERATIONS as f64).round() as usize).max(1)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `get_expon_lr_func(lr_init=0.005, lr_final=0.00005, lr_delay_mult=0.01,
    /// max_steps=600000)` (no `lr_delay_steps`): 0.005 at 0, 0.0005 half way (the geometric
    /// mean), 0.00005 at and after the end.
    #[test]
    fn position_lr_follows_get_expon_lr_func() {
        let lr = |s| expon_lr(POSITION_LR_INIT, POSITION_LR_FINAL, s, REFERENCE_ITERATIONS);
        assert!((lr(0) - 0.005).abs() < 1e-12);
        assert!((lr(300_000) - 0.0005).abs() < 1e-10);
        assert!((lr(600_000) - 0.000_05).abs() < 1e-12);
        assert!((lr(900_000) - 0.000_05).abs() < 1e-12);
    }

    #[test]
    fn intervals_scale_with_the_run() {
        assert_eq!(scaled(DENSIFICATION_INTERVAL, REFERENCE_ITERATIONS), 2_000);
        assert_eq!(scaled(DENSIFY_FROM_ITER, 6_000), 100);
        assert_eq!(scaled(OPACITY_RESET_INTERVAL, 6_000), 600);
        assert_eq!(scaled(DENSIFICATION_INTERVAL, 100), 1);
    }
}
