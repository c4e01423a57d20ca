//! `texavatars metrics`: PSNR, SSIM and LPIPS between two images, as one JSON object.

use std::path::PathBuf;

use clap::Args;

use crate::device::BackendKind;
use crate::eval::Scorer;
use crate::io::image::read_rgb;

/// Arguments of `metrics`.
#[derive(Debug, Args)]
pub struct MetricsArgs {
    /// The ground-truth image (PNG, RGB or grayscale, 8 or 16 bit).
    #[arg(long)]
    pub reference: PathBuf,
    /// The image to score, same size.
    #[arg(long)]
    pub image: PathBuf,
    /// Only PSNR and SSIM (no LPIPS, no weights needed).
    #[arg(long)]
    pub no_lpips: bool,
    /// Where the networks run. Defaults to flex: on the CPU, burn-ndarray's convolutions
    /// make LPIPS-alex slower than burn-flex's (LPIPS-vgg runs on the host network on
    /// both).
    #[arg(long, value_enum, default_value_t = BackendKind::Flex)]
    pub backend: BackendKind,
}

/// The numbers `metrics` prints. PSNR is `null` for identical images (infinite).
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Scores {
    pub psnr: f64,
    pub ssim: f64,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lpips_alex: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lpips_vgg: Option<f64>,
    /// LPIPS-alex fed [0, 1] images without mapping them to [-1, 1] (GaussianAvatars'
    /// evaluation code; not LPIPS as defined).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lpips_alex_unscaled_inputs: Option<f64>,
}

/// Scores `image` against `reference` on `backend`.
pub fn score(
    reference: &std::path::Path,
    image: &std::path::Path,
    lpips: bool,
    backend: BackendKind,
) -> anyhow::Result<Scores> {
    let r = read_rgb(reference)?;
    let i = read_rgb(image)?;
    if (r.width, r.height) != (i.width, i.height) {
        anyhow::bail!(
            "{}: size {}x{} differs from the reference {} ({}x{})",
            image.display(),
            i.width,
            i.height,
            reference.display(),
            r.width,
            r.height
        );
    }
    if lpips {
        crate::metrics::lpips::check_size(i.height, i.width, &image.display().to_string())?;
    }
    let scores = Scorer::new(&backend.device(), lpips)?.score(&r.rgb, &i.rgb, r.height, r.width)?;
    let s = Scores {
        psnr: scores.psnr,
        ssim: scores.ssim,
        lpips_alex: scores.lpips_alex,
        lpips_vgg: scores.lpips_vgg,
        lpips_alex_unscaled_inputs: scores.lpips_alex_unscaled_inputs,
    };
    Ok(s)
}

/// Runs `metrics`.
pub fn run(a: MetricsArgs) -> anyhow::Result<()> {
    let s = score(&a.reference, &a.image, !a.no_lpips, a.backend)?;
    println!("{}", serde_json::to_string(&s)?);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn images_too_small_for_lpips_are_an_error_not_a_panic() {
        let dir = std::env::temp_dir().join(format!("texavatars-metrics-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        let p = dir.join("small.png");
        image::RgbImage::new(30, 40).save(&p).expect("png");
        let e = score(&p, &p, true, BackendKind::Cpu)
            .expect_err("too small")
            .to_string();
        assert!(e.contains("small.png") && e.contains("31"), "{e}");
        let s = score(&p, &p, false, BackendKind::Cpu).expect("without LPIPS");
        assert!(s.lpips_alex.is_none());
        let _ = std::fs::remove_dir_all(&dir);
    }
}
