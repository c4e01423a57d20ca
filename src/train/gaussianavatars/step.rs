//! The training step ([`GaTraining`], what burn's learner trains): GaussianAvatars'
//! [`objective`] on one view, and `optimize`, which adds the view's statistics and densifies
//! or resets the opacities on their iterations.

use burn::lr_scheduler::module_lr_scheduler::ModuleLearningRate;
use burn::module::{Module, Param, ParamId};
use burn::optim::{GradientsParams, ModuleOptimizer};
use burn::tensor::{Tensor, TensorData};
use burn::train::{InferenceStep, TrainOutput, TrainStep};

use super::moments::edit_moments;
use super::state::{DensityState, GaSetup, Pending, frozen, host1};
use crate::camera::Camera;
use crate::data::BACKGROUND;
use crate::metrics::{self, psnr};
use crate::models::gaussianavatars::model::GaModel;
use crate::splat::cpu::{self, ProjCamera};
use crate::splat::{self, Gaussians, SplatParams};
use crate::train::gaussianavatars::constants as ga;
use crate::train::gaussianavatars::density::{self, DensifySettings, Stats};
use crate::train::gaussianavatars::losses::{position_loss, scale_loss};
use crate::train::loss::LossTerms;
use crate::train::refine::FlameRefinement;
use crate::train::step::guarded;
use crate::train::{StepOutput, TrainBatch};
use crate::util::rng::Pcg;

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
        let face_scale =
            crate::models::gaussianavatars::binding::face_frames(&self.setup.faces, &verts)
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

#[cfg(test)]
mod tests {
    use burn::tensor::Device;

    use super::*;

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
}
