//! Training GaussianAvatars in texavatars: `texavatars train --model gaussianavatars`.
//!
//! GaussianAvatars' `train.py` through burn's `Learner`, with the run shell of
//! [`crate::train`] (data checks, one run per folder, checkpoints every interval, resume,
//! signals, progress, non-finite guard):
//!
//! - **model**: [`GaModel`] initialised as GaussianAvatars (one Gaussian per triangle),
//!   rendered by texavatars' rasterizer on the data's white background;
//! - **objective** (`train.py`): `0.8 L1 + 0.2 (1 - SSIM)` plus the position and scale
//!   regularisers over the visible Gaussians ([`super::losses`]); the metric lines report
//!   the regularisers weighted;
//! - **optimiser** (`training_setup`): Adam, eps 1e-15, one learning rate per attribute
//!   ([`super::constants`]); the position's decays as `get_expon_lr_func` over the run and
//!   is multiplied by the cameras' extent (`spatial_lr_scale = cameras_extent`, as
//!   GaussianAvatars' `Scene` passes it);
//! - **schedule**: GaussianAvatars' 600,000-iteration intervals scaled to the run
//!   ([`super::constants::scaled`]): SH degree raised every `scaled(1000)`, densification
//!   from `scaled(10,000)` every `scaled(2,000)` iterations, opacity reset every
//!   `scaled(60,000)` and, on a white background, once at the start of densification;
//! - **density control** ([`super::density`]): the screen-space gradient of every step
//!   comes from the rasterizer's tap ([`crate::splat::render_tapped`]); on a densification
//!   or reset iteration the Gaussians change as in GaussianAvatars, and the optimiser's
//!   moments follow the rows (edited through its burnpack record). As in GaussianAvatars,
//!   whose new parameters carry no gradient, no Adam step is taken for the Gaussians on a
//!   densification iteration, nor for the opacities on a reset.
//!
//! burn's learner calls [`TrainStep::step`] and then [`TrainStep::optimize`] on the same
//! thread (single-device strategy): the step leaves the view's statistics in
//! [`GaSetup::pending`], `optimize` adds them to the statistics the module keeps (saved with
//! every checkpoint, so a resumed run continues the interval it stopped in) and densifies.
//!
//! Not here: GaussianAvatars also fine-tunes the FLAME pose, translation and expression of
//! every training frame (`flame_gaussian_model.py`, `training_setup`); texavatars keeps the
//! tracked meshes fixed, as it does for its own model.

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use burn::lr_scheduler::module_lr_scheduler::{ModuleLearningRate, ModuleLrScheduler};
use burn::lr_scheduler::{LrScheduler, LrSchedulerRecord};
use burn::module::{Module, Param, ParamGroup, ParamId};
use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer, OptimizerRecord};
use burn::tensor::{DType, Device, Shape, Tensor, TensorData};
use burn::train::{InferenceStep, TrainOutput, TrainStep};
use serde::{Deserialize, Serialize};

use super::binding::check_binding;
use super::constants::{self as ga, scaled};
use super::density::{self, DensifySettings, Stats};
use super::folder::write_point_cloud;
use super::losses::{position_loss, scale_loss};
use super::model::GaModel;
use crate::camera::Camera;
use crate::data::BACKGROUND;
use crate::device::BackendKind;
use crate::error::{Error, Result};
use crate::head::HeadAsset;
use crate::metrics::{self, psnr};
use crate::splat::cpu::{self, ProjCamera};
use crate::splat::demo::Pcg;
use crate::splat::{self, Gaussians, SplatParams};
use crate::train::loss::LossTerms;
use crate::train::refine::{self, FlameRefinement, Timesteps};
use crate::train::step::guarded;
use crate::train::{
    Launch, Schedule, StepOutput, StopControl, TrainBatch, TrainOptions, files, open_frames,
    prepare_folder,
};

/// Files of a GaussianAvatars run in its output folder.
pub mod ga_files {
    /// The resolved config of the run (read back by `--resume`).
    pub const CONFIG: &str = "train_gaussianavatars.json";
    /// GaussianAvatars' output layout: `point_cloud/iteration_N/point_cloud.ply`.
    pub const POINT_CLOUD_DIR: &str = "point_cloud";
}

/// What a GaussianAvatars run writes into its folder, removed by `--force`.
pub const OWNED: [&str; 9] = [
    ga_files::CONFIG,
    refine::REFINED_NPZ,
    refine::REFINED_INDEX,
    ga_files::POINT_CLOUD_DIR,
    files::CHECKPOINTS,
    files::IDENTITY,
    "train",
    "valid",
    "experiment.log",
];

/// GaussianAvatars' references iteration of the SH degree increments (`train.py`:
/// `if iteration % 1000 == 0: gaussians.oneupSHdegree()`).
pub const SH_INTERVAL: usize = 1_000;

/// A GaussianAvatars training run (`configs/train_gaussianavatars.json`): its length and
/// bookkeeping; everything else is GaussianAvatars' ([`super::constants`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GaTrainConfig {
    /// Optimiser steps of the run (GaussianAvatars: 600,000); every interval of its
    /// schedule is scaled to it.
    pub iterations: usize,
    /// Iterations between checkpoints (one burn epoch each; a validation pass follows).
    pub checkpoint_every: usize,
    /// SH degree (GaussianAvatars: 3).
    #[serde(default = "three")]
    pub sh_degree: usize,
    /// Validation frames evaluated at each checkpoint (0: none).
    #[serde(default = "four")]
    pub val_frames: usize,
    /// Iterations between progress lines (0: none).
    #[serde(default = "ten")]
    pub log_every: usize,
    /// Seed of the initial colours, the frame order and the split samples.
    #[serde(default)]
    pub seed: u64,
    /// Where tensors live (`--backend` overrides it).
    #[serde(default = "flex")]
    pub backend: BackendKind,
    /// FLAME refinement ([`crate::train::refine`]; GaussianAvatars' default, off with its
    /// `--not_finetune_flame_params`), at GaussianAvatars' learning rates.
    #[serde(default = "yes")]
    pub flame_refinement: bool,
}

fn yes() -> bool {
    true
}
fn three() -> usize {
    3
}
fn four() -> usize {
    4
}
fn ten() -> usize {
    10
}
fn flex() -> BackendKind {
    BackendKind::Flex
}

impl GaTrainConfig {
    /// Reads and validates a config file.
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let c: Self = serde_json::from_str(&text)
            .map_err(|e| Error::invalid(path.display().to_string(), "json", e.to_string()))?;
        c.validate(&path.display().to_string())?;
        Ok(c)
    }

    /// Checks the values (`what` names the source in errors).
    pub fn validate(&self, what: &str) -> Result<()> {
        if self.iterations == 0 {
            return Err(Error::invalid(what, "iterations", "must be at least 1"));
        }
        if self.checkpoint_every == 0 {
            return Err(Error::invalid(
                what,
                "checkpoint_every",
                "must be at least 1",
            ));
        }
        if self.sh_degree > 3 {
            return Err(Error::invalid(
                what,
                "sh_degree",
                format!("{} (0 to 3)", self.sh_degree),
            ));
        }
        Ok(())
    }

    /// Pretty JSON.
    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).expect("serialises") + "\n"
    }

    /// `Err(field)` when a run saved with `self` cannot be resumed as `other` (only
    /// `val_frames`, `log_every` and `backend` may change: the schedule is scaled to
    /// `iterations`).
    pub fn resumable_as(&self, other: &Self) -> std::result::Result<(), &'static str> {
        if self.iterations != other.iterations {
            return Err("iterations");
        }
        if self.checkpoint_every != other.checkpoint_every {
            return Err("checkpoint_every");
        }
        if self.sh_degree != other.sh_degree {
            return Err("sh_degree");
        }
        if self.seed != other.seed {
            return Err("seed");
        }
        if self.flame_refinement != other.flame_refinement {
            return Err("flame_refinement");
        }
        Ok(())
    }
}

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

/// The learning rates of [`GaTraining`]'s parameters (`training_setup`).
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

/// One view's statistics, from the step to `optimize`.
#[derive(Clone, Debug)]
pub struct Pending {
    /// The global iteration (0-based, burn's).
    pub iteration: usize,
    /// `[N, 2]` the tap's gradient.
    pub screen_grad: Vec<f32>,
    /// `[N]` screen radii (0: not visible).
    pub radii: Vec<f32>,
    /// `[F]` the frame's triangle scales `k`.
    pub face_scale: Vec<f32>,
}

/// What the training needs besides its parameters (never saved).
#[derive(Clone)]
pub struct GaSetup {
    /// The head model's triangles.
    pub faces: Arc<Vec<[u32; 3]>>,
    pub schedule: GaSchedule,
    /// The training cameras' extent ([`density::cameras_extent`]).
    pub extent: f32,
    pub seed: u64,
    /// The view the last step rendered, for `optimize`.
    pub pending: Arc<Mutex<Option<Pending>>>,
    /// Reports a non-finite loss or gradient ([`crate::train::stop`]).
    pub guard: Option<StopControl>,
}

impl std::fmt::Debug for GaSetup {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GaSetup")
            .field("faces", &self.faces.len())
            .field("schedule", &self.schedule)
            .field("extent", &self.extent)
            .finish()
    }
}

/// The densification statistics as module state (saved with checkpoints, never trained).
#[derive(Module, Debug)]
pub struct DensityState {
    /// `[N]` summed screen-space gradient norms.
    pub grad_accum: Param<Tensor<1>>,
    /// `[N]` views that saw each Gaussian.
    pub denom: Param<Tensor<1>>,
    /// `[N]` largest screen radius.
    pub max_radii: Param<Tensor<1>>,
    /// `[F]` triangle scales of the frame trained last (GaussianAvatars' `face_scaling`).
    pub face_scale: Param<Tensor<1>>,
}

fn frozen(v: Vec<f32>, device: &Device) -> Param<Tensor<1>> {
    let n = v.len();
    Param::from_tensor(Tensor::from_data(TensorData::new(v, [n]), device)).set_require_grad(false)
}

fn host1(t: Tensor<1>) -> Vec<f32> {
    t.into_data().iter::<f32>().collect()
}

impl DensityState {
    /// State of `stats` and `face_scale` on `device`.
    pub fn new(stats: Stats, face_scale: Vec<f32>, device: &Device) -> Self {
        Self {
            grad_accum: frozen(stats.grad_accum, device),
            denom: frozen(stats.denom, device),
            max_radii: frozen(stats.max_radii, device),
            face_scale: frozen(face_scale, device),
        }
    }

    /// The same parameters (ids kept) holding `stats`.
    pub fn with_stats(&self, stats: Stats, device: &Device) -> Self {
        let keep = |old: &Param<Tensor<1>>, v: Vec<f32>| {
            Param::initialized(old.id, frozen(v, device).val()).set_require_grad(false)
        };
        Self {
            grad_accum: keep(&self.grad_accum, stats.grad_accum),
            denom: keep(&self.denom, stats.denom),
            max_radii: keep(&self.max_radii, stats.max_radii),
            face_scale: self.face_scale.clone(),
        }
    }

    /// The statistics on the host.
    pub fn stats(&self) -> Stats {
        Stats {
            grad_accum: host1(self.grad_accum.val()),
            denom: host1(self.denom.val()),
            max_radii: host1(self.max_radii.val()),
        }
    }
}

/// What burn's learner trains: the Gaussians and their densification statistics.
#[derive(Module, Debug)]
pub struct GaTraining {
    pub model: GaModel,
    pub density: DensityState,
    /// FLAME refinement (`None`: the tracked meshes as they are).
    pub refine: Option<FlameRefinement>,
    #[module(skip)]
    pub setup: GaSetup,
}

/// Screen radii of `g` seen by `camera` (3DGS's `radii`: `ceil(3 sqrt(lambda_max))` of the
/// projected covariance, 0 for the Gaussians the rasterizer culls), on the host.
pub fn screen_radii(g: &Gaussians, camera: &Camera) -> Vec<f32> {
    let h2 = |t: Tensor<2>| -> Vec<f32> { t.detach().into_data().iter::<f32>().collect() };
    let (means, cov6, colors) = (
        h2(g.means.clone()),
        h2(g.cov6.clone()),
        h2(g.colors.clone()),
    );
    let opacities = host1(g.opacities.clone().detach());
    let scene = cpu::Scene {
        means: &means,
        cov6: &cov6,
        colors: &colors,
        opacities: &opacities,
    };
    cpu::project_all(&scene, &ProjCamera::new(camera))
        .into_iter()
        .map(|p| match p {
            Some(p) => {
                let s = p.splat;
                // The conic is the inverse of the (low-passed) 2D covariance.
                let det_conic = s.a * s.c - s.b * s.b;
                let (cxx, cyy) = (s.c / det_conic, s.a / det_conic);
                let det = 1.0 / det_conic;
                let mid = 0.5 * (cxx + cyy);
                let lambda = mid + (mid * mid - det).max(0.1).sqrt();
                let r = (3.0 * lambda.sqrt()).ceil();
                if r.is_finite() { r } else { 0.0 }
            }
            None => 0.0,
        })
        .collect()
}

/// One view through [`objective`]: the terms, the PSNR, the tap (whose gradient is the
/// screen-space one), the screen radii and the posed vertices.
pub struct FrameLoss {
    pub terms: LossTerms,
    pub psnr: Tensor<1>,
    pub screen: Tensor<2>,
    pub radii: Vec<f32>,
    pub vertices: Tensor<2>,
}

/// GaussianAvatars' objective (`train.py`) on frame 0 of `item`, colours from the SH bands
/// up to `degree`; `tap`: track the screen-space tap for its gradient; `refine`: pose the
/// frame with its refined FLAME parameters.
pub fn objective(
    model: &GaModel,
    faces: &[[u32; 3]],
    item: &TrainBatch,
    degree: usize,
    tap: bool,
    refine: Option<&FlameRefinement>,
) -> FrameLoss {
    let batch = &item.batch;
    let camera = batch.cameras[0];
    let [_, v, _] = batch.vertices.dims();
    let vertices = match refine {
        Some(r) => r.apply(batch).0,
        None => batch.vertices.clone(),
    }
    .narrow(0, 0, 1)
    .reshape([v, 3]);
    let g = model.gaussians_at_degree(faces, vertices.clone(), camera.position(), degree);
    let n = g.len();
    let mut screen = Tensor::<2>::zeros([n, 2], &g.means.device());
    if tap {
        screen = screen.require_grad();
    }
    let params = SplatParams {
        camera,
        background: BACKGROUND,
    };
    let rendered = splat::render_tapped(&g, screen.clone(), &params)
        .unwrap_or_else(|e| panic!("GaussianAvatars render: {e}"));
    let radii = screen_radii(&g, &camera);
    let visible = Tensor::<1>::from_data(
        TensorData::new(
            radii
                .iter()
                .map(|&r| f32::from(r > 0.0))
                .collect::<Vec<_>>(),
            [n],
        ),
        &g.means.device(),
    );
    let [h, w, _] = rendered.image.dims();
    let a = rendered.image.reshape([1, h, w, 3]).permute([0, 3, 1, 2]);
    let b = batch.images.clone().narrow(0, 0, 1).permute([0, 3, 1, 2]);
    let l1 = metrics::l1(a.clone(), b.clone());
    let dssim = metrics::ssim_loss(a.clone(), b.clone());
    let position = position_loss(model.xyz.val(), visible.clone());
    let scale = scale_loss(model.scaling.val(), visible);
    let total = l1.clone() * (1.0 - ga::LAMBDA_DSSIM)
        + dssim.clone() * ga::LAMBDA_DSSIM
        + position.clone()
        + scale.clone();
    let psnr = psnr(a.detach(), b);
    FrameLoss {
        terms: LossTerms {
            total,
            l1,
            dssim,
            vgg: None,
            position,
            scale,
        },
        psnr,
        screen,
        radii,
        vertices,
    }
}

impl GaTraining {
    /// The parameter ids of the Gaussians' attributes, in [`GaModel`]'s order.
    fn attribute_ids(&self) -> Vec<ParamId> {
        let m = &self.model;
        let mut ids = vec![m.xyz.id, m.features_dc.id];
        if let Some(r) = &m.features_rest {
            ids.push(r.id);
        }
        ids.extend([m.opacity.id, m.scaling.id, m.rotation.id]);
        ids
    }

    /// This module with the stored Gaussians, binding and statistics replaced, every
    /// parameter keeping its id (so the optimiser's state stays attached).
    fn replaced(
        self,
        stored: &crate::splat::ply::PlyGaussians,
        binding: &[u32],
        stats: Stats,
    ) -> Self {
        let device = self.model.xyz.val().device();
        let fresh = GaModel::from_stored(stored, binding, &device)
            .expect("densification keeps the binding valid");
        fn keep<const D: usize>(
            old: &Param<Tensor<D>>,
            new: Param<Tensor<D>>,
            grad: bool,
        ) -> Param<Tensor<D>> {
            Param::initialized(old.id, new.val()).set_require_grad(grad)
        }
        let m = &self.model;
        let model = GaModel {
            xyz: keep(&m.xyz, fresh.xyz, true),
            features_dc: keep(&m.features_dc, fresh.features_dc, true),
            features_rest: match (&m.features_rest, fresh.features_rest) {
                (Some(o), Some(n)) => Some(keep(o, n, true)),
                _ => None,
            },
            opacity: keep(&m.opacity, fresh.opacity, true),
            scaling: keep(&m.scaling, fresh.scaling, true),
            rotation: keep(&m.rotation, fresh.rotation, true),
            binding: Param::initialized(m.binding.id, fresh.binding.val()),
            sh_degree: m.sh_degree,
        };
        let density = self.density.with_stats(stats, &device);
        Self {
            model,
            density,
            refine: self.refine,
            setup: self.setup,
        }
    }
}

impl TrainStep for GaTraining {
    type Input = TrainBatch;
    type Output = StepOutput;

    /// Renders the batch's first frame (GaussianAvatars trains one view per step), evaluates
    /// the objective, back-propagates it and leaves the view's statistics for `optimize`.
    fn step(&self, item: TrainBatch) -> TrainOutput<StepOutput> {
        let i = item.iteration + 1;
        let degree = self.setup.schedule.degree(i, self.model.sh_degree);
        let FrameLoss {
            terms,
            psnr,
            screen,
            radii,
            vertices,
        } = objective(
            &self.model,
            &self.setup.faces,
            &item,
            degree,
            true,
            self.refine.as_ref(),
        );
        let raw = terms.total.backward();
        let screen_grad = screen
            .grad(&raw)
            .map(|g| g.into_data().iter::<f32>().collect())
            .unwrap_or_else(|| vec![0.0; 2 * self.model.len()]);
        let grads = GradientsParams::from_grads(raw, self);
        let verts: Vec<[f32; 3]> = vertices
            .detach()
            .into_data()
            .iter::<f32>()
            .collect::<Vec<_>>()
            .chunks(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect();
        let face_scale = super::binding::face_frames(&self.setup.faces, &verts)
            .iter()
            .map(|f| f.scale)
            .collect();
        *self.setup.pending.lock().expect("not poisoned") = Some(Pending {
            iteration: item.iteration,
            screen_grad,
            radii,
            face_scale,
        });
        let out = guarded(
            self.setup.guard.as_ref(),
            StepOutput::new(&terms, psnr, 1),
            item.iteration,
            &grads,
            self,
        );
        TrainOutput { grads, item: out }
    }

    /// Adds the view's statistics, then either densifies (no Adam step for the Gaussians,
    /// as in GaussianAvatars), or steps Adam and, on a reset iteration, resets the
    /// opacities (without their step).
    fn optimize(
        self,
        optim: &mut ModuleOptimizer,
        lr: ModuleLearningRate,
        mut grads: GradientsParams,
    ) -> Self {
        let pending = self.setup.pending.lock().expect("not poisoned").take();
        let Some(p) = pending else {
            return optim.step(lr, self, grads);
        };
        let i = p.iteration + 1;
        let schedule = self.setup.schedule;
        let device = self.model.xyz.val().device();
        let mut stats = self.density.stats();
        if schedule.tracks(i) {
            stats.add_view(&p.screen_grad, &p.radii);
        }
        let mut me = self;
        me.density.face_scale = Param::initialized(
            me.density.face_scale.id,
            frozen(p.face_scale.clone(), &device).val(),
        )
        .set_require_grad(false);
        let white = BACKGROUND == [1.0, 1.0, 1.0];
        let reset = schedule.resets(i, white);
        if let Some(size) = schedule.densifies(i) {
            let (stored, binding) = me.model.to_stored();
            let settings = DensifySettings {
                grad_threshold: ga::DENSIFY_GRAD_THRESHOLD,
                min_opacity: ga::PRUNE_MIN_OPACITY,
                extent: me.setup.extent,
                percent_dense: ga::PERCENT_DENSE,
                max_screen_size: size,
            };
            let mut rng = Pcg::new(me.setup.seed ^ (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
            let mut d = density::densify_and_prune(
                &stored,
                &binding,
                &p.face_scale,
                &stats,
                &settings,
                &mut rng,
            );
            let ids = me.attribute_ids();
            if reset {
                density::reset_opacity(&mut d.stored.opacity_logits);
            }
            let n = d.stored.len();
            // Every tenth densification, and the first, in the progress output.
            let event = (i - schedule.densify_from) / schedule.densify_interval;
            if event.is_multiple_of(10) || event <= 1 {
                eprintln!(
                    "train: it {i}: densified: {} cloned, {} split, {} pruned: {} -> {n} Gaussians",
                    d.cloned,
                    d.split,
                    d.pruned,
                    stored.len()
                );
            }
            me = me.replaced(&d.stored, &d.binding, Stats::zeros(n));
            let zeroed = reset.then_some(me.model.opacity.id);
            *optim = edit_moments(optim, &ids, &d.old_from_new, zeroed);
            if me.refine.is_none() {
                return me;
            }
            // GaussianAvatars steps Adam after densifying: the new Gaussian tensors have no
            // gradient yet, the FLAME parameters do.
            let m = &me.model;
            grads.remove::<2>(m.xyz.id);
            grads.remove::<3>(m.features_dc.id);
            if let Some(r) = &m.features_rest {
                grads.remove::<3>(r.id);
            }
            grads.remove::<1>(m.opacity.id);
            grads.remove::<2>(m.scaling.id);
            grads.remove::<2>(m.rotation.id);
            return optim.step(lr, me, grads);
        }
        if reset {
            grads.remove::<1>(me.model.opacity.id);
        }
        me.density = me.density.with_stats(stats, &device);
        let mut me = optim.step(lr, me, grads);
        if reset {
            // Only the opacities change: that parameter alone is replaced (id kept).
            let mut logits = host1(me.model.opacity.val());
            density::reset_opacity(&mut logits);
            let id = me.model.opacity.id;
            me.model.opacity =
                Param::initialized(id, frozen(logits, &device).val()).set_require_grad(true);
            *optim = edit_moments(optim, &[], &[], Some(id));
        }
        me
    }
}

impl InferenceStep for GaTraining {
    type Input = TrainBatch;
    type Output = StepOutput;

    /// The objective on a held-out frame, every SH band on.
    fn step(&self, item: TrainBatch) -> StepOutput {
        let f = objective(
            &self.model,
            &self.setup.faces,
            &item,
            self.model.sh_degree,
            false,
            self.refine.as_ref(),
        );
        StepOutput::new(&f.terms, f.psnr, 1)
    }
}

/// The optimiser with the moments of the parameters `ids` re-rowed by `old_from_new`
/// (`Some(old)`: that row's; `None`: zeros), and every moment of `zeroed` set to zero
/// (GaussianAvatars' `cat_tensors_to_optimizer`, `_prune_optimizer`,
/// `replace_tensor_to_optimizer`). Goes through the optimiser's burnpack record; a
/// parameter's step count is kept.
pub fn edit_moments(
    optim: &ModuleOptimizer,
    ids: &[ParamId],
    old_from_new: &[Option<usize>],
    zeroed: Option<ParamId>,
) -> ModuleOptimizer {
    let bytes = optim
        .to_record()
        .into_bytes()
        .expect("an optimiser record serialises");
    let reader = burn_pack::Reader::from_bytes(bytes).expect("burnpack written just now");
    let scalars = reader.scalars().clone();
    let metadata = reader.metadata().clone();
    let tensors = reader.into_tensors().expect("burnpack written just now");
    let ids: Vec<u64> = ids.iter().map(|i| i.val()).collect();
    let zeroed = zeroed.map(|i| i.val());
    let edited: Vec<burn_pack::Tensor> = tensors
        .into_iter()
        .map(|t| {
            let (name, dtype, shape, param_id, bytes) =
                t.into_parts().expect("burnpack written just now");
            let rerow = param_id.is_some_and(|p| ids.contains(&p));
            let zero = param_id.is_some() && param_id == zeroed;
            if !(rerow || zero) || dtype != DType::F32 || shape.num_dims() == 0 {
                return burn_pack::Tensor::new(name, dtype, shape, param_id, bytes);
            }
            let data = TensorData::from_bytes(bytes, shape.clone(), dtype);
            let values: Vec<f32> = data.try_to_vec().expect("f32 moments");
            let dims = shape.as_slice().to_vec();
            let row = dims[1..].iter().product::<usize>();
            let mut out = if rerow {
                let mut out = vec![0.0f32; old_from_new.len() * row];
                for (new, old) in old_from_new.iter().enumerate() {
                    if let Some(o) = old {
                        out[new * row..(new + 1) * row]
                            .copy_from_slice(&values[o * row..(o + 1) * row]);
                    }
                }
                out
            } else {
                values
            };
            if zero {
                out.iter_mut().for_each(|v| *v = 0.0);
            }
            let mut dims = dims;
            if rerow {
                dims[0] = old_from_new.len();
            }
            let data = TensorData::new(out, Shape::from(dims));
            let (bytes, shape, dtype) = data.into_parts();
            burn_pack::Tensor::new(name, dtype, shape, param_id, bytes)
        })
        .collect();
    let mut writer = burn_pack::Writer::new(edited);
    for (k, v) in &scalars {
        writer = writer.with_scalar(k, *v);
    }
    for (k, v) in &metadata {
        writer = writer.with_metadata(k, v);
    }
    let record = OptimizerRecord::from_bytes(writer.into_bytes().expect("serialises"))
        .expect("a record written just now");
    optim.clone().load_record(record)
}

/// The module of a checkpoint's record (`model-E.bpk`): the Gaussians, binding and
/// statistics it holds, so that burn's own load finds matching shapes (densification
/// changes them).
pub fn from_checkpoint(
    path: &Path,
    setup: GaSetup,
    refine: Option<FlameRefinement>,
    device: &Device,
) -> Result<GaTraining> {
    let what = path.display().to_string();
    let reader = burn_pack::Reader::from_file(path)
        .map_err(|e| Error::invalid(&what, "burnpack", e.to_string()))?;
    let mut floats = std::collections::HashMap::new();
    for t in reader
        .into_tensors()
        .map_err(|e| Error::invalid(&what, "burnpack", e.to_string()))?
    {
        let (name, dtype, shape, _, bytes) = t
            .into_parts()
            .map_err(|e| Error::invalid(&what, "burnpack", e.to_string()))?;
        let data = TensorData::from_bytes(bytes, shape.clone(), dtype);
        let values: Vec<f64> = data.iter::<f64>().collect();
        floats.insert(name, (shape.as_slice().to_vec(), values));
    }
    let get = |name: &str| -> Result<(Vec<usize>, Vec<f64>)> {
        floats
            .get(name)
            .cloned()
            .ok_or_else(|| Error::invalid(&what, name, "missing from the checkpoint"))
    };
    let f32s = |v: Vec<f64>| -> Vec<f32> { v.into_iter().map(|x| x as f32).collect() };
    let (_, xyz) = get("model.xyz")?;
    let (dc_shape, dc) = get("model.features_dc")?;
    let n = dc_shape[0];
    let rest = get("model.features_rest").ok();
    let k = 1 + rest.as_ref().map_or(0, |(s, _)| s[1]);
    let mut sh = Vec::with_capacity(n * k * 3);
    for g in 0..n {
        sh.extend(dc[3 * g..3 * g + 3].iter().map(|&x| x as f32));
        if let Some((_, r)) = &rest {
            let w = (k - 1) * 3;
            sh.extend(r[w * g..w * (g + 1)].iter().map(|&x| x as f32));
        }
    }
    let degree = (k as f64).sqrt() as usize - 1;
    let stored = crate::splat::ply::PlyGaussians {
        means: f32s(xyz),
        sh,
        sh_degree: degree,
        opacity_logits: f32s(get("model.opacity")?.1),
        log_scales: f32s(get("model.scaling")?.1),
        quats: f32s(get("model.rotation")?.1),
    };
    let binding: Vec<u32> = get("model.binding")?.1.iter().map(|&b| b as u32).collect();
    let model = GaModel::from_stored(&stored, &binding, device)?;
    let stats = Stats {
        grad_accum: f32s(get("density.grad_accum")?.1),
        denom: f32s(get("density.denom")?.1),
        max_radii: f32s(get("density.max_radii")?.1),
    };
    let density = DensityState::new(stats, f32s(get("density.face_scale")?.1), device);
    Ok(GaTraining {
        model,
        density,
        refine,
        setup,
    })
}

/// What a GaussianAvatars [`train`] did.
#[derive(Debug)]
pub struct GaTrainReport {
    pub start_iteration: usize,
    pub end_iteration: usize,
    /// Gaussians at the end.
    pub gaussians: usize,
    /// The trained Gaussians (on the inner, non-autodiff device).
    pub model: GaModel,
    pub seconds: f64,
    /// `OUT/point_cloud/iteration_N/` (only a complete run writes it).
    pub output: PathBuf,
    pub complete: bool,
}

/// Trains a GaussianAvatars avatar on `options.data` (see the module documentation) and
/// writes `OUT/point_cloud/iteration_N/point_cloud.ply` (with `binding_0`) and the subject's
/// `flame_param.npz` next to it: a folder `render`, `eval` and `export ply` read as any
/// GaussianAvatars output.
pub fn train(config: &GaTrainConfig, options: &TrainOptions) -> Result<GaTrainReport> {
    config.validate("train config")?;
    let head = match &options.head {
        Some(h) => h.clone(),
        None => {
            let next = options.data.join("..").join("head").join("head.npz");
            if next.is_file() {
                HeadAsset::load(&next, None)?
            } else {
                HeadAsset::embedded()?
            }
        }
    };
    let model = Arc::new(head.model.clone());
    let (train_set, val_set) = open_frames(options, model, config.val_frames)?;
    let out = &options.out;
    let folder = prepare_folder(options, &OWNED, ga_files::POINT_CLOUD_DIR, || {
        let path = out.join(ga_files::CONFIG);
        let saved = GaTrainConfig::load(&path)?;
        saved.resumable_as(config).map_err(|field| {
            Error::invalid(
                path.display().to_string(),
                field,
                "differs from the given config; a resumed run must keep its schedule (only \
                 val_frames, log_every and backend may change)",
            )
        })
    })?;
    let probe = train_set.load_item(0)?;
    if probe.vertices.len() != head.model.num_vertices() {
        return Err(Error::invalid(
            train_set.transforms_path().display().to_string(),
            "flame_param_path",
            format!(
                "posed meshes have {} vertices, the head model {}",
                probe.vertices.len(),
                head.model.num_vertices()
            ),
        ));
    }
    let centers: Vec<[f32; 3]> = train_set
        .frames()
        .iter()
        .map(|f| f.camera.position())
        .collect();
    let extent = density::cameras_extent(&centers);
    let backend = options.backend.unwrap_or(config.backend);
    let device = backend.autodiff_device();
    let stop = options.stop.clone().unwrap_or_default();
    let faces = Arc::new(head.model.faces.clone());
    let setup = GaSetup {
        faces: faces.clone(),
        schedule: GaSchedule::new(config.iterations),
        extent,
        seed: config.seed,
        pending: Arc::new(Mutex::new(None)),
        guard: Some(stop.clone()),
    };
    let refine = if config.flame_refinement {
        let timesteps = Timesteps::of_dataset(&train_set)?;
        Some(FlameRefinement::new(&head.model, timesteps, &device)?)
    } else {
        None
    };
    let training = match folder.checkpoint {
        Some(c) => from_checkpoint(
            &folder.ckpt_dir.join(format!("model-{c}.bpk")),
            setup,
            refine,
            &device,
        )?,
        None => {
            let model = GaModel::init(faces.len(), config.sh_degree, config.seed, &device)?;
            let n = model.len();
            GaTraining {
                model,
                density: DensityState::new(Stats::zeros(n), vec![1.0; faces.len()], &device),
                refine,
                setup,
            }
        }
    };
    let start_gaussians = training.model.len();

    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    std::fs::write(out.join(ga_files::CONFIG), config.to_json())
        .map_err(|e| Error::io(&out.join(ga_files::CONFIG), e))?;
    train_set
        .identity()
        .save(&head.model, &out.join(files::IDENTITY))?;

    let launch = Launch {
        schedule: Schedule {
            seed: config.seed,
            per_epoch: config.checkpoint_every,
            total: config.iterations,
            batch_size: 1,
            resume: folder.resume_at,
        },
        checkpoint: folder.checkpoint,
        log_every: config.log_every,
        val_frames: config.val_frames,
        stop,
        model_arg: " --model gaussianavatars",
    };
    let frames = train_set.len();
    let ga_schedule = GaSchedule::new(config.iterations);
    let launched = launch.run(
        options,
        training,
        (optimizer(), lr_scheduler(config.iterations, extent)),
        (train_set, val_set),
        &device,
        |start, end| {
            eprintln!(
                "train: GaussianAvatars, {frames} frames, {start_gaussians} Gaussians, {} backend, \
                 iterations {start}..{end} of {}, extent {extent:.3}, densify from {} every {}, \
                 opacity reset every {}, SH degree up every {}",
                format!("{backend:?}").to_lowercase(),
                config.iterations,
                ga_schedule.densify_from,
                ga_schedule.densify_interval,
                ga_schedule.opacity_reset,
                ga_schedule.sh_interval,
            )
        },
    )?;
    let error = launched.result.error.as_ref().map(|e| e.to_string());
    let (reached, complete) = launch.outcome(options, error, launched.end_iteration)?;
    let trained = launched.result.model;
    let gaussians = trained.model.len();
    let output = out
        .join(ga_files::POINT_CLOUD_DIR)
        .join(format!("iteration_{}", config.iterations));
    if complete {
        let (stored, binding) = trained.model.to_stored();
        check_binding(&binding, stored.len(), faces.len())?;
        std::fs::create_dir_all(&output).map_err(|e| Error::io(&output, e))?;
        write_point_cloud(&output, &stored, &binding)?;
        let identity = out.join(files::IDENTITY);
        let flame = output.join(super::folder::FLAME_PARAM);
        std::fs::copy(&identity, &flame).map_err(|e| Error::io(&flame, e))?;
        if let Some(r) = &trained.refine {
            r.refined().save(out)?;
        }
    } else {
        launch.stopped(options, reached)?;
    }
    drop(folder);
    Ok(GaTrainReport {
        start_iteration: launched.start_iteration,
        end_iteration: reached,
        gaussians,
        model: trained.model,
        seconds: launched.seconds,
        output,
        complete,
    })
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

    /// 3DGS's radius (diff-gaussian-rasterization `cuda_rasterizer/forward.cu`,
    /// `preprocessCUDA`: `lambda1 = mid +
    /// sqrt(max(0.1, mid^2 - det))`, `radius = ceil(3 sqrt(lambda1))` of the 2D covariance
    /// with its 0.3 low-pass): an isotropic Gaussian of standard deviation 0.1 on the axis
    /// of a camera 2 units away with f = 100 has variance 25 + 0.3 in pixels, so
    /// `lambda1 = 25.3 + sqrt(0.1)` and the radius `ceil(3 sqrt(lambda1)) = 16`; one behind
    /// the camera has none.
    #[test]
    fn screen_radius_follows_3dgs() {
        let device = Device::flex();
        let mut w2c = [[0.0f32; 4]; 4];
        for (i, row) in w2c.iter_mut().enumerate() {
            row[i] = 1.0;
        }
        w2c[2][3] = 2.0;
        let camera = Camera {
            width: 64,
            height: 64,
            fx: 100.0,
            fy: 100.0,
            cx: 32.0,
            cy: 32.0,
            world_to_camera: w2c,
        };
        let t = |v: Vec<f32>, w: usize| {
            let n = v.len() / w;
            Tensor::<2>::from_data(TensorData::new(v, [n, w]), &device)
        };
        let g = Gaussians {
            means: t(vec![0.0, 0.0, 0.0, 0.0, 0.0, -5.0], 3),
            cov6: t([0.01, 0.0, 0.0, 0.01, 0.0, 0.01].repeat(2), 6),
            colors: t(vec![0.5; 6], 3),
            opacities: Tensor::from_data(TensorData::new(vec![0.9f32, 0.9], [2]), &device),
        };
        let r = screen_radii(&g, &camera);
        let lambda1 = 25.3f32 + 0.1f32.sqrt();
        assert_eq!(r, vec![(3.0 * lambda1.sqrt()).ceil(), 0.0]);
        assert_eq!(r[0], 16.0);
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
