//! `texavatars bench fps`: GaussianAvatars' frame-rate protocol on a chosen backend.

use std::path::PathBuf;

use clap::{Args, Subcommand};

use crate::cli::render::parse_size;
use crate::device::BackendKind;
use crate::drive::fps::{self, Round};
use crate::drive::{self, CameraPath, Identity, Motion, View};
use crate::head::{HeadAsset, HeadPose};
use crate::models::Drivable;
use crate::models::texavatars::{AvatarConfig, NetConfig};

/// Benchmark commands.
#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// Frames per second: one view rendered `--renders` times, `--rounds` rounds, by stage
    /// (decoders, lifting, rasterizer).
    Fps(FpsArgs),
}

/// Arguments of `bench fps`.
#[derive(Debug, Args)]
pub struct FpsArgs {
    /// A trained avatar: a `texavatars train` run of either model, or a GaussianAvatars
    /// output folder. Without it, an untrained TexAvatars avatar of `--net` (random weights;
    /// the rasterizer's share then depends on the random sizes).
    #[arg(long)]
    pub checkpoint: Option<PathBuf>,
    /// Network configuration for an untrained avatar.
    #[arg(long, default_value = "configs/paper.json")]
    pub net: PathBuf,
    /// The frame to render: the first frame of this motion (see `render --motion`); default
    /// the head's neutral pose.
    #[arg(long)]
    pub motion: Option<PathBuf>,
    /// Renders per round.
    #[arg(long, default_value_t = 500)]
    pub renders: usize,
    /// Rounds.
    #[arg(long, default_value_t = 3)]
    pub rounds: usize,
    /// Image size, WIDTHxHEIGHT (GaussianAvatars' protocol: NeRSemble's 550x802).
    #[arg(long, default_value = "550x802")]
    pub size: String,
    /// Head model (`.npz`); default the embedded head.
    #[arg(long)]
    pub head: Option<PathBuf>,
    /// Where tensors live.
    #[arg(long, value_enum, default_value_t = BackendKind::Flex)]
    pub backend: BackendKind,
    /// Also write the report as JSON here.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

/// Runs a benchmark command.
pub fn run(cmd: BenchCommand) -> anyhow::Result<()> {
    match cmd {
        BenchCommand::Fps(a) => fps_command(a),
    }
}

fn fps_command(a: FpsArgs) -> anyhow::Result<()> {
    let head = match &a.head {
        Some(p) => HeadAsset::load(p, None)?,
        None => HeadAsset::embedded()?,
    };
    let device = a.backend.device();
    let avatar: Box<dyn Drivable> = match &a.checkpoint {
        Some(run) => crate::models::load(run, &head, &device)?.avatar,
        None => {
            let mut net = NetConfig::load(&a.net)?;
            net.condition.expression = head.model.num_expr;
            Box::new(
                AvatarConfig::new(net)
                    .init_seeded(0, &head.mesh, &device)?
                    .for_inference(),
            )
        }
    };
    let avatar = avatar.as_ref();
    let identity = Identity::mean(&head.model);
    let conditioning = match &a.motion {
        Some(m) => {
            let motion = Motion::load(m, &head.model, &head.meta, &identity)?;
            motion.frames[0].conditioning.clone()
        }
        None => std::sync::Arc::new(crate::data::dataset::pose_conditioning(
            &head.model,
            HeadPose::neutral(&head.model),
            vec![0.0; crate::data::vhap::ETA_DIM],
            "neutral pose",
        )?),
    };
    let (w, h) = parse_size(&a.size)?;
    let one = Motion {
        kind: drive::MotionKind::Curves,
        source: "bench".into(),
        frames: vec![drive::MotionFrame {
            timestep: 0,
            conditioning: conditioning.clone(),
            cameras: Vec::new(),
        }],
    };
    drive::render::check_motion(avatar, &one)?;
    let camera = drive::cameras(
        &one,
        CameraPath::Front,
        &View {
            width: w,
            height: h,
            ..View::default()
        },
    )?[0];
    eprintln!(
        "bench fps: {}, {} Gaussians, {w}x{h}, {:?}, {} renders x {} rounds",
        avatar.model_name(),
        avatar.num_gaussians(),
        a.backend,
        a.renders,
        a.rounds
    );
    let report = fps::measure(
        avatar,
        &conditioning,
        &camera,
        &device,
        a.renders,
        a.rounds,
        &mut |k, r| eprintln!("round {k}: {}", line(r)),
    )?;
    println!(
        "mean of {} rounds: {} (what the view alone needs, once: {:.1} ms)",
        report.rounds.len(),
        line(&report.mean()),
        report.view_input_ms
    );
    if let Some(p) = &a.json {
        std::fs::write(p, serde_json::to_string_pretty(&report)? + "\n")?;
    }
    Ok(())
}

fn line(r: &Round) -> String {
    let stages: Vec<String> = r
        .stages_ms
        .iter()
        .map(|(k, v)| format!("{} {v:.1} ms", k.trim_end_matches("_ms")))
        .collect();
    format!(
        "{:.2} FPS ({:.1} ms per frame: {}, rasterizer {:.1} ms)",
        r.fps,
        r.total_ms,
        stages.join(", "),
        r.rasterizer_ms
    )
}
