//! Per-image scores and their means per split.
//!
//! Every image is scored on the full frame with a white background, clamped to [0, 1]:
//! PSNR, SSIM (11x11 Gaussian window, sigma 1.5), LPIPS-alex v0.1 with inputs scaled to
//! [-1, 1] (the metric's definition), LPIPS-vgg, and the GaussianAvatars-compatible
//! LPIPS-alex that passes [0, 1] images unscaled (its issue #100).

use std::collections::BTreeMap;

use burn::tensor::{Device, Tensor, TensorData};
use serde::Serialize;

use crate::error::{Error, Result};
use crate::metrics::{self, Lpips, Net};

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
    vgg: Option<Lpips>,
}

impl Scorer {
    /// A scorer on `device`; with `lpips` the AlexNet and VGG16 weights are loaded (a clear
    /// error naming the missing file and the install command when absent).
    pub fn new(device: &Device, lpips: bool) -> Result<Self> {
        let (alex, vgg) = if lpips {
            (
                Some(Lpips::load(Net::AlexNet, device)?),
                Some(Lpips::load(Net::Vgg16, device)?),
            )
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
        let t = |x: &[f32]| {
            let clamped: Vec<f32> = x.iter().map(|v| v.clamp(0.0, 1.0)).collect();
            metrics::hwc_to_nchw(Tensor::<3>::from_data(
                TensorData::new(clamped, [height, width, 3]),
                &self.device,
            ))
        };
        let (a, b) = (t(image), t(reference));
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
            lpips_vgg: self
                .vgg
                .as_ref()
                .map(|m| first(m.distance(a.clone(), b.clone()))),
            lpips_alex_unscaled_inputs: self
                .alex
                .as_ref()
                .map(|m| first(m.distance_raw(a.clone(), b.clone()))),
        })
    }
}

/// Means of scores over a split.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Means {
    pub images: usize,
    pub psnr: f64,
    pub ssim: f64,
    pub lpips_alex: Option<f64>,
    pub lpips_vgg: Option<f64>,
    pub lpips_alex_unscaled_inputs: Option<f64>,
}

/// Running sums per split. PSNR is averaged per image in dB (as GaussianAvatars does); an
/// identical pair (infinite PSNR) is counted at [`PSNR_CAP`].
#[derive(Clone, Debug, Default)]
pub struct Tally {
    sums: BTreeMap<String, Sums>,
}

/// Per split: images, PSNR sum, SSIM sum, LPIPS sums (alex, vgg, alex unscaled) and counts.
type Sums = (usize, f64, f64, [f64; 3], [usize; 3]);

/// PSNR used for a perfect match when averaging (100 dB).
pub const PSNR_CAP: f64 = 100.0;

impl Tally {
    /// Adds one image's scores to the split named `split` (a [`crate::data::Split`]'s name or an extra
    /// split's).
    pub fn add(&mut self, split: &str, s: &Scores) {
        let e = self.sums.entry(split.to_string()).or_default();
        e.0 += 1;
        e.1 += if s.psnr.is_finite() { s.psnr } else { PSNR_CAP };
        e.2 += s.ssim;
        for (k, v) in [s.lpips_alex, s.lpips_vgg, s.lpips_alex_unscaled_inputs]
            .into_iter()
            .enumerate()
        {
            if let Some(v) = v {
                e.3[k] += v;
                e.4[k] += 1;
            }
        }
    }

    /// The means per split name.
    pub fn means(&self) -> BTreeMap<String, Means> {
        self.sums
            .iter()
            .map(|(k, (n, p, s, l, c))| {
                let n = (*n).max(1) as f64;
                let m = |i: usize| (c[i] > 0).then(|| l[i] / c[i] as f64);
                (
                    k.clone(),
                    Means {
                        images: n as usize,
                        psnr: p / n,
                        ssim: s / n,
                        lpips_alex: m(0),
                        lpips_vgg: m(1),
                        lpips_alex_unscaled_inputs: m(2),
                    },
                )
            })
            .collect()
    }
}

/// The paper's table (method.md §7): rows novel expression (held-out = `test`), novel
/// expression (FREE = `free`), novel view (`val`); columns LPIPS (alex), SSIM, PSNR. The
/// paper's mean over NeRSemble subjects is given beside each row for orientation only: the
/// data differ.
pub fn paper_table(means: &BTreeMap<String, Means>) -> String {
    let rows = [
        ("novel expression (held-out)", "test", (0.048, 0.894, 25.61)),
        ("novel expression (FREE)", "free", (0.077, 0.861, 22.84)),
        ("novel view", "val", (0.030, 0.947, 35.15)),
    ];
    let mut s = String::from(
        "| split | LPIPS | SSIM | PSNR | images | paper (NeRSemble) LPIPS / SSIM / PSNR |\n|---|---|---|---|---|---|\n",
    );
    for (label, key, paper) in rows {
        let Some(m) = means.get(key) else { continue };
        let lp = m
            .lpips_alex
            .map_or("n/a".to_string(), |v| format!("{v:.3}"));
        s.push_str(&format!(
            "| {label} | {lp} | {:.3} | {:.2} | {} | {:.3} / {:.3} / {:.2} |\n",
            m.ssim, m.psnr, m.images, paper.0, paper.1, paper.2
        ));
    }
    // Extra splits (`eval --split NAME=PATH`) have no paper figure.
    for (key, m) in means {
        if rows.iter().any(|r| r.1 == key) {
            continue;
        }
        let lp = m
            .lpips_alex
            .map_or("n/a".to_string(), |v| format!("{v:.3}"));
        s.push_str(&format!(
            "| {key} | {lp} | {:.3} | {:.2} | {} | |\n",
            m.ssim, m.psnr, m.images
        ));
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
    use crate::eval::plot;
    let render = if psnr.is_finite() {
        format!("render, {psnr:.1} dB")
    } else {
        "render, identical".to_string()
    };
    let mut out = plot::header(width, &["ground truth", &render, "error ×4"])?;
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
        let table = paper_table(&m);
        assert!(
            table.contains("| novel expression (held-out) | 0.100 | 0.850 | 25.00 | 2 |"),
            "{table}"
        );
        assert!(table.contains("| novel view |"));
        assert!(!table.contains("FREE"), "no free rows without free images");
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
