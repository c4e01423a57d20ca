//! Per-image scores and their means and standard deviations per split, and over subjects.
//!
//! Every image is scored on the full frame with a white background, clamped to [0, 1]:
//! PSNR, SSIM (11x11 Gaussian window, sigma 1.5), LPIPS-alex v0.1 with inputs scaled to
//! [-1, 1] (the metric's definition), LPIPS-vgg, and the GaussianAvatars-compatible
//! LPIPS-alex that passes [0, 1] images unscaled (its issue #100).

use std::collections::BTreeMap;

use burn::tensor::{Device, Tensor, TensorData};
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::metrics::{self, Lpips, LpipsVggCpu, Net};

/// Scores of one image.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Scores {
    pub psnr: f64,
    pub ssim: f64,
    pub lpips_alex: Option<f64>,
    pub lpips_vgg: Option<f64>,
    pub lpips_alex_unscaled_inputs: Option<f64>,
}

/// Scores images; LPIPS needs the installed weights (`texavatars weights install`).
pub struct Scorer {
    device: Device,
    alex: Option<Lpips>,
    vgg: Option<VggLpips>,
}

/// LPIPS-vgg on burn's ops, or on the host's VGG16 network on the CPU backends (the same
/// metric, several times faster there).
enum VggLpips {
    Burn(Lpips),
    Host(LpipsVggCpu),
}

impl Scorer {
    /// A scorer on `device`; with `lpips` the AlexNet and VGG16 weights are loaded (a clear
    /// error naming the missing file and the install command when absent).
    pub fn new(device: &Device, lpips: bool) -> Result<Self> {
        let (alex, vgg) = if lpips {
            let vgg = if metrics::on_cpu(device) {
                VggLpips::Host(LpipsVggCpu::load()?)
            } else {
                VggLpips::Burn(Lpips::load(Net::Vgg16, device)?)
            };
            (Some(Lpips::load(Net::AlexNet, device)?), Some(vgg))
        } else {
            (None, None)
        };
        Ok(Scorer {
            device: device.clone(),
            alex,
            vgg,
        })
    }

    /// Scores `image` against `reference`, both [H, W, 3] row-major in [0, 1].
    pub fn score(
        &self,
        reference: &[f32],
        image: &[f32],
        height: usize,
        width: usize,
    ) -> Result<Scores> {
        let n = height * width * 3;
        if reference.len() != n || image.len() != n {
            return Err(Error::invalid(
                "evaluation",
                "image",
                format!(
                    "{} and {} values for a {width}x{height} RGB image",
                    reference.len(),
                    image.len()
                ),
            ));
        }
        let clamp = |x: &[f32]| -> Vec<f32> { x.iter().map(|v| v.clamp(0.0, 1.0)).collect() };
        let (image, reference) = (clamp(image), clamp(reference));
        let t = |x: &[f32]| {
            metrics::hwc_to_nchw(Tensor::<3>::from_data(
                TensorData::new(x.to_vec(), [height, width, 3]),
                &self.device,
            ))
        };
        let (a, b) = (t(&image), t(&reference));
        if self.alex.is_some() || self.vgg.is_some() {
            crate::metrics::lpips::check_size(height, width, "evaluation image")?;
        }
        let first = |x| metrics::to_host(x)[0];
        Ok(Scores {
            psnr: first(metrics::psnr(a.clone(), b.clone())),
            ssim: first(metrics::ssim(a.clone(), b.clone())),
            lpips_alex: self
                .alex
                .as_ref()
                .map(|m| first(m.distance(a.clone(), b.clone()))),
            lpips_vgg: self.vgg.as_ref().map(|m| match m {
                VggLpips::Burn(m) => first(m.distance(a.clone(), b.clone())),
                VggLpips::Host(m) => m.distance(&image, &reference, height, width),
            }),
            lpips_alex_unscaled_inputs: self
                .alex
                .as_ref()
                .map(|m| first(m.distance_raw(a.clone(), b.clone()))),
        })
    }
}

/// Means and standard deviations of scores over a split: over its images
/// ([`Tally::means`]) or, for several subjects, over the subjects' means
/// ([`combine_subjects`]; then `subjects` > 0).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Means {
    pub images: usize,
    pub psnr: f64,
    pub ssim: f64,
    pub lpips_alex: Option<f64>,
    pub lpips_vgg: Option<f64>,
    pub lpips_alex_unscaled_inputs: Option<f64>,
    /// Standard deviations (sample, n - 1; 0 for one value) of the same scores.
    #[serde(default)]
    pub psnr_std: f64,
    #[serde(default)]
    pub ssim_std: f64,
    #[serde(default)]
    pub lpips_alex_std: Option<f64>,
    #[serde(default)]
    pub lpips_vgg_std: Option<f64>,
    #[serde(default)]
    pub lpips_alex_unscaled_inputs_std: Option<f64>,
    /// Subjects the means and deviations are taken over (0: over the images of one).
    #[serde(default)]
    pub subjects: usize,
}

/// Mean and sample standard deviation (n - 1; 0 for fewer than two values).
pub fn mean_std(v: &[f64]) -> (f64, f64) {
    if v.is_empty() {
        return (0.0, 0.0);
    }
    let n = v.len() as f64;
    let m = v.iter().sum::<f64>() / n;
    if v.len() < 2 {
        return (m, 0.0);
    }
    let var = v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0);
    (m, var.sqrt())
}

/// Per split, the scores of every image. PSNR is averaged per image in dB (as
/// GaussianAvatars does); an identical pair (infinite PSNR) is counted at [`PSNR_CAP`].
#[derive(Clone, Debug, Default)]
pub struct Tally {
    scores: BTreeMap<String, Vec<Scores>>,
}

/// PSNR used for a perfect match when averaging (100 dB).
pub const PSNR_CAP: f64 = 100.0;

/// Mean and deviation of the values present, `None` when there are none.
fn mean_std_some(v: &[Option<f64>]) -> (Option<f64>, Option<f64>) {
    let some: Vec<f64> = v.iter().flatten().copied().collect();
    if some.is_empty() {
        return (None, None);
    }
    let (m, s) = mean_std(&some);
    (Some(m), Some(s))
}

/// Means and deviations over a list of per-item values: `(psnr, ssim, [lpips x3])`.
fn summarise(items: &[(f64, f64, [Option<f64>; 3])], images: usize, subjects: usize) -> Means {
    let (psnr, psnr_std) = mean_std(&items.iter().map(|i| i.0).collect::<Vec<_>>());
    let (ssim, ssim_std) = mean_std(&items.iter().map(|i| i.1).collect::<Vec<_>>());
    let l = |k: usize| mean_std_some(&items.iter().map(|i| i.2[k]).collect::<Vec<_>>());
    let (a, v, u) = (l(0), l(1), l(2));
    Means {
        images,
        psnr,
        ssim,
        lpips_alex: a.0,
        lpips_vgg: v.0,
        lpips_alex_unscaled_inputs: u.0,
        psnr_std,
        ssim_std,
        lpips_alex_std: a.1,
        lpips_vgg_std: v.1,
        lpips_alex_unscaled_inputs_std: u.1,
        subjects,
    }
}

impl Tally {
    /// Adds one image's scores to the split named `split` (a [`crate::data::Split`]'s name or an extra
    /// split's).
    pub fn add(&mut self, split: &str, s: &Scores) {
        self.scores.entry(split.to_string()).or_default().push(*s);
    }

    /// The means and standard deviations over the images, per split name.
    pub fn means(&self) -> BTreeMap<String, Means> {
        self.scores
            .iter()
            .map(|(k, v)| {
                let items: Vec<_> = v
                    .iter()
                    .map(|s| {
                        (
                            if s.psnr.is_finite() { s.psnr } else { PSNR_CAP },
                            s.ssim,
                            [s.lpips_alex, s.lpips_vgg, s.lpips_alex_unscaled_inputs],
                        )
                    })
                    .collect();
                (k.clone(), summarise(&items, v.len(), 0))
            })
            .collect()
    }
}

/// Several subjects' means per split (each from [`Tally::means`]) combined as the paper
/// reports a multi-subject benchmark: per split, the mean over the subjects of each
/// subject's mean, and the standard deviation over the subjects. A split counts the
/// subjects that have it; `images` is their total.
pub fn combine_subjects(subjects: &[BTreeMap<String, Means>]) -> BTreeMap<String, Means> {
    let mut splits: BTreeMap<String, Vec<Means>> = BTreeMap::new();
    for s in subjects {
        for (k, m) in s {
            splits.entry(k.clone()).or_default().push(*m);
        }
    }
    splits
        .into_iter()
        .map(|(k, ms)| {
            let items: Vec<_> = ms
                .iter()
                .map(|m| {
                    (
                        m.psnr,
                        m.ssim,
                        [m.lpips_alex, m.lpips_vgg, m.lpips_alex_unscaled_inputs],
                    )
                })
                .collect();
            let images = ms.iter().map(|m| m.images).sum();
            (k, summarise(&items, images, ms.len()))
        })
        .collect()
}

/// `mean ± std` with `digits` decimals.
fn pm(mean: f64, std: f64, digits: usize) -> String {
    format!("{mean:.digits$} ± {std:.digits$}")
}

/// The paper's table (method.md §7): rows novel expression (held-out = `test`), novel
/// expression (FREE = `free`), novel view (`val`); columns LPIPS (alex), SSIM, PSNR, each
/// as mean ± standard deviation (over the images, or over the subjects when the means were
/// [`combine_subjects`]d, as the caption line under the table says). The paper's mean over
/// NeRSemble subjects is given beside each row for orientation only: the data differ.
pub fn paper_table(means: &BTreeMap<String, Means>) -> String {
    let rows = [
        ("novel expression (held-out)", "test", (0.048, 0.894, 25.61)),
        ("novel expression (FREE)", "free", (0.077, 0.861, 22.84)),
        ("novel view", "val", (0.030, 0.947, 35.15)),
    ];
    let lpips = |m: &Means| match (m.lpips_alex, m.lpips_alex_std) {
        (Some(v), s) => pm(v, s.unwrap_or(0.0), 3),
        (None, _) => "n/a".to_string(),
    };
    let mut s = String::from(
        "| split | LPIPS | SSIM | PSNR | images | paper (NeRSemble) LPIPS / SSIM / PSNR |\n|---|---|---|---|---|---|\n",
    );
    for (label, key, paper) in rows {
        let Some(m) = means.get(key) else { continue };
        s.push_str(&format!(
            "| {label} | {} | {} | {} | {} | {:.3} / {:.3} / {:.2} |\n",
            lpips(m),
            pm(m.ssim, m.ssim_std, 3),
            pm(m.psnr, m.psnr_std, 2),
            m.images,
            paper.0,
            paper.1,
            paper.2
        ));
    }
    // Extra splits (`eval --split NAME=PATH`) have no paper figure.
    for (key, m) in means {
        if rows.iter().any(|r| r.1 == key) {
            continue;
        }
        s.push_str(&format!(
            "| {key} | {} | {} | {} | {} | |\n",
            lpips(m),
            pm(m.ssim, m.ssim_std, 3),
            pm(m.psnr, m.psnr_std, 2),
            m.images
        ));
    }
    let subjects = means.values().map(|m| m.subjects).max().unwrap_or(0);
    if subjects > 0 {
        s.push_str(&format!(
            "\nMean ± standard deviation over {subjects} subjects (each subject's mean over its images); images: the subjects' total.\n"
        ));
    } else if !means.is_empty() {
        s.push_str("\nMean ± standard deviation over the images.\n");
    }
    s
}

/// Ground truth | render | error side by side under a header row naming the columns, the
/// render's with its PSNR (`psnr`, dB; "identical" when infinite): a 3W-wide image of
/// [`header_height`](crate::eval::plot::header_height)`(W)` header rows and the H image rows. The error e is the mean
/// absolute channel difference times 4 ("error ×4"), shown black (0) → red (e = 0.5) →
/// yellow (e >= 1, i.e. a mean difference of 0.25 or more).
pub fn panel(
    reference: &[f32],
    image: &[f32],
    height: usize,
    width: usize,
    psnr: f64,
) -> Result<crate::io::image::RgbImage> {
    let render = if psnr.is_finite() {
        format!("render, {psnr:.1} dB")
    } else {
        "render, identical".to_string()
    };
    panel_named(
        reference,
        image,
        height,
        width,
        ["ground truth", &render, "error ×4"],
    )
}

/// [`panel`] under the header `names` (reference, image, difference).
pub fn panel_named(
    reference: &[f32],
    image: &[f32],
    height: usize,
    width: usize,
    names: [&str; 3],
) -> Result<crate::io::image::RgbImage> {
    use crate::eval::plot;
    let mut out = plot::header(width, &names)?;
    let top = out.len();
    out.resize(top + height * width * 9, 0.0);
    for y in 0..height {
        for x in 0..width {
            let i = (y * width + x) * 3;
            let o = top + (y * width * 3 + x) * 3;
            let (r, g) = (&reference[i..i + 3], &image[i..i + 3]);
            let e = (0..3).map(|c| (r[c] - g[c]).abs()).sum::<f32>() / 3.0 * 4.0;
            let heat = [
                (2.0 * e).clamp(0.0, 1.0),
                (2.0 * e - 1.0).clamp(0.0, 1.0),
                0.0,
            ];
            for c in 0..3 {
                out[o + c] = r[c];
                out[o + width * 3 + c] = g[c].clamp(0.0, 1.0);
                out[o + width * 6 + c] = heat[c];
            }
        }
    }
    Ok(crate::io::image::RgbImage {
        width: 3 * width,
        height: plot::header_height(width) + height,
        rgb: out,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::plot;

    #[test]
    fn tally_means_and_table() {
        let mut t = Tally::default();
        let s = |p, q| Scores {
            psnr: p,
            ssim: q,
            lpips_alex: Some(0.1),
            ..Default::default()
        };
        t.add("test", &s(20.0, 0.8));
        t.add("test", &s(30.0, 0.9));
        t.add("val", &s(f64::INFINITY, 1.0));
        let m = t.means();
        assert_eq!(m["test"].images, 2);
        assert!((m["test"].psnr - 25.0).abs() < 1e-12);
        assert!((m["test"].ssim - 0.85).abs() < 1e-12);
        assert_eq!(m["val"].psnr, PSNR_CAP);
        assert_eq!(m["test"].lpips_vgg, None);
        // Sample deviations over the images: PSNR 20 and 30 → 7.07; SSIM 0.8, 0.9 → 0.0707.
        assert!((m["test"].psnr_std - 50f64.sqrt()).abs() < 1e-9);
        assert!((m["test"].ssim_std - 0.005f64.sqrt()).abs() < 1e-9);
        assert_eq!(m["test"].lpips_alex_std, Some(0.0));
        assert_eq!(m["val"].psnr_std, 0.0, "one image");
        let table = paper_table(&m);
        assert!(
            table.contains(
                "| novel expression (held-out) | 0.100 ± 0.000 | 0.850 ± 0.071 | 25.00 ± 7.07 | 2 |"
            ),
            "{table}"
        );
        assert!(table.contains("| novel view |"));
        assert!(table.contains("over the images"));
        assert!(!table.contains("FREE"), "no free rows without free images");
        // Two subjects: mean and deviation over the subjects' means.
        let mut t2 = Tally::default();
        t2.add("test", &s(40.0, 0.95));
        let both = combine_subjects(&[m.clone(), t2.means()]);
        let b = both["test"];
        assert_eq!((b.subjects, b.images), (2, 3));
        assert!((b.psnr - 32.5).abs() < 1e-12);
        assert!((b.psnr_std - (2.0 * 7.5f64.powi(2)).sqrt()).abs() < 1e-9);
        assert_eq!(both["val"].subjects, 1);
        let table = paper_table(&both);
        assert!(table.contains("32.50 ± 10.61"), "{table}");
        assert!(table.contains("over 2 subjects"), "{table}");
        // metrics.json written before the deviations existed still reads.
        let old: Means = serde_json::from_str(
            r#"{"images": 2, "psnr": 25.0, "ssim": 0.85, "lpips_alex": null, "lpips_vgg": null, "lpips_alex_unscaled_inputs": null}"#,
        )
        .expect("old means");
        assert_eq!((old.psnr, old.psnr_std, old.subjects), (25.0, 0.0, 0));
    }

    #[test]
    fn panel_shows_both_images_and_the_error() {
        let r = vec![0.5f32; 2 * 2 * 3];
        let mut g = r.clone();
        g[0] = 1.0; // pixel (0, 0), red channel off by 0.5
        let p = panel(&r, &g, 2, 2, 31.24).expect("panel");
        let top = plot::header_height(2);
        assert_eq!((p.width, p.height), (6, top + 2));
        assert_eq!(p.rgb.len(), (top + 2) * 6 * 3);
        let q = &p.rgb[top * 6 * 3..];
        assert_eq!(&q[0..3], &[0.5, 0.5, 0.5]); // reference
        assert_eq!(&q[6..9], &[1.0, 0.5, 0.5]); // render
        // error of pixel (0, 0): mean 0.5 / 3 * 4 = 0.667: red on, some green
        assert!(
            q[12] > 0.6 && q[13] > 0.3 && q[14] == 0.0,
            "{:?}",
            &q[12..15]
        );
        // error-free pixel (1, 0) is black
        assert_eq!(&q[15..18], &[0.0, 0.0, 0.0]);
    }

    #[test]
    fn panel_header_names_the_columns() {
        // The demo's image size: 138 x 200, a uniform grey reference and a darker render.
        let (h, w) = (200, 138);
        let r = vec![0.5f32; h * w * 3];
        let g = vec![0.4f32; h * w * 3];
        let p = panel(&r, &g, h, w, 20.0).expect("panel");
        let top = plot::header_height(w);
        assert!(top >= 17, "{top} header rows");
        assert_eq!((p.width, p.height), (3 * w, top + h));
        let px = |y: usize, x: usize| &p.rgb[(y * p.width + x) * 3..(y * p.width + x) * 3 + 3];
        // a white band with dark text in each of the three columns
        for k in 0..3 {
            let (mut text, mut white) = (0, 0);
            for y in 0..top {
                for x in k * w..(k + 1) * w {
                    let v = px(y, x);
                    text += usize::from(v.iter().all(|&c| c < 0.5));
                    white += usize::from(v.iter().all(|&c| c == 1.0));
                }
            }
            assert!(text > 20, "column {k}: {text} text pixels");
            assert!(white > top * w / 2, "column {k}: {white} white pixels");
        }
        // the columns' contents start right below the header, at their offsets
        for y in [top, top + h - 1] {
            assert_eq!(px(y, 0), &[0.5, 0.5, 0.5]);
            assert_eq!(px(y, w - 1), &[0.5, 0.5, 0.5]);
            assert_eq!(px(y, w), &[0.4, 0.4, 0.4]);
            assert_eq!(px(y, 2 * w - 1), &[0.4, 0.4, 0.4]);
            // error 0.1 * 4 = 0.4: red 0.8, no green
            let e = px(y, 2 * w);
            assert!((e[0] - 0.8).abs() < 1e-5 && e[1] == 0.0, "{e:?}");
        }
        if std::env::var_os("TEXAVATARS_KEEP_PANEL").is_some() {
            let out = std::env::temp_dir().join("texavatars-panel.png");
            crate::io::image::write_png(&out, p.width, p.height, &p.rgb).expect("png");
        }
    }

    #[test]
    fn scorer_without_lpips() {
        let d = crate::device::BackendKind::Cpu.device();
        let s = Scorer::new(&d, false).expect("scorer");
        let a = vec![0.25f32; 8 * 8 * 3];
        let mut b = a.clone();
        b[0] = 0.35;
        let sc = s.score(&a, &b, 8, 8).expect("score");
        // MSE = 0.01 / 192 → PSNR = 10 log10(19200)
        assert!(
            (sc.psnr - 10.0 * 19200f64.log10()).abs() < 1e-3,
            "{}",
            sc.psnr
        );
        assert!(sc.ssim < 1.0 && sc.ssim > 0.9);
        assert!(sc.lpips_alex.is_none());
        assert!(s.score(&a, &b[..10], 8, 8).is_err());
    }
}
