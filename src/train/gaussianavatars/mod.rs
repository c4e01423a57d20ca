//! Training GaussianAvatars in texavatars: `texavatars train --model gaussianavatars`.
//!
//! GaussianAvatars' `train.py` through burn's `Learner`, with the run shell of
//! [`crate::train`] (data checks, one run per folder, checkpoints every interval, resume,
//! signals, progress, non-finite guard):
//!
//! - **model**: [`GaModel`](crate::models::gaussianavatars::GaModel) initialised as GaussianAvatars (one Gaussian
//!   per triangle), rendered by texavatars' rasterizer on the data's white background;
//! - **objective** (`train.py`): `0.8 L1 + 0.2 (1 - SSIM)` plus the position and scale
//!   regularisers over the visible Gaussians ([`losses`]); the metric lines report
//!   the regularisers weighted;
//! - **optimiser** (`training_setup`): Adam, eps 1e-15, one learning rate per attribute
//!   ([`constants`]); the position's decays as `get_expon_lr_func` over the run and
//!   is multiplied by the cameras' extent (`spatial_lr_scale = cameras_extent`, as
//!   GaussianAvatars' `Scene` passes it);
//! - **schedule**: GaussianAvatars' 600,000-iteration intervals scaled to the run
//!   ([`constants::scaled`]): SH degree raised every `scaled(1000)`, densification
//!   from `scaled(10,000)` every `scaled(2,000)` iterations, opacity reset every
//!   `scaled(60,000)` and, on a white background, once at the start of densification;
//! - **density control** ([`density`]): the screen-space gradient of every step
//!   comes from the rasterizer's tap ([`crate::splat::render_tapped`]); on a densification
//!   or reset iteration the Gaussians change as in GaussianAvatars, and the optimiser's
//!   moments follow the rows (edited through its burnpack record). As in GaussianAvatars,
//!   whose new parameters carry no gradient, no Adam step is taken for the Gaussians on a
//!   densification iteration, nor for the opacities on a reset.
//!
//! burn's learner calls [`TrainStep::step`](burn::train::TrainStep::step) and then
//! [`TrainStep::optimize`](burn::train::TrainStep::optimize) on the same
//! thread (single-device strategy): the step leaves the view's statistics in
//! [`GaSetup::pending`], `optimize` adds them to the statistics the module keeps (saved with
//! every checkpoint, so a resumed run continues the interval it stopped in) and densifies.
//!
//! The files: [`config`] ([`GaTrainConfig`]), [`schedule`] (the scaled intervals, the
//! optimiser and learning rates), [`state`] (what the training keeps besides the Gaussians),
//! [`step`] (the objective and burn's train and inference steps), [`moments`] (the
//! optimiser's moments following densification), [`checkpoint`] (a checkpoint's module) and
//! [`run`] ([`train`], the folder's files).
//!
//! FLAME refinement: as GaussianAvatars (`flame_gaussian_model.py`, `training_setup`), the
//! pose, translation and expression of every training frame are fine-tuned with the
//! Gaussians unless `flame_refinement` is off ([`config`]), through the refinement
//! TexAvatars' training uses ([`crate::train::refine`]).

pub mod checkpoint;
pub mod config;
pub mod constants;
pub mod density;
pub mod losses;
pub mod moments;
pub mod run;
pub mod schedule;
pub mod state;
pub mod step;

pub use checkpoint::from_checkpoint;
pub use config::GaTrainConfig;
pub use moments::edit_moments;
pub use run::{GaTrainReport, OWNED, ga_files, train};
pub use schedule::{GaSchedule, PositionLr, SH_INTERVAL, lr_scheduler, optimizer};
pub use state::{DensityState, GaSetup, Pending};
pub use step::{FrameLoss, GaTraining, objective, screen_radii};
