//! PNG images from float tensors.

use std::path::Path;

use crate::error::{Error, Result};

/// Float values in [0, 1] (clamped) as bytes, rounded: how every image is written.
pub fn to_bytes8(values: &[f32]) -> Vec<u8> {
    values
        .iter()
        .map(|&v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
        .collect()
}

/// An [H, W, 3] float image in [0, 1] encoded in memory as PNG, or as JPEG of `quality`
/// (1-100) when `jpeg_quality` is given.
pub fn encode_rgb(
    width: usize,
    height: usize,
    rgb: &[f32],
    jpeg_quality: Option<u8>,
) -> Result<Vec<u8>> {
    use image::ImageEncoder;
    if rgb.len() != width * height * 3 {
        return Err(Error::invalid(
            "image",
            "size",
            format!("{} values for {width}x{height}x3", rgb.len()),
        ));
    }
    let bytes = to_bytes8(rgb);
    let mut out = Vec::new();
    let (w, h, t) = (width as u32, height as u32, image::ExtendedColorType::Rgb8);
    let r = match jpeg_quality {
        Some(q) => image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, q.clamp(1, 100))
            .write_image(&bytes, w, h, t),
        None => image::codecs::png::PngEncoder::new(&mut out).write_image(&bytes, w, h, t),
    };
    r.map_err(|e| Error::invalid("image", "encode", e.to_string()))?;
    Ok(out)
}

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
    let buf = image::GrayImage::from_raw(width as u32, height as u32, to_bytes8(gray))
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
    let buf = image::RgbImage::from_raw(width as u32, height as u32, to_bytes8(rgb))
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
