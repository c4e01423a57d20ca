//! A burn [`Dataset`] over one split of a VHAP / GaussianAvatars export.
//!
//! Each item is one frame (one timestep seen by one camera): its image and foreground mask,
//! its camera, and the timestep's conditioning (expression coefficients, the 15-value pose,
//! eta) and posed head vertices. Items are read from disk when asked for
//! ([`HeadDataset::load_item`]); the per-timestep part (FLAME parameters, eta, skinning) is
//! cached, since every camera of a timestep shares it.
//!
//! # Conventions
//! - Images: 8- or 16-bit PNG, RGB or RGBA; RGBA is composited on white
//!   (`rgb a + (1 - a)`, as GaussianAvatars' `readCamerasFromTransforms` does). Values in
//!   [0, 1].
//! - Masks (`fg_mask_path`): the PNG's grey value (luma for a colour PNG) in [0, 1]. Masks are
//!   optional, as in GaussianAvatars: a frame without `fg_mask_path`, or whose mask file does
//!   not exist, gets all ones (the second case is reported once per dataset on stderr).
//! - Subject: every frame is posed with one [`Identity`] (shape and static offsets) per
//!   dataset, not with its own file's (see [`crate::data::identity`]).
//! - Images and masks must have the frame's `w` x `h` pixels.
//! - Expression coefficients are fitted to the model: a file with fewer than
//!   `model.num_expr` is zero-padded, one with more is truncated (FLAME files carry 100;
//!   models may use fewer). The posed vertices use the fitted coefficients.
//! - Shape coefficients are not truncated: a file with more than `model.num_shape` is an
//!   error, since dropping identity components would change the head.

use std::collections::HashMap;
use std::io::Cursor;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use burn::data::dataset::{Dataset, DatasetError};

use crate::camera::Camera;
use crate::data::identity::Identity;
use crate::data::split::Split;
use crate::data::validate::{PathPolicy, check_paths, report};
use crate::data::vhap::{self, ETA_DIM, VhapFrame};
use crate::error::{Error, Result};
use crate::head::model::JOINTS;
use crate::head::{HeadModel, HeadPose, lbs};

/// Length of the pose vector (`[global 3, neck 3, jaw 3, eyes 6]`).
pub const POSE_DIM: usize = 15;

/// The per-timestep part of an item: conditioning and posed vertices.
///
/// # Shapes
/// - `expr`: `[E]` with E = `model.num_expr`
/// - `pose`: `[15]`
/// - `eta`: `[128]`
/// - `vertices`: `[V]`
#[derive(Clone, Debug, PartialEq)]
pub struct Conditioning {
    /// Expression coefficients, fitted to the model (padded or truncated).
    pub expr: Vec<f32>,
    /// [`HeadPose::pose15`].
    pub pose: [f32; POSE_DIM],
    /// The eta side file's values, zeros when it is absent.
    pub eta: Vec<f32>,
    /// The head's translation (VHAP's `translation`).
    pub translation: [f32; 3],
    /// The posed vertices ([`lbs()`], with translation and static offsets).
    pub vertices: Vec<[f32; 3]>,
}

/// One frame of the dataset.
///
/// # Shapes
/// - `image`: [H, W, 3] row-major, RGB in [0, 1]
/// - `mask`: [H, W] row-major, in [0, 1]
/// - `expr`: `[E]`; `pose`: `[15]`; `eta`: `[128]`; `vertices`: `[V]`
///
/// with H, W = `camera.height`, `camera.width`.
#[derive(Clone, Debug, PartialEq)]
pub struct HeadItem {
    /// The image, composited on white when it had alpha.
    pub image: Vec<f32>,
    /// The foreground mask; all ones when the frame has none.
    pub mask: Vec<f32>,
    /// The frame's camera (OpenCV world-to-camera, pixels).
    pub camera: Camera,
    /// VHAP's `timestep_index`.
    pub timestep: usize,
    /// VHAP's `camera_index`.
    pub camera_index: usize,
    /// The image file (for logs).
    pub image_path: PathBuf,
    /// Expression coefficients, `[E]`.
    pub expr: Vec<f32>,
    /// Pose, `[global 3, neck 3, jaw 3, eyes 6]` axis-angle.
    pub pose: [f32; POSE_DIM],
    /// Eta, `[128]`.
    pub eta: Vec<f32>,
    /// The head's translation.
    pub translation: [f32; 3],
    /// Posed vertices, `[V]`.
    pub vertices: Vec<[f32; 3]>,
    /// The frame's `flame_param_path` relative to the transforms file's folder
    /// ([`HeadDataset::flame_key`]): which timestep FLAME refinement corrects.
    pub flame_key: String,
}

impl HeadItem {
    /// Image height in pixels.
    pub fn height(&self) -> usize {
        self.camera.height as usize
    }

    /// Image width in pixels.
    pub fn width(&self) -> usize {
        self.camera.width as usize
    }
}

/// One split of a VHAP export with the head model that poses it.
pub struct HeadDataset {
    transforms: PathBuf,
    frames: Vec<VhapFrame>,
    model: Arc<HeadModel>,
    identity: Arc<Identity>,
    cache: Option<Cache>,
    /// Refined parameters that replace the tracked ones of their timesteps.
    refined: Option<Arc<crate::data::refined::RefinedParams>>,
    /// Set once a missing mask file has been reported.
    mask_warned: std::sync::atomic::AtomicBool,
}

impl std::fmt::Debug for HeadDataset {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("HeadDataset")
            .field("transforms", &self.transforms)
            .field("frames", &self.frames.len())
            .field("identity", &self.identity.source)
            .field("cached", &self.cache.is_some())
            .finish()
    }
}

impl HeadDataset {
    /// Opens `root/transforms_<split>.json` (see [`Split::file_name`]); its files must stay
    /// inside the dataset root ([`PathPolicy::InsideRoot`]).
    pub fn open(root: &Path, split: Split, model: Arc<HeadModel>) -> Result<Self> {
        Self::open_with(root, split, model, PathPolicy::InsideRoot)
    }

    /// [`HeadDataset::open`] with a choice of where the files may live.
    pub fn open_with(
        root: &Path,
        split: Split,
        model: Arc<HeadModel>,
        paths: PathPolicy,
    ) -> Result<Self> {
        Self::from_transforms_with(&root.join(split.file_name()), model, paths)
    }

    /// Opens one `transforms_*.json` whose files stay inside the dataset root
    /// ([`PathPolicy::InsideRoot`]); see [`HeadDataset::from_transforms_with`].
    pub fn from_transforms(path: &Path, model: Arc<HeadModel>) -> Result<Self> {
        Self::from_transforms_with(path, model, PathPolicy::InsideRoot)
    }

    /// Opens one `transforms_*.json`. Reads and checks the JSON (every frame must have a
    /// `flame_param_path`; every file named must be where `paths` allows, see
    /// [`check_paths`]), the model and the subject's identity ([`Identity::of_transforms`],
    /// fitted to the model); images and parameters are read per item, or all at once by
    /// [`HeadDataset::check_files`].
    pub fn from_transforms_with(
        path: &Path,
        model: Arc<HeadModel>,
        paths: PathPolicy,
    ) -> Result<Self> {
        let what = path.display().to_string();
        model.validate("head model")?;
        if model.num_joints() != JOINTS {
            return Err(Error::invalid(
                "head model",
                "kintree_table",
                format!(
                    "{} joints; FLAME poses {JOINTS} (global, neck, jaw, eyes)",
                    model.num_joints()
                ),
            ));
        }
        let frames = vhap::load_transforms(path)?;
        if let Some(i) = frames.iter().position(|f| f.flame_param.is_none()) {
            return Err(Error::invalid(
                what,
                format!("frames[{i}].flame_param_path"),
                "missing; every frame needs its FLAME parameters",
            ));
        }
        if let Some(e) = report(&what, &check_paths(path, &frames, paths)) {
            return Err(e);
        }
        let identity = Arc::new(Identity::of_transforms(path)?.fit(&model)?);
        Ok(HeadDataset {
            transforms: path.to_path_buf(),
            frames,
            model,
            identity,
            cache: Some(Mutex::default()),
            refined: None,
            mask_warned: Default::default(),
        })
    }

    /// Poses every frame with `identity` instead of the export's own (e.g. a trained
    /// avatar's subject when evaluating another export of it).
    pub fn with_identity(mut self, identity: &Identity) -> Result<Self> {
        self.identity = Arc::new(identity.fit(&self.model)?);
        if let Some(cache) = &self.cache {
            lock(cache).clear();
        }
        Ok(self)
    }

    /// The subject every frame is posed with (fitted to the model).
    pub fn identity(&self) -> &Identity {
        &self.identity
    }

    /// Turns the per-timestep cache on (the default) or off. The cache keeps one
    /// [`Conditioning`] per `flame_param` file: about 12 V bytes (60 KB for FLAME's 5023
    /// vertices) per timestep.
    pub fn with_cache(mut self, on: bool) -> Self {
        self.cache = on.then(Mutex::default);
        self
    }

    /// The `transforms_*.json` this dataset reads.
    pub fn transforms_path(&self) -> &Path {
        &self.transforms
    }

    /// The frames, in the JSON's order (item `i` is frame `i`).
    pub fn frames(&self) -> &[VhapFrame] {
        &self.frames
    }

    /// The head model.
    pub fn model(&self) -> &Arc<HeadModel> {
        &self.model
    }

    /// Number of frames.
    pub fn len(&self) -> usize {
        self.frames.len()
    }

    /// Whether the split has no frames.
    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    fn frame(&self, index: usize) -> Result<&VhapFrame> {
        self.frames.get(index).ok_or_else(|| {
            Error::invalid(
                self.transforms.display().to_string(),
                "frames",
                format!("index {index} is past the {} frames", self.frames.len()),
            )
        })
    }

    /// Frame `index`'s `flame_param` file (`from_transforms` refuses frames without one;
    /// the error is for an index past the end).
    fn flame_param(&self, index: usize) -> Result<&PathBuf> {
        self.frame(index)?.flame_param.as_ref().ok_or_else(|| {
            Error::invalid(
                self.transforms.display().to_string(),
                format!("frames[{index}].flame_param_path"),
                "missing",
            )
        })
    }

    /// Frame `index`'s `flame_param_path` relative to the transforms file's folder, as the
    /// JSON writes it (the key of its timestep in FLAME refinement).
    pub fn flame_key(&self, index: usize) -> Result<String> {
        let path = self.flame_param(index)?;
        let dir = self.transforms.parent().unwrap_or(Path::new(""));
        Ok(path
            .strip_prefix(dir)
            .unwrap_or(path)
            .to_string_lossy()
            .replace('\\', "/"))
    }

    /// Poses the timesteps that `refined` holds with its (refined) parameters instead of
    /// the tracked ones (its shape and static offsets included); the others keep theirs.
    /// Evaluation uses it for a split that shares timesteps with training (novel view), as
    /// GaussianAvatars' `render.py` does with the `flame_param.npz` of a trained model.
    pub fn with_refined(mut self, refined: Arc<crate::data::refined::RefinedParams>) -> Self {
        self.refined = Some(refined);
        if let Some(cache) = &self.cache {
            lock(cache).clear();
        }
        self
    }

    /// Reads frame `index`: image, mask, camera and the timestep's conditioning. Errors name
    /// the file and the field at fault (an index past the end names the JSON's `frames`).
    pub fn load_item(&self, index: usize) -> Result<HeadItem> {
        let frame = self.frame(index)?;
        let json = self.transforms.display().to_string();
        let (w, h) = (frame.camera.width, frame.camera.height);
        let expect = Expected {
            json: &json,
            index,
            width: w,
            height: h,
        };
        let image = read_png(&frame.image, &expect, "file_path", "image")?;
        let image = if image.color().has_alpha() {
            image
                .to_rgba32f()
                .into_raw()
                .chunks_exact(4)
                .flat_map(|p| {
                    let a = p[3];
                    [0, 1, 2].map(|c| p[c] * a + (1.0 - a))
                })
                .collect()
        } else {
            image.to_rgb32f().into_raw()
        };
        let mask = match &frame.mask {
            Some(path) if path.exists() => read_png(path, &expect, "fg_mask_path", "mask")?
                .to_luma32f()
                .into_raw(),
            Some(path) => {
                if !self
                    .mask_warned
                    .swap(true, std::sync::atomic::Ordering::Relaxed)
                {
                    eprintln!(
                        "{json}: frames[{index}].fg_mask_path {} does not exist; frames \
                         without a mask file use no mask (reported once)",
                        path.display()
                    );
                }
                vec![1.0; w as usize * h as usize]
            }
            None => vec![1.0; w as usize * h as usize],
        };
        let cond = self.conditioning(index)?;
        Ok(HeadItem {
            image,
            mask,
            camera: frame.camera,
            timestep: frame.timestep,
            camera_index: frame.camera_index,
            image_path: frame.image.clone(),
            expr: cond.expr.clone(),
            pose: cond.pose,
            eta: cond.eta.clone(),
            translation: cond.translation,
            vertices: cond.vertices.clone(),
            flame_key: self.flame_key(index)?,
        })
    }

    /// The conditioning and posed vertices of frame `index`'s timestep (from the cache when
    /// it is on and holds them).
    pub fn conditioning(&self, index: usize) -> Result<Arc<Conditioning>> {
        let path = self.flame_param(index)?;
        if let Some(cache) = &self.cache
            && let Some(c) = lock(cache).get(path)
        {
            return Ok(c.clone());
        }
        let refined = match &self.refined {
            Some(r) => r.get(&self.flame_key(index)?).cloned(),
            None => None,
        };
        let c = Arc::new(match refined {
            Some(pose) => {
                let what = path.display().to_string();
                pose_conditioning(&self.model, pose, vhap::load_eta(path)?, &what)?
            }
            None => load_conditioning(&self.model, &self.identity, path)?,
        });
        if let Some(cache) = &self.cache {
            lock(cache).insert(path.clone(), c.clone());
        }
        Ok(c)
    }
}

type Cache = Mutex<HashMap<PathBuf, Arc<Conditioning>>>;

/// Locks the cache; a worker that panicked while holding the lock leaves a usable map.
fn lock(m: &Cache) -> std::sync::MutexGuard<'_, HashMap<PathBuf, Arc<Conditioning>>> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// Reads a timestep's FLAME parameters and eta, and poses the model with the subject's
/// `identity` (already fitted to the model).
fn load_conditioning(model: &HeadModel, identity: &Identity, path: &Path) -> Result<Conditioning> {
    let what = path.display().to_string();
    let mut pose = HeadPose::load_npz(path)?;
    pose.shape.clone_from(&identity.shape);
    pose.static_offset.clone_from(&identity.static_offset);
    let eta = vhap::load_eta(path)?;
    pose_conditioning(model, pose, eta, &what)
}

/// The conditioning of FLAME parameters `pose` with `eta` (128 values): expression
/// coefficients fitted to the model (zero-padded or truncated) and the posed vertices.
/// Errors name `what` (the parameters' source).
pub fn pose_conditioning(
    model: &HeadModel,
    mut pose: HeadPose,
    eta: Vec<f32>,
    what: &str,
) -> Result<Conditioning> {
    if eta.len() != ETA_DIM {
        return Err(Error::invalid(
            what,
            "eta",
            format!("{} values, expected {ETA_DIM}", eta.len()),
        ));
    }
    pose.expr.resize(model.num_expr, 0.0);
    let vertices = lbs(model, &pose).map_err(|e| match e {
        // `lbs` names its input "head pose"; name the source instead.
        Error::Invalid { field, why, .. } => Error::invalid(what, field, why),
        other => other,
    })?;
    Ok(Conditioning {
        pose: pose.pose15(),
        translation: pose.translation,
        expr: pose.expr,
        eta,
        vertices,
    })
}

/// What an image of frame `index` of `json` must look like.
struct Expected<'a> {
    json: &'a str,
    index: usize,
    width: u32,
    height: u32,
}

/// Reads and decodes a PNG named by frame field `field`, and checks its size. `kind`
/// (`image` or `mask`) is the field named when the file's content is at fault.
fn read_png(
    path: &Path,
    expect: &Expected,
    field: &str,
    kind: &str,
) -> Result<image::DynamicImage> {
    let bytes = std::fs::read(path).map_err(|e| {
        Error::invalid(
            expect.json,
            format!("frames[{}].{field}", expect.index),
            format!("cannot read {}: {e}", path.display()),
        )
    })?;
    let what = path.display().to_string();
    let image = image::ImageReader::new(Cursor::new(bytes))
        .with_guessed_format()
        .map_err(|e| Error::io(path, e))?
        .decode()
        .map_err(|e| Error::invalid(&what, kind, format!("not a readable PNG: {e}")))?;
    if (image.width(), image.height()) != (expect.width, expect.height) {
        return Err(Error::invalid(
            &what,
            "size",
            format!(
                "{}x{} pixels, but frames[{}] of {} has w = {}, h = {}",
                image.width(),
                image.height(),
                expect.index,
                expect.json,
                expect.width,
                expect.height
            ),
        ));
    }
    Ok(image)
}

/// Reads items lazily. `get` never panics, not even for an index past the end (burn's trait
/// allows a panic there): any failure, including an unreadable or malformed file, is an
/// `Err` wrapping the [`Error`] of [`HeadDataset::load_item`], whose message names the file
/// and the field.
///
/// Note: burn 0.22's single-threaded data loader does not move past a failed batch (its
/// iterator yields the same `Err` again on every `next`), so a consumer must stop at the
/// first error rather than skip it.
impl Dataset<HeadItem> for HeadDataset {
    fn get(&self, index: usize) -> std::result::Result<HeadItem, DatasetError> {
        self.load_item(index).map_err(DatasetError::new)
    }

    fn len(&self) -> usize {
        self.frames.len()
    }
}
