//! A GaussianAvatars output folder, driven.
//!
//! GaussianAvatars' `train.py` saves `point_cloud/iteration_N/point_cloud.ply` under its
//! model folder, and `FlameGaussianModel.save_ply` (`scene/flame_gaussian_model.py`) writes
//! `flame_param.npz` next to each: the fine-tuned FLAME parameters of every training
//! timestep (`shape`, `static_offset` and per-timestep `expr`, `rotation`, `neck_pose`,
//! `jaw_pose`, `eyes_pose`, `translation`, `dynamic_offset`). `--checkpoint` may name the
//! model folder (the highest iteration is used) or the folder holding `point_cloud.ply`.
//! The FLAME model itself is the user's (`--head`, with GaussianAvatars' teeth:
//! `texavatars head add-teeth`); its triangle count must cover every binding.

use std::path::{Path, PathBuf};

use burn::tensor::Device;

use super::binding::{check_binding, face_frames, to_world};
use crate::camera::Camera;
use crate::data::Conditioning;
use crate::error::{Error, Result};
use crate::limits;
use crate::models::{Drivable, StageMark, ViewCache};
use crate::splat::Gaussians;
use crate::splat::ply::{self, PlyGaussians};

/// The Gaussians' file in a GaussianAvatars output folder.
pub const POINT_CLOUD: &str = "point_cloud.ply";
/// The FLAME parameters saved beside it.
pub const FLAME_PARAM: &str = "flame_param.npz";

/// A GaussianAvatars avatar bound to a head model's triangles.
#[derive(Clone, Debug)]
pub struct GaAvatar {
    /// The Gaussians as stored: positions, rotations and log scales local to their
    /// triangles.
    pub local: PlyGaussians,
    /// `[N]`: each Gaussian's triangle.
    pub binding: Vec<u32>,
    /// The head model's triangles.
    pub faces: Vec<[u32; 3]>,
    /// The head model's vertex count.
    pub num_vertices: usize,
    /// The `point_cloud.ply` read.
    pub source: PathBuf,
}

impl GaAvatar {
    /// The folder holding `point_cloud.ply` for `checkpoint`: itself, or the highest
    /// `point_cloud/iteration_N` of a GaussianAvatars model folder; `None` when it is not a
    /// GaussianAvatars output folder.
    pub fn find(checkpoint: &Path) -> Option<PathBuf> {
        if checkpoint.join(POINT_CLOUD).is_file() {
            return Some(checkpoint.to_path_buf());
        }
        let iterations = std::fs::read_dir(checkpoint.join("point_cloud")).ok()?;
        iterations
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.join(POINT_CLOUD).is_file())
            .filter_map(|p| {
                let n: u64 = p
                    .file_name()?
                    .to_str()?
                    .strip_prefix("iteration_")?
                    .parse()
                    .ok()?;
                Some((n, p))
            })
            .max_by_key(|(n, _)| *n)
            .map(|(_, p)| p)
    }

    /// Loads the avatar of `checkpoint` (see [`GaAvatar::find`]) for a head model with
    /// `faces` and `num_vertices`.
    pub fn load(checkpoint: &Path, faces: &[[u32; 3]], num_vertices: usize) -> Result<Self> {
        let dir = Self::find(checkpoint).ok_or_else(|| {
            Error::invalid(
                checkpoint.display().to_string(),
                POINT_CLOUD,
                "not found here or in point_cloud/iteration_*/ (a GaussianAvatars output folder)",
            )
        })?;
        let source = dir.join(POINT_CLOUD);
        let (local, binding) = ply::read_bound(&source)?;
        check_binding(&binding, local.len(), faces.len()).map_err(|e| {
            Error::invalid(source.display().to_string(), "binding_0", e.to_string())
        })?;
        if let Some(i) = faces
            .iter()
            .flatten()
            .find(|&&i| i as usize >= num_vertices)
        {
            return Err(Error::invalid(
                "head model",
                "faces",
                format!("vertex {i} of {num_vertices}"),
            ));
        }
        Ok(Self {
            local,
            binding,
            faces: faces.to_vec(),
            num_vertices,
            source,
        })
    }

    /// `flame_param.npz` beside the loaded `point_cloud.ply`, when present: the subject's
    /// shape and static offsets, and the fine-tuned training motion.
    pub fn flame_param(&self) -> Option<PathBuf> {
        let p = self.source.with_file_name(FLAME_PARAM);
        p.is_file().then_some(p)
    }

    /// The world-space Gaussians on the posed mesh `vertices` (GaussianAvatars' binding,
    /// [`super::binding`]).
    pub fn world(&self, vertices: &[[f32; 3]]) -> Result<PlyGaussians> {
        if vertices.len() != self.num_vertices {
            return Err(Error::invalid(
                self.source.display().to_string(),
                "vertices",
                format!(
                    "the posed mesh has {} vertices, the head model {}",
                    vertices.len(),
                    self.num_vertices
                ),
            ));
        }
        to_world(
            &self.local,
            &self.binding,
            &face_frames(&self.faces, vertices),
        )
    }
}

/// Writes `point_cloud.ply` (stored Gaussians with `binding_0`) into `dir`, in
/// GaussianAvatars' layout, so that its tools and [`GaAvatar::load`] read it; the FLAME
/// parameters (`flame_param.npz`) are the caller's to copy beside it.
pub fn write_point_cloud(dir: &Path, stored: &PlyGaussians, binding: &[u32]) -> Result<PathBuf> {
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let path = dir.join(POINT_CLOUD);
    ply::write_bound(&path, stored, binding)?;
    Ok(path)
}

impl Drivable for GaAvatar {
    fn model_name(&self) -> &'static str {
        "GaussianAvatars"
    }

    fn num_vertices(&self) -> usize {
        self.num_vertices
    }

    fn condition_width(&self) -> Option<usize> {
        None
    }

    fn num_gaussians(&self) -> usize {
        self.local.len()
    }

    fn inference_bytes(&self) -> u64 {
        // The stored and the world copy on the host, and the tensors.
        limits::product(&[3, self.local.len() as u64, limits::GAUSSIAN_BYTES])
    }

    fn frame_gaussians(
        &self,
        c: &Conditioning,
        camera: &Camera,
        device: &Device,
    ) -> Result<Gaussians> {
        let world = self.world(&c.vertices)?;
        Ok(Gaussians::from_ply(&world, camera.position(), device))
    }

    /// One stage, "binding": the triangles' frames and the world-space Gaussians on the
    /// host ([`super::binding::to_world`]), uploaded, colours evaluated on the device.
    fn frame_gaussians_staged(
        &self,
        c: &Conditioning,
        camera: &Camera,
        _view: Option<&ViewCache>,
        device: &Device,
        mark: StageMark<'_>,
    ) -> Result<Gaussians> {
        let g = self.frame_gaussians(c, camera, device)?;
        mark("binding")?;
        Ok(g)
    }

    fn frame_ply(&self, c: &Conditioning) -> Option<Result<PlyGaussians>> {
        Some(self.world(&c.vertices))
    }
}
