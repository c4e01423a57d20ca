//! `texavatars eval`: render a trained avatar on the evaluation splits and score it.
//!
//! Splits (method.md §7): `val` = novel view (the held-out camera on training frames),
//! `test` = novel expression (the held-out sequence), `free` = the FREE sequence; plus any
//! other VHAP export as an extra split (`--split NAME=PATH/transforms.json`: VHAP writes a
//! FREE sequence as an export folder of its own). Every split is posed with the avatar's
//! subject (`RUN/canonical_flame_param.npz`, written by `train`; for runs without it, each
//! export's own, see [`crate::data::identity`]). With `stride` k > 1 a split is scored on
//! `ceil(n / k)` of its n images, spread evenly over its timesteps and cameras
//! ([`crate::eval::sample::spread`]). Writes
//! `metrics.json` (means and standard deviations per split and every image's scores),
//! `table.md` (the paper's layout, mean ± standard deviation over the images),
//! `regions.md` (each split's error per face region, [`crate::eval::regions`]) and
//! `images/<split>/TTTTT_CC.png` panels (ground truth | render | error, under a header row
//! naming them, with the render's PSNR).

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use serde::Serialize;

use crate::data::{Conditioning, HeadDataset, Identity, PathPolicy, Split};
use crate::device::BackendKind;
use crate::drive::render::{check_frame, render_frame};
use crate::error::{Error, Result};
use crate::eval::regions::{REGIONS, RegionLabeler, RegionScore, RegionTally, TriangleCoverage};
use crate::eval::score::{Means, Scorer, Scores, Tally, panel, paper_table};
use crate::head::{HeadAsset, HeadPose};
use crate::io;

/// How to run [`evaluate`].
#[derive(Clone, Debug)]
pub struct EvalOptions {
    /// The export's split folder (e.g. `OUT/union` of `texavatars synth`).
    pub data: PathBuf,
    /// The training run's folder (`avatar.json`, `avatar.bpk`).
    pub run: PathBuf,
    /// Output folder.
    pub out: PathBuf,
    /// Splits to evaluate (those without a transforms file are skipped with a message).
    pub splits: Vec<Split>,
    /// Extra splits: a name and a `transforms*.json` of any VHAP export of the subject.
    pub extra: Vec<(String, PathBuf)>,
    /// The head model the avatar was trained with; default [`head_for`] `data`.
    pub head: Option<PathBuf>,
    /// Score LPIPS too (needs `texavatars weights install`).
    pub lpips: bool,
    /// Score `ceil(n / stride)` of each split's n images, spread evenly over its timesteps
    /// and cameras (1 = all).
    pub stride: usize,
    /// Panels written per split (spread over the split).
    pub panels: usize,
    /// Where to compute.
    pub backend: BackendKind,
    /// Where the datasets' files may live ([`PathPolicy`]; `--allow-outside-paths`).
    pub paths: PathPolicy,
    /// Pose every frame with its tracked parameters, ignoring the run's refined ones
    /// (`--tracked`). By default a frame of a timestep the run refined (the novel-view
    /// split's) is posed with the refined parameters, as GaussianAvatars' `render.py` does;
    /// held-out and FREE timesteps were never refined and keep their tracked ones either way.
    pub tracked: bool,
    /// Also write the render and the ground truth of each panel's frame on their own
    /// (`images/SPLIT/TTTTT_CC_{render,gt}.png`; `texavatars study` puts runs side by side).
    pub renders: bool,
}

/// One scored image.
#[derive(Clone, Debug, Serialize)]
pub struct ImageScore {
    pub split: String,
    pub timestep: usize,
    pub camera: usize,
    #[serde(flatten)]
    pub scores: Scores,
}

/// What [`evaluate`] produced.
#[derive(Clone, Debug, Serialize)]
pub struct EvalReport {
    pub means: BTreeMap<String, Means>,
    pub images: Vec<ImageScore>,
    pub table: String,
    /// Each split's error per face region ([`crate::eval::regions`]).
    pub regions: BTreeMap<String, BTreeMap<String, RegionScore>>,
    /// Each split's pixels per visible triangle.
    pub triangles: BTreeMap<String, TriangleCoverage>,
    pub seconds: f64,
}

pub use crate::data::head_for;

/// Evenly spread `count` indices of `0..n`.
fn spread(n: usize, count: usize) -> Vec<usize> {
    if n == 0 || count == 0 {
        return Vec::new();
    }
    let c = count.min(n);
    (0..c).map(|i| i * n / c).collect()
}

/// Renders and scores the splits; `progress` receives one line per split. Runs on rayon's
/// pool ([`texavatars_cpu::threads::on_pool`]), as [`crate::train::train`].
pub fn evaluate(opts: &EvalOptions, progress: &mut (dyn FnMut(&str) + Send)) -> Result<EvalReport> {
    texavatars_cpu::threads::on_pool(|| evaluate_here(opts, progress))
}

/// [`evaluate`] on the calling thread.
fn evaluate_here(opts: &EvalOptions, progress: &mut dyn FnMut(&str)) -> Result<EvalReport> {
    let start = Instant::now();
    let device = opts.backend.device();
    let head = match &opts.head {
        Some(p) => HeadAsset::load(p, None)?,
        None => head_for(&opts.data)?,
    };
    let loaded = crate::models::load(&opts.run, &head, &device)?;
    let avatar = loaded.avatar;
    let identity = match &loaded.identity {
        Some(p) => Some(Identity::load(p)?),
        None => None,
    };
    let refined = if opts.tracked {
        None
    } else {
        crate::data::refined::RefinedParams::load(&opts.run)?.map(Arc::new)
    };
    let mut splits: Vec<(String, PathBuf)> = Vec::new();
    for &split in &opts.splits {
        let path = opts.data.join(split.file_name());
        if path.exists() {
            splits.push((split.name().to_string(), path));
        } else {
            progress(&format!(
                "{split}: no {} in {}, skipped",
                split.file_name(),
                opts.data.display()
            ));
        }
    }
    for (name, path) in &opts.extra {
        if splits.iter().any(|(n, _)| n == name) {
            return Err(Error::invalid(
                "eval",
                "--split",
                format!("{name:?} is evaluated twice; give each split its own name"),
            ));
        }
        splits.push((name.clone(), path.clone()));
    }
    let scorer = Scorer::new(&device, opts.lpips)?;
    let model = Arc::new(head.model.clone());
    let neutral = match &identity {
        Some(id) => HeadPose {
            shape: id.shape.clone(),
            static_offset: id.static_offset.clone(),
            ..Default::default()
        },
        None => HeadPose::default(),
    };
    let labeler = RegionLabeler::new(&head, &neutral)?;
    let mut region_tally = RegionTally::default();
    let mut tally = Tally::default();
    let mut images = Vec::new();
    // Every split's files, before any scoring (issue 15.5).
    let mut datasets = Vec::with_capacity(splits.len());
    for (split, path) in &splits {
        let t0 = Instant::now();
        let mut ds = HeadDataset::from_transforms_with(path, model.clone(), opts.paths)?;
        if let Some(id) = &identity {
            ds = ds.with_identity(id)?;
        }
        if let Some(r) = &refined {
            ds = ds.with_refined(r.clone());
        }
        let checked = ds.check_files()?;
        progress(&format!(
            "{split}: checked {} frames and {} timesteps in {:.1} s",
            checked.frames,
            checked.timesteps,
            t0.elapsed().as_secs_f64()
        ));
        let eta = crate::data::eta::EtaFiles::scan(ds.frames())?;
        progress(&eta.line(split));
        let sources = eta.folders.values().flatten();
        if let Some(w) = crate::eta::projection::run_mismatch(sources, &opts.run, split) {
            progress(&w);
        }
        datasets.push(ds);
    }
    std::fs::create_dir_all(&opts.out).map_err(|e| Error::io(&opts.out, e))?;
    for ((split, _), ds) in splits.iter().zip(datasets) {
        let t0 = Instant::now();
        let frames: Vec<(usize, usize)> = ds
            .frames()
            .iter()
            .map(|f| (f.timestep, f.camera_index))
            .collect();
        let indices = crate::eval::sample::spread(&frames, ds.len().div_ceil(opts.stride.max(1)));
        let panel_at = spread(indices.len(), opts.panels);
        let dir = opts.out.join("images").join(split);
        if !panel_at.is_empty() {
            std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
        }
        for (k, &i) in indices.iter().enumerate() {
            let item = ds.load_item(i)?;
            let (h, w) = (item.height(), item.width());
            let (t, c) = (item.timestep, item.camera_index);
            let frame = Conditioning {
                expr: item.expr,
                pose: item.pose,
                eta: item.eta,
                translation: item.translation,
                vertices: item.vertices,
            };
            let (labels, coverage, shear) = labeler.label(&item.camera, &frame.vertices);
            region_tally.add_coverage(split, coverage, &shear);
            check_frame(
                avatar.as_ref(),
                &frame,
                &item.image_path.display().to_string(),
            )?;
            let (render, _) = render_frame(avatar.as_ref(), &frame, &item.camera, &device)?;
            let gt = item.image;
            let scores = scorer.score(&gt, &render, h, w)?;
            tally.add(split, &scores);
            region_tally.add(split, &gt, &render, &labels);
            if panel_at.binary_search(&k).is_ok() {
                let p = panel(&gt, &render, h, w, scores.psnr)?;
                let png = dir.join(format!("{t:05}_{c:02}.png"));
                io::image::write_png(&png, p.width, p.height, &p.rgb)?;
                if opts.renders {
                    let name = |kind: &str| dir.join(format!("{t:05}_{c:02}_{kind}.png"));
                    io::image::write_png(&name("render"), w, h, &render)?;
                    io::image::write_png(&name("gt"), w, h, &gt)?;
                }
            }
            images.push(ImageScore {
                split: split.clone(),
                timestep: t,
                camera: c,
                scores,
            });
        }
        let m = tally.means();
        if let Some(m) = m.get(split.as_str()) {
            progress(&format!(
                "{split}: {} images in {:.1} s: PSNR {:.2} ± {:.2} dB, SSIM {:.4} ± {:.4}{}",
                m.images,
                t0.elapsed().as_secs_f64(),
                m.psnr,
                m.psnr_std,
                m.ssim,
                m.ssim_std,
                m.lpips_alex.map_or(String::new(), |l| format!(
                    ", LPIPS {l:.4} ± {:.4}",
                    m.lpips_alex_std.unwrap_or(0.0)
                ))
            ));
        }
    }
    let means = tally.means();
    let table = paper_table(&means);
    let regions = region_tally.scores();
    let triangles = region_tally.coverage();
    let report = EvalReport {
        means,
        images,
        table,
        regions,
        triangles,
        seconds: start.elapsed().as_secs_f64(),
    };
    let json = serde_json::to_string_pretty(&report)
        .map_err(|e| Error::invalid("evaluation", "json", e.to_string()))?;
    let path = opts.out.join("metrics.json");
    std::fs::write(&path, json).map_err(|e| Error::io(&path, e))?;
    let path = opts.out.join("table.md");
    std::fs::write(&path, &report.table).map_err(|e| Error::io(&path, e))?;
    let path = opts.out.join("regions.md");
    let md = regions_table(&report.regions) + "\n" + &triangles_table(&report.triangles);
    std::fs::write(&path, md).map_err(|e| Error::io(&path, e))?;
    Ok(report)
}

/// Each split's pixels per visible triangle as Markdown.
pub fn triangles_table(triangles: &BTreeMap<String, TriangleCoverage>) -> String {
    let mut s = String::from(
        "| split | images | visible triangles per image | pixels covered per image | pixels per visible triangle | shear median / 90th / 99th percentile | pixels with shear over 10 % |\n|---|---|---|---|---|---|---|\n",
    );
    for (split, t) in triangles {
        s += &format!(
            "| {split} | {} | {:.0} | {:.0} | {:.2} | {:.3} / {:.3} / {:.3} | {:.4} |\n",
            t.images,
            t.visible_faces,
            t.covered_pixels,
            t.pixels_per_triangle,
            t.shear_median,
            t.shear_p90,
            t.shear_p99,
            t.shear_over_10pct
        );
    }
    s += "\nA triangle is visible where it is the nearest face at one pixel centre or more of the posed mesh (`texavatars::mesh::raster`). Shear: the covered pixels' face `ln(σ1 / σ2)` against the neutral head, the in-plane deformation GaussianAvatars' frame `k R` cannot follow and the Jacobian does (`texavatars::eval::regions`); over 10 %: `σ1 / σ2 > 1.1`.\n";
    s
}

/// Each split's error per face region as Markdown: PSNR of the region's pooled pixels, its
/// share of the pixels and of the squared error.
pub fn regions_table(regions: &BTreeMap<String, BTreeMap<String, RegionScore>>) -> String {
    let mut s = String::from(
        "| split | region | PSNR | pixels | share of pixels | share of squared error |\n|---|---|---|---|---|---|\n",
    );
    for (split, r) in regions {
        for name in REGIONS {
            if let Some(x) = r.get(name) {
                s += &format!(
                    "| {split} | {name} | {} | {} | {:.3} | {:.3} |\n",
                    x.psnr.map_or("-".into(), |p| format!("{p:.2}")),
                    x.pixels,
                    x.pixel_share,
                    x.error_share
                );
            }
        }
    }
    s += "\nRegions: `texavatars::eval::regions` (docs/evaluation.md). PSNR is over the region's pixels pooled over the split's scored images.\n";
    s
}
