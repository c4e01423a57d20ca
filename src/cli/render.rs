//! `texavatars render` and the arguments it shares with `export ply`: which avatar, which
//! motion, which cameras.

use std::ops::Range;
use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::{Args, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};

use crate::camera::Camera;
use crate::device::BackendKind;
use crate::drive::{self, CameraPath, Identity, Motion, MotionKind, RenderOptions, View};
use crate::models::{self, Drivable};

use crate::limits;

/// Camera paths on the command line.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum CamerasArg {
    /// The dataset's camera (`--camera-index`, default the middle index); dataset motions.
    Dataset,
    /// Swing `--orbit-degrees` to either side of the face and back.
    Orbit,
    /// A fixed frontal camera.
    Front,
}

/// Which avatar, driven by what, seen from where.
#[derive(Debug, Args)]
pub struct DriveArgs {
    /// The trained avatar: a `texavatars train` output folder (`avatar.json`, `avatar.bpk`),
    /// or a GaussianAvatars output folder (`point_cloud.ply` with `binding_0`, directly or in
    /// `point_cloud/iteration_N/`; give its FLAME model with teeth as --head).
    #[arg(long)]
    pub checkpoint: PathBuf,
    /// The motion: a dataset split (`DATA/transforms_test.json`), another subject's FLAME
    /// parameters (a VHAP export folder with `flame_param/`, a folder of `.npz`, or one
    /// `.npz`), or a curves JSON (see `texavatars::drive::Curves`).
    #[arg(long)]
    pub motion: PathBuf,
    /// Camera path. Default: `dataset` for a dataset motion, else `orbit`.
    #[arg(long, value_enum)]
    pub cameras: Option<CamerasArg>,
    /// The dataset camera for `--cameras dataset`.
    #[arg(long)]
    pub camera_index: Option<usize>,
    /// Swing of the orbit, degrees to either side.
    #[arg(long, default_value_t = 30.0)]
    pub orbit_degrees: f32,
    /// Image size of the orbit and front cameras, WIDTHxHEIGHT (each side at most 16384;
    /// the frame's buffers must fit the memory budget, see --max-memory).
    #[arg(long, default_value = "550x802")]
    pub size: String,
    /// Vertical field of view of the orbit and front cameras, degrees.
    #[arg(long, default_value_t = 20.0)]
    pub fov: f32,
    /// Distance of the orbit and front cameras from the head centre (model units).
    #[arg(long, default_value_t = 1.0)]
    pub distance: f32,
    /// Motion frames to use, `A..B` (B excluded) or `A`; default all.
    #[arg(long)]
    pub frames: Option<String>,
    /// The avatar's subject for FLAME-parameter and curve motions: a `flame_param` `.npz`
    /// whose shape and static offsets are used. Default: the run's
    /// `canonical_flame_param.npz` (the subject it was trained on) or a GaussianAvatars
    /// folder's `flame_param.npz`, else the head model's mean shape.
    #[arg(long)]
    pub identity: Option<PathBuf>,
    /// The head model the avatar was trained with (`.npz`, its `.obj` next to it). Default:
    /// `DATA/../head/head.npz` of a dataset motion when present, else the embedded head.
    #[arg(long)]
    pub head: Option<PathBuf>,
    /// Where tensors live.
    #[arg(long, value_enum, default_value_t = BackendKind::Flex)]
    pub backend: BackendKind,
}

/// A loaded avatar with its motion and cameras.
pub struct Driven {
    pub avatar: Box<dyn Drivable>,
    pub motion: Motion,
    pub cameras: Vec<Camera>,
    pub device: burn::tensor::Device,
    /// Position of the first selected frame in the whole motion.
    pub first: usize,
}

/// Parses `A..B` or `A` into a range (B excluded).
pub fn parse_frames(s: &str) -> anyhow::Result<Range<usize>> {
    let bad = || format!("--frames {s:?}: expected A..B (B excluded) or A");
    if let Some((a, b)) = s.split_once("..") {
        let a: usize = a.trim().parse().with_context(bad)?;
        let b: usize = b.trim().parse().with_context(bad)?;
        Ok(a..b)
    } else {
        let a: usize = s.trim().parse().with_context(bad)?;
        Ok(a..a + 1)
    }
}

/// Parses `WIDTHxHEIGHT`.
pub fn parse_size(s: &str) -> anyhow::Result<(u32, u32)> {
    let bad = || format!("--size {s:?}: expected WIDTHxHEIGHT, e.g. 550x802");
    let (w, h) = s.split_once(['x', 'X']).with_context(bad)?;
    Ok((
        w.trim().parse().with_context(bad)?,
        h.trim().parse().with_context(bad)?,
    ))
}

impl DriveArgs {
    /// Checks `--size` and `--frames` before anything is loaded: the size's syntax, its
    /// sides against [`limits::IMAGE_SIDE`] and one frame's buffers against the memory budget.
    pub fn check(&self) -> anyhow::Result<()> {
        let (width, height) = parse_size(&self.size)?;
        let what = format!("--size {}", self.size);
        limits::check_image_size(&what, "", width.into(), height.into())?;
        limits::check_memory(
            &what,
            "width x height",
            limits::render_bytes(width.into(), height.into()),
        )?;
        if let Some(f) = &self.frames {
            parse_frames(f)?;
        }
        Ok(())
    }

    /// Loads the avatar, the motion (restricted to `--frames`) and one camera per frame,
    /// after [`DriveArgs::check`]; the motion's frame count and the memory of the whole run
    /// (frames, image buffers, the avatar) are checked as soon as they are known.
    pub fn load(&self) -> anyhow::Result<Driven> {
        self.check()?;
        let head = drive::motion::head_for(self.head.as_deref(), Some(&self.motion))?;
        let device = self.backend.device();
        let loaded = models::load(&self.checkpoint, &head, &device)?;
        let avatar = loaded.avatar;
        let identity = match self.identity.as_ref().or(loaded.identity.as_ref()) {
            Some(p) => Identity::load(p)?,
            None => Identity::mean(&head.model),
        };
        let mut motion = Motion::load(&self.motion, &head.model, &head.meta, &identity)?;
        warn_eta(&self.motion, motion.kind, &self.checkpoint)?;
        let first = match &self.frames {
            Some(s) => {
                let r = parse_frames(s)?;
                let first = r.start;
                motion.select(r)?;
                first
            }
            None => 0,
        };
        let path = match self
            .cameras
            .unwrap_or(if motion.kind == MotionKind::Dataset {
                CamerasArg::Dataset
            } else {
                CamerasArg::Orbit
            }) {
            CamerasArg::Dataset => CameraPath::Dataset {
                index: self.camera_index,
            },
            CamerasArg::Orbit => CameraPath::Orbit {
                degrees: self.orbit_degrees,
            },
            CamerasArg::Front => CameraPath::Front,
        };
        let (width, height) = parse_size(&self.size)?;
        let view = View {
            width,
            height,
            fov_y_degrees: self.fov,
            distance: self.distance,
        };
        let cameras = drive::cameras(&motion, path, &view)?;
        drive::render::check_motion(avatar.as_ref(), &motion)?;
        drive::render::check_render_memory(avatar.as_ref(), &motion, &cameras)?;
        Ok(Driven {
            avatar,
            motion,
            cameras,
            device,
            first,
        })
    }
}

/// A progress bar on stderr for `total` frames.
pub fn progress_bar(total: usize, what: &str) -> ProgressBar {
    let bar = ProgressBar::new(total as u64);
    bar.set_style(
        ProgressStyle::with_template(&format!(
            "{what} {{bar:40}} {{pos}}/{{len}} frames  {{per_sec}}  eta {{eta}}"
        ))
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    bar
}

/// Arguments of `render`.
#[derive(Debug, Args)]
pub struct RenderArgs {
    #[command(flatten)]
    pub drive: DriveArgs,
    /// Output folder: frames/, contact_sheet.png, render.gif, render.mp4 (with ffmpeg). The
    /// files an earlier render left there (frames/NNNNN.png, contact_sheet.png, render.gif,
    /// render.mp4 and their unfinished *.partial files) are deleted first, so frames of a
    /// longer earlier run never mix with the new ones; nothing else is touched.
    #[arg(long)]
    pub out: PathBuf,
    /// Frames per second of the GIF and the MP4.
    #[arg(long, default_value_t = 25)]
    pub fps: u32,
    /// Do not write the MP4 even when ffmpeg is on the PATH.
    #[arg(long)]
    pub no_mp4: bool,
}

/// Runs `render`.
pub fn run(a: RenderArgs) -> anyhow::Result<()> {
    let d = a.drive.load()?;
    let n = d.motion.frames.len();
    let bar = progress_bar(n, "render");
    let opts = RenderOptions {
        out: a.out.clone(),
        fps: a.fps,
        mp4: !a.no_mp4,
    };
    let report = drive::render_motion(
        d.avatar.as_ref(),
        &d.motion,
        &d.cameras,
        &d.device,
        &opts,
        &mut |i, _| bar.set_position(i as u64),
    )?;
    bar.finish_and_clear();
    println!(
        "rendered {} frames of {} into {}: frames/, {}, {}",
        report.frames.len(),
        d.motion.source.display(),
        a.out.display(),
        file_name(&report.sheet),
        file_name(&report.gif)
    );
    match &report.mp4 {
        Ok(p) => println!("and {}", file_name(p)),
        Err(why) if !a.no_mp4 => println!("no MP4: {why}"),
        Err(_) => {}
    }
    Ok(())
}

fn file_name(p: &Path) -> String {
    p.file_name().map_or_else(
        || p.display().to_string(),
        |f| f.to_string_lossy().into_owned(),
    )
}

/// Says where the motion's eta comes from, and warns when its image codes were made with
/// another projection than the avatar's (`crate::eta::projection::run_mismatch`).
fn warn_eta(
    motion: &std::path::Path,
    kind: MotionKind,
    run: &std::path::Path,
) -> anyhow::Result<()> {
    use crate::data::eta::{EtaFiles, EtaSource};
    let what = motion.display().to_string();
    let sources: Vec<EtaSource> = match kind {
        MotionKind::Dataset => {
            let files = EtaFiles::scan(&crate::data::vhap::load_transforms(motion)?)?;
            eprintln!("{}", files.line(&what));
            files.folders.into_values().flatten().collect()
        }
        MotionKind::Parameters if motion.is_dir() => {
            let dir = if motion.join("flame_param").is_dir() {
                motion.join("eta")
            } else {
                motion.join("../eta")
            };
            EtaSource::read(&dir)?.into_iter().collect()
        }
        _ => Vec::new(),
    };
    if let Some(w) = crate::eta::projection::run_mismatch(&sources, run, &what) {
        eprintln!("{w}");
    }
    Ok(())
}
