//! The model burn's learner trains ([`AvatarTraining`]: the avatar and its objective), its
//! [`TrainStep`] / [`InferenceStep`], and the step output the metrics read.

use std::sync::Arc;

use burn::module::{Module, ModuleVisitor, Param};
use burn::optim::GradientsParams;
use burn::tensor::Tensor;
use burn::train::metric::ItemLazy;
use burn::train::{InferenceStep, TrainOutput, TrainStep};

use super::loader::TrainBatch;
use super::loss::{LossTerms, LossWeights, objective};
use super::metrics::{Term, TermsInput};
use super::refine::FlameRefinement;
use super::stop::{Fault, StopControl};
use crate::metrics::{VggPerceptual, psnr};
use crate::models::texavatars::Avatar;

/// The objective's settings: weights, and the VGG loss with the iteration it starts at.
#[derive(Clone)]
pub struct Objective {
    /// Weights and thresholds.
    pub weights: LossWeights,
    /// The frozen VGG16 of the perceptual loss (`None`: "w/o VGG"); it lives on the
    /// training device.
    pub vgg: Option<Arc<VggPerceptual>>,
    /// The first (0-based) iteration that includes the VGG loss.
    pub vgg_from: usize,
    /// Checks every step's loss terms and gradients and reports a non-finite one here
    /// ([`super::stop`]); `None`: no check (and no read-back of the loss in the step).
    pub guard: Option<StopControl>,
}

impl std::fmt::Debug for Objective {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Objective")
            .field("weights", &self.weights)
            .field("vgg", &self.vgg.is_some())
            .field("vgg_from", &self.vgg_from)
            .field("guard", &self.guard.is_some())
            .finish()
    }
}

impl Objective {
    /// The VGG network when iteration `iteration` uses it.
    pub fn vgg_at(&self, iteration: usize) -> Option<&VggPerceptual> {
        self.vgg.as_deref().filter(|_| iteration >= self.vgg_from)
    }
}

/// What burn's learner trains: the avatar (all parameters) and the objective (no parameters,
/// never saved).
#[derive(Module, Debug)]
pub struct AvatarTraining {
    /// The avatar.
    pub avatar: Avatar,
    /// FLAME refinement ([`super::refine`]); `None`: the tracked meshes as they are.
    pub refine: Option<FlameRefinement>,
    /// The loss settings.
    #[module(skip)]
    pub objective: Objective,
}

/// One step's numbers: the loss terms (unweighted, `total` weighted) and PSNR.
///
/// The values are gathered into one small tensor on the device by the step and read back
/// once, by [`ItemLazy::sync`] on burn's metric thread; [`Term`] indexes them.
pub struct StepOutput {
    /// `[Term::COUNT]` values in [`Term`]'s order, detached from the graph.
    values: Tensor<1>,
    /// Host copy of `values` once synced.
    host: Option<Vec<f64>>,
    /// Frames in the batch.
    pub batch_size: usize,
}

impl StepOutput {
    /// Gathers `terms` and the batch's mean PSNR.
    ///
    /// # Shapes
    /// - `psnr`: `[N]`
    pub fn new(terms: &LossTerms, psnr: Tensor<1>, batch_size: usize) -> Self {
        let zero = || terms.l1.clone().zeros_like();
        let mut values = vec![zero(); Term::COUNT];
        values[Term::Loss as usize] = terms.total.clone();
        values[Term::L1 as usize] = terms.l1.clone();
        values[Term::DSsim as usize] = terms.dssim.clone();
        values[Term::Vgg as usize] = terms.vgg.clone().unwrap_or_else(zero);
        values[Term::Position as usize] = terms.position.clone();
        values[Term::Scale as usize] = terms.scale.clone();
        values[Term::Psnr as usize] = psnr.mean();
        StepOutput {
            values: Tensor::cat(values, 0).detach(),
            host: None,
            batch_size,
        }
    }

    /// Reads the values to the host now (a step that checks them).
    pub fn synced(self) -> Self {
        let host = read_host(&self.values);
        StepOutput {
            host: Some(host),
            ..self
        }
    }

    /// The values on the host (reads the device when not yet synced).
    pub fn host_values(&self) -> Vec<f64> {
        match &self.host {
            Some(h) => h.clone(),
            None => read_host(&self.values),
        }
    }
}

fn read_host(t: &Tensor<1>) -> Vec<f64> {
    t.clone()
        .into_data()
        .iter::<f32>()
        .map(|v| v as f64)
        .collect()
}

impl ItemLazy for StepOutput {
    fn sync(self) -> Result<Self, burn::tensor::ExecutionError> {
        let host = read_host(&self.values);
        Ok(StepOutput {
            host: Some(host),
            ..self
        })
    }
}

impl burn::train::metric::Adaptor<TermsInput> for StepOutput {
    fn adapt(&self) -> TermsInput {
        TermsInput {
            values: self.host_values(),
            batch_size: self.batch_size,
        }
    }
}

impl AvatarTraining {
    /// Forward pass and objective for one batch (any device; autodiff for training), with the
    /// VGG term when `vgg` is given. Returns the terms and the PSNR per frame (`[N]`).
    pub fn losses(&self, item: &TrainBatch, vgg: Option<&VggPerceptual>) -> (LossTerms, Tensor<1>) {
        let batch = &item.batch;
        let out = match &self.refine {
            Some(refine) => {
                let (vertices, condition) = refine.apply(batch);
                self.avatar.render(condition, &batch.cameras, vertices)
            }
            None => self.avatar.forward(batch),
        }
        .unwrap_or_else(|e| panic!("avatar forward: {e}"));
        let terms = objective(
            out.renders.clone(),
            item.batch.images.clone(),
            &out.maps,
            vgg,
            &self.objective.weights,
        );
        let psnr = psnr(
            out.renders.detach().permute([0, 3, 1, 2]),
            item.batch.images.clone().permute([0, 3, 1, 2]),
        );
        (terms, psnr)
    }
}

impl TrainStep for AvatarTraining {
    type Input = TrainBatch;
    type Output = StepOutput;

    /// Renders the batch, evaluates the objective and back-propagates it.
    ///
    /// # Panics
    /// When the batch does not fit the avatar (vertex count, condition width); [`super::train`]
    /// checks the dataset against the avatar before training starts.
    ///
    /// With a [`Objective::guard`], the step reads its loss terms and the gradients' L1 norm
    /// back (one small read per step) and reports a non-finite one: burn then stops before
    /// the next checkpoint ([`super::stop`]). PSNR may be infinite (a perfect render) and is
    /// not checked.
    fn step(&self, item: TrainBatch) -> TrainOutput<StepOutput> {
        let n = item.batch.cameras.len();
        let (terms, psnr) = self.losses(&item, self.objective.vgg_at(item.iteration));
        let grads = GradientsParams::from_grads(terms.total.backward(), self);
        let out = StepOutput::new(&terms, psnr, n);
        let out = guarded(
            self.objective.guard.as_ref(),
            out,
            item.iteration,
            &grads,
            self,
        );
        TrainOutput { grads, item: out }
    }
}

/// A step's output checked by `guard` (when there is one): the loss terms and the
/// gradients' L1 norm are read back (one small read per step) and a non-finite one is
/// reported as a [`Fault`] at `iteration`, so that burn stops before the next checkpoint
/// ([`super::stop`]). PSNR may be infinite (a perfect render) and is not checked. Both
/// models' steps use it.
pub fn guarded<M: Module>(
    guard: Option<&StopControl>,
    out: StepOutput,
    iteration: usize,
    grads: &GradientsParams,
    module: &M,
) -> StepOutput {
    let Some(guard) = guard else {
        return out;
    };
    let out = out.synced();
    let mut values: Vec<(String, f64)> = Term::ALL
        .iter()
        .zip(out.host_values())
        .map(|(t, v)| (t.name().to_string(), v))
        .collect();
    values.push(("gradient L1".into(), gradient_l1(grads, module)));
    if values
        .iter()
        .any(|(name, v)| name != Term::Psnr.name() && !v.is_finite())
    {
        guard.fault(Fault { iteration, values });
    }
    out
}

/// The sum of the absolute values of every parameter's gradient (not finite when any
/// gradient entry is not, or when the sum overflows).
pub fn gradient_l1<M: Module>(grads: &GradientsParams, module: &M) -> f64 {
    struct Sum<'a> {
        grads: &'a GradientsParams,
        total: Option<Tensor<1>>,
    }
    impl ModuleVisitor for Sum<'_> {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            if let Some(g) = self.grads.get::<D>(param.id) {
                let s = g.abs().sum();
                self.total = Some(match self.total.take() {
                    Some(t) => t + s,
                    None => s,
                });
            }
        }
    }
    let mut sum = Sum { grads, total: None };
    module.visit(&mut sum);
    sum.total
        .map(|t| t.into_scalar::<f32>() as f64)
        .unwrap_or(0.0)
}

impl InferenceStep for AvatarTraining {
    type Input = TrainBatch;
    type Output = StepOutput;

    /// The objective without the VGG term (validation reports L1, D-SSIM, the regularizers
    /// and PSNR on the held-out frames).
    fn step(&self, item: TrainBatch) -> StepOutput {
        let n = item.batch.cameras.len();
        let (terms, psnr) = self.losses(&item, None);
        StepOutput::new(&terms, psnr, n)
    }
}
