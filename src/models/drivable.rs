//! The one interface every avatar model offers to the commands that drive it: a frame in,
//! Gaussians out.
//!
//! `render`, `export ply`, evaluation and the drive helpers ([`crate::drive`]) hold a
//! `Box<dyn Drivable>` from [`super::load()`] and never name a model. The models are sibling
//! folders that each implement this trait: [`super::texavatars`] (TexAvatars: decoders,
//! texel lift) and [`super::gaussianavatars`] (GaussianAvatars: Gaussians bound to mesh
//! triangles); neither knows the other, and a third model is one more folder, one more
//! `impl` and one more case in [`super::load()`].

use burn::tensor::Device;

use crate::camera::Camera;
use crate::data::Conditioning;
use crate::error::Result;
use crate::splat::Gaussians;
use crate::splat::ply::PlyGaussians;

/// What a model computes from the camera alone and keeps while the camera stays put
/// ([`Drivable::view_cache`]); each model knows its own type.
pub type ViewCache = Box<dyn std::any::Any>;

/// Called at the end of each stage of [`Drivable::frame_gaussians_staged`] with the stage's
/// name (e.g. to synchronise the device and time it).
pub type StageMark<'a> = &'a mut dyn FnMut(&'static str) -> Result<()>;

/// An avatar that turns one tracked frame into Gaussians.
///
/// `Sync`, so that rendering can run on rayon's pool with a borrowed avatar.
pub trait Drivable: Sync {
    /// The model's name in messages ("TexAvatars", "GaussianAvatars").
    fn model_name(&self) -> &'static str;

    /// Vertices of the posed mesh the avatar is rigged to.
    fn num_vertices(&self) -> usize;

    /// Values of `expr`, `pose` and `eta` together that the avatar reads per frame; `None`
    /// when it reads only the posed mesh.
    fn condition_width(&self) -> Option<usize>;

    /// Gaussians per frame.
    fn num_gaussians(&self) -> usize;

    /// Bytes one frame's inference holds (for [`crate::limits`]).
    fn inference_bytes(&self) -> u64;

    /// The Gaussians of frame `c` for `camera` (view-dependent colours are evaluated for
    /// it).
    fn frame_gaussians(
        &self,
        c: &Conditioning,
        camera: &Camera,
        device: &Device,
    ) -> Result<Gaussians>;

    /// What the model computes from `camera` alone, to reuse for every frame seen from it
    /// (TexAvatars: the view's Pluecker map); `None`: nothing.
    fn view_cache(&self, _camera: &Camera, _device: &Device) -> Result<Option<ViewCache>> {
        Ok(None)
    }

    /// [`Drivable::frame_gaussians`] with the view's cache (from [`Drivable::view_cache`]
    /// for the same camera), calling `mark` at the end of each of the model's stages
    /// (TexAvatars: "decoders", "lifting"; GaussianAvatars: "binding").
    fn frame_gaussians_staged(
        &self,
        c: &Conditioning,
        camera: &Camera,
        view: Option<&ViewCache>,
        device: &Device,
        mark: StageMark<'_>,
    ) -> Result<Gaussians>;

    /// The frame's world-space Gaussians as a 3DGS PLY in the model's own terms (e.g. its
    /// SH coefficients), when it has them; `None`: exporters convert
    /// [`Drivable::frame_gaussians`] (colours baked for the camera).
    fn frame_ply(&self, _c: &Conditioning) -> Option<Result<PlyGaussians>> {
        None
    }
}
