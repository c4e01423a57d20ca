//! The TexAvatars model behind [`Drivable`]: condition and camera through the decoders,
//! the texel lift with the frame's posed mesh, Gaussians out.

use burn::tensor::{Device, Tensor, TensorData};

use super::Avatar;
use crate::camera::Camera;
use crate::data::Conditioning;
use crate::error::Result;
use crate::limits;
use crate::models::{Drivable, StageMark, ViewCache};
use crate::splat::Gaussians;

/// The networks' condition `[expr, pose, eta]` [1, C] and the posed vertices [1, V, 3] of a
/// frame.
pub fn frame_inputs(c: &Conditioning, device: &Device) -> (Tensor<2>, Tensor<3>) {
    let cond: Vec<f32> = c
        .expr
        .iter()
        .chain(&c.pose)
        .chain(&c.eta)
        .copied()
        .collect();
    let n = cond.len();
    let v: Vec<f32> = c.vertices.iter().flatten().copied().collect();
    (
        Tensor::from_data(TensorData::new(cond, [1, n]), device),
        Tensor::from_data(TensorData::new(v, [1, c.vertices.len(), 3]), device),
    )
}

impl Avatar {
    /// The Gaussians of frame `c` for `camera`, with the camera's Pluecker map already
    /// computed ([`crate::models::texavatars::TexAvatarNet::view_input`]), e.g. kept while the camera
    /// stays put.
    pub fn frame_gaussians_with(
        &self,
        c: &Conditioning,
        pluecker: Tensor<4>,
        device: &Device,
    ) -> Result<Gaussians> {
        let (cond, verts) = frame_inputs(c, device);
        let maps = self.net.forward(cond, pluecker)?;
        self.gaussians(&maps, 0, verts.squeeze_dim::<2>(0))
    }
}

impl Drivable for Avatar {
    fn model_name(&self) -> &'static str {
        "TexAvatars"
    }

    fn num_vertices(&self) -> usize {
        Avatar::num_vertices(self)
    }

    fn condition_width(&self) -> Option<usize> {
        Some(self.net.cond_dim)
    }

    fn num_gaussians(&self) -> usize {
        Avatar::num_gaussians(self)
    }

    fn inference_bytes(&self) -> u64 {
        limits::avatar_bytes(self.net.uv_res, Avatar::num_gaussians(self))
    }

    fn frame_gaussians(
        &self,
        c: &Conditioning,
        camera: &Camera,
        device: &Device,
    ) -> Result<Gaussians> {
        let pluecker = self.net.view_input(std::slice::from_ref(camera), device)?;
        self.frame_gaussians_with(c, pluecker, device)
    }

    fn view_cache(&self, camera: &Camera, device: &Device) -> Result<Option<ViewCache>> {
        let pluecker = self.net.view_input(std::slice::from_ref(camera), device)?;
        Ok(Some(Box::new(pluecker)))
    }

    fn frame_gaussians_staged(
        &self,
        c: &Conditioning,
        camera: &Camera,
        view: Option<&ViewCache>,
        device: &Device,
        mark: StageMark<'_>,
    ) -> Result<Gaussians> {
        let pluecker = match view.and_then(|v| v.downcast_ref::<Tensor<4>>()) {
            Some(p) => p.clone(),
            None => self.net.view_input(std::slice::from_ref(camera), device)?,
        };
        let (cond, verts) = frame_inputs(c, device);
        let maps = self.net.forward(cond, pluecker)?;
        mark("decoders")?;
        let g = self.gaussians(&maps, 0, verts.squeeze_dim::<2>(0))?;
        mark("lifting")?;
        Ok(g)
    }
}
