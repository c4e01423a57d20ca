//! Motions that drive a trained avatar: a sequence of frames, each with the conditioning the
//! networks read (expression, 15-value pose, eta) and the posed head vertices the lifting
//! operator places the Gaussians on.
//!
//! [`Motion::load`] tells three sources apart by what the path is:
//! - **a dataset split**: a VHAP / GaussianAvatars `transforms_*.json` (a file whose JSON has
//!   `frames`). One motion frame per timestep, in the file's order, with the timestep's
//!   cameras (for `--cameras dataset`). The subject is the dataset's own.
//! - **FLAME parameters** (cross-reenactment): a VHAP export folder with `flame_param/`, a
//!   folder of `.npz` files, or one `.npz`. Files in name order; a file of T frames
//!   (GaussianAvatars' `flame_param.npz`, VHAP's `tracked_flame_params_*.npz`, (T, ·) arrays)
//!   gives T motion frames, a VHAP `flame_param` file one. The driver gives the
//!   expression, the jaw, eye, neck and global rotations and the translation, the avatar's
//!   subject ([`Identity`]) the shape and the static offsets, as GaussianAvatars' and the
//!   paper's cross-identity reenactment do. A driver's eta side file (`eta/TTTTT.npy` next to
//!   `flame_param/`) is used when present, zeros otherwise.
//! - **curves**: any other `.json`, expression and pose keyframes interpolated linearly
//!   ([`Curves`]).
//!
//! Every source's frame count is checked against [`limits::FRAMES`] and the memory the
//! loaded frames take against the budget ([`check_frames`]) before the frames are built.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use serde::Deserialize;

use crate::camera::Camera;
pub use crate::data::Identity;
use crate::data::dataset::{POSE_DIM, pose_conditioning};
use crate::data::vhap::{self, ETA_DIM};
use crate::data::{Conditioning, HeadDataset};
use crate::error::{Error, Result};
use crate::head::{HeadAsset, HeadMeta, HeadModel, HeadPose};
use crate::io::npz::Npz;
use crate::limits;

/// Where a motion came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MotionKind {
    /// A dataset split (`transforms_*.json`).
    Dataset,
    /// FLAME / VHAP parameter files of a driver (cross-reenactment).
    Parameters,
    /// A curves JSON.
    Curves,
}

/// One frame of a motion.
#[derive(Clone, Debug)]
pub struct MotionFrame {
    /// The timestep (the dataset's, the file's position, or the curve frame).
    pub timestep: usize,
    /// Conditioning and posed vertices.
    pub conditioning: Arc<Conditioning>,
    /// The dataset's cameras at this timestep, `(camera index, camera)`; empty for other
    /// sources.
    pub cameras: Vec<(usize, Camera)>,
}

impl MotionFrame {
    /// The dataset camera with `index` at this timestep.
    pub fn camera(&self, index: usize) -> Option<Camera> {
        self.cameras.iter().find(|c| c.0 == index).map(|c| c.1)
    }
}

/// A loaded motion.
#[derive(Clone, Debug)]
pub struct Motion {
    pub kind: MotionKind,
    pub source: PathBuf,
    pub frames: Vec<MotionFrame>,
}

impl Motion {
    /// Loads the motion at `path` (see the module docs for how its kind is told).
    pub fn load(
        path: &Path,
        model: &HeadModel,
        meta: &HeadMeta,
        identity: &Identity,
    ) -> Result<Self> {
        if path.is_dir() {
            return Self::parameters(path, model, identity);
        }
        if !path.exists() {
            return Err(Error::invalid(
                path.display().to_string(),
                "motion",
                "no such file or folder",
            ));
        }
        match path.extension().and_then(|e| e.to_str()) {
            Some("npz") => Self::parameters(path, model, identity),
            Some("json") => {
                let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
                let value: serde_json::Value = serde_json::from_str(&text).map_err(|e| {
                    Error::invalid(
                        path.display().to_string(),
                        format!("line {}", e.line()),
                        e.to_string(),
                    )
                })?;
                if value.get("frames").is_some_and(|f| f.is_array()) {
                    Self::dataset(path, model)
                } else {
                    let curves: Curves = serde_json::from_value(value).map_err(|e| {
                        Error::invalid(path.display().to_string(), "curves", e.to_string())
                    })?;
                    Self::curves(&curves, path, model, meta, identity)
                }
            }
            _ => Err(Error::invalid(
                path.display().to_string(),
                "motion",
                "expected a transforms_*.json, a curves .json, a FLAME parameter .npz or a \
                 folder of them",
            )),
        }
    }

    /// A dataset split: one frame per timestep with its cameras.
    fn dataset(path: &Path, model: &HeadModel) -> Result<Self> {
        let ds = HeadDataset::from_transforms(path, Arc::new(model.clone()))?;
        let mut timesteps: Vec<usize> = ds.frames().iter().map(|f| f.timestep).collect();
        timesteps.sort_unstable();
        timesteps.dedup();
        check_frames(
            &path.display().to_string(),
            "frames",
            timesteps.len(),
            model,
        )?;
        let mut frames: Vec<MotionFrame> = Vec::new();
        let mut at: BTreeMap<usize, usize> = BTreeMap::new();
        for (i, f) in ds.frames().iter().enumerate() {
            let k = match at.get(&f.timestep) {
                Some(&k) => k,
                None => {
                    at.insert(f.timestep, frames.len());
                    frames.push(MotionFrame {
                        timestep: f.timestep,
                        conditioning: ds.conditioning(i)?,
                        cameras: Vec::new(),
                    });
                    frames.len() - 1
                }
            };
            frames[k].cameras.push((f.camera_index, f.camera));
        }
        if frames.is_empty() {
            return Err(Error::invalid(
                path.display().to_string(),
                "frames",
                "empty",
            ));
        }
        Ok(Motion {
            kind: MotionKind::Dataset,
            source: path.to_path_buf(),
            frames,
        })
    }

    /// Driver parameter files with the avatar's identity.
    fn parameters(path: &Path, model: &HeadModel, identity: &Identity) -> Result<Self> {
        let files = if path.is_dir() {
            let dir = if path.join("flame_param").is_dir() {
                path.join("flame_param")
            } else {
                path.to_path_buf()
            };
            let files = crate::io::files_with_extension(&dir, "npz")?;
            if files.is_empty() {
                return Err(Error::invalid(
                    dir.display().to_string(),
                    "motion",
                    "no .npz FLAME parameter files",
                ));
            }
            files
        } else {
            vec![path.to_path_buf()]
        };
        let identity = identity.fit(model)?;
        // Frame counts first (the `expr` arrays' rows): the frames' meshes are built only
        // when they all fit.
        let mut total = 0usize;
        for f in &files {
            let what = f.display().to_string();
            let t = match Npz::open(f)?.floats("expr")?.shape.as_slice() {
                [t, _] => *t,
                _ => 1, // (E,): one frame; other shapes: refused by the reader below
            };
            total = total.saturating_add(t.max(1));
            let field = if files.len() == 1 {
                "expr (frames)".to_string()
            } else {
                format!("expr (frames, {total} so far over {} files)", files.len())
            };
            check_frames(&what, &field, total, model)?;
        }
        let mut frames = Vec::new();
        for f in &files {
            let poses = HeadPose::load_npz_frames(f)?;
            let what = f.display().to_string();
            if poses.len() == 1 {
                let eta = vhap::load_eta(f)?;
                let pose = poses.into_iter().next().expect("one pose");
                frames.push(driven(frames.len(), pose, eta, model, &identity, &what)?);
            } else {
                for (i, pose) in poses.into_iter().enumerate() {
                    let what = format!("{what} (frame {i})");
                    let eta = vec![0.0; ETA_DIM];
                    frames.push(driven(frames.len(), pose, eta, model, &identity, &what)?);
                }
            }
        }
        Ok(Motion {
            kind: MotionKind::Parameters,
            source: path.to_path_buf(),
            frames,
        })
    }

    /// Curves evaluated at every frame, with the avatar's identity.
    fn curves(
        curves: &Curves,
        path: &Path,
        model: &HeadModel,
        meta: &HeadMeta,
        identity: &Identity,
    ) -> Result<Self> {
        let what = path.display().to_string();
        check_frames(&what, "frames", curves.frames, model)?;
        let identity = identity.fit(model)?;
        let poses = curves.poses(model, meta, &what)?;
        let frames = poses
            .into_iter()
            .enumerate()
            .map(|(t, pose)| driven(t, pose, vec![0.0; ETA_DIM], model, &identity, &what))
            .collect::<Result<Vec<_>>>()?;
        Ok(Motion {
            kind: MotionKind::Curves,
            source: path.to_path_buf(),
            frames,
        })
    }

    /// The dataset camera indices of all frames, sorted, once each (empty for other kinds).
    pub fn camera_indices(&self) -> Vec<usize> {
        let mut all: Vec<usize> = self
            .frames
            .iter()
            .flat_map(|f| f.cameras.iter().map(|c| c.0))
            .collect();
        all.sort_unstable();
        all.dedup();
        all
    }

    /// Keeps frames `range` (positions in the motion, end exclusive); errors when the range
    /// is empty or past the end.
    pub fn select(&mut self, range: std::ops::Range<usize>) -> Result<()> {
        let n = self.frames.len();
        if range.start >= range.end || range.end > n {
            return Err(Error::invalid(
                self.source.display().to_string(),
                "frames",
                format!(
                    "{}..{} is empty or past the motion's {n} frames",
                    range.start, range.end
                ),
            ));
        }
        self.frames = self.frames[range].to_vec();
        Ok(())
    }
}

/// The head model of a driven avatar: `head` when given, else the head a dataset motion's
/// export carries (`DATA/../head/head.npz`, as the synthetic benchmark writes), else the
/// embedded default head.
pub fn head_for(head: Option<&Path>, motion: Option<&Path>) -> Result<HeadAsset> {
    if let Some(p) = head {
        return HeadAsset::load(p, None);
    }
    let beside = motion
        .and_then(|m| m.parent())
        .map(|d| d.join("../head/head.npz"))
        .filter(|p| p.exists());
    match beside {
        Some(p) => HeadAsset::load(&p, None),
        None => HeadAsset::embedded(),
    }
}

/// Checks a motion of `frames` frames on `model`: at most [`limits::FRAMES`], and the
/// loaded frames (their posed meshes, [`limits::motion_frame_bytes`]) within the memory
/// budget. `what` and `field` name the source in errors.
pub fn check_frames(what: &str, field: &str, frames: usize, model: &HeadModel) -> Result<()> {
    limits::check_size(what, field, frames, &limits::FRAMES)?;
    let per = limits::motion_frame_bytes(model.num_vertices(), model.num_expr + POSE_DIM + ETA_DIM);
    limits::check_estimate(
        what,
        field,
        &limits::Estimate::new().add(
            format!("{frames} motion frames"),
            limits::product(&[frames as u64, per]),
        ),
    )
}

/// Frame `t` of a driver's `pose` on the avatar's `identity`.
fn driven(
    t: usize,
    mut pose: HeadPose,
    eta: Vec<f32>,
    model: &HeadModel,
    identity: &Identity,
    what: &str,
) -> Result<MotionFrame> {
    pose.shape.clone_from(&identity.shape);
    pose.static_offset.clone_from(&identity.static_offset);
    Ok(MotionFrame {
        timestep: t,
        conditioning: Arc::new(pose_conditioning(model, pose, eta, what)?),
        cameras: Vec::new(),
    })
}

/// A keyframed motion (JSON):
///
/// ```json
/// {
///   "frames": 48,
///   "expression": { "jawOpen": [[0, 0.0], [24, 1.0], [47, 0.0]], "3": [[0, 0.5]] },
///   "pose": { "jaw": [[0, [0, 0, 0]], [24, [0.3, 0, 0]]], "rotation": [[0, [0, 0.2, 0]]] }
/// }
/// ```
///
/// `expression` keys are the head's expression names (`head.json`'s `expr_names`) or
/// coefficient indices; `pose` keys are `rotation`, `neck`, `jaw`, `translation` (3 values)
/// and `eyes` (6: left then right axis-angle). Keys are `[frame, value]`, interpolated
/// linearly between keyframes and held before the first and after the last; unnamed values
/// stay zero.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Curves {
    /// Number of frames.
    pub frames: usize,
    /// Expression coefficients by name or index.
    #[serde(default)]
    pub expression: BTreeMap<String, Vec<(f32, f32)>>,
    /// Pose vectors by joint.
    #[serde(default)]
    pub pose: BTreeMap<String, Vec<(f32, Vec<f32>)>>,
}

impl Curves {
    /// The pose at every frame (shape zero; the caller sets the identity).
    pub fn poses(&self, model: &HeadModel, meta: &HeadMeta, what: &str) -> Result<Vec<HeadPose>> {
        if self.frames == 0 {
            return Err(Error::invalid(what, "frames", "must be at least 1"));
        }
        limits::check_size(what, "frames", self.frames, &limits::FRAMES)?;
        let mut out = vec![HeadPose::neutral(model); self.frames];
        for (name, keys) in &self.expression {
            let field = format!("expression.{name}");
            let index = match meta.expr(name) {
                Some(i) => i,
                None => match name.parse::<usize>() {
                    Ok(i) if i < model.num_expr => i,
                    _ => {
                        return Err(Error::invalid(
                            what,
                            field,
                            format!(
                                "not an expression of the head (names: {}; or an index below {})",
                                meta.expr_names.join(", "),
                                model.num_expr
                            ),
                        ));
                    }
                },
            };
            let keys: Vec<(f32, Vec<f32>)> = keys.iter().map(|&(t, v)| (t, vec![v])).collect();
            let values = sample(&keys, 1, self.frames, what, &field)?;
            for (pose, v) in out.iter_mut().zip(values) {
                pose.expr[index] = v[0];
            }
        }
        for (name, keys) in &self.pose {
            let field = format!("pose.{name}");
            let dim = match name.as_str() {
                "eyes" => 6,
                "rotation" | "neck" | "jaw" | "translation" => 3,
                _ => {
                    return Err(Error::invalid(
                        what,
                        field,
                        "not a pose key (rotation, neck, jaw, eyes, translation)",
                    ));
                }
            };
            let values = sample(keys, dim, self.frames, what, &field)?;
            for (pose, v) in out.iter_mut().zip(values) {
                let dst: &mut [f32] = match name.as_str() {
                    "eyes" => &mut pose.eyes,
                    "rotation" => &mut pose.rotation,
                    "neck" => &mut pose.neck,
                    "jaw" => &mut pose.jaw,
                    _ => &mut pose.translation,
                };
                dst.copy_from_slice(&v);
            }
        }
        Ok(out)
    }
}

/// Piecewise-linear samples of keyframes at frames `0..frames`.
fn sample(
    keys: &[(f32, Vec<f32>)],
    dim: usize,
    frames: usize,
    what: &str,
    field: &str,
) -> Result<Vec<Vec<f32>>> {
    if keys.is_empty() {
        return Err(Error::invalid(what, field, "no keyframes"));
    }
    for (i, (t, v)) in keys.iter().enumerate() {
        if v.len() != dim {
            return Err(Error::invalid(
                what,
                format!("{field}[{i}]"),
                format!("{} values, expected {dim}", v.len()),
            ));
        }
        if !t.is_finite() || *t < 0.0 || v.iter().any(|x| !x.is_finite()) {
            return Err(Error::invalid(
                what,
                format!("{field}[{i}]"),
                "frame must be a finite number >= 0 and values finite",
            ));
        }
        if i > 0 && keys[i - 1].0 >= *t {
            return Err(Error::invalid(
                what,
                format!("{field}[{i}]"),
                "keyframes must be in increasing frame order",
            ));
        }
    }
    Ok((0..frames)
        .map(|f| {
            let f = f as f32;
            let j = keys.partition_point(|(t, _)| *t <= f);
            if j == 0 {
                keys[0].1.clone()
            } else if j == keys.len() {
                keys[j - 1].1.clone()
            } else {
                let ((t0, a), (t1, b)) = (&keys[j - 1], &keys[j]);
                let w = (f - t0) / (t1 - t0);
                a.iter().zip(b).map(|(a, b)| a + w * (b - a)).collect()
            }
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn linear_interpolation_holds_ends() {
        let keys = vec![(2.0, vec![0.0]), (4.0, vec![1.0])];
        let v = sample(&keys, 1, 6, "t", "f").expect("valid");
        let v: Vec<f32> = v.into_iter().map(|x| x[0]).collect();
        assert_eq!(v, vec![0.0, 0.0, 0.0, 0.5, 1.0, 1.0]);
    }

    #[test]
    fn bad_keyframes_name_the_field() {
        let e =
            sample(&[(1.0, vec![0.0, 1.0])], 3, 4, "m.json", "pose.jaw").expect_err("wrong length");
        assert!(e.to_string().contains("pose.jaw[0]"), "{e}");
        let e = sample(
            &[(3.0, vec![0.0]), (1.0, vec![1.0])],
            1,
            4,
            "m.json",
            "expression.x",
        )
        .expect_err("unsorted");
        assert!(e.to_string().contains("increasing"), "{e}");
    }
}
