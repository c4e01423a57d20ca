//! Batching [`HeadItem`]s into tensors: burn's [`Batcher`] for
//! [`HeadDataset`](crate::data::dataset::HeadDataset).

use burn::data::dataloader::batcher::Batcher;
use burn::tensor::{Device, Tensor, TensorData};

use crate::camera::Camera;
use crate::data::dataset::{HeadItem, POSE_DIM};
use crate::data::vhap::ETA_DIM;
use crate::error::{Error, Result};

/// A batch of frames.
///
/// # Shapes
/// - `images`: [N, H, W, 3], RGB in [0, 1]
/// - `masks`: [N, H, W, 1]
/// - `expr`: [N, E]
/// - `pose`: [N, 15]
/// - `eta`: [N, 128]
/// - `condition`: [N, E + 15 + 128], the paper's order: `[expr, pose, eta]`
/// - `translation`: [N, 3]
/// - `vertices`: [N, V, 3]
/// - `cameras`, `timesteps`, `camera_indices`, `flame_keys`: N entries
#[derive(Clone, Debug)]
pub struct HeadBatch {
    pub images: Tensor<4>,
    pub masks: Tensor<4>,
    pub expr: Tensor<2>,
    pub pose: Tensor<2>,
    pub eta: Tensor<2>,
    pub condition: Tensor<2>,
    pub translation: Tensor<2>,
    pub vertices: Tensor<3>,
    pub cameras: Vec<Camera>,
    pub timesteps: Vec<usize>,
    pub camera_indices: Vec<usize>,
    /// Each frame's `flame_param_path` ([`HeadItem::flame_key`]).
    pub flame_keys: Vec<String>,
}

/// Stacks [`HeadItem`]s into a [`HeadBatch`] on a device.
#[derive(Clone, Copy, Debug, Default)]
pub struct HeadBatcher;

impl HeadBatcher {
    /// Stacks `items` on `device`. Every item must have the first item's image size, number
    /// of expression coefficients and number of vertices (the frames of one dataset do);
    /// `items` must not be empty.
    pub fn try_batch(&self, items: Vec<HeadItem>, device: &Device) -> Result<HeadBatch> {
        let what = "head batch";
        let Some(first) = items.first() else {
            return Err(Error::invalid(what, "items", "no items to batch"));
        };
        let (h, w) = (first.height(), first.width());
        let e = first.expr.len();
        let v = first.vertices.len();
        let n = items.len();
        for (i, it) in items.iter().enumerate() {
            let mismatch = |field: &str, got: String, want: String| {
                Err(Error::invalid(
                    what,
                    field,
                    format!(
                        "item {i} ({}) has {got}, item 0 ({}) has {want}",
                        it.image_path.display(),
                        first.image_path.display()
                    ),
                ))
            };
            if (it.height(), it.width()) != (h, w) {
                return mismatch(
                    "images",
                    format!("{}x{} pixels", it.width(), it.height()),
                    format!("{w}x{h}"),
                );
            }
            if it.image.len() != h * w * 3 || it.mask.len() != h * w {
                return mismatch(
                    "images",
                    format!("{} image and {} mask values", it.image.len(), it.mask.len()),
                    format!("{w}x{h} pixels"),
                );
            }
            if it.expr.len() != e {
                return mismatch("expr", it.expr.len().to_string(), e.to_string());
            }
            if it.eta.len() != ETA_DIM {
                return mismatch("eta", it.eta.len().to_string(), ETA_DIM.to_string());
            }
            if it.vertices.len() != v {
                return mismatch(
                    "vertices",
                    format!("{} vertices", it.vertices.len()),
                    v.to_string(),
                );
            }
        }
        let stack = |f: &dyn Fn(&HeadItem) -> &[f32]| -> Vec<f32> {
            items.iter().flat_map(|it| f(it).iter().copied()).collect()
        };
        let images = stack(&|it| &it.image);
        let masks = stack(&|it| &it.mask);
        let expr = stack(&|it| &it.expr);
        let pose = stack(&|it| &it.pose);
        let eta = stack(&|it| &it.eta);
        let translation = stack(&|it| &it.translation);
        let vertices: Vec<f32> = items
            .iter()
            .flat_map(|it| it.vertices.iter().flatten().copied())
            .collect();
        let expr = Tensor::<2>::from_data(TensorData::new(expr, [n, e]), device);
        let pose = Tensor::<2>::from_data(TensorData::new(pose, [n, POSE_DIM]), device);
        let eta = Tensor::<2>::from_data(TensorData::new(eta, [n, ETA_DIM]), device);
        Ok(HeadBatch {
            images: Tensor::from_data(TensorData::new(images, [n, h, w, 3]), device),
            masks: Tensor::from_data(TensorData::new(masks, [n, h, w, 1]), device),
            condition: Tensor::cat(vec![expr.clone(), pose.clone(), eta.clone()], 1),
            expr,
            pose,
            eta,
            translation: Tensor::from_data(TensorData::new(translation, [n, 3]), device),
            vertices: Tensor::from_data(TensorData::new(vertices, [n, v, 3]), device),
            cameras: items.iter().map(|it| it.camera).collect(),
            timesteps: items.iter().map(|it| it.timestep).collect(),
            camera_indices: items.iter().map(|it| it.camera_index).collect(),
            flame_keys: items.iter().map(|it| it.flame_key.clone()).collect(),
        })
    }
}

impl Batcher<HeadItem, HeadBatch> for HeadBatcher {
    /// [`HeadBatcher::try_batch`].
    ///
    /// # Panics
    /// When the items cannot be stacked (different image sizes, expression or vertex
    /// counts, or no items): burn's trait has no error path, and items of one
    /// [`HeadDataset`](crate::data::dataset::HeadDataset) always stack.
    fn batch(&self, items: Vec<HeadItem>, device: &Device) -> HeadBatch {
        match self.try_batch(items, device) {
            Ok(b) => b,
            Err(e) => panic!("{e}"),
        }
    }
}
