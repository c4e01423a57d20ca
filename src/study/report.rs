//! `study --collect`: the paper's tables, charts, training curves and side-by-side panels
//! from whatever runs have finished.
//!
//! Written into `OUT/report/`:
//! - `table1.md`, `table2.md`, `tables.json`: Table 1 (every variant on held-out, FREE and
//!   novel view × LPIPS / SSIM / PSNR) and Table 2 (the ablations on FREE, with the change
//!   against the full method), mean ± standard deviation over subjects (a subject's full
//!   method first averaged over its seeds; one row per seed shows the seed noise), and
//!   whether "full > each ablation > GaussianAvatars" holds on FREE per metric;
//! - `bars_{psnr,ssim,lpips}.png`: the tables as grouped bars (error bars: std over
//!   subjects);
//! - `curves.png`: every run's training PSNR (a moving average over 100 iterations);
//! - `panels/SUBJECT_SPLIT_TTTTT_CC.png`: ground truth | full | each variant at the same
//!   frames, and below, the same columns zoomed into the window where the variants differ
//!   most from the full method;
//! - `regions.md`: PSNR per face region ([`crate::eval::regions`]) on FREE and held-out,
//!   per variant (mean over subjects) with its change against the full method.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::Serialize;

use super::config::{RunSpec, Study, Variant};
use super::run::{finished, run_dir};
use crate::error::{Error, Result};
use crate::eval::plot::{self, Bars, Figure, Series};
use crate::eval::regions::RegionScore;
use crate::eval::score::{Means, combine_subjects};
use crate::io;

/// The evaluation splits in the tables' order: (metrics.json key, label).
pub const SPLITS: [(&str, &str); 3] = [
    ("test", "held-out"),
    ("free", "FREE"),
    ("val", "novel view"),
];

/// A finished run's scores.
#[derive(Clone, Debug, Serialize)]
pub struct RunScores {
    pub id: String,
    pub subject: String,
    pub variant: Variant,
    pub seed: u64,
    pub means: BTreeMap<String, Means>,
    /// Errors per face region and split (empty for an evaluation made before they existed).
    pub regions: BTreeMap<String, BTreeMap<String, RegionScore>>,
}

/// One row of the tables: scores per split over subjects.
#[derive(Clone, Debug, Serialize)]
pub struct Row {
    pub label: String,
    pub variant: Variant,
    /// `None`: every seed (averaged per subject); `Some(s)`: that seed only.
    pub seed: Option<u64>,
    pub subjects: usize,
    pub splits: BTreeMap<String, Means>,
}

/// What [`collect`] found and wrote.
#[derive(Clone, Debug, Serialize)]
pub struct Collected {
    pub runs: Vec<RunScores>,
    pub missing: Vec<String>,
    pub rows: Vec<Row>,
    /// The ordering on FREE, one sentence per metric.
    pub ordering: Vec<String>,
    pub table1: String,
    pub table2: String,
}

type Regions = BTreeMap<String, BTreeMap<String, RegionScore>>;

fn read_means(path: &Path) -> Result<(BTreeMap<String, Means>, Regions)> {
    let what = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let json: serde_json::Value = serde_json::from_str(&text)
        .map_err(|e| Error::invalid(&what, format!("line {}", e.line()), e.to_string()))?;
    let means = serde_json::from_value(json.get("means").cloned().unwrap_or_default())
        .map_err(|e| Error::invalid(&what, "means", e.to_string()))?;
    let regions = match json.get("regions") {
        Some(r) => serde_json::from_value(r.clone())
            .map_err(|e| Error::invalid(&what, "regions", e.to_string()))?,
        None => Regions::new(),
    };
    Ok((means, regions))
}

/// A region's PSNR for `variant` (`seed`: one seed, else every seed) on `split`: mean over
/// a subject's runs, then over the subjects that have it.
fn region_psnr(
    study: &Study,
    runs: &[RunScores],
    variant: Variant,
    seed: Option<u64>,
    split: &str,
    region: &str,
) -> Option<f64> {
    let mean = |v: &[f64]| (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64);
    let per_subject: Vec<f64> = study
        .config
        .subjects
        .iter()
        .filter_map(|s| {
            let v: Vec<f64> = runs
                .iter()
                .filter(|r| r.variant == variant && r.subject == s.name)
                .filter(|r| seed.is_none_or(|x| r.seed == x))
                .filter_map(|r| r.regions.get(split)?.get(region)?.psnr)
                .collect();
            mean(&v)
        })
        .collect();
    mean(&per_subject)
}

/// `regions.md`: per split (FREE, held-out), every row's PSNR per face region and its change
/// against the full method; below, the full method's share of pixels and of squared error.
fn regions_table(study: &Study, runs: &[RunScores], rows: &[Row]) -> String {
    use crate::eval::regions::REGIONS;
    if runs.iter().all(|r| r.regions.is_empty()) {
        return String::from(
            "No run's evaluation has errors per region (evaluations made before they existed: `texavatars study --reevaluate`).\n",
        );
    }
    let mut s = String::from(
        "# PSNR per face region\n\nRegions: `texavatars::eval::regions` (docs/evaluation.md). Each cell: PSNR (dB) of the region's pixels pooled over a run's scored images, mean over the subjects (a subject's full method over its seeds), and in brackets the change against the full method.\n",
    );
    for (split, label) in [("free", "FREE"), ("test", "held-out")] {
        s += &format!("\n## {label}\n\n| variant |");
        for r in REGIONS {
            s += &format!(" {r} |");
        }
        s += "\n|---|";
        s += &"---|".repeat(REGIONS.len());
        s += "\n";
        let full: Vec<Option<f64>> = REGIONS
            .iter()
            .map(|r| region_psnr(study, runs, Variant::Full, None, split, r))
            .collect();
        for row in rows {
            s += &format!("| {} |", row.label);
            for (region, &full) in REGIONS.iter().zip(&full) {
                let v = region_psnr(study, runs, row.variant, row.seed, split, region);
                s += &match (v, full) {
                    (Some(v), Some(f)) if !(row.variant == Variant::Full && row.seed.is_none()) => {
                        format!(" {v:.2} ({:+.2}) |", v - f)
                    }
                    (Some(v), _) => format!(" {v:.2} |"),
                    _ => " – |".into(),
                };
            }
            s += "\n";
        }
        let share = |f: &dyn Fn(&RegionScore) -> f64| -> Vec<String> {
            REGIONS
                .iter()
                .map(|region| {
                    let v: Vec<f64> = runs
                        .iter()
                        .filter(|r| r.variant == Variant::Full)
                        .filter_map(|r| r.regions.get(split)?.get(*region).map(f))
                        .collect();
                    if v.is_empty() {
                        "–".into()
                    } else {
                        format!("{:.3}", v.iter().sum::<f64>() / v.len() as f64)
                    }
                })
                .collect()
        };
        s += &format!(
            "| full: share of pixels | {} |\n| full: share of squared error | {} |\n",
            share(&|x| x.pixel_share).join(" | "),
            share(&|x| x.error_share).join(" | ")
        );
    }
    s
}

/// The rows: per variant (and per seed of the full method when it has several), over the
/// subjects that have it.
fn rows(study: &Study, runs: &[RunScores]) -> Vec<Row> {
    let mut out = Vec::new();
    let seeds = &study.config.seeds;
    for &v in &study.config.variants {
        let mut variants: Vec<(Option<u64>, String)> = vec![(None, v.label().to_string())];
        if (v == Variant::Full || study.config.every_seed.contains(&v)) && seeds.len() > 1 {
            variants.extend(
                seeds
                    .iter()
                    .map(|s| (Some(*s), format!("{} seed {s}", v.label()))),
            );
        }
        for (seed, label) in variants {
            let mut per_subject = Vec::new();
            for s in &study.config.subjects {
                let of: Vec<BTreeMap<String, Means>> = runs
                    .iter()
                    .filter(|r| r.variant == v && r.subject == s.name)
                    .filter(|r| seed.is_none_or(|x| r.seed == x))
                    .map(|r| r.means.clone())
                    .collect();
                match of.len() {
                    0 => {}
                    1 => per_subject.push(of[0].clone()),
                    _ => per_subject.push(combine_subjects(&of)),
                }
            }
            if per_subject.is_empty() {
                continue;
            }
            out.push(Row {
                label,
                variant: v,
                seed,
                subjects: per_subject.len(),
                splits: if per_subject.len() == 1 {
                    per_subject.remove(0)
                } else {
                    combine_subjects(&per_subject)
                },
            });
        }
    }
    out
}

fn cell(m: Option<&Means>, metric: &str) -> String {
    let Some(m) = m else {
        return "–".into();
    };
    // Over subjects when there were several, else over the images.
    let (v, s, digits) = match metric {
        "lpips" => match m.lpips_alex {
            Some(l) => (l, m.lpips_alex_std.unwrap_or(0.0), 3),
            None => return "–".into(),
        },
        "ssim" => (m.ssim, m.ssim_std, 3),
        _ => (m.psnr, m.psnr_std, 2),
    };
    format!("{v:.digits$} ± {s:.digits$}")
}

fn table1(rows: &[Row]) -> String {
    let mut t = String::from("| variant | subjects |");
    for (_, label) in SPLITS {
        t.push_str(&format!(" {label} LPIPS | {label} SSIM | {label} PSNR |"));
    }
    t.push_str("\n|---|---|");
    t.push_str(&"---|".repeat(3 * SPLITS.len()));
    t.push('\n');
    for r in rows {
        t.push_str(&format!("| {} | {} |", r.label, r.subjects));
        for (key, _) in SPLITS {
            for metric in ["lpips", "ssim", "psnr"] {
                t.push_str(&format!(" {} |", cell(r.splits.get(key), metric)));
            }
        }
        t.push('\n');
    }
    t.push_str(
        "\nMean ± standard deviation over subjects (a subject's full method averaged over its \
         seeds, ± then over the seeds' means; a row for one seed shows the seed noise). With \
         one subject and one run, ± is over that run's images. LPIPS is LPIPS-alex.\n",
    );
    t
}

fn table2(rows: &[Row]) -> String {
    let full = rows
        .iter()
        .find(|r| r.variant == Variant::Full && r.seed.is_none())
        .and_then(|r| r.splits.get("free"));
    let mut t = String::from(
        "| variant (FREE) | LPIPS | SSIM | PSNR | ΔLPIPS | ΔSSIM | ΔPSNR |\n|---|---|---|---|---|---|---|\n",
    );
    for r in rows
        .iter()
        .filter(|r| r.variant != Variant::Gaussianavatars)
    {
        let m = r.splits.get("free");
        let delta = |f: fn(&Means) -> Option<f64>, digits: usize| match (m, full) {
            (Some(a), Some(b)) => match (f(a), f(b)) {
                (Some(x), Some(y)) => format!("{:+.digits$}", x - y),
                _ => "–".into(),
            },
            _ => "–".into(),
        };
        t.push_str(&format!(
            "| {} | {} | {} | {} | {} | {} | {} |\n",
            r.label,
            cell(m, "lpips"),
            cell(m, "ssim"),
            cell(m, "psnr"),
            delta(|m| m.lpips_alex, 3),
            delta(|m| Some(m.ssim), 3),
            delta(|m| Some(m.psnr), 2),
        ));
    }
    t.push_str("\nΔ: the row minus the full method (every seed).\n");
    t
}

/// "full > each ablation > GaussianAvatars" on FREE, per metric (lower LPIPS is better).
fn ordering(rows: &[Row]) -> Vec<String> {
    let main: Vec<&Row> = rows.iter().filter(|r| r.seed.is_none()).collect();
    let get = |v: Variant| {
        main.iter()
            .find(|r| r.variant == v)
            .and_then(|r| r.splits.get("free"))
    };
    let mut out = Vec::new();
    for (name, f, higher) in [
        (
            "LPIPS",
            (|m: &Means| m.lpips_alex) as fn(&Means) -> Option<f64>,
            false,
        ),
        ("SSIM", |m: &Means| Some(m.ssim), true),
        ("PSNR", |m: &Means| Some(m.psnr), true),
    ] {
        let better = |a: f64, b: f64| if higher { a > b } else { a < b };
        let Some(full) = get(Variant::Full).and_then(f) else {
            continue;
        };
        let ga = get(Variant::Gaussianavatars).and_then(f);
        let mut fails = Vec::new();
        for r in main
            .iter()
            .filter(|r| !matches!(r.variant, Variant::Full | Variant::Gaussianavatars))
        {
            let Some(a) = r.splits.get("free").and_then(f) else {
                continue;
            };
            if !better(full, a) {
                fails.push(format!("the full method is not better than {}", r.label));
            }
            if let Some(g) = ga
                && !better(a, g)
            {
                fails.push(format!("{} is not better than GaussianAvatars", r.label));
            }
        }
        if let Some(g) = ga
            && !better(full, g)
        {
            fails.push("the full method is not better than GaussianAvatars".into());
        }
        let claim = if ga.is_some() {
            "full > each ablation > GaussianAvatars"
        } else {
            "full > each ablation (GaussianAvatars not in this study)"
        };
        out.push(if fails.is_empty() {
            format!("{name} on FREE: {claim} holds.")
        } else {
            format!(
                "{name} on FREE: the ordering does not hold: {}.",
                fails.join("; ")
            )
        });
    }
    out
}

/// Distinct colours of the variants (and the full method's seeds, lighter).
fn color(v: Variant) -> [u8; 3] {
    match v {
        Variant::Full => [31, 119, 180],
        Variant::NoGlobalUv => [255, 127, 14],
        Variant::NoJacobian => [44, 160, 44],
        Variant::NoEta => [214, 39, 40],
        Variant::ImageEta => [23, 190, 207],
        Variant::Crop => [188, 189, 34],
        Variant::NoVgg => [148, 103, 189],
        Variant::NoFlameRefinement => [140, 86, 75],
        Variant::Gaussianavatars => [127, 127, 127],
    }
}

fn bars(dir: &Path, rows: &[Row]) -> Result<()> {
    let main: Vec<&Row> = rows.iter().filter(|r| r.seed.is_none()).collect();
    let groups: Vec<String> = SPLITS.iter().map(|(_, l)| l.to_string()).collect();
    for (file, title, f) in [
        (
            "bars_psnr.png",
            "PSNR (dB, higher is better)",
            (|m: &Means| (m.psnr, m.psnr_std)) as fn(&Means) -> (f64, f64),
        ),
        ("bars_ssim.png", "SSIM (higher is better)", |m: &Means| {
            (m.ssim, m.ssim_std)
        }),
        (
            "bars_lpips.png",
            "LPIPS-alex (lower is better)",
            |m: &Means| {
                (
                    m.lpips_alex.unwrap_or(f64::NAN),
                    m.lpips_alex_std.unwrap_or(0.0),
                )
            },
        ),
    ] {
        let series: Vec<Bars> = main
            .iter()
            .map(|r| Bars {
                label: r.label.clone(),
                color: color(r.variant),
                values: SPLITS
                    .iter()
                    .map(|(k, _)| r.splits.get(*k).map_or((f64::NAN, 0.0), f))
                    .collect(),
            })
            .collect();
        let fig = Figure {
            title: title.to_string(),
            x_label: "split".into(),
            y_label: "mean over subjects ± std".into(),
            log_x: false,
            log_y: false,
            width: 1000,
            height: 560,
        };
        plot::bar_chart(&dir.join(file), &fig, &groups, &series)?;
    }
    Ok(())
}

/// The training PSNR of a run, per iteration: burn's `train/epoch-E/PSNR.log` lines
/// (`value,batch size`), epochs in order.
fn psnr_curve(train: &Path) -> Vec<f64> {
    let mut values = Vec::new();
    for e in 1.. {
        let f = train
            .join("train")
            .join(format!("epoch-{e}"))
            .join("PSNR.log");
        let Ok(text) = std::fs::read_to_string(&f) else {
            break;
        };
        values.extend(
            text.lines()
                .filter_map(|l| l.split(',').next()?.trim().parse::<f64>().ok()),
        );
    }
    values
}

fn curves(study: &Study, out: &Path, dir: &Path, runs: &[RunSpec]) -> Result<()> {
    let window = 100;
    let series: Vec<Series> = runs
        .iter()
        .filter_map(|r| {
            let v = psnr_curve(&run_dir(out, r).join("train"));
            if v.is_empty() {
                return None;
            }
            let mut points = Vec::new();
            let mut sum = 0.0;
            for (i, x) in v.iter().enumerate() {
                sum += x;
                if i >= window {
                    sum -= v[i - window];
                }
                let n = (i + 1).min(window);
                if (i + 1) % 10 == 0 || i + 1 == v.len() {
                    points.push(((i + 1) as f64, sum / n as f64));
                }
            }
            let mut c = color(r.variant);
            if r.variant == Variant::Full && r.seed != study.config.seeds[0] {
                c = c.map(|x| ((x as u32 + 255) / 2) as u8);
            }
            Some(Series {
                label: format!("{} {} seed {}", r.subject, r.variant.label(), r.seed),
                color: c,
                width: 2,
                markers: false,
                points,
                errors: Vec::new(),
            })
        })
        .collect();
    if series.is_empty() {
        return Ok(());
    }
    let fig = Figure {
        title: "Training PSNR of every run (moving average over 100 iterations)".into(),
        x_label: "iteration".into(),
        y_label: "PSNR (dB)".into(),
        log_x: false,
        log_y: false,
        width: 1100,
        height: 650,
    };
    plot::line_plot(&dir.join("curves.png"), &fig, &series)
}

fn read(path: &Path) -> Option<io::image::RgbImage> {
    io::image::read_rgb(path).ok()
}

/// Ground truth | full | variants at the full run's panel frames, with a zoomed row.
fn panels(study: &Study, out: &Path, dir: &Path) -> Result<usize> {
    let pdir = dir.join("panels");
    let mut written = 0;
    let seed = study.config.seeds[0];
    let others: Vec<Variant> = study
        .config
        .variants
        .iter()
        .copied()
        .filter(|v| *v != Variant::Full)
        .collect();
    for s in &study.config.subjects {
        let at = |v: Variant| {
            run_dir(
                out,
                &RunSpec {
                    subject: s.name.clone(),
                    variant: v,
                    seed,
                },
            )
            .join("eval")
            .join("images")
        };
        let full_dir = at(Variant::Full);
        for (split, _) in [("free", ""), ("test", "")] {
            let Ok(entries) = std::fs::read_dir(full_dir.join(split)) else {
                continue;
            };
            let mut frames: Vec<String> = entries
                .filter_map(|e| e.ok())
                .filter_map(|e| {
                    let name = e.file_name().to_string_lossy().into_owned();
                    name.strip_suffix("_gt.png").map(str::to_string)
                })
                .collect();
            frames.sort();
            for frame in frames {
                let Some(gt) = read(&full_dir.join(split).join(format!("{frame}_gt.png"))) else {
                    continue;
                };
                let full_path = full_dir.join(split).join(format!("{frame}_render.png"));
                let Some(full) = read(&full_path) else {
                    continue;
                };
                let mut columns = vec![
                    ("ground truth".to_string(), gt),
                    (Variant::Full.label().to_string(), full),
                ];
                for &v in &others {
                    let p = at(v).join(split).join(format!("{frame}_render.png"));
                    if let Some(img) = read(&p)
                        && (img.width, img.height) == (columns[0].1.width, columns[0].1.height)
                    {
                        columns.push((v.label().to_string(), img));
                    }
                }
                if columns.len() < 3 {
                    continue;
                }
                std::fs::create_dir_all(&pdir).map_err(|e| Error::io(&pdir, e))?;
                let path = pdir.join(format!("{}_{split}_{frame}.png", s.name));
                side_by_side(&path, &columns)?;
                written += 1;
            }
        }
    }
    Ok(written)
}

/// Writes the columns side by side under a header, and below them the same columns cropped
/// to the square window (a third of the smaller side) where the variants (columns 2..)
/// differ most from the full method (column 1), enlarged to the column width.
fn side_by_side(path: &Path, columns: &[(String, io::image::RgbImage)]) -> Result<()> {
    let (w, h) = (columns[0].1.width, columns[0].1.height);
    let n = columns.len();
    // Summed absolute difference to the full method per pixel.
    let mut diff = vec![0.0f64; w * h];
    for (_, img) in &columns[2..] {
        for (p, d) in diff.iter_mut().enumerate() {
            for c in 0..3 {
                *d += f64::from((img.rgb[p * 3 + c] - columns[1].1.rgb[p * 3 + c]).abs());
            }
        }
    }
    let win = (w.min(h) / 3).max(1);
    // Integral image for the window sums.
    let mut integral = vec![0.0f64; (w + 1) * (h + 1)];
    for y in 0..h {
        for x in 0..w {
            integral[(y + 1) * (w + 1) + x + 1] =
                diff[y * w + x] + integral[y * (w + 1) + x + 1] + integral[(y + 1) * (w + 1) + x]
                    - integral[y * (w + 1) + x];
        }
    }
    let (mut best, mut at) = (-1.0, (0, 0));
    for y in 0..=h - win {
        for x in 0..=w - win {
            let s = integral[(y + win) * (w + 1) + x + win]
                - integral[y * (w + 1) + x + win]
                - integral[(y + win) * (w + 1) + x]
                + integral[y * (w + 1) + x];
            if s > best {
                (best, at) = (s, (x, y));
            }
        }
    }
    let zoom = (w / win).max(1);
    let zh = win * zoom;
    let labels: Vec<&str> = columns.iter().map(|(l, _)| l.as_str()).collect();
    let header = plot::header(w, &labels)?;
    let hh = plot::header_height(w);
    let total_w = w * n;
    let total_h = hh + h + zh;
    let mut out = vec![1.0f32; total_w * total_h * 3];
    out[..header.len()].copy_from_slice(&header);
    for (k, (_, img)) in columns.iter().enumerate() {
        for y in 0..h {
            let dst = ((hh + y) * total_w + k * w) * 3;
            out[dst..dst + w * 3].copy_from_slice(&img.rgb[y * w * 3..(y + 1) * w * 3]);
        }
        for y in 0..zh {
            for x in 0..win * zoom {
                let (sx, sy) = (at.0 + x / zoom, at.1 + y / zoom);
                let src = (sy * w + sx) * 3;
                let dst = ((hh + h + y) * total_w + k * w + x) * 3;
                out[dst..dst + 3].copy_from_slice(&img.rgb[src..src + 3]);
            }
        }
    }
    io::image::write_png(path, total_w, total_h, &out)
}

/// Reads every finished run and writes the report into `OUT/report/`.
pub fn collect(study: &Study, out: &Path) -> Result<Collected> {
    let all = study.runs();
    let mut runs = Vec::new();
    let mut missing = Vec::new();
    for r in &all {
        if finished(out, r).is_none() {
            missing.push(r.id());
            continue;
        }
        let (means, regions) = read_means(&run_dir(out, r).join("eval").join("metrics.json"))?;
        runs.push(RunScores {
            id: r.id(),
            subject: r.subject.clone(),
            variant: r.variant,
            seed: r.seed,
            means,
            regions,
        });
    }
    let rows = rows(study, &runs);
    let dir = out.join("report");
    std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
    let c = Collected {
        table1: table1(&rows),
        table2: table2(&rows),
        ordering: ordering(&rows),
        runs,
        missing,
        rows,
    };
    let write = |name: &str, text: &str| -> Result<PathBuf> {
        let p = dir.join(name);
        std::fs::write(&p, text).map_err(|e| Error::io(&p, e))?;
        Ok(p)
    };
    let mut t1 = format!("# Table 1\n\n{}", c.table1);
    if !c.missing.is_empty() {
        t1.push_str(&format!(
            "\nNot finished ({} of {} runs): {}.\n",
            c.missing.len(),
            all.len(),
            c.missing.join(", ")
        ));
    }
    write("table1.md", &t1)?;
    let mut t2 = format!("# Table 2: ablations on FREE\n\n{}\n", c.table2);
    for line in &c.ordering {
        t2.push_str(&format!("- {line}\n"));
    }
    write("table2.md", &t2)?;
    write("regions.md", &regions_table(study, &c.runs, &c.rows))?;
    write(
        "tables.json",
        &(serde_json::to_string_pretty(&c).expect("serialises") + "\n"),
    )?;
    if !c.rows.is_empty() {
        bars(&dir, &c.rows)?;
    }
    let finished_runs: Vec<RunSpec> = all
        .iter()
        .filter(|r| finished(out, r).is_some())
        .cloned()
        .collect();
    curves(study, out, &dir, &finished_runs)?;
    panels(study, out, &dir)?;
    Ok(c)
}
