//! GaussianAvatars' schedule scaled to a run ([`GaSchedule`]: SH degree, densification,
//! opacity resets) and its optimiser and learning rates (`training_setup`).

use burn::lr_scheduler::module_lr_scheduler::ModuleLrScheduler;
use burn::lr_scheduler::{LrScheduler, LrSchedulerRecord};
use burn::module::ParamGroup;
use burn::optim::{AdamConfig, ModuleOptimizer};

use crate::train::gaussianavatars::constants::{self as ga, scaled};
use crate::train::refine;

/// GaussianAvatars' references iteration of the SH degree increments (`train.py`:
/// `if iteration % 1000 == 0: gaussians.oneupSHdegree()`).
pub const SH_INTERVAL: usize = 1_000;

/// GaussianAvatars' schedule for a run of `total` iterations; iterations are 1-based here,
/// as in `train.py`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GaSchedule {
    pub total: usize,
    pub sh_interval: usize,
    pub densify_from: usize,
    pub densify_interval: usize,
    pub densify_until: usize,
    pub opacity_reset: usize,
}

impl GaSchedule {
    /// GaussianAvatars' intervals scaled to `total` iterations.
    pub fn new(total: usize) -> Self {
        Self {
            total,
            sh_interval: scaled(SH_INTERVAL, total),
            densify_from: scaled(ga::DENSIFY_FROM_ITER, total),
            densify_interval: scaled(ga::DENSIFICATION_INTERVAL, total),
            densify_until: scaled(ga::DENSIFY_UNTIL_ITER, total),
            opacity_reset: scaled(ga::OPACITY_RESET_INTERVAL, total),
        }
    }

    /// The active SH degree at iteration `i` (`oneupSHdegree` every `sh_interval`).
    pub fn degree(&self, i: usize, max: usize) -> usize {
        (i / self.sh_interval).min(max)
    }

    /// Whether iteration `i` accumulates densification statistics.
    pub fn tracks(&self, i: usize) -> bool {
        i < self.densify_until
    }

    /// `Some(size_threshold)` when iteration `i` densifies.
    pub fn densifies(&self, i: usize) -> Option<Option<f32>> {
        (self.tracks(i) && i > self.densify_from && i.is_multiple_of(self.densify_interval))
            .then(|| (i > self.opacity_reset).then_some(ga::PRUNE_SCREEN_SIZE))
    }

    /// Whether iteration `i` resets the opacities (`white`: the background is white).
    pub fn resets(&self, i: usize, white: bool) -> bool {
        self.tracks(i)
            && (i.is_multiple_of(self.opacity_reset) || (white && i == self.densify_from))
    }
}

/// The position's learning rate (`get_expon_lr_func` with `spatial_lr_scale`), a burn
/// scheduler: step `i` (1-based, one per iteration) returns `expon_lr(i)`.
#[derive(Clone, Debug)]
pub struct PositionLr {
    /// `position_lr_init x spatial_lr_scale`.
    pub init: f64,
    /// `position_lr_final x spatial_lr_scale`.
    pub last: f64,
    /// `position_lr_max_steps` (the run's length).
    pub max_steps: usize,
    /// Steps taken.
    pub step: usize,
}

impl LrScheduler for PositionLr {
    fn step(&mut self) -> f64 {
        self.step += 1;
        ga::expon_lr(self.init, self.last, self.step, self.max_steps)
    }

    fn to_record(&self) -> LrSchedulerRecord {
        LrSchedulerRecord::new().with_scalar("step", self.step as u64)
    }

    fn load_record(&mut self, record: LrSchedulerRecord) {
        if let Some(s) = record.scalar::<u64>("step") {
            self.step = s as usize;
        }
    }
}

/// The learning rates of [`GaTraining`](super::GaTraining)'s parameters (`training_setup`).
pub fn lr_scheduler(total: usize, extent: f32) -> ModuleLrScheduler {
    let group =
        |name: &str| ParamGroup::from_regex(format!(r"(^|\.){name}$")).expect("a valid pattern");
    let ext = extent as f64;
    ModuleLrScheduler::new(0.0)
        .with_group(
            group("xyz"),
            PositionLr {
                init: ga::POSITION_LR_INIT * ext,
                last: ga::POSITION_LR_FINAL * ext,
                max_steps: scaled(ga::DENSIFY_UNTIL_ITER, total),
                step: 0,
            },
        )
        .with_group(group("features_dc"), ga::FEATURE_LR)
        .with_group(
            group("features_rest"),
            ga::FEATURE_LR / ga::FEATURE_REST_LR_DIVISOR,
        )
        .with_group(group("opacity"), ga::OPACITY_LR)
        .with_group(group("scaling"), ga::SCALING_LR)
        .with_group(group("rotation"), ga::ROTATION_LR)
        .with_group(group(refine::REFINE_EXPR), ga::FLAME_EXPR_LR)
        .with_group(group(refine::REFINE_POSE), ga::FLAME_POSE_LR)
        .with_group(group(refine::REFINE_TRANSLATION), ga::FLAME_TRANS_LR)
}

/// Adam as GaussianAvatars sets it up (betas 0.9, 0.999; eps 1e-15).
pub fn optimizer() -> ModuleOptimizer {
    AdamConfig::new().with_epsilon(ga::ADAM_EPS).init()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// GaussianAvatars' schedule at its own length, and scaled.
    #[test]
    fn schedule_follows_train_py() {
        let s = GaSchedule::new(ga::REFERENCE_ITERATIONS);
        assert_eq!(s.degree(999, 3), 0);
        assert_eq!(s.degree(1000, 3), 1);
        assert_eq!(s.degree(5000, 3), 3);
        assert_eq!(s.densifies(10_000), None);
        assert_eq!(s.densifies(12_000), Some(None));
        assert_eq!(s.densifies(12_001), None);
        assert_eq!(s.densifies(62_000), Some(Some(20.0)));
        assert!(s.resets(60_000, false));
        assert!(!s.resets(10_000, false));
        assert!(s.resets(10_000, true));
        let s = GaSchedule::new(6_000);
        assert_eq!(
            (
                s.sh_interval,
                s.densify_from,
                s.densify_interval,
                s.opacity_reset
            ),
            (10, 100, 20, 600)
        );
    }

    #[test]
    fn position_lr_steps_like_get_expon_lr_func() {
        let mut lr = PositionLr {
            init: 0.005,
            last: 0.000_05,
            max_steps: 100,
            step: 0,
        };
        let first = lr.step();
        assert!((first - ga::expon_lr(0.005, 0.000_05, 1, 100)).abs() < 1e-15);
        for _ in 1..50 {
            lr.step();
        }
        assert!((lr.step() - ga::expon_lr(0.005, 0.000_05, 51, 100)).abs() < 1e-15);
        let rec = lr.to_record();
        let mut other = PositionLr {
            step: 0,
            ..lr.clone()
        };
        other.load_record(rec);
        assert_eq!(other.step, 51);
    }
}
