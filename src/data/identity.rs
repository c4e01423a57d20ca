//! One identity per subject: the shape coefficients and static offsets every frame is posed
//! with.
//!
//! VHAP tracks each sequence on its own, so the `shape` and `static_offset` stored in the
//! `flame_param` files of a union export differ from sequence to sequence. GaussianAvatars
//! (`FlameGaussianModel.load_meshes`, `scene/flame_gaussian_model.py`) and the TexAvatars
//! reference take them once, from the subject's first timestep, zero-pad offsets shorter than
//! the model's vertex count, and pose every frame of every split with them. This module does
//! the same: [`Identity::of_transforms`] picks
//!
//! 1. `canonical_flame_param.npz` in the export's folder when present (VHAP's
//!    `combine_nerf_datasets.py` copies the first training sequence's there), else
//! 2. the `flame_param` file of the first (smallest) timestep of `transforms_train.json` in
//!    that folder, else
//! 3. that of the first timestep of the split itself (a lone export without a training split).
//!
//! A trained avatar keeps its identity (`RUN/canonical_flame_param.npz`, written by `train`),
//! so evaluating another export (`eval --split NAME=PATH`) and driving it with another
//! subject's motion use the avatar's subject.

use std::path::{Path, PathBuf};

use crate::data::vhap;
use crate::error::{Error, Result};
use crate::head::{HeadModel, HeadPose};

/// File name of a subject's canonical parameters (VHAP's export and a training run's folder).
pub const CANONICAL: &str = "canonical_flame_param.npz";

/// Vertices VHAP's `add_teeth` appends to FLAME (`vhap/model/flame.py`, `FlameHead.add_teeth`):
/// 8 rings of 15.
pub const VHAP_TEETH_VERTICES: usize = 120;

/// A subject: shape coefficients and static offsets.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Identity {
    pub shape: Vec<f32>,
    pub static_offset: Option<Vec<[f32; 3]>>,
    /// Where it was read from (for messages); empty for the mean head.
    pub source: PathBuf,
}

impl Identity {
    /// The model's mean head (zero shape, no offsets): the subject of the synthetic
    /// benchmark.
    pub fn mean(model: &HeadModel) -> Self {
        Identity {
            shape: vec![0.0; model.num_shape],
            static_offset: None,
            source: PathBuf::new(),
        }
    }

    /// The shape and static offsets of a FLAME parameter file (one frame, or the shared
    /// arrays of a multi-frame file).
    pub fn load(path: &Path) -> Result<Self> {
        // Only the shared arrays: a tracked sequence's per-frame arrays are not read.
        let mut z = crate::io::npz::Npz::open(path)?;
        let (shape, static_offset) =
            crate::head::params::subject(&mut z, &path.display().to_string())?;
        Ok(Identity {
            shape,
            static_offset,
            source: path.to_path_buf(),
        })
    }

    /// The subject of the export that `transforms` (a `transforms_*.json`) belongs to (see
    /// the module docs for the order of the sources).
    pub fn of_transforms(transforms: &Path) -> Result<Self> {
        let dir = transforms.parent().unwrap_or(Path::new("."));
        let canonical = dir.join(CANONICAL);
        if canonical.is_file() {
            return Self::load(&canonical);
        }
        let train = dir.join("transforms_train.json");
        let from = if train.is_file() {
            train
        } else {
            transforms.to_path_buf()
        };
        let frames = vhap::load_transforms(&from)?;
        let first = frames
            .iter()
            .filter(|f| f.flame_param.is_some())
            .min_by_key(|f| f.timestep)
            .and_then(|f| f.flame_param.clone())
            .ok_or_else(|| {
                Error::invalid(
                    from.display().to_string(),
                    "frames",
                    format!(
                        "no frame with a flame_param_path to take the subject's shape from \
                         (and no {CANONICAL} next to it)"
                    ),
                )
            })?;
        Self::load(&first)
    }

    /// Writes the identity as VHAP's canonical parameters (zero pose and expression).
    pub fn save(&self, model: &HeadModel, path: &Path) -> Result<()> {
        HeadPose {
            shape: self.shape.clone(),
            static_offset: self.static_offset.clone(),
            ..HeadPose::neutral(model)
        }
        .save_npz(path)
    }

    /// The identity fitted to `model`: static offsets shorter than the model's vertex count
    /// are zero-padded (GaussianAvatars); more shape coefficients or more offsets than the
    /// model has are errors naming the source. Offsets for exactly VHAP's 120 teeth vertices
    /// more than the model say which command adds them.
    pub fn fit(&self, model: &HeadModel) -> Result<Self> {
        let what = if self.source.as_os_str().is_empty() {
            "identity".to_string()
        } else {
            self.source.display().to_string()
        };
        if self.shape.len() > model.num_shape {
            return Err(Error::invalid(
                &what,
                "shape",
                format!(
                    "{} coefficients, the model has {}",
                    self.shape.len(),
                    model.num_shape
                ),
            ));
        }
        let v = model.num_vertices();
        let static_offset = match &self.static_offset {
            Some(o) if o.len() == v + VHAP_TEETH_VERTICES => {
                return Err(Error::invalid(
                    &what,
                    "static_offset",
                    format!(
                        "{} offsets, the model has {v} vertices: the data was tracked by VHAP \
                         with its teeth ({VHAP_TEETH_VERTICES} vertices more). Add them to the \
                         model with `texavatars head add-teeth --model MODEL.npz --out DIR` \
                         (the .npz must hold FLAME's lip rings, see docs/captures.md) and pass \
                         `--head DIR/MODEL.npz`",
                        o.len()
                    ),
                ));
            }
            Some(o) if o.len() > v => {
                return Err(Error::invalid(
                    &what,
                    "static_offset",
                    format!("{} offsets, the model has {v} vertices", o.len()),
                ));
            }
            Some(o) => {
                let mut o = o.clone();
                o.resize(v, [0.0; 3]);
                Some(o)
            }
            None => None,
        };
        Ok(Identity {
            shape: self.shape.clone(),
            static_offset,
            source: self.source.clone(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn model(v: usize) -> HeadModel {
        HeadModel {
            v_template: vec![[0.0; 3]; v],
            shapedirs: vec![0.0; v * 3 * 3],
            num_shape: 2,
            num_expr: 1,
            posedirs: vec![0.0; v * 3 * 36],
            j_regressor: vec![0.0; 5 * v],
            weights: vec![0.0; v * 5],
            parents: vec![None, Some(0), Some(1), Some(1), Some(1)],
            faces: vec![],
        }
    }

    #[test]
    fn offsets_are_zero_padded_and_extra_teeth_offsets_name_the_command() {
        let m = model(4);
        let id = Identity {
            shape: vec![0.1],
            static_offset: Some(vec![[1.0; 3]; 2]),
            source: PathBuf::from("a.npz"),
        };
        let fitted = id.fit(&m).expect("fit");
        assert_eq!(
            fitted.static_offset,
            Some(vec![[1.0; 3], [1.0; 3], [0.0; 3], [0.0; 3]])
        );
        let teeth = Identity {
            static_offset: Some(vec![[0.0; 3]; 4 + VHAP_TEETH_VERTICES]),
            ..id.clone()
        };
        let e = teeth.fit(&m).unwrap_err().to_string();
        assert!(
            e.contains("a.npz") && e.contains("static_offset") && e.contains("head add-teeth"),
            "{e}"
        );
        let more = Identity {
            static_offset: Some(vec![[0.0; 3]; 5]),
            ..id.clone()
        };
        assert!(!more.fit(&m).unwrap_err().to_string().contains("add-teeth"));
        let shape = Identity {
            shape: vec![0.0; 3],
            ..id
        };
        assert!(shape.fit(&m).unwrap_err().to_string().contains("shape"));
    }

    #[test]
    fn offsets_tracked_with_vhaps_teeth_fit_the_model_with_teeth() {
        let (model, _, rings) = crate::head::teeth::tests::lips_model();
        let v = model.num_vertices();
        let tracked = Identity {
            shape: vec![0.2],
            static_offset: Some(vec![[0.001; 3]; v + VHAP_TEETH_VERTICES]),
            source: PathBuf::from("canonical_flame_param.npz"),
        };
        assert!(tracked.fit(&model).is_err());
        let (with_teeth, _) = crate::head::teeth::add_teeth(&model, None, &rings).expect("teeth");
        let fitted = tracked.fit(&with_teeth).expect("fits");
        assert_eq!(fitted, tracked);
    }
}
