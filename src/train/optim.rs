//! The optimiser (Adam, [`texavatars_cpu::adam`]) and the learning rates of a TexAvatars run.

use burn::lr_scheduler::module_lr_scheduler::{ModuleLrScheduler, ModuleLrSchedulerConfig};
use burn::module::ParamGroup;
use burn::optim::ModuleOptimizer;

use super::config::TrainConfig;
use super::constants::ENCODER_MODULES;
use super::refine;
use texavatars_cpu::adam;

/// The learning rates: `lr_decoders` for every parameter, `lr_encoders` for those under
/// [`ENCODER_MODULES`], and FLAME refinement's three ([`refine`]).
pub fn lr_scheduler(config: &TrainConfig) -> ModuleLrScheduler {
    ModuleLrSchedulerConfig::new(config.lr_decoders.into())
        .with_group(
            ParamGroup::from_any_predicates(ENCODER_MODULES.to_vec()),
            config.lr_encoders,
        )
        .with_group(
            ParamGroup::from_predicate(refine::REFINE_EXPR),
            config.lr_flame_expr,
        )
        .with_group(
            ParamGroup::from_predicate(refine::REFINE_POSE),
            config.lr_flame_pose,
        )
        .with_group(
            ParamGroup::from_predicate(refine::REFINE_TRANSLATION),
            config.lr_flame_translation,
        )
        .init()
        .expect("constant learning rates are valid")
}

/// Adam with the config's betas and epsilon.
pub fn optimizer(config: &TrainConfig) -> ModuleOptimizer {
    adam::FusedAdam {
        beta_1: config.adam_beta1 as f32,
        beta_2: config.adam_beta2 as f32,
        epsilon: config.adam_eps as f32,
    }
    .init()
}
