//! `texavatars splat ...`: render 3DGS PLY files.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use clap::{Args, Subcommand};

use crate::camera::CameraFile;
use crate::device::BackendKind;
use crate::io;
use crate::limits;
use crate::splat::{Gaussians, SplatParams, demo, ply, render};

/// Rasterizer commands.
#[derive(Debug, Subcommand)]
pub enum SplatCommand {
    /// Render a standard 3DGS PLY from a camera.
    Render(RenderArgs),
    /// Write a small procedural head-like scene (PLY + camera JSON) and render it.
    Demo(DemoArgs),
}

/// Arguments of `splat render`.
#[derive(Debug, Args)]
pub struct RenderArgs {
    /// The 3DGS PLY file (INRIA layout, SH degree 0-3).
    #[arg(long)]
    pub ply: PathBuf,
    /// Camera JSON: width, height, fx, fy, cx, cy, world_to_camera (row-major, OpenCV),
    /// optional background. Width and height are at most 16384 and the image's buffers must
    /// fit the memory budget (see --max-memory).
    #[arg(long)]
    pub camera: PathBuf,
    /// Output PNG.
    #[arg(long)]
    pub out: PathBuf,
    /// Also write the float32 [H, W, 3] image as .npy.
    #[arg(long)]
    pub raw: Option<PathBuf>,
    /// Where to run.
    #[arg(long, value_enum, default_value_t = BackendKind::Cpu)]
    pub backend: BackendKind,
}

/// Arguments of `splat demo`.
#[derive(Debug, Args)]
pub struct DemoArgs {
    /// Output folder (scene.ply, camera.json, render.png).
    #[arg(long, default_value = "out/splat-demo")]
    pub out: PathBuf,
    /// Number of Gaussians (at most 16777216).
    #[arg(long, default_value_t = 30_000)]
    pub gaussians: usize,
    /// Where to run.
    #[arg(long, value_enum, default_value_t = BackendKind::Cpu)]
    pub backend: BackendKind,
}

/// Runs a rasterizer command.
pub fn run(cmd: SplatCommand) -> anyhow::Result<()> {
    match cmd {
        SplatCommand::Render(a) => {
            let rendered = render_file(&a.ply, &a.camera, &a.out, a.raw.as_deref(), a.backend)?;
            println!("{rendered}");
            Ok(())
        }
        SplatCommand::Demo(a) => {
            limits::check_size("splat demo", "--gaussians", a.gaussians, &limits::GAUSSIANS)?;
            limits::check_memory(
                "splat demo",
                "--gaussians",
                limits::product(&[a.gaussians as u64, limits::GAUSSIAN_BYTES]),
            )?;
            std::fs::create_dir_all(&a.out)
                .with_context(|| format!("creating {}", a.out.display()))?;
            let ply_path = a.out.join("scene.ply");
            let cam_path = a.out.join("camera.json");
            ply::write(&ply_path, &demo::scene(a.gaussians, 7))?;
            let cam = serde_json::to_string_pretty(&demo::camera())?;
            std::fs::write(&cam_path, cam)
                .with_context(|| format!("writing {}", cam_path.display()))?;
            let out = a.out.join("render.png");
            let rendered = render_file(&ply_path, &cam_path, &out, None, a.backend)?;
            println!("{rendered}");
            Ok(())
        }
    }
}

/// Loads `ply` and `camera`, renders on `backend`, writes the PNG (and the raw .npy).
/// Returns a one-line summary.
pub fn render_file(
    ply_path: &Path,
    camera: &Path,
    out: &Path,
    raw: Option<&Path>,
    backend: BackendKind,
) -> anyhow::Result<String> {
    let cam = CameraFile::load(camera)?;
    let (cam_what, w, h) = (
        camera.display().to_string(),
        u64::from(cam.camera.width),
        u64::from(cam.camera.height),
    );
    limits::check_image_size(&cam_what, "", w, h)?;
    let image = limits::product(&[w, h, limits::SPLAT_BYTES_PER_PIXEL]);
    limits::check_memory(&cam_what, "width x height", image)?;
    let scene = ply::read(ply_path)?;
    let ply_what = ply_path.display().to_string();
    limits::check_size(&ply_what, "vertex count", scene.len(), &limits::GAUSSIANS)?;
    limits::check_estimate(
        &ply_what,
        "vertex count",
        &limits::Estimate::new()
            .add(format!("{w}x{h} image buffers"), image)
            .add(
                format!("{} Gaussians", scene.len()),
                limits::product(&[scene.len() as u64, limits::GAUSSIAN_BYTES]),
            ),
    )?;
    let device = backend.device();
    let start = Instant::now();
    let gaussians = Gaussians::from_ply(&scene, cam.camera.position(), &device);
    let params = SplatParams {
        camera: cam.camera,
        background: cam.background,
    };
    let rendered = render(&gaussians, &params)?;
    let (w, h) = (cam.camera.width as usize, cam.camera.height as usize);
    let rgb: Vec<f32> = rendered.image.into_data().iter::<f32>().collect();
    let elapsed = start.elapsed();
    for p in [Some(out), raw].into_iter().flatten() {
        if let Some(parent) = p.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(parent)
                .with_context(|| format!("creating {}", parent.display()))?;
        }
    }
    io::image::write_png(out, w, h, &rgb)?;
    if let Some(raw) = raw {
        io::npy::write(raw, &[h, w, 3], &rgb)?;
    }
    Ok(format!(
        "rendered {} Gaussians at {w}x{h} on {backend:?} in {:.1} ms -> {}",
        scene.len(),
        elapsed.as_secs_f64() * 1e3,
        out.display()
    ))
}
