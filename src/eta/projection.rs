//! The projection from image features to the 128 eta values: principal components of the
//! training split's features, on one common scale.
//!
//! Fitted on the `N` training timesteps' feature vectors `f` ([`super::features`]), which
//! come in blocks (one per VGG tap and camera):
//!
//! - each feature is centred and each block scaled as a whole:
//!   `z = (f - mean) / scale`, `scale` the root mean square over the block of its features'
//!   standard deviations over the `N` (1 for a constant block), so that every tap weighs
//!   the same whatever its channel count and activation level, and no feature that is
//!   nearly constant on the training frames is magnified;
//! - the components `v_k` are the leading eigenvectors of the `z`s' covariance (through the
//!   `N x N` Gram matrix, as `N` is far below the feature count);
//! - `eta_k = (z . v_k) / sqrt(mean(lambda))`, one scale for every component (the mean over
//!   the kept components' eigenvalues): over the training timesteps the values are
//!   uncorrelated, with mean 0 and mean variance 1, and each component keeps its share of
//!   the variance. Whitening each component instead (`/ sqrt(lambda_k)`) would divide
//!   frames outside the training set by the smallest eigenvalues: their codes would be
//!   dominated by the weakest directions.
//!
//! At most `min(128, N - 1)` components carry variance; the rest (and any with
//! `lambda_k <= 1e-9 lambda_1`) are zero rows, so their eta values are 0.
//!
//! Saved as one safetensors file ([`FILE_NAME`]): `mean`, `scale` `[D]` (the block's scale
//! repeated per feature), `components` `[128, D]`, `whiten` `[128]` (the common
//! `1 / sqrt(mean(lambda))`, 0 for an empty row), and the [`ProjectionMeta`] as JSON in the
//! metadata under `texavatars-eta`.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use nalgebra::{DMatrix, SymmetricEigen};
use safetensors::SafeTensors;
use safetensors::tensor::{Dtype, TensorView};
use serde::{Deserialize, Serialize};

use crate::data::vhap::ETA_DIM;
use crate::error::{Error, Result};

/// The projection's file name, written at the export's root by `texavatars eta`.
pub const FILE_NAME: &str = "eta_projection.safetensors";

/// The metadata key of [`ProjectionMeta`].
const META_KEY: &str = "texavatars-eta";

/// How the codes a projection applies to were made, and what it was fitted on.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ProjectionMeta {
    /// [`super::features::NETWORK`].
    pub network: String,
    /// Side of the face crop in pixels.
    pub crop: usize,
    /// The camera indices whose features are concatenated, in order.
    pub cameras: Vec<usize>,
    /// The training split it was fitted on.
    pub fitted_on: PathBuf,
    /// Training timesteps it was fitted on.
    pub timesteps: usize,
    /// Components that carry variance (the rest of the 128 are zero).
    pub rank: usize,
    /// Fraction of the standardised features' variance each kept component explains.
    pub explained: Vec<f32>,
}

/// A fitted projection (see the module docs).
#[derive(Clone, Debug, PartialEq)]
pub struct Projection {
    /// Per-feature mean over the training timesteps, `[D]`.
    pub mean: Vec<f32>,
    /// Per-feature scale: its block's root mean square standard deviation, `[D]`.
    pub scale: Vec<f32>,
    /// Unit components, `[ETA_DIM, D]` row-major.
    pub components: Vec<f32>,
    /// The common `1 / sqrt(mean(lambda))`, `[ETA_DIM]` (0 for a zero row).
    pub whiten: Vec<f32>,
    /// How it was made.
    pub meta: ProjectionMeta,
}

impl Projection {
    /// Fits the projection to `features` (one vector per training timestep, equal lengths,
    /// made of consecutive blocks of the lengths `blocks`). `meta.rank` and
    /// `meta.explained` are filled in here. Errors name `what` when there are fewer than
    /// two vectors, their lengths differ or the blocks do not add up to them.
    pub fn fit(
        features: &[Vec<f32>],
        blocks: &[usize],
        mut meta: ProjectionMeta,
        what: &str,
    ) -> Result<Self> {
        let n = features.len();
        if n < 2 {
            return Err(Error::invalid(
                what,
                "frames",
                format!("{n} timesteps; fitting the eta projection needs at least 2"),
            ));
        }
        let d = features[0].len();
        if let Some(i) = features.iter().position(|f| f.len() != d) {
            return Err(Error::invalid(
                what,
                "features",
                format!(
                    "timestep {i} has {} values, the first {d}",
                    features[i].len()
                ),
            ));
        }
        let mut mean = vec![0.0f64; d];
        for f in features {
            for (m, &v) in mean.iter_mut().zip(f) {
                *m += f64::from(v);
            }
        }
        mean.iter_mut().for_each(|m| *m /= n as f64);
        let mut var = vec![0.0f64; d];
        for f in features {
            for ((s, &v), m) in var.iter_mut().zip(f).zip(&mean) {
                *s += (f64::from(v) - m).powi(2);
            }
        }
        if blocks.iter().sum::<usize>() != d {
            return Err(Error::invalid(
                what,
                "features",
                format!("{d} values, blocks {blocks:?}"),
            ));
        }
        let mut scale = Vec::with_capacity(d);
        let mut at = 0;
        for &b in blocks {
            let ms = var[at..at + b].iter().sum::<f64>() / ((n - 1) * b.max(1)) as f64;
            let s = if ms.sqrt() > 1e-12 { ms.sqrt() } else { 1.0 };
            scale.extend(std::iter::repeat_n(s, b));
            at += b;
        }
        // Standardised features, N x D.
        let z: Vec<Vec<f64>> = features
            .iter()
            .map(|f| {
                f.iter()
                    .zip(&mean)
                    .zip(&scale)
                    .map(|((&v, m), s)| (f64::from(v) - m) / s)
                    .collect()
            })
            .collect();
        let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
        let gram = DMatrix::from_fn(n, n, |i, j| dot(&z[i], &z[j]) / (n - 1) as f64);
        let total: f64 = (0..n).map(|i| gram[(i, i)]).sum();
        let eig = SymmetricEigen::new(gram);
        let mut order: Vec<usize> = (0..n).collect();
        order.sort_by(|&a, &b| eig.eigenvalues[b].total_cmp(&eig.eigenvalues[a]));
        let top = eig.eigenvalues[order[0]].max(0.0);
        let mut components = vec![0.0f32; ETA_DIM * d];
        let mut whiten = vec![0.0f32; ETA_DIM];
        let mut explained = Vec::new();
        let mut kept: Vec<f64> = Vec::new();
        for (k, &o) in order.iter().take(ETA_DIM.min(n - 1)).enumerate() {
            let lambda = eig.eigenvalues[o];
            if !(lambda > 1e-9 * top && lambda > 0.0) {
                break;
            }
            // v_k = Z^T u_k / sqrt((N - 1) lambda_k): unit length.
            let u = eig.eigenvectors.column(o);
            let norm = ((n - 1) as f64 * lambda).sqrt();
            let row = &mut components[k * d..(k + 1) * d];
            for (i, zi) in z.iter().enumerate() {
                let w = u[i] / norm;
                for (r, &zv) in row.iter_mut().zip(zi) {
                    *r += (w * zv) as f32;
                }
            }
            kept.push(lambda);
            explained.push((lambda / total.max(1e-300)) as f32);
        }
        if !kept.is_empty() {
            let common = 1.0 / (kept.iter().sum::<f64>() / kept.len() as f64).sqrt();
            whiten[..kept.len()].fill(common as f32);
        }
        meta.rank = explained.len();
        meta.explained = explained;
        Ok(Projection {
            mean: mean.iter().map(|&v| v as f32).collect(),
            scale: scale.iter().map(|&v| v as f32).collect(),
            components,
            whiten,
            meta,
        })
    }

    /// Features per code.
    pub fn dims(&self) -> usize {
        self.mean.len()
    }

    /// The eta code of one feature vector (`[D]` in, [`ETA_DIM`] out).
    pub fn apply(&self, features: &[f32]) -> Vec<f32> {
        let z: Vec<f64> = features
            .iter()
            .zip(&self.mean)
            .zip(&self.scale)
            .map(|((&v, m), s)| (f64::from(v) - f64::from(*m)) / f64::from(*s))
            .collect();
        let d = self.dims();
        (0..ETA_DIM)
            .map(|k| {
                let row = &self.components[k * d..(k + 1) * d];
                let p: f64 = row.iter().zip(&z).map(|(&c, v)| f64::from(c) * v).sum();
                (p * f64::from(self.whiten[k])) as f32
            })
            .collect()
    }

    /// The safetensors bytes of the file (see the module docs).
    pub fn to_bytes(&self) -> Result<Vec<u8>> {
        let what = FILE_NAME;
        let d = self.dims();
        let le = |v: &[f32]| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
        let tensors = [
            ("mean", vec![d], le(&self.mean)),
            ("scale", vec![d], le(&self.scale)),
            ("components", vec![ETA_DIM, d], le(&self.components)),
            ("whiten", vec![ETA_DIM], le(&self.whiten)),
        ];
        let mut views = Vec::new();
        for (name, shape, bytes) in &tensors {
            let v = TensorView::new(Dtype::F32, shape.clone(), bytes)
                .map_err(|e| Error::invalid(what, *name, e.to_string()))?;
            views.push((name.to_string(), v));
        }
        let meta = serde_json::to_string(&self.meta).expect("serialises");
        safetensors::tensor::serialize(views, Some(HashMap::from([(META_KEY.to_string(), meta)])))
            .map_err(|e| Error::invalid(what, "safetensors", e.to_string()))
    }

    /// Reads a projection file; errors name the file and the field at fault.
    pub fn load(path: &Path) -> Result<Self> {
        let what = path.display().to_string();
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        Self::from_bytes(&bytes, &what)
    }

    /// Parses the bytes of a projection file; errors name `what`.
    pub fn from_bytes(bytes: &[u8], what: &str) -> Result<Self> {
        let (_, header) = SafeTensors::read_metadata(bytes)
            .map_err(|e| Error::invalid(what, "safetensors", e.to_string()))?;
        let meta_json = header
            .metadata()
            .as_ref()
            .and_then(|m| m.get(META_KEY))
            .ok_or_else(|| {
                Error::invalid(what, META_KEY, "missing: not a texavatars eta projection")
            })?;
        let meta: ProjectionMeta = serde_json::from_str(meta_json)
            .map_err(|e| Error::invalid(what, META_KEY, e.to_string()))?;
        let st = SafeTensors::deserialize(bytes)
            .map_err(|e| Error::invalid(what, "safetensors", e.to_string()))?;
        let get = |name: &str| -> Result<(Vec<usize>, Vec<f32>)> {
            let t = st
                .tensor(name)
                .map_err(|e| Error::invalid(what, name, e.to_string()))?;
            if t.dtype() != Dtype::F32 {
                return Err(Error::invalid(
                    what,
                    name,
                    format!("{:?}, expected F32", t.dtype()),
                ));
            }
            let v = t
                .data()
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect();
            Ok((t.shape().to_vec(), v))
        };
        let (ms, mean) = get("mean")?;
        let d = mean.len();
        let (ss, scale) = get("scale")?;
        let (cs, components) = get("components")?;
        let (ws, whiten) = get("whiten")?;
        for (name, got, want) in [
            ("mean", ms, vec![d]),
            ("scale", ss, vec![d]),
            ("components", cs, vec![ETA_DIM, d]),
            ("whiten", ws, vec![ETA_DIM]),
        ] {
            if got != want {
                return Err(Error::invalid(
                    what,
                    name,
                    format!("shape {got:?}, expected {want:?}"),
                ));
            }
        }
        let bad = |v: &[f32]| v.iter().any(|x| !x.is_finite());
        if bad(&mean)
            || bad(&scale)
            || bad(&components)
            || bad(&whiten)
            || scale.iter().any(|&s| s <= 0.0)
        {
            return Err(Error::invalid(
                what,
                "tensors",
                "not finite, or a scale <= 0",
            ));
        }
        Ok(Projection {
            mean,
            scale,
            components,
            whiten,
            meta,
        })
    }
}

/// Copies the projection that the image codes of `frames` were made with into `out` (as
/// [`FILE_NAME`]), so that a trained run carries it for coding the captures that will
/// drive it. Nothing happens when the codes are not image codes, or come from more than one
/// projection (a warning says so); a projection file that no longer matches its recorded
/// identity is not copied (a warning says so). Returns the copy's path.
pub fn copy_for_run(
    frames: &[crate::data::vhap::VhapFrame],
    out: &Path,
) -> Result<Option<PathBuf>> {
    let files = crate::data::eta::EtaFiles::scan(frames)?;
    let sources: Vec<&crate::data::eta::EtaSource> = files.folders.values().flatten().collect();
    let Some(first) = sources.first() else {
        return Ok(None);
    };
    if sources
        .iter()
        .any(|s| s.projection_id != first.projection_id)
    {
        eprintln!(
            "warning: the training split's eta codes come from several projections ({:?}); none is copied into the run",
            files.projection_ids()
        );
        return Ok(None);
    }
    let bytes = match std::fs::read(&first.projection) {
        Ok(b) => b,
        Err(e) => {
            eprintln!(
                "warning: the eta projection {} ({}) cannot be read ({e}); not copied into the run",
                first.projection.display(),
                first.projection_id
            );
            return Ok(None);
        }
    };
    if crate::data::eta::fnv1a_hex(&bytes) != first.projection_id {
        eprintln!(
            "warning: {} is no longer the projection {} the eta codes were made with; not copied into the run",
            first.projection.display(),
            first.projection_id
        );
        return Ok(None);
    }
    let dest = out.join(FILE_NAME);
    crate::util::files::write_atomic(&dest, &bytes)?;
    Ok(Some(dest))
}

/// A warning when image codes were made with another projection than the one a trained
/// run carries (`run/eta_projection.safetensors`, [`copy_for_run`]): the avatar would be
/// driven by codes in another basis. `None` when they agree, or when either side has none
/// to compare.
pub fn run_mismatch<'a>(
    sources: impl IntoIterator<Item = &'a crate::data::eta::EtaSource>,
    run: &Path,
    what: &str,
) -> Option<String> {
    let bytes = std::fs::read(run.join(FILE_NAME)).ok()?;
    let own = crate::data::eta::fnv1a_hex(&bytes);
    let other: std::collections::BTreeSet<&str> = sources
        .into_iter()
        .map(|s| s.projection_id.as_str())
        .filter(|id| *id != own)
        .collect();
    (!other.is_empty()).then(|| {
        format!(
            "warning: {what}: its eta codes were made with projection {other:?}, the avatar was \
             trained with {own}; code the capture with `texavatars eta --projection {}`",
            run.join(FILE_NAME).display()
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::util::rng::Pcg;

    fn meta() -> ProjectionMeta {
        ProjectionMeta {
            network: "test".into(),
            crop: 8,
            cameras: vec![3],
            fitted_on: PathBuf::from("transforms_train.json"),
            timesteps: 0,
            rank: 0,
            explained: Vec::new(),
        }
    }

    /// `n` feature vectors of length `d` from 3 latent factors of unequal strength, plus a
    /// little noise, and two nearly constant features.
    fn low_rank(r: &mut Pcg, mix: &[f32], n: usize, d: usize) -> Vec<Vec<f32>> {
        (0..n)
            .map(|_| {
                let l = [3.0 * r.normal(), r.normal(), 0.5 * r.normal()];
                (0..d)
                    .map(|j| {
                        let noise = if j < 2 { 1e-7 } else { 0.01 };
                        let signal: f32 = if j < 2 {
                            0.0
                        } else {
                            (0..3).map(|k| l[k] * mix[k * d + j]).sum()
                        };
                        2.0 + signal + noise * r.normal()
                    })
                    .collect()
            })
            .collect()
    }

    /// On the fitting set the codes are uncorrelated, centred, with mean variance 1 over the
    /// components, which keep their order of strength.
    #[test]
    fn fit_decorrelates_on_one_scale() {
        let mut r = Pcg::new(5);
        let (n, d) = (40, 30);
        let mix: Vec<f32> = (0..3 * d).map(|_| r.normal()).collect();
        let feats = low_rank(&mut r, &mix, n, d);
        let p = Projection::fit(&feats, &[10, 20], meta(), "test").expect("fit");
        let total: f32 = p.meta.explained.iter().sum();
        assert!((total - 1.0).abs() < 1e-4, "{total}");
        assert!(
            p.meta.explained[0] > 0.5 && p.meta.explained[3] < 0.01,
            "{:?}",
            p.meta.explained
        );
        let k = p.meta.rank;
        let codes: Vec<Vec<f32>> = feats.iter().map(|f| p.apply(f)).collect();
        let cov =
            |a: usize, b: usize| codes.iter().map(|c| c[a] * c[b]).sum::<f32>() / (n - 1) as f32;
        for a in 0..ETA_DIM {
            let mean: f32 = codes.iter().map(|c| c[a]).sum::<f32>() / n as f32;
            assert!(mean.abs() < 1e-3, "component {a}: mean {mean}");
            for b in 0..a {
                assert!(cov(a, b).abs() < 2e-3, "cov[{a}][{b}] = {}", cov(a, b));
            }
        }
        let mean_var = (0..k).map(|a| cov(a, a)).sum::<f32>() / k as f32;
        assert!((mean_var - 1.0).abs() < 1e-3, "{mean_var}");
        assert!(cov(0, 0) > cov(1, 1) && cov(1, 1) > cov(2, 2));
        assert!(codes.iter().all(|c| c[k..].iter().all(|v| *v == 0.0)));
        // Round trip through the file format.
        let back = Projection::from_bytes(&p.to_bytes().expect("bytes"), "mem").expect("read");
        assert_eq!(back, p);
        let e = Projection::from_bytes(b"not safetensors", "x.safetensors").expect_err("junk");
        assert!(e.to_string().contains("x.safetensors"), "{e}");
    }

    /// New frames from the same distribution get codes of the training codes' size: neither
    /// the nearly constant features nor the weakest components are magnified.
    #[test]
    fn new_frames_get_codes_of_the_same_size() {
        let mut r = Pcg::new(9);
        let (n, d) = (40, 30);
        let mix: Vec<f32> = (0..3 * d).map(|_| r.normal()).collect();
        let feats = low_rank(&mut r, &mix, n, d);
        let p = Projection::fit(&feats, &[d], meta(), "test").expect("fit");
        let rms = |fs: &[Vec<f32>]| {
            let s: f32 = fs
                .iter()
                .map(|f| p.apply(f).iter().map(|v| v * v).sum::<f32>())
                .sum();
            (s / fs.len() as f32).sqrt()
        };
        let fresh = low_rank(&mut r, &mix, 200, d);
        let (seen, new) = (rms(&feats), rms(&fresh));
        assert!(new < 1.5 * seen, "new frames {new}, training frames {seen}");
    }

    #[test]
    fn fit_needs_two_equal_vectors() {
        let e = Projection::fit(&[vec![1.0]], &[1], meta(), "train.json").expect_err("one");
        assert!(e.to_string().contains("train.json") && e.to_string().contains("at least 2"));
        let e = Projection::fit(&[vec![1.0], vec![1.0, 2.0]], &[1], meta(), "train.json")
            .expect_err("ragged");
        assert!(e.to_string().contains("timestep 1"), "{e}");
    }
}
