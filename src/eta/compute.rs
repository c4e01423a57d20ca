//! `texavatars eta`: every timestep's code of an export, written as its eta side files.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use glam::{Quat, Vec3};

use crate::data::eta::{EtaSource, SOURCE_FILE, fnv1a_hex};
use crate::data::vhap::{ETA_DIM, eta_path};
use crate::data::{HeadDataset, Split};
use crate::error::{Error, Result};
use crate::eta::crop::{crop, head_box};
use crate::eta::features::{self, Extractor, NETWORK};
use crate::eta::projection::{FILE_NAME, Projection, ProjectionMeta};
use crate::head::HeadAsset;

/// Default side of the face crop in pixels.
pub const CROP: usize = 128;

/// What `texavatars eta` computes and where it writes.
#[derive(Clone, Debug)]
pub struct EtaOptions {
    /// The export: `transforms_{train,val,test}.json` (and `transforms_free.json`) at its
    /// root, each present split coded; else a single sequence's `transforms.json` (which
    /// needs `projection`).
    pub data: PathBuf,
    /// More splits to code, `(name, transforms file)` (e.g. a FREE sequence's export).
    pub splits: Vec<(String, PathBuf)>,
    /// Camera indices whose images the codes see; empty: the most frontal camera of the
    /// training split ([`frontal_camera`]). With `projection`, the projection's own.
    pub cameras: Vec<usize>,
    /// Apply this projection instead of fitting one on `data`'s training split (another
    /// subject's, for cross-reenactment; a FREE export of the same subject).
    pub projection: Option<PathBuf>,
    /// Head model that poses the tracked meshes; default [`crate::data::head_for`].
    pub head: Option<PathBuf>,
    /// Overwrite eta files and a projection file that exist.
    pub force: bool,
    /// Side of the face crop ([`CROP`]); with `projection`, the projection's own.
    pub crop: usize,
    /// Timesteps per feature batch.
    pub batch: usize,
}

impl EtaOptions {
    /// Defaults for `data`: every split, frontal camera, fit, no overwriting.
    pub fn new(data: &Path) -> Self {
        EtaOptions {
            data: data.to_path_buf(),
            splits: Vec::new(),
            cameras: Vec::new(),
            projection: None,
            head: None,
            force: false,
            crop: CROP,
            batch: 8,
        }
    }
}

/// What `eta` did.
#[derive(Clone, Debug, PartialEq)]
pub struct EtaReport {
    /// The projection applied (written here when `fitted`).
    pub projection: PathBuf,
    /// Its identity ([`fnv1a_hex`] of the file).
    pub projection_id: String,
    /// Whether it was fitted by this call (on the training split).
    pub fitted: bool,
    /// Components that carry variance.
    pub rank: usize,
    /// The cameras the codes see.
    pub cameras: Vec<usize>,
    /// Timesteps coded per split (a timestep in two splits counts in both).
    pub timesteps: BTreeMap<String, usize>,
    /// Eta files written.
    pub written: usize,
    /// Wall time.
    pub seconds: f64,
}

/// One timestep of the export and the frames that show it.
struct Step {
    /// Its `flame_param` path as the first split names it (the eta file goes next to it).
    param: PathBuf,
    splits: BTreeSet<String>,
    /// camera index -> (dataset, frame index).
    frames: BTreeMap<usize, (usize, usize)>,
}

/// Computes and writes the eta side files of every timestep of `opts.data`'s splits (see
/// [`crate::eta`]); `progress` receives one line per stage. Runs on rayon's pool.
pub fn compute(
    opts: &EtaOptions,
    extractor: &Extractor,
    progress: &mut (dyn FnMut(&str) + Send),
) -> Result<EtaReport> {
    texavatars_cpu::threads::on_pool(|| compute_here(opts, extractor, progress))
}

fn compute_here(
    opts: &EtaOptions,
    extractor: &Extractor,
    progress: &mut dyn FnMut(&str),
) -> Result<EtaReport> {
    let start = Instant::now();
    let head = match &opts.head {
        Some(p) => HeadAsset::load(p, None)?,
        None => crate::data::head_for(&opts.data)?,
    };
    let model = Arc::new(head.model.clone());
    let mut named: Vec<(String, PathBuf)> = Split::ALL
        .iter()
        .map(|s| (s.name().to_string(), opts.data.join(s.file_name())))
        .filter(|(_, p)| p.exists())
        .collect();
    // A single sequence's export (a FREE sequence): its `transforms.json`.
    let single = opts.data.join("transforms.json");
    if named.is_empty() && single.is_file() {
        named.push(("transforms".to_string(), single));
    }
    for (name, path) in &opts.splits {
        if named.iter().any(|(n, _)| n == name) {
            return Err(Error::invalid(
                "eta",
                "--split",
                format!("split {name} given twice"),
            ));
        }
        named.push((name.clone(), path.clone()));
    }
    if named.is_empty() {
        return Err(Error::invalid(
            opts.data.display().to_string(),
            "transforms_*.json",
            "no split found (transforms_train.json, _val, _test, _free, or a sequence's transforms.json); is this an export's root?",
        ));
    }
    let sets: Vec<(String, HeadDataset)> = named
        .iter()
        .map(|(n, p)| Ok((n.clone(), HeadDataset::from_transforms(p, model.clone())?)))
        .collect::<Result<_>>()?;
    let steps = timesteps(&sets)?;

    // The projection: given, or fitted on the training split.
    let given = match &opts.projection {
        Some(p) => Some((p.clone(), Projection::load(p)?)),
        None => None,
    };
    let train = sets.iter().position(|(n, _)| n == Split::Train.name());
    let (cameras, size) = match &given {
        Some((path, p)) => {
            if !opts.cameras.is_empty() && opts.cameras != p.meta.cameras {
                return Err(Error::invalid(
                    "eta",
                    "--camera",
                    format!(
                        "{:?}, but the projection {} was fitted on cameras {:?}; codes must see \
                         the cameras their projection was fitted on",
                        opts.cameras,
                        path.display(),
                        p.meta.cameras
                    ),
                ));
            }
            (p.meta.cameras.clone(), p.meta.crop)
        }
        None => {
            let Some(t) = train else {
                return Err(Error::invalid(
                    opts.data.display().to_string(),
                    "transforms_train.json",
                    "missing: the projection is fitted on the training split; give one fitted \
                     elsewhere with --projection (e.g. the training export's eta_projection.safetensors)",
                ));
            };
            let cams = if opts.cameras.is_empty() {
                vec![frontal_camera(&sets[t].1)?]
            } else {
                opts.cameras.clone()
            };
            (cams, opts.crop)
        }
    };
    if size < 32 {
        return Err(Error::invalid(
            "eta",
            "crop",
            format!("{size} pixels; at least 32"),
        ));
    }
    let projection_path = match &given {
        Some((p, _)) => p.clone(),
        None => opts.data.join(FILE_NAME),
    };

    // Refuse before anything is written.
    let targets: Vec<PathBuf> = steps.iter().map(|s| eta_path(&s.param)).collect();
    if !opts.force {
        let existing: Vec<&PathBuf> = targets.iter().filter(|p| p.exists()).collect();
        if let Some(first) = existing.first() {
            return Err(Error::invalid(
                first.display().to_string(),
                "file",
                format!(
                    "exists ({} of the {} eta files do); --force overwrites them",
                    existing.len(),
                    targets.len()
                ),
            ));
        }
        if given.is_none() && projection_path.exists() {
            return Err(Error::invalid(
                projection_path.display().to_string(),
                "file",
                "exists; --force fits and overwrites it, --projection applies it",
            ));
        }
    }
    for s in &steps {
        for c in &cameras {
            if !s.frames.contains_key(c) {
                return Err(Error::invalid(
                    s.param.display().to_string(),
                    "camera_index",
                    format!(
                        "no frame of camera {c} shows this timestep (splits {:?}); every \
                         timestep needs an image of each camera the codes see (--camera)",
                        s.splits
                    ),
                ));
            }
        }
    }
    progress(&format!(
        "eta: {} timesteps over {} splits, cameras {cameras:?}, {size} x {size} face crops, {NETWORK}",
        steps.len(),
        sets.len()
    ));

    // Features of every timestep.
    let mut feats: Vec<Vec<f32>> = Vec::with_capacity(steps.len());
    let batch = opts.batch.max(1);
    for chunk in steps.chunks(batch) {
        let mut crops = Vec::with_capacity(chunk.len() * cameras.len());
        for s in chunk {
            for c in &cameras {
                let (d, i) = s.frames[c];
                crops.push(face_crop(&sets[d].1, i, size)?);
            }
        }
        let f = extractor.features(&crops, size);
        for per_step in f.chunks(cameras.len()) {
            feats.push(per_step.concat());
        }
        if feats.len() % (batch * 8) < batch || feats.len() == steps.len() {
            progress(&format!(
                "eta: features of {}/{} timesteps",
                feats.len(),
                steps.len()
            ));
        }
    }

    let (projection, bytes, fitted) = match given {
        Some((_, p)) => {
            if p.dims() != features::dims() * cameras.len() {
                return Err(Error::invalid(
                    projection_path.display().to_string(),
                    "mean",
                    format!(
                        "{} features, the codes have {}",
                        p.dims(),
                        features::dims() * cameras.len()
                    ),
                ));
            }
            let bytes =
                std::fs::read(&projection_path).map_err(|e| Error::io(&projection_path, e))?;
            (p, bytes, false)
        }
        None => {
            let t = train.expect("checked above");
            let train_feats: Vec<Vec<f32>> = steps
                .iter()
                .zip(&feats)
                .filter(|(s, _)| s.splits.contains(Split::Train.name()))
                .map(|(_, f)| f.clone())
                .collect();
            let fitted_on = sets[t].1.transforms_path().to_path_buf();
            let meta = ProjectionMeta {
                network: NETWORK.to_string(),
                crop: size,
                cameras: cameras.clone(),
                fitted_on: fitted_on.clone(),
                timesteps: train_feats.len(),
                rank: 0,
                explained: Vec::new(),
            };
            let blocks: Vec<usize> = cameras.iter().flat_map(|_| features::blocks()).collect();
            let p = Projection::fit(
                &train_feats,
                &blocks,
                meta,
                &fitted_on.display().to_string(),
            )?;
            let bytes = p.to_bytes()?;
            crate::util::files::write_atomic(&projection_path, &bytes)?;
            progress(&format!(
                "eta: projection fitted on {} training timesteps ({} components, first five \
                 explain {:.1}% of the variance): {}",
                p.meta.timesteps,
                p.meta.rank,
                100.0 * p.meta.explained.iter().take(5).sum::<f32>(),
                projection_path.display()
            ));
            (p, bytes, true)
        }
    };
    let projection_id = fnv1a_hex(&bytes);
    let source = EtaSource {
        kind: "image".to_string(),
        projection: projection_path.clone(),
        projection_id: projection_id.clone(),
        cameras: cameras.clone(),
        network: NETWORK.to_string(),
    };
    let mut dirs = BTreeSet::new();
    for (target, f) in targets.iter().zip(&feats) {
        let code = projection.apply(f);
        debug_assert_eq!(code.len(), ETA_DIM);
        if let Some(dir) = target.parent() {
            std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
            dirs.insert(dir.to_path_buf());
        }
        crate::io::npy::write(target, &[ETA_DIM], &code)?;
    }
    for dir in &dirs {
        let path = dir.join(SOURCE_FILE);
        let json = serde_json::to_string_pretty(&source).expect("serialises") + "\n";
        crate::util::files::write_atomic(&path, json.as_bytes())?;
    }
    let mut per_split = BTreeMap::new();
    for s in &steps {
        for n in &s.splits {
            *per_split.entry(n.clone()).or_insert(0) += 1;
        }
    }
    Ok(EtaReport {
        projection: projection_path,
        projection_id,
        fitted,
        rank: projection.meta.rank,
        cameras,
        timesteps: per_split,
        written: targets.len(),
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// The timesteps of `sets` (distinct `flame_param` files, compared as canonical paths) in
/// the order they first appear, with the frames that show each.
fn timesteps(sets: &[(String, HeadDataset)]) -> Result<Vec<Step>> {
    let mut index: BTreeMap<PathBuf, usize> = BTreeMap::new();
    let mut steps: Vec<Step> = Vec::new();
    for (d, (name, set)) in sets.iter().enumerate() {
        for (i, f) in set.frames().iter().enumerate() {
            let Some(param) = &f.flame_param else {
                continue; // refused by HeadDataset already
            };
            let key = std::fs::canonicalize(param).map_err(|e| Error::io(param, e))?;
            let k = *index.entry(key).or_insert_with(|| {
                steps.push(Step {
                    param: param.clone(),
                    splits: BTreeSet::new(),
                    frames: BTreeMap::new(),
                });
                steps.len() - 1
            });
            steps[k].splits.insert(name.clone());
            steps[k].frames.entry(f.camera_index).or_insert((d, i));
        }
    }
    Ok(steps)
}

/// The face crop of frame `index` of `set`.
fn face_crop(set: &HeadDataset, index: usize, size: usize) -> Result<Vec<f32>> {
    let item = set.load_item(index)?;
    let b = head_box(&item.camera, &item.vertices).ok_or_else(|| {
        Error::invalid(
            item.image_path.display().to_string(),
            "transform_matrix",
            "the tracked head is behind this camera: no face region",
        )
    })?;
    Ok(crop(&item.image, item.width(), item.height(), &b, size))
}

/// The camera index of `set` that looks at the face most directly: the largest mean, over
/// its frames, of the cosine between the head's forward axis (the model's +z turned by the
/// global rotation) and the camera's viewing direction reversed (the optical axis pointing
/// back at the camera).
pub fn frontal_camera(set: &HeadDataset) -> Result<usize> {
    // Up to 16 frames per camera, spread over its frames (the per-timestep meshes are
    // cached).
    let mut by_camera: BTreeMap<usize, Vec<usize>> = BTreeMap::new();
    for (i, f) in set.frames().iter().enumerate() {
        by_camera.entry(f.camera_index).or_default().push(i);
    }
    let mut score: BTreeMap<usize, (f64, usize)> = BTreeMap::new();
    for (camera, frames) in &by_camera {
        let take = frames.len().min(16);
        for k in 0..take {
            let i = frames[k * frames.len() / take];
            let f = &set.frames()[i];
            let c = set.conditioning(i)?;
            let rot = Quat::from_scaled_axis(Vec3::new(c.pose[0], c.pose[1], c.pose[2]));
            let forward = rot * Vec3::Z;
            // OpenCV world-to-camera: the optical axis in world space is the rotation's
            // third row.
            let r = f.camera.world_to_camera[2];
            let axis = Vec3::new(r[0], r[1], r[2]).normalize_or_zero();
            let e = score.entry(*camera).or_insert((0.0, 0));
            e.0 += f64::from(-forward.dot(axis));
            e.1 += 1;
        }
    }
    score
        .into_iter()
        .max_by(|a, b| (a.1.0 / a.1.1 as f64).total_cmp(&(b.1.0 / b.1.1 as f64)))
        .map(|(c, _)| c)
        .ok_or_else(|| {
            Error::invalid(
                set.transforms_path().display().to_string(),
                "frames",
                "empty: no camera to choose",
            )
        })
}
