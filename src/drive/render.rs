//! Rendering a driven avatar: one PNG per motion frame, a contact sheet, an animated GIF, and
//! an MP4 when `ffmpeg` is on the PATH.
//!
//! Frames are written as they are rendered (`OUT/frames/00000.png`, ...), so an interrupted
//! run keeps what it made; the GIF is encoded frame by frame into a temporary file, the sheet
//! and MP4 are written at the end, each through a temporary file. A run first removes the
//! files of an earlier run in the same folder ([`crate::drive::outputs`]).

use std::path::{Path, PathBuf};
use std::process::Command;

use burn::tensor::Device;
use image::codecs::gif::{GifEncoder, Repeat};
use image::imageops::FilterType;
use image::{Delay, Frame, RgbImage, RgbaImage};

use crate::camera::Camera;
use crate::data::Conditioning;
use crate::drive::motion::Motion;
use crate::drive::outputs;
use crate::error::{Error, Result};
use crate::io;
use crate::limits;
use crate::models::{Drivable, ViewCache};
use crate::splat::Gaussians;

/// Frames on the contact sheet (evenly spread over the motion).
const SHEET_FRAMES: usize = 16;
/// Columns of the contact sheet.
const SHEET_COLUMNS: usize = 4;
/// Longest side of a contact-sheet tile and of a GIF frame, pixels.
const THUMB_SIDE: u32 = 256;
const GIF_SIDE: u32 = 400;

/// Options of [`render_motion`].
#[derive(Clone, Debug)]
pub struct RenderOptions {
    /// Output folder.
    pub out: PathBuf,
    /// Frames per second of the GIF and the MP4.
    pub fps: u32,
    /// Write the MP4 when `ffmpeg` is found.
    pub mp4: bool,
}

/// What [`render_motion`] wrote.
#[derive(Clone, Debug)]
pub struct RenderReport {
    pub frames: Vec<PathBuf>,
    pub sheet: PathBuf,
    pub gif: PathBuf,
    /// The MP4, or why there is none.
    pub mp4: std::result::Result<PathBuf, String>,
}

/// Checks that a motion fits an avatar (vertex count and condition width).
pub fn check_motion(avatar: &dyn Drivable, motion: &Motion) -> Result<()> {
    let what = motion.source.display().to_string();
    for f in &motion.frames {
        check_frame(avatar, &f.conditioning, &what)?;
    }
    Ok(())
}

/// Checks that one frame fits an avatar: its posed mesh's vertex count and, for a model
/// with networks, its condition width; `what` names the frame's source in errors.
pub fn check_frame(avatar: &dyn Drivable, c: &Conditioning, what: &str) -> Result<()> {
    if c.vertices.len() != avatar.num_vertices() {
        return Err(Error::invalid(
            what,
            "vertices",
            format!(
                "the motion's head has {} vertices, the avatar's {}: drive it with the head \
                 model it was trained on (--head)",
                c.vertices.len(),
                avatar.num_vertices()
            ),
        ));
    }
    let got = c.expr.len() + c.pose.len() + c.eta.len();
    if let Some(want) = avatar.condition_width().filter(|w| *w != got) {
        return Err(Error::invalid(
            what,
            "condition",
            format!("{got} values, the avatar's networks take {want}"),
        ));
    }
    Ok(())
}

/// The avatar's image [H, W, 3] (host, row-major) and Gaussians for one frame and camera.
pub fn render_frame(
    avatar: &dyn Drivable,
    c: &Conditioning,
    camera: &Camera,
    device: &Device,
) -> Result<(Vec<f32>, Gaussians)> {
    render_frame_in_view(avatar, c, camera, None, device)
}

/// [`render_frame`] with what the model computed from this camera alone
/// ([`Drivable::view_cache`]), kept by callers while the camera stays put.
pub fn render_frame_in_view(
    avatar: &dyn Drivable,
    c: &Conditioning,
    camera: &Camera,
    view: Option<&ViewCache>,
    device: &Device,
) -> Result<(Vec<f32>, Gaussians)> {
    let g = avatar.frame_gaussians_staged(c, camera, view, device, &mut |_| Ok(()))?;
    let params = crate::splat::SplatParams {
        camera: *camera,
        background: crate::data::BACKGROUND,
    };
    let image = crate::splat::render(&g, &params)?.image;
    Ok((image.into_data().iter::<f32>().collect(), g))
}

/// Renders every frame of `motion` from `cameras` (one per frame) into `opts.out`;
/// `progress(done, total)` is called after each frame. The work runs on rayon's pool
/// ([`texavatars_cpu::threads::on_pool`]).
///
/// After the inputs are checked, the files an earlier `render` left in `opts.out` are
/// removed ([`crate::drive::outputs::clear_render_outputs`]: `frames/NNNNN.png`, the sheet,
/// the GIF, the MP4; nothing else), so a shorter run never leaves frames of a longer one
/// behind. Frames are encoded into the GIF as they are rendered, so memory does not grow
/// with the motion's length. On an error the temporary files are removed.
pub fn render_motion(
    avatar: &dyn Drivable,
    motion: &Motion,
    cameras: &[Camera],
    device: &Device,
    opts: &RenderOptions,
    progress: &mut (dyn FnMut(usize, usize) + Send),
) -> Result<RenderReport> {
    texavatars_cpu::threads::on_pool(|| {
        render_motion_here(avatar, motion, cameras, device, opts, progress)
    })
}

fn render_motion_here(
    avatar: &dyn Drivable,
    motion: &Motion,
    cameras: &[Camera],
    device: &Device,
    opts: &RenderOptions,
    progress: &mut (dyn FnMut(usize, usize) + Send),
) -> Result<RenderReport> {
    check_motion(avatar, motion)?;
    if cameras.len() != motion.frames.len() {
        return Err(Error::invalid(
            "render",
            "cameras",
            format!(
                "{} cameras for {} frames",
                cameras.len(),
                motion.frames.len()
            ),
        ));
    }
    if opts.fps == 0 {
        return Err(Error::invalid("render", "fps", "must be at least 1"));
    }
    check_render_memory(avatar, motion, cameras)?;
    outputs::clear_render_outputs(&opts.out)?;
    let r = render_frames(avatar, motion, cameras, device, opts, progress);
    if r.is_err() {
        outputs::remove_render_partials(&opts.out);
    }
    r
}

/// The memory a render of `motion` from `cameras` needs, checked against
/// [`crate::limits::budget`] (the motion's frames held, one frame's buffers at the largest
/// camera, the avatar's inference).
pub fn check_render_memory(
    avatar: &dyn Drivable,
    motion: &Motion,
    cameras: &[Camera],
) -> Result<()> {
    let what = motion.source.display().to_string();
    let (mut w, mut h, mut px) = (0u64, 0u64, 0u64);
    for c in cameras {
        limits::check_image_size(&what, "camera ", c.width.into(), c.height.into())?;
        let p = u64::from(c.width) * u64::from(c.height);
        if p > px {
            (w, h, px) = (c.width.into(), c.height.into(), p);
        }
    }
    let per_frame = motion.frames.first().map_or(0, |f| {
        let c = &f.conditioning;
        limits::motion_frame_bytes(c.vertices.len(), c.expr.len() + c.pose.len() + c.eta.len())
    });
    let (image, frames) = (
        limits::render_bytes(w, h),
        limits::product(&[motion.frames.len() as u64, per_frame]),
    );
    let estimate = limits::Estimate::new()
        .add(format!("{w}x{h} frame buffers"), image)
        .add(format!("{} motion frames", motion.frames.len()), frames)
        .add("avatar", avatar.inference_bytes());
    let field = if frames > image {
        "frames"
    } else {
        "image size"
    };
    limits::check_estimate(&what, field, &estimate)
}

fn render_frames(
    avatar: &dyn Drivable,
    motion: &Motion,
    cameras: &[Camera],
    device: &Device,
    opts: &RenderOptions,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<RenderReport> {
    let dir = opts.out.join("frames");
    std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
    let n = motion.frames.len();
    let sheet_at: Vec<usize> = (0..SHEET_FRAMES.min(n))
        .map(|i| i * n / SHEET_FRAMES.min(n))
        .collect();
    let mut thumbs = Vec::new();
    let gif = opts.out.join("render.gif");
    let mut gif_out = GifWriter::create(&gif, opts.fps)?;
    let mut frames = Vec::with_capacity(n);
    // The view's cache, kept while the camera stays put (a fixed camera: one for the run).
    let mut view: Option<(Camera, Option<ViewCache>)> = None;
    for (i, (f, cam)) in motion.frames.iter().zip(cameras).enumerate() {
        if view.as_ref().is_none_or(|(c, _)| c != cam) {
            view = Some((*cam, avatar.view_cache(cam, device)?));
        }
        let cache = view.as_ref().and_then(|(_, v)| v.as_ref());
        let (rgb, _) = render_frame_in_view(avatar, &f.conditioning, cam, cache, device)?;
        let (w, h) = (cam.width as usize, cam.height as usize);
        let path = dir.join(format!("{i:05}.png"));
        io::image::write_png(&path, w, h, &rgb)?;
        let img = to_rgb8(&rgb, w, h)?;
        if sheet_at.contains(&i) {
            thumbs.push(fit(&img, THUMB_SIDE));
        }
        gif_out.push(&fit(&img, GIF_SIDE))?;
        frames.push(path);
        progress(i + 1, n);
    }
    let sheet = opts.out.join("contact_sheet.png");
    write_sheet(&sheet, &thumbs)?;
    gif_out.finish()?;
    let mp4 = if opts.mp4 {
        write_mp4(&dir, &opts.out.join("render.mp4"), opts.fps)
    } else {
        Err("not asked for".into())
    };
    Ok(RenderReport {
        frames,
        sheet,
        gif,
        mp4,
    })
}

fn to_rgb8(rgb: &[f32], w: usize, h: usize) -> Result<RgbImage> {
    RgbImage::from_raw(w as u32, h as u32, io::image::to_bytes8(rgb))
        .ok_or_else(|| Error::invalid("render", "image", "size does not fit"))
}

/// Downscales so that the longer side is at most `side` (never upscales).
fn fit(img: &RgbImage, side: u32) -> RgbImage {
    let (w, h) = img.dimensions();
    let long = w.max(h);
    if long <= side {
        return img.clone();
    }
    let (nw, nh) = ((w * side / long).max(1), (h * side / long).max(1));
    image::imageops::resize(img, nw, nh, FilterType::Triangle)
}

fn write_sheet(path: &Path, thumbs: &[RgbImage]) -> Result<()> {
    let Some(first) = thumbs.first() else {
        return Err(Error::invalid("render", "frames", "no frames"));
    };
    let (tw, th) = first.dimensions();
    let cols = SHEET_COLUMNS.min(thumbs.len()) as u32;
    let rows = thumbs.len().div_ceil(cols as usize) as u32;
    let mut sheet = RgbImage::from_pixel(cols * tw, rows * th, image::Rgb([255, 255, 255]));
    for (k, t) in thumbs.iter().enumerate() {
        let (x, y) = ((k as u32 % cols) * tw, (k as u32 / cols) * th);
        image::imageops::overlay(&mut sheet, t, x as i64, y as i64);
    }
    let tmp = path.with_extension("png.partial");
    sheet
        .save_with_format(&tmp, image::ImageFormat::Png)
        .map_err(|e| Error::invalid(tmp.display().to_string(), "png", e.to_string()))?;
    std::fs::rename(&tmp, path).map_err(|e| Error::io(path, e))
}

/// An animated GIF written frame by frame to `X.gif.partial`, renamed to `X.gif` by
/// [`GifWriter::finish`].
struct GifWriter {
    path: PathBuf,
    tmp: PathBuf,
    enc: GifEncoder<std::io::BufWriter<std::fs::File>>,
    delay: Delay,
}

impl GifWriter {
    fn create(path: &Path, fps: u32) -> Result<Self> {
        let tmp = path.with_extension("gif.partial");
        let file = std::fs::File::create(&tmp).map_err(|e| Error::io(&tmp, e))?;
        let mut enc = GifEncoder::new_with_speed(std::io::BufWriter::new(file), 10);
        enc.set_repeat(Repeat::Infinite)
            .map_err(|e| Error::invalid(tmp.display().to_string(), "gif", e.to_string()))?;
        Ok(GifWriter {
            path: path.to_path_buf(),
            tmp,
            enc,
            delay: Delay::from_numer_denom_ms(1000, fps),
        })
    }

    fn push(&mut self, frame: &RgbImage) -> Result<()> {
        let rgba: RgbaImage = image::DynamicImage::ImageRgb8(frame.clone()).to_rgba8();
        self.enc
            .encode_frame(Frame::from_parts(rgba, 0, 0, self.delay))
            .map_err(|e| Error::invalid(self.tmp.display().to_string(), "gif", e.to_string()))
    }

    /// Writes the trailer (when the encoder is dropped) and renames the file into place.
    fn finish(self) -> Result<()> {
        let GifWriter { path, tmp, enc, .. } = self;
        drop(enc);
        std::fs::rename(&tmp, &path).map_err(|e| Error::io(&path, e))
    }
}

/// Encodes `frames/%05d.png` with ffmpeg (H.264, yuv420p, sizes padded to even); `Err` says
/// why there is no MP4 (no ffmpeg, or its error).
fn write_mp4(frames: &Path, path: &Path, fps: u32) -> std::result::Result<PathBuf, String> {
    let found = Command::new("ffmpeg")
        .arg("-version")
        .output()
        .is_ok_and(|o| o.status.success());
    if !found {
        return Err("ffmpeg is not on the PATH".into());
    }
    let tmp = path.with_extension("partial.mp4");
    let out = Command::new("ffmpeg")
        .args(["-y", "-loglevel", "error", "-framerate"])
        .arg(fps.to_string())
        .arg("-i")
        .arg(frames.join("%05d.png"))
        .args([
            "-vf",
            "pad=ceil(iw/2)*2:ceil(ih/2)*2:color=white",
            "-pix_fmt",
            "yuv420p",
        ])
        .arg(&tmp)
        .output()
        .map_err(|e| format!("ffmpeg: {e}"))?;
    if !out.status.success() {
        let _ = std::fs::remove_file(&tmp);
        return Err(format!(
            "ffmpeg failed: {}",
            String::from_utf8_lossy(&out.stderr).trim()
        ));
    }
    std::fs::rename(&tmp, path).map_err(|e| format!("{}: {e}", path.display()))?;
    Ok(path.to_path_buf())
}
