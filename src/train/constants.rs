//! Constants of the training objective and the optimiser (method §6), each with its reason,
//! in one place. [`super::TrainConfig`] and [`super::LossWeights`] take their defaults from
//! here.

/// Weight of the L1 photometric term (3DGS / GaussianAvatars / TexAvatars: 0.8).
pub const L1_WEIGHT: f64 = 0.8;

/// Weight of the D-SSIM term `1 - SSIM` (0.2, the complement of [`L1_WEIGHT`]).
pub const DSSIM_WEIGHT: f64 = 0.2;

/// Weight of the VGG perceptual loss once it is on (method §6: 0.01).
pub const VGG_WEIGHT: f64 = 0.01;

/// Fraction of the iterations after which the VGG loss is switched on (the paper: 300k of
/// 600k; on from the start it destabilises training).
pub const VGG_START: f64 = 0.5;

/// Weight of the position regularizer L_pos (GaussianAvatars' `lambda_xyz`, kept by
/// TexAvatars: 0.01).
pub const POSITION_WEIGHT: f64 = 0.01;

/// L_pos penalises local offsets longer than this, in units of the face frame (1.0:
/// GaussianAvatars' `threshold_xyz`; beyond it a Gaussian drifts away from its triangle).
pub const POSITION_THRESHOLD: f64 = 1.0;

/// Weight of the scale regularizer L_scale (GaussianAvatars' `lambda_scale`: 1.0).
pub const SCALE_WEIGHT: f64 = 1.0;

/// L_scale penalises local scales `exp(s)` above this, in units of the face frame (0.6:
/// GaussianAvatars' `threshold_scale`; larger Gaussians blur across triangles).
pub const SCALE_THRESHOLD: f64 = 0.6;

/// The regularizers take Euclidean norms of vectors that are often exactly zero (an offset
/// of 0, or a scale excess `relu(exp(s) - 0.6)` of 0). `sqrt` has an infinite derivative
/// at 0, and `0 * inf` is NaN in the backward pass, so they use `sqrt(x . x + NORM_EPS^2)`:
/// the value moves by at most 1e-8 and the derivative at 0 is 0.
pub const NORM_EPS: f64 = 1e-8;

/// Learning rate of both decoders (method §6: 6e-4).
pub const LR_DECODERS: f64 = 6e-4;

/// Learning rate of Exp2Code and the view encoder (method §6: 4e-4).
pub const LR_ENCODERS: f64 = 4e-4;

/// Learning rate of the refined expression coefficients (GaussianAvatars' and the
/// TexAvatars reference's `flame_expr_lr`, `arguments/__init__.py`: 1e-3).
pub const LR_FLAME_EXPR: f64 = 1e-3;

/// Learning rate of the refined rotations, global, neck, jaw and eyes (`flame_pose_lr`:
/// 1e-5 rad per step).
pub const LR_FLAME_POSE: f64 = 1e-5;

/// Learning rate of the refined translation (`flame_trans_lr`: 1e-6, in the model's units,
/// metres for FLAME).
pub const LR_FLAME_TRANSLATION: f64 = 1e-6;

/// Adam's epsilon (method §6: 1e-15, as 3DGS; burn's default 1e-5 would damp the updates of
/// parameters whose gradients are small).
pub const ADAM_EPS: f64 = 1e-15;

/// Adam's first-moment decay (PyTorch's and the authors' default).
pub const ADAM_BETA1: f64 = 0.9;

/// Adam's second-moment decay (PyTorch's and the authors' default).
pub const ADAM_BETA2: f64 = 0.999;

/// Parameter paths (module field names) that train at [`LR_ENCODERS`]; every other
/// parameter (the geometry and appearance decoders) trains at [`LR_DECODERS`]. A path
/// matches when it contains the name (burn's `ParamGroup::from_any_predicates`); the names
/// are the fields of [`crate::models::texavatars::TexAvatarNet`].
pub const ENCODER_MODULES: [&str; 2] = ["exp2code", "view_encoder"];

/// Checkpoints kept on disk: the newest and the one before, so that a run killed while
/// writing a checkpoint resumes from the previous one.
pub const KEEP_CHECKPOINTS: usize = 2;
