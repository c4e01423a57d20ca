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
//!
//! With `against` (a second run of the same subject), every scored frame is rendered by
//! both runs and `against.md` (and `metrics.json`'s `against`) says where their renders
//! differ: per split and face region, the PSNR between them, the region's share of the
//! pixels and of the squared difference, and the ratio of the two shares (above 1: the
//! runs differ more there than on average). Each panel frame gets `TTTTT_CC_against.png`
//! (the other run | this run | difference), and each split's frame whose faces shear most
//! `most_sheared_TTTTT_CC_against.png`. This locates an ablation's effect: a variant
//! trained with the full method's seed differs from it through the component only, while
//! two seeds of the full method show the training's own noise.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use serde::Serialize;

use crate::data::{Conditioning, HeadDataset, Identity, PathPolicy, Split};
use crate::device::BackendKind;
use crate::drive::render::{check_frame, render_frame};
use crate::error::{Error, Result};
use crate::eval::regions::{
    REGIONS, RegionLabeler, RegionScore, RegionTally, SHEAR_10PCT, TriangleCoverage,
};
use crate::eval::score::{Means, Scorer, Scores, Tally, panel, panel_named, paper_table};
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
    /// A second run of the same subject to compare renders with (`--against`; the module
    /// docs). Both runs are posed with the same meshes: the tracked parameters, as with
    /// `tracked`, since each run refined its own.
    pub against: Option<PathBuf>,
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
    /// Where this run's renders differ from `against`'s.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub against: Option<Against>,
    pub seconds: f64,
}

/// Where two runs' renders differ (`EvalOptions::against`).
#[derive(Clone, Debug, Serialize, serde::Deserialize)]
pub struct Against {
    /// The other run.
    pub run: PathBuf,
    /// Per split and region: `psnr` between the two renders, `pixel_share`, and
    /// `error_share`, the region's share of the squared difference.
    pub regions: BTreeMap<String, BTreeMap<String, RegionScore>>,
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
    let other = match &opts.against {
        Some(path) => {
            let b = crate::models::load(path, &head, &device)?;
            let theirs = match &b.identity {
                Some(p) => Some(Identity::load(p)?),
                None => None,
            };
            same_subject(&opts.run, identity.as_ref(), path, theirs.as_ref())?;
            Some(b.avatar)
        }
        None => None,
    };
    let refined = if opts.tracked || other.is_some() {
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
    // The two runs' names for `against`'s panels.
    let names = (
        run_name(opts.against.as_deref().unwrap_or(&opts.run)),
        run_name(&opts.run),
    );
    let mut region_tally = RegionTally::default();
    let mut differ = RegionTally::default();
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
        // The frame whose faces shear most (the largest share of covered pixels with
        // σ1 / σ2 > 1.1), with both runs' renders, for `against`'s extreme-frame panel.
        let mut sheared: Option<Sheared> = None;
        let dir = opts.out.join("images").join(split);
        if !panel_at.is_empty() || other.is_some() {
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
            let on_panel = panel_at.binary_search(&k).is_ok();
            if let Some(b) = &other {
                let (theirs, _) = render_frame(b.as_ref(), &frame, &item.camera, &device)?;
                differ.add(split, &theirs, &render, &labels);
                if on_panel {
                    let png = dir.join(format!("{t:05}_{c:02}_against.png"));
                    against_panel(&png, &theirs, &render, h, w, &names)?;
                }
                let share = shear.share_above(SHEAR_10PCT);
                if sheared.as_ref().is_none_or(|s| share > s.share) {
                    sheared = Some(Sheared {
                        share,
                        name: format!("{t:05}_{c:02}"),
                        theirs,
                        render: render.clone(),
                        size: (h, w),
                    });
                }
            }
            if on_panel {
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
        if let Some(r) = differ.scores().get(split.as_str()) {
            progress(&against_line(split, r));
        }
        if let Some(s) = sheared {
            let png = dir.join(format!("most_sheared_{}_against.png", s.name));
            against_panel(&png, &s.theirs, &s.render, s.size.0, s.size.1, &names)?;
            progress(&format!(
                "{split}: the frame whose faces shear most ({:.1} % of its covered pixels over 10 %) compared in {}",
                100.0 * s.share,
                png.display()
            ));
        }
    }
    let means = tally.means();
    let table = paper_table(&means);
    let regions = region_tally.scores();
    let triangles = region_tally.coverage();
    let against = opts.against.as_ref().map(|run| Against {
        run: run.clone(),
        regions: differ.scores(),
    });
    let report = EvalReport {
        means,
        images,
        table,
        regions,
        triangles,
        against,
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
    if let Some(a) = &report.against {
        let path = opts.out.join("against.md");
        std::fs::write(&path, against_table(a)).map_err(|e| Error::io(&path, e))?;
    }
    Ok(report)
}

/// Refuses to compare runs of different subjects: their identities (shape and static
/// offsets) must agree.
fn same_subject(
    run: &Path,
    mine: Option<&Identity>,
    other: &Path,
    theirs: Option<&Identity>,
) -> Result<()> {
    let differs = match (mine, theirs) {
        (None, None) => false,
        (Some(a), Some(b)) => {
            let close = |x: &[f32], y: &[f32]| {
                x.len() == y.len() && x.iter().zip(y).all(|(p, q)| (p - q).abs() <= 1e-6)
            };
            let offsets = match (&a.static_offset, &b.static_offset) {
                (None, None) => true,
                (Some(p), Some(q)) => close(p.as_flattened(), q.as_flattened()),
                _ => false,
            };
            !(close(&a.shape, &b.shape) && offsets)
        }
        _ => true,
    };
    if differs {
        return Err(Error::invalid(
            other.display().to_string(),
            "canonical_flame_param.npz",
            format!(
                "its subject (shape, static offsets) is not {}'s: --against compares two runs of the same subject",
                run.display()
            ),
        ));
    }
    Ok(())
}

/// A split's frame whose faces shear most, with both runs' renders (`against`).
struct Sheared {
    /// Its share of covered pixels with `σ1 / σ2 > 1.1`.
    share: f64,
    /// `TTTTT_CC`.
    name: String,
    theirs: Vec<f32>,
    render: Vec<f32>,
    /// (H, W).
    size: (usize, usize),
}

/// A run's name for a panel header: its folder's, or its parent's for a `train` folder (a
/// study's `VARIANT-seedS/train`).
fn run_name(run: &Path) -> String {
    let name = |p: &Path| p.file_name().map(|n| n.to_string_lossy().into_owned());
    match name(run) {
        Some(n) if n == "train" => run.parent().and_then(name).unwrap_or(n),
        Some(n) => n,
        None => run.display().to_string(),
    }
}

/// Writes `png`: the other run's render | this run's, with the PSNR between them | their
/// difference; `names` are (other, this).
fn against_panel(
    png: &Path,
    theirs: &[f32],
    render: &[f32],
    h: usize,
    w: usize,
    names: &(String, String),
) -> Result<()> {
    let psnr = image_psnr(theirs, render);
    let mine = if psnr.is_finite() {
        format!("{}, {psnr:.1} dB from it", names.1)
    } else {
        format!("{}, identical", names.1)
    };
    let p = panel_named(theirs, render, h, w, [&names.0, &mine, "difference ×4"])?;
    io::image::write_png(png, p.width, p.height, &p.rgb)
}

/// The PSNR between two images `[H * W * 3]` clamped to [0, 1] (infinite when equal).
fn image_psnr(a: &[f32], b: &[f32]) -> f64 {
    let sum: f64 = a
        .iter()
        .zip(b)
        .map(|(&x, &y)| (f64::from(x.clamp(0.0, 1.0)) - f64::from(y.clamp(0.0, 1.0))).powi(2))
        .sum();
    -10.0 * (sum / a.len().max(1) as f64).log10()
}

/// One split's summary of where two runs differ, for the progress line.
fn against_line(split: &str, r: &BTreeMap<String, RegionScore>) -> String {
    let psnr = |name: &str| {
        r.get(name)
            .and_then(|x| x.psnr)
            .map_or("-".to_string(), |p| format!("{p:.2} dB"))
    };
    let share = |name: &str| {
        r.get(name).map_or("-".to_string(), |x| {
            format!(
                "{:.1} % of the difference on {:.1} % of the pixels",
                100.0 * x.error_share,
                100.0 * x.pixel_share
            )
        })
    };
    format!(
        "{split}: against the other run: PSNR {} (stretched faces: {}; creases: {})",
        psnr("all"),
        share("stretched"),
        share("creases")
    )
}

/// Where two runs differ as Markdown (`against.md`).
pub fn against_table(a: &Against) -> String {
    let mut s = format!(
        "Where this run's renders differ from {}'s, per face region.\n\n| split | region | PSNR between the runs | pixels | share of pixels | share of squared difference | concentration |\n|---|---|---|---|---|---|---|\n",
        a.run.display()
    );
    s += &region_rows(&a.regions, true);
    s += "\nConcentration: the region's share of the squared difference over its share of the pixels (above 1: the two runs differ more there than on average). Both runs are posed with the tracked parameters. Regions: `texavatars::eval::regions` (docs/evaluation.md).\n";
    s
}

/// One Markdown row per split and region (in [`REGIONS`]' order): PSNR, pixels, share of
/// the pixels and of the squared error, and with `concentration` their ratio.
fn region_rows(
    regions: &BTreeMap<String, BTreeMap<String, RegionScore>>,
    concentration: bool,
) -> String {
    let mut s = String::new();
    for (split, r) in regions {
        for (name, x) in REGIONS.iter().filter_map(|n| r.get(*n).map(|x| (n, x))) {
            s += &format!(
                "| {split} | {name} | {} | {} | {:.3} | {:.3} |",
                x.psnr.map_or("-".into(), |p| format!("{p:.2}")),
                x.pixels,
                x.pixel_share,
                x.error_share
            );
            if concentration {
                s += &format!(
                    " {} |",
                    x.concentration().map_or("-".into(), |c| format!("{c:.2}"))
                );
            }
            s.push('\n');
        }
    }
    s
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
    s += &region_rows(regions, false);
    s += "\nRegions: `texavatars::eval::regions` (docs/evaluation.md). PSNR is over the region's pixels pooled over the split's scored images.\n";
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    fn id(shape: f32, offset: Option<f32>) -> Identity {
        Identity {
            shape: vec![0.0, shape],
            static_offset: offset.map(|o| vec![[o, 0.0, 0.0]; 2]),
            source: PathBuf::new(),
        }
    }

    #[test]
    fn against_needs_the_same_subject() {
        let (a, b) = (Path::new("a"), Path::new("b"));
        assert!(same_subject(a, None, b, None).is_ok());
        let mine = id(0.5, Some(0.1));
        assert!(same_subject(a, Some(&mine), b, Some(&id(0.5, Some(0.1)))).is_ok());
        // Another shape, other offsets, offsets against none, a subject against none: each
        // refused, naming the other run's file.
        for theirs in [
            Some(id(0.6, Some(0.1))),
            Some(id(0.5, Some(0.2))),
            Some(id(0.5, None)),
            None,
        ] {
            let e = same_subject(a, Some(&mine), b, theirs.as_ref())
                .unwrap_err()
                .to_string();
            assert!(e.contains("canonical_flame_param.npz"), "{e}");
        }
    }

    #[test]
    fn region_tables_share_their_rows() {
        let score = |pixels, pixel_share, error_share| RegionScore {
            pixels,
            mse: 0.01,
            psnr: (pixels > 0).then_some(20.0),
            pixel_share,
            error_share,
        };
        let split = BTreeMap::from([
            ("all".to_string(), score(100, 1.0, 1.0)),
            ("eyes".to_string(), score(10, 0.1, 0.3)),
            ("mouth".to_string(), score(0, 0.0, 0.0)),
        ]);
        let regions = BTreeMap::from([("free".to_string(), split)]);
        let eyes = &regions["free"]["eyes"];
        assert!((eyes.concentration().unwrap() - 3.0).abs() < 1e-12);
        assert_eq!(regions["free"]["mouth"].concentration(), None);

        let plain = regions_table(&regions);
        let against = against_table(&Against {
            run: PathBuf::from("other"),
            regions: regions.clone(),
        });
        let rows = |t: &str| -> Vec<String> {
            t.lines()
                .filter(|l| l.starts_with("| free |"))
                .map(String::from)
                .collect()
        };
        let (p, a) = (rows(&plain), rows(&against));
        assert_eq!(p.len(), 3);
        // The same rows in REGIONS' order; --against adds the concentration column.
        for (p, a) in p.iter().zip(&a) {
            assert!(a.starts_with(p.as_str()), "{a} / {p}");
        }
        assert!(p[0].starts_with("| free | all | 20.00 | 100 | 1.000 | 1.000 |"));
        // REGIONS puts the mouth before the eyes.
        assert!(a[1].starts_with("| free | mouth |") && a[1].ends_with("| - |"));
        assert_eq!(a[2], format!("{} 3.00 |", p[2]));
    }
}
