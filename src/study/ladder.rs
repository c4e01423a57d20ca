//! `study --ladder`: one study at several image sizes (a resolution ladder) read side by
//! side: each component's effect against the full method, and TexAvatars against
//! GaussianAvatars, against the pixels per visible triangle of each rung.
//!
//! Each rung is a study output folder whose `--collect` has run (`OUT/report/tables.json`);
//! its pixels per visible triangle are the mean over its full method's runs of `eval`'s
//! figure (`OUT/runs/ID/eval/metrics.json`, `triangles`). Written into the destination:
//! - `ladder.md`, `ladder.json`: per split (FREE, held-out) and metric (PSNR, LPIPS), per
//!   rung: the full method's seed spread (the sample standard deviation of its per-seed
//!   rows), each ablation's change against the full method and the full method minus
//!   GaussianAvatars; below, per rung, the PSNR change of every variant per face region;
//! - `ladder_{free,held-out}_{psnr,lpips}.png`: the changes against pixels per triangle (a
//!   log axis), each with its rung's seed spread as an error bar;
//! - in `ladder.md`, each rung's `report/paired.md` when `study --paired` has written it
//!   ([`super::paired`]).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::Serialize;

use super::config::Variant;
use crate::error::{Error, Result};
use crate::eval::plot::{Figure, Series, line_plot};
use crate::eval::regions::RegionScore;
use crate::eval::score::Means;

/// The splits the ladder reads: (metrics.json key, label, file name part).
const SPLITS: [(&str, &str, &str); 2] =
    [("free", "FREE", "free"), ("test", "held-out", "held-out")];
/// The regions of the per-region table.
const REGIONS: [&str; 5] = ["all", "stretched", "creases", "mouth", "eyes"];

/// One metric of the ladder.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub enum Metric {
    Psnr,
    Lpips,
}

impl Metric {
    fn name(self) -> &'static str {
        match self {
            Metric::Psnr => "psnr",
            Metric::Lpips => "lpips",
        }
    }

    fn label(self) -> &'static str {
        match self {
            Metric::Psnr => "PSNR (dB)",
            Metric::Lpips => "LPIPS",
        }
    }

    fn of(self, m: &Means) -> Option<f64> {
        match self {
            Metric::Psnr => Some(m.psnr),
            Metric::Lpips => m.lpips_alex,
        }
    }
}

/// One rung's figures for one split and metric.
#[derive(Clone, Debug, Default, Serialize)]
pub struct Effects {
    /// The full method's score (every seed).
    pub full: Option<f64>,
    /// Sample standard deviation of the full method's per-seed scores.
    pub seed_spread: Option<f64>,
    /// Variant name → its score minus the full method's (GaussianAvatars included).
    pub change: BTreeMap<String, f64>,
}

/// One rung of the ladder.
#[derive(Clone, Debug, Serialize)]
pub struct Rung {
    /// The study output folder.
    pub out: PathBuf,
    /// Split → pixels per visible triangle (mean over the full method's runs).
    pub pixels_per_triangle: BTreeMap<String, f64>,
    /// `split/metric` → effects.
    pub effects: BTreeMap<String, Effects>,
    /// Split → variant → region → PSNR change against the full method (mean over runs).
    pub regions: BTreeMap<String, BTreeMap<String, BTreeMap<String, f64>>>,
}

fn field<T: serde::de::DeserializeOwned>(
    path: &Path,
    v: &serde_json::Value,
    name: &str,
) -> Result<T> {
    serde_json::from_value(v.get(name).cloned().unwrap_or_default())
        .map_err(|e| Error::invalid(path.display().to_string(), name, e.to_string()))
}

fn mean(v: &[f64]) -> Option<f64> {
    (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
}

fn sample_sd(v: &[f64]) -> Option<f64> {
    let m = mean(v)?;
    (v.len() > 1)
        .then(|| (v.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / (v.len() - 1) as f64).sqrt())
}

/// Reads one rung (a collected study folder).
pub fn read_rung(out: &Path) -> Result<Rung> {
    let tables = out.join("report/tables.json");
    let json = crate::util::files::read_json(&tables)?;
    #[derive(serde::Deserialize)]
    struct RowIn {
        variant: Variant,
        seed: Option<u64>,
        splits: BTreeMap<String, Means>,
    }
    #[derive(serde::Deserialize)]
    struct RunIn {
        id: String,
        variant: Variant,
        #[serde(default)]
        regions: BTreeMap<String, BTreeMap<String, RegionScore>>,
    }
    let rows: Vec<RowIn> = field(&tables, &json, "rows")?;
    let runs: Vec<RunIn> = field(&tables, &json, "runs")?;
    if !rows
        .iter()
        .any(|r| r.variant == Variant::Full && r.seed.is_none())
    {
        return Err(Error::invalid(
            tables.display().to_string(),
            "rows",
            "no row of the full method: collect a study whose full method has finished",
        ));
    }

    let mut pixels: BTreeMap<String, Vec<f64>> = BTreeMap::new();
    for r in runs.iter().filter(|r| r.variant == Variant::Full) {
        let path = out.join("runs").join(&r.id).join("eval/metrics.json");
        let m = crate::util::files::read_json(&path)?;
        for (split, _, _) in SPLITS {
            if let Some(p) = m
                .pointer(&format!("/triangles/{split}/pixels_per_triangle"))
                .and_then(|v| v.as_f64())
            {
                pixels.entry(split.into()).or_default().push(p);
            }
        }
    }
    let pixels_per_triangle = pixels
        .into_iter()
        .filter_map(|(s, v)| Some((s, mean(&v)?)))
        .collect();

    let score = |variant: Variant, seed: Option<u64>, split: &str, metric: Metric| {
        rows.iter()
            .find(|r| r.variant == variant && r.seed == seed)
            .and_then(|r| metric.of(r.splits.get(split)?))
    };
    let mut effects = BTreeMap::new();
    for (split, _, _) in SPLITS {
        for metric in [Metric::Psnr, Metric::Lpips] {
            let full = score(Variant::Full, None, split, metric);
            let seeds: Vec<f64> = rows
                .iter()
                .filter(|r| r.variant == Variant::Full && r.seed.is_some())
                .filter_map(|r| metric.of(r.splits.get(split)?))
                .collect();
            let mut change = BTreeMap::new();
            for v in Variant::ALL.into_iter().filter(|&v| v != Variant::Full) {
                if let (Some(f), Some(x)) = (full, score(v, None, split, metric)) {
                    change.insert(v.name().to_string(), x - f);
                }
            }
            effects.insert(
                format!("{split}/{}", metric.name()),
                Effects {
                    full,
                    seed_spread: sample_sd(&seeds),
                    change,
                },
            );
        }
    }

    let region_mean = |variant: Variant, split: &str, region: &str| {
        let v: Vec<f64> = runs
            .iter()
            .filter(|r| r.variant == variant)
            .filter_map(|r| r.regions.get(split)?.get(region)?.psnr)
            .collect();
        mean(&v)
    };
    let mut regions = BTreeMap::new();
    for (split, _, _) in SPLITS {
        let mut per_variant = BTreeMap::new();
        for v in Variant::ALL.into_iter().filter(|&v| v != Variant::Full) {
            let changes: BTreeMap<String, f64> = REGIONS
                .iter()
                .filter_map(|&reg| {
                    let d = region_mean(v, split, reg)? - region_mean(Variant::Full, split, reg)?;
                    Some((reg.to_string(), d))
                })
                .collect();
            if !changes.is_empty() {
                per_variant.insert(v.name().to_string(), changes);
            }
        }
        regions.insert(split.to_string(), per_variant);
    }
    Ok(Rung {
        out: out.to_path_buf(),
        pixels_per_triangle,
        effects,
        regions,
    })
}

/// What [`collect`] wrote.
#[derive(Clone, Debug, Serialize)]
pub struct Ladder {
    pub rungs: Vec<Rung>,
    pub markdown: String,
}

fn signed(x: f64, digits: usize) -> String {
    format!("{x:+.digits$}")
}

fn label_of(name: &str) -> &'static str {
    Variant::ALL
        .into_iter()
        .find(|v| v.name() == name)
        .map_or("?", |v| v.label())
}

/// A variant's column: its change against the full method.
fn column_of(name: &str) -> String {
    format!("{} − full", label_of(name))
}

/// Reads the rungs `outs` (in order) and writes the ladder's tables and figures into
/// `dest`.
pub fn collect(outs: &[PathBuf], dest: &Path) -> Result<Ladder> {
    let rungs = outs
        .iter()
        .map(|o| read_rung(o))
        .collect::<Result<Vec<_>>>()?;
    std::fs::create_dir_all(dest).map_err(|e| Error::io(dest, e))?;
    let mut md = String::from(
        "# The resolution ladder\n\nEach rung is a study folder. Pixels per visible triangle: the mean over the full method's runs of `eval`'s figure. \
         Each column is a variant's score minus the full method's (GaussianAvatars − full: the negative of TexAvatars − GaussianAvatars) (over the subjects, the full method averaged over its seeds); \
         the seed spread is the sample standard deviation of the full method's per-seed scores.\n",
    );
    let variants: Vec<String> = {
        let mut v: Vec<String> = rungs
            .iter()
            .flat_map(|r| r.effects.values().flat_map(|e| e.change.keys().cloned()))
            .collect();
        v.sort_by_key(|n| Variant::ALL.iter().position(|x| x.name() == n));
        v.dedup();
        v
    };
    for (split, split_label, file_part) in SPLITS {
        for metric in [Metric::Psnr, Metric::Lpips] {
            let key = format!("{split}/{}", metric.name());
            let digits = if metric == Metric::Psnr { 2 } else { 4 };
            md += &format!("\n## {split_label} {}\n\n", metric.label());
            md += "| rung | pixels per triangle | full | seed spread |";
            for v in &variants {
                md += &format!(" {} |", column_of(v));
            }
            md += "\n|---|---|---|---|";
            md += &"---|".repeat(variants.len());
            md += "\n";
            let mut series: Vec<Series> = Vec::new();
            let colors = [
                [255, 127, 14],
                [44, 160, 44],
                [127, 127, 127],
                [214, 39, 40],
                [148, 103, 189],
                [140, 86, 75],
                [23, 190, 207],
                [188, 189, 34],
            ];
            for r in &rungs {
                let e = r.effects.get(&key).cloned().unwrap_or_default();
                let ppt = r.pixels_per_triangle.get(split).copied();
                let cell =
                    |x: Option<f64>, d: usize| x.map_or("–".into(), |x| format!("{x:.d$}"));
                md += &format!(
                    "| {} | {} | {} | {} |",
                    r.out.display(),
                    cell(ppt, 1),
                    cell(e.full, digits),
                    e.seed_spread
                        .map_or("–".into(), |s| format!("± {s:.digits$}"))
                );
                for v in &variants {
                    md += &format!(
                        " {} |",
                        e.change.get(v).map_or("–".into(), |&d| signed(d, digits))
                    );
                }
                md += "\n";
            }
            // The full method's level, then each variant with the rung's seed spread as its
            // error bar; the variants sit side by side around the rung's pixels per triangle
            // (a factor of 1.03 apart on the log axis) so that their bars stay apart.
            let xs: Vec<f64> = rungs
                .iter()
                .filter_map(|r| r.pixels_per_triangle.get(split).copied())
                .collect();
            let (x_lo, x_hi) = xs
                .iter()
                .fold((f64::MAX, f64::MIN), |(a, b), &x| (a.min(x), b.max(x)));
            if x_lo <= x_hi {
                series.push(Series {
                    label: String::new(),
                    color: [31, 119, 180],
                    width: 1,
                    markers: false,
                    points: vec![(x_lo, 0.0), (x_hi, 0.0)],
                    errors: Vec::new(),
                });
            }
            let n = variants.len() as f64;
            for (k, v) in variants.iter().enumerate() {
                let shift = 1.03f64.powf(k as f64 - 0.5 * (n - 1.0));
                let (points, errors): (Vec<(f64, f64)>, Vec<f64>) = rungs
                    .iter()
                    .filter_map(|r| {
                        let x = *r.pixels_per_triangle.get(split)?;
                        let e = r.effects.get(&key)?;
                        Some(((x * shift, *e.change.get(v)?), e.seed_spread.unwrap_or(0.0)))
                    })
                    .unzip();
                series.push(Series {
                    label: column_of(v),
                    color: colors[k % colors.len()],
                    width: 2,
                    markers: true,
                    points,
                    errors,
                });
            }
            let fig = Figure {
                title: format!(
                    "{split_label}: change against the full method (bars: ± seed spread)"
                ),
                x_label: "pixels per visible triangle (log scale)".into(),
                y_label: format!("Δ {}", metric.label()),
                log_x: true,
                log_y: false,
                width: 800,
                height: 500,
            };
            line_plot(
                &dest.join(format!("ladder_{file_part}_{}.png", metric.name())),
                &fig,
                &series,
            )?;
        }
    }
    md += "\n## PSNR change per face region (dB, against the full method)\n";
    for r in &rungs {
        for (split, split_label, _) in SPLITS {
            let Some(per_variant) = r.regions.get(split).filter(|p| !p.is_empty()) else {
                continue;
            };
            md += &format!("\n### {} — {split_label}\n\n| variant |", r.out.display());
            for reg in REGIONS {
                md += &format!(" {reg} |");
            }
            md += "\n|---|";
            md += &"---|".repeat(REGIONS.len());
            md += "\n";
            let mut ordered: Vec<_> = per_variant.iter().collect();
            ordered.sort_by_key(|(n, _)| Variant::ALL.iter().position(|x| x.name() == *n));
            for (v, changes) in ordered {
                md += &format!("| {} |", label_of(v));
                for reg in REGIONS {
                    md += &format!(
                        " {} |",
                        changes.get(reg).map_or("–".into(), |&d| signed(d, 2))
                    );
                }
                md += "\n";
            }
        }
    }
    let paired: Vec<(&Rung, String)> = rungs
        .iter()
        .filter_map(|r| {
            let text = std::fs::read_to_string(r.out.join("report").join("paired.md")).ok()?;
            // The table without its title line.
            let body = text.split_once('\n').map_or("", |(_, b)| b).trim();
            Some((r, body.to_string()))
        })
        .collect();
    if !paired.is_empty() {
        md += "\n## Where each run's images differ from the full method's (`study --paired`)\n";
        for (r, body) in paired {
            md += &format!("\n### {}\n\n{body}\n", r.out.display());
        }
    }
    let write = |name: &str, text: &str| {
        let p = dest.join(name);
        std::fs::write(&p, text).map_err(|e| Error::io(&p, e))
    };
    write("ladder.md", &md)?;
    let ladder = Ladder {
        rungs,
        markdown: md,
    };
    write(
        "ladder.json",
        &(serde_json::to_string_pretty(&ladder).expect("serialises") + "\n"),
    )?;
    Ok(ladder)
}
