//! `texavatars export ply`: a driven avatar's Gaussians as per-frame 3DGS PLY files;
//! `texavatars export flame-param`: a trained avatar's refined FLAME parameters as VHAP
//! `flame_param` files.

use std::path::PathBuf;

use anyhow::Context;
use clap::{Args, Subcommand};

use crate::camera::CameraFile;
use crate::cli::render::{DriveArgs, Driven, progress_bar};
use crate::data::BACKGROUND;
use crate::drive::{self, ExportStats, outputs};
use crate::io;
use crate::splat::ply;

/// Export commands.
#[derive(Debug, Subcommand)]
pub enum ExportCommand {
    /// Per-frame world-space 3DGS PLY files (INRIA layout, SH degree 0 unless
    /// `--sh-degree`), with each frame's camera as JSON (`splat render --camera`).
    Ply(PlyArgs),
    /// A trained avatar's refined FLAME parameters (FLAME refinement, on by default in
    /// `train`) as VHAP `flame_param` files: `OUT/flame_param/TTTTT.npz` per training
    /// timestep (T: its `timestep_index`), in the layout VHAP's export writes.
    FlameParam(FlameParamArgs),
}

/// Arguments of `export flame-param`.
#[derive(Debug, Args)]
pub struct FlameParamArgs {
    /// The training run's folder (its `refined_flame_param.npz`).
    #[arg(long)]
    pub run: PathBuf,
    /// Output folder; its `flame_param/` must not exist or be empty.
    #[arg(long)]
    pub out: PathBuf,
}

/// Arguments of `export ply`.
#[derive(Debug, Args)]
pub struct PlyArgs {
    #[command(flatten)]
    pub drive: DriveArgs,
    /// Output folder: `FFFFF.ply` and `FFFFF_camera.json` per frame (F: the frame's position
    /// in the motion). The files an earlier export left there (`FFFFF.ply`,
    /// `FFFFF_camera.json`, `FFFFF_render.png`, `FFFFF_render.npy` and their unfinished
    /// `*.partial` files, whatever their frame numbers) are deleted first, so frames of an
    /// earlier, longer export never mix with the new ones; nothing else is touched (export
    /// chunks of a motion with --frames into separate folders).
    #[arg(long)]
    pub out: PathBuf,
    /// Also write the avatar's own render of each frame (`FFFFF_render.png` and the float
    /// image `FFFFF_render.npy`), e.g. to compare with `splat render`.
    #[arg(long)]
    pub render: bool,
    /// SH degree of the files (0-3): above 0, `f_rest_*` coefficients are written as zeros
    /// (the same colours) for 3DGS loaders that insist on a degree (3: 45 `f_rest_*`). A
    /// GaussianAvatars avatar's files keep its own coefficients (and degree, when higher).
    #[arg(long, default_value_t = 0, value_parser = clap::value_parser!(u8).range(0..=3))]
    pub sh_degree: u8,
}

/// Runs an export command.
pub fn run(cmd: ExportCommand) -> anyhow::Result<()> {
    match cmd {
        ExportCommand::Ply(a) => ply_command(a),
        ExportCommand::FlameParam(a) => flame_param_command(a),
    }
}

fn flame_param_command(a: FlameParamArgs) -> anyhow::Result<()> {
    use crate::data::refined::{REFINED_NPZ, RefinedParams};
    let Some(refined) = RefinedParams::load(&a.run)? else {
        return Err(crate::error::Error::invalid(
            a.run.display().to_string(),
            REFINED_NPZ,
            "missing: the run was trained without FLAME refinement, or has not finished",
        )
        .into());
    };
    let folder = a.out.join("flame_param");
    if std::fs::read_dir(&folder).is_ok_and(|mut d| d.next().is_some()) {
        return Err(crate::error::Error::invalid(
            folder.display().to_string(),
            "folder",
            "is not empty; choose another --out (nothing was written)",
        )
        .into());
    }
    let files = refined.export_vhap(&a.out)?;
    println!(
        "wrote {} refined flame_param files to {}",
        files.len(),
        folder.display()
    );
    Ok(())
}

fn ply_command(a: PlyArgs) -> anyhow::Result<()> {
    let d = a.drive.load()?;
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let removed = outputs::clear_export_outputs(&a.out)?;
    if removed > 0 {
        eprintln!(
            "export: removed {removed} file(s) of an earlier export from {}",
            a.out.display()
        );
    }
    let r = export_frames(&a, &d);
    if r.is_err() {
        outputs::remove_export_partials(&a.out);
    }
    r
}

/// Writes every frame's files (after the folder was cleared).
fn export_frames(a: &PlyArgs, d: &Driven) -> anyhow::Result<()> {
    let n = d.motion.frames.len();
    let bar = progress_bar(n, "export");
    let mut total = ExportStats::default();
    for (k, (f, cam)) in d.motion.frames.iter().zip(&d.cameras).enumerate() {
        let i = d.first + k;
        let (rgb, g) = drive::render_frame(d.avatar.as_ref(), &f.conditioning, cam, &d.device)?;
        let (mut p, stats) = drive::export::frame_ply(d.avatar.as_ref(), &f.conditioning, g)?;
        // Padded to --sh-degree; a model's own higher degree is kept.
        let degree = p.sh_degree.max(a.sh_degree.into());
        p.pad_sh_degree(degree)?;
        ply::write(&a.out.join(format!("{i:05}.ply")), &p)?;
        let cam_path = a.out.join(format!("{i:05}_camera.json"));
        let cam_file = CameraFile {
            camera: *cam,
            background: BACKGROUND,
        };
        let tmp = cam_path.with_extension("json.partial");
        std::fs::write(&tmp, serde_json::to_string_pretty(&cam_file)? + "\n")
            .with_context(|| format!("writing {}", tmp.display()))?;
        std::fs::rename(&tmp, &cam_path)
            .with_context(|| format!("writing {}", cam_path.display()))?;
        if a.render {
            let (w, h) = (cam.width as usize, cam.height as usize);
            io::image::write_png(&a.out.join(format!("{i:05}_render.png")), w, h, &rgb)?;
            io::npy::write(&a.out.join(format!("{i:05}_render.npy")), &[h, w, 3], &rgb)?;
        }
        total.gaussians += stats.gaussians;
        total.negative_colors += stats.negative_colors;
        total.degenerate_covariances += stats.degenerate_covariances;
        bar.set_position(k as u64 + 1);
    }
    bar.finish_and_clear();
    println!(
        "exported {n} frames ({} Gaussians each) to {}",
        total.gaussians / n.max(1),
        a.out.display()
    );
    if total.negative_colors > 0 || total.degenerate_covariances > 0 {
        println!(
            "clamped: {} Gaussian-frames with a colour channel below 0 (3DGS viewers clamp \
             colours at 0), {} with a variance below {:e} (written at that floor)",
            total.negative_colors,
            total.degenerate_covariances,
            drive::export::MIN_VARIANCE
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use clap::Parser;

    use super::*;

    #[derive(Debug, Parser)]
    struct Cli {
        #[command(subcommand)]
        cmd: ExportCommand,
    }

    fn parse(extra: &[&str]) -> Result<PlyArgs, clap::Error> {
        let base = [
            "t",
            "ply",
            "--checkpoint",
            "c",
            "--motion",
            "m",
            "--out",
            "o",
        ];
        Cli::try_parse_from(base.iter().chain(extra)).map(|c| match c.cmd {
            ExportCommand::Ply(a) => a,
            ExportCommand::FlameParam(a) => panic!("parsed export ply as {a:?}"),
        })
    }

    #[test]
    fn sh_degree_defaults_to_0_and_is_at_most_3() {
        assert_eq!(parse(&[]).unwrap().sh_degree, 0);
        assert_eq!(parse(&["--sh-degree", "3"]).unwrap().sh_degree, 3);
        let e = parse(&["--sh-degree", "4"]).unwrap_err().to_string();
        assert!(e.contains("--sh-degree") && e.contains("0..=3"), "{e}");
    }
}
