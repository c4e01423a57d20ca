//! FLAME refinement: per-timestep corrections to the tracked translation, rotations
//! (global, neck, jaw, eyes) and expression of every training frame, optimised with the
//! avatar, as GaussianAvatars (`scene/flame_gaussian_model.py`,
//! `FlameGaussianModel.training_setup`, on unless `--not_finetune_flame_params`) and the
//! TexAvatars reference (the same file and method) do by default.
//!
//! - The corrections are parameters `[T, ·]` (T: the training split's distinct `flame_param`
//!   files), zero at the start; a frame's parameters are its tracked ones plus its row.
//!   Gradients reach them through the lift's vertices and the tensor LBS ([`Rig`]).
//! - Learning rates (Adam, constant), the peers' `flame_expr_lr` 1e-3, `flame_pose_lr` 1e-5
//!   (all four rotations) and `flame_trans_lr` 1e-6 ([`super::constants`]), are burn
//!   parameter groups matched on the field names ([`REFINE_EXPR`], ...).
//! - The networks' condition is built from the refined expression and pose, detached, as the
//!   reference's `select_mesh_by_timestep` does (`exp.detach()`): the refinement moves the
//!   mesh; the condition follows without a gradient.
//! - A frame whose `flame_param` file is not a training one (another split's timestep) keeps
//!   its tracked parameters and vertices.
//! - The refined parameters are written with the avatar ([`crate::data::refined::RefinedParams`],
//!   `refined_flame_param.npz` in GaussianAvatars' multi-frame layout plus a JSON index) and
//!   `texavatars export flame-param` writes them as VHAP `flame_param` files.

use std::collections::HashMap;
use std::sync::Arc;

use burn::module::{Module, Param};
use burn::tensor::{Device, Tensor};

use crate::data::refined::RefinedParams;
use crate::data::{HeadBatch, HeadDataset};
use crate::error::{Error, Result};
use crate::head::rig::POSE_LEN;
use crate::head::{HeadModel, HeadPose, Rig};

/// Field name (and burn parameter path part) of the expression corrections.
pub const REFINE_EXPR: &str = "refine_expr";
/// Field name of the pose corrections (global, neck, jaw, eyes).
pub const REFINE_POSE: &str = "refine_pose";
/// Field name of the translation corrections.
pub const REFINE_TRANSLATION: &str = "refine_translation";

/// The training frames' timesteps: one row per distinct `flame_param` file.
#[derive(Clone, Debug, PartialEq)]
pub struct Timesteps {
    /// `flame_param_path` of each row, relative to the transforms file's folder, as the JSON
    /// writes it ([`HeadDataset::flame_key`]).
    pub keys: Vec<String>,
    /// VHAP's `timestep_index` of each row.
    pub timesteps: Vec<usize>,
    /// The tracked parameters of each row, posed with the dataset's subject.
    pub tracked: Vec<HeadPose>,
    /// Row of each key.
    index: HashMap<String, usize>,
}

impl Timesteps {
    /// The distinct timesteps of `dataset`, in the order of their first frame.
    pub fn of_dataset(dataset: &HeadDataset) -> Result<Self> {
        let mut keys = Vec::new();
        let mut timesteps = Vec::new();
        let mut tracked = Vec::new();
        let mut index = HashMap::new();
        for (i, frame) in dataset.frames().iter().enumerate() {
            let key = dataset.flame_key(i)?;
            if index.contains_key(&key) {
                continue;
            }
            let c = dataset.conditioning(i)?;
            let id = dataset.identity();
            let mut pose = HeadPose {
                shape: id.shape.clone(),
                expr: c.expr.clone(),
                translation: c.translation,
                static_offset: id.static_offset.clone(),
                ..Default::default()
            };
            pose.set_pose15(&c.pose);
            index.insert(key.clone(), keys.len());
            keys.push(key);
            timesteps.push(frame.timestep);
            tracked.push(pose);
        }
        Ok(Timesteps {
            keys,
            timesteps,
            tracked,
            index,
        })
    }

    /// Number of rows.
    pub fn len(&self) -> usize {
        self.keys.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.keys.is_empty()
    }

    /// The row of `key`, when it is a training timestep.
    pub fn row(&self, key: &str) -> Option<usize> {
        self.index.get(key).copied()
    }
}

/// The refinement parameters (corrections, zero at the start) and the rig that poses them.
///
/// # Shapes
/// - `refine_expr`: [T, E]; `refine_pose`: [T, 15]; `refine_translation`: [T, 3]
#[derive(Module, Debug)]
pub struct FlameRefinement {
    /// Expression corrections.
    pub refine_expr: Param<Tensor<2>>,
    /// Pose corrections `[global 3, neck 3, jaw 3, eyes 6]` (axis-angle).
    pub refine_pose: Param<Tensor<2>>,
    /// Translation corrections.
    pub refine_translation: Param<Tensor<2>>,
    /// The subject's rig (constant tensors).
    pub rig: Rig,
    /// The rows' files and tracked values.
    #[module(skip)]
    pub timesteps: Arc<Timesteps>,
}

impl FlameRefinement {
    /// Zero corrections for the timesteps of `timesteps`, posed by `model` with their subject.
    pub fn new(model: &HeadModel, timesteps: Timesteps, device: &Device) -> Result<Self> {
        let Some(first) = timesteps.tracked.first() else {
            return Err(Error::invalid(
                "flame refinement",
                "frames",
                "no training timesteps",
            ));
        };
        let rig = Rig::new(model, first, device)?;
        let t = timesteps.len();
        let zeros = |w: usize| Param::from_tensor(Tensor::<2>::zeros([t, w], device));
        Ok(FlameRefinement {
            refine_expr: zeros(rig.num_expr()),
            refine_pose: zeros(POSE_LEN),
            refine_translation: zeros(3),
            rig,
            timesteps: Arc::new(timesteps),
        })
    }

    /// The posed vertices and the networks' condition of `batch` with the refined
    /// parameters of its training frames (others keep the batch's).
    ///
    /// # Shapes
    /// - returns vertices [N, V, 3] and condition [N, E + 15 + 128]
    pub fn apply(&self, batch: &HeadBatch) -> (Tensor<3>, Tensor<2>) {
        let n = batch.cameras.len();
        let mut vertices = Vec::with_capacity(n);
        let mut condition = Vec::with_capacity(n);
        for i in 0..n {
            let own = |t: &Tensor<2>| t.clone().narrow(0, i, 1);
            match self.timesteps.row(&batch.flame_keys[i]) {
                Some(row) => {
                    let at = |p: &Param<Tensor<2>>| p.val().narrow(0, row, 1);
                    let expr = own(&batch.expr) + at(&self.refine_expr);
                    let pose = own(&batch.pose) + at(&self.refine_pose);
                    let translation = own(&batch.translation) + at(&self.refine_translation);
                    vertices.push(self.rig.pose(expr.clone(), pose.clone(), translation));
                    condition.push(Tensor::cat(
                        vec![expr.detach(), pose.detach(), own(&batch.eta)],
                        1,
                    ));
                }
                None => {
                    vertices.push(batch.vertices.clone().narrow(0, i, 1));
                    condition.push(own(&batch.condition));
                }
            }
        }
        (Tensor::cat(vertices, 0), Tensor::cat(condition, 0))
    }

    /// The refined (absolute) parameters of every row.
    pub fn refined(&self) -> RefinedParams {
        let host =
            |p: &Param<Tensor<2>>| -> Vec<f32> { p.val().into_data().iter::<f32>().collect() };
        let (de, dp, dt) = (
            host(&self.refine_expr),
            host(&self.refine_pose),
            host(&self.refine_translation),
        );
        let e = self.rig.num_expr();
        let ts = &self.timesteps;
        let poses = ts
            .tracked
            .iter()
            .enumerate()
            .map(|(r, p)| {
                let mut q = p.clone();
                for (k, x) in q.expr.iter_mut().enumerate() {
                    *x += de[r * e + k];
                }
                let d = &dp[r * POSE_LEN..(r + 1) * POSE_LEN];
                let mut pose = q.pose15();
                for (x, dx) in pose.iter_mut().zip(d) {
                    *x += dx;
                }
                q.set_pose15(&pose);
                for (x, dx) in q.translation.iter_mut().zip(&dt[r * 3..r * 3 + 3]) {
                    *x += dx;
                }
                q
            })
            .collect();
        RefinedParams {
            keys: ts.keys.clone(),
            timesteps: ts.timesteps.clone(),
            poses,
            num_vertices: self.rig.num_vertices(),
        }
    }
}
