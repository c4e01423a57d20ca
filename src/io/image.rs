//! PNG images from float tensors.

use std::path::Path;

use crate::error::{Error, Result};

/// Writes an [H, W] float image in [0, 1] (clamped, rounded) as an 8-bit grayscale PNG
/// (a foreground mask), through a temporary file.
pub fn write_gray_png(path: &Path, width: usize, height: usize, gray: &[f32]) -> Result<()> {
    if gray.len() != width * height {
        return Err(Error::invalid(
            path.display().to_string(),
            "image",
            format!("{} values for {width}x{height}", gray.len()),
        ));
    }
    let bytes: Vec<u8> = gray
        .iter()
        .map(|&v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
        .collect();
    let buf = image::GrayImage::from_raw(width as u32, height as u32, bytes)
        .ok_or_else(|| Error::invalid(path.display().to_string(), "image", "size does not fit"))?;
    let tmp = path.with_extension("png.partial");
    buf.save_with_format(&tmp, image::ImageFormat::Png)
        .map_err(|e| Error::invalid(tmp.display().to_string(), "png", e.to_string()))?;
    std::fs::rename(&tmp, path).map_err(|e| Error::io(path, e))
}

/// Writes an [H, W, 3] float image in [0, 1] (clamped, rounded) as an 8-bit PNG, through a
/// temporary file so an existing image is never left half-written.
pub fn write_png(path: &Path, width: usize, height: usize, rgb: &[f32]) -> Result<()> {
    if rgb.len() != width * height * 3 {
        return Err(Error::invalid(
            path.display().to_string(),
            "image",
            format!("{} values for {width}x{height}x3", rgb.len()),
        ));
    }
    let bytes: Vec<u8> = rgb
        .iter()
        .map(|&v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
        .collect();
    let buf = image::RgbImage::from_raw(width as u32, height as u32, bytes)
        .ok_or_else(|| Error::invalid(path.display().to_string(), "image", "size does not fit"))?;
    let tmp = path.with_extension("png.partial");
    buf.save_with_format(&tmp, image::ImageFormat::Png)
        .map_err(|e| Error::invalid(tmp.display().to_string(), "png", e.to_string()))?;
    std::fs::rename(&tmp, path).map_err(|e| Error::io(path, e))
}

/// An RGB image read from a file, values in [0, 1].
#[derive(Clone, Debug, PartialEq)]
pub struct RgbImage {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// [H, W, 3] row-major values (8-bit files give value / 255, 16-bit value / 65535).
    pub rgb: Vec<f32>,
}

/// Reads a grayscale or RGB PNG (8 or 16 bit) as [H, W, 3] floats in [0, 1]. Images with an
/// alpha channel are refused: composite them onto their background first, so that a metric
/// never silently ignores transparency.
pub fn read_rgb(path: &Path) -> Result<RgbImage> {
    let what = path.display().to_string();
    let reader = image::ImageReader::open(path)
        .map_err(|e| Error::io(path, e))?
        .with_guessed_format()
        .map_err(|e| Error::io(path, e))?;
    let img = reader
        .decode()
        .map_err(|e| Error::invalid(&what, "image", format!("cannot decode: {e}")))?;
    if img.color().has_alpha() {
        return Err(Error::invalid(
            &what,
            "image",
            format!(
                "has an alpha channel ({:?}); composite it onto its background first",
                img.color()
            ),
        ));
    }
    let rgb = img.to_rgb32f();
    Ok(RgbImage {
        width: rgb.width() as usize,
        height: rgb.height() as usize,
        rgb: rgb.into_raw(),
    })
}
