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
