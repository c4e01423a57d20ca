//! `texavatars uv ...`: look at a mesh's UV layout.

use std::path::PathBuf;

use anyhow::Context;
use clap::{Args, Subcommand};

use crate::io;
use crate::lift::Topology;
use crate::limits;
use crate::mesh::UvMesh;
use crate::texel::inspect;

/// UV layout commands.
#[derive(Debug, Subcommand)]
pub enum UvCommand {
    /// Write pictures of the layout (validity, face ids, kept samples) and print the number
    /// of Gaussians it gives.
    Inspect(InspectArgs),
}

/// Arguments of `uv inspect`.
#[derive(Debug, Args)]
pub struct InspectArgs {
    /// OBJ mesh with UVs (`f p/t ...`).
    #[arg(long)]
    pub mesh: PathBuf,
    /// Texel resolution R of the layout maps (at most 4096).
    #[arg(long, default_value_t = 512)]
    pub res: usize,
    /// Sample grid size S (defaults to R; at most 4096).
    #[arg(long)]
    pub samples: Option<usize>,
    /// Output folder.
    #[arg(long)]
    pub out: PathBuf,
}

/// Runs a UV command.
pub fn run(cmd: UvCommand) -> anyhow::Result<()> {
    match cmd {
        UvCommand::Inspect(a) => inspect_layout(a),
    }
}

/// Checks `--res` and `--samples` against their caps and the memory budget.
pub fn check_inspect(a: &InspectArgs) -> crate::error::Result<()> {
    let what = "uv inspect";
    let s = a.samples.unwrap_or(a.res);
    limits::check_size(what, "--res", a.res, &limits::UV_RES)?;
    let samples_field = if a.samples.is_some() {
        "--samples"
    } else {
        "--res"
    };
    limits::check_size(what, samples_field, s, &limits::SAMPLE_GRID)?;
    let (r, s) = (a.res as u64, s as u64);
    let estimate = limits::Estimate::new()
        .add(
            format!("{r}x{r} texel maps"),
            limits::product(&[r, r, limits::LAYOUT_BYTES_PER_TEXEL]),
        )
        .add(
            format!("{s}x{s} sample grid"),
            limits::product(&[s, s, limits::SAMPLE_BYTES]),
        );
    let field = if s > r { samples_field } else { "--res" };
    limits::check_estimate(what, field, &estimate)
}

fn inspect_layout(a: InspectArgs) -> anyhow::Result<()> {
    check_inspect(&a)?;
    let mesh = UvMesh::load(&a.mesh)?;
    let s = a.samples.unwrap_or(a.res);
    let topo = Topology::new(&mesh, a.res, s)?;
    std::fs::create_dir_all(&a.out).with_context(|| format!("{}: creating", a.out.display()))?;
    for p in inspect::pictures(&topo.layout, &topo.samples) {
        io::image::write_png(&a.out.join(p.name), p.width, p.height, &p.rgb)?;
    }
    let covered = topo.layout.valid_count();
    println!(
        "{}: {} vertices, {} faces; R = {}: {} of {} texels covered ({:.1}%); S = {}: {} Gaussians",
        a.mesh.display(),
        mesh.positions.len(),
        mesh.faces.len(),
        a.res,
        covered,
        a.res * a.res,
        100.0 * covered as f64 / (a.res * a.res) as f64,
        s,
        topo.len()
    );
    println!(
        "wrote validity.png, faces.png, samples.png to {}",
        a.out.display()
    );
    Ok(())
}
