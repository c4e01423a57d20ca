//! What the training keeps besides the Gaussians: the view a step hands to `optimize`
//! ([`Pending`]), the run's fixed setup ([`GaSetup`]) and the densification statistics as
//! module state ([`DensityState`]).

use std::sync::{Arc, Mutex};

use burn::module::{Module, Param};
use burn::tensor::{Device, Tensor, TensorData};

use super::schedule::GaSchedule;
use crate::train::StopControl;
use crate::train::gaussianavatars::density::Stats;

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
    /// The training cameras' extent
    /// ([`density::cameras_extent`](crate::train::gaussianavatars::density::cameras_extent)).
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

pub(super) fn frozen(v: Vec<f32>, device: &Device) -> Param<Tensor<1>> {
    let n = v.len();
    Param::from_tensor(Tensor::from_data(TensorData::new(v, [n]), device)).set_require_grad(false)
}

pub(super) fn host1(t: Tensor<1>) -> Vec<f32> {
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
