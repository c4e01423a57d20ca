//! Clap commands: thin wrappers that parse, call the library and report.

pub mod head;
pub mod splat;
pub mod synth;
pub mod uv;

use clap::{Parser, Subcommand};

/// TexAvatars: hybrid texel-3D Gaussian head avatars.
#[derive(Debug, Parser)]
#[command(name = "texavatars", version, about)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

/// Top-level commands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Head models: import the default head, print a summary.
    #[command(subcommand)]
    Head(head::HeadCommand),
    /// The Gaussian rasterizer on its own.
    #[command(subcommand)]
    Splat(splat::SplatCommand),
    /// Render the synthetic multi-view head benchmark (VHAP / GaussianAvatars format).
    Synth(synth::SynthArgs),
    /// UV layouts of meshes.
    #[command(subcommand)]
    Uv(uv::UvCommand),
}

/// Runs a parsed command line.
pub fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Head(c) => head::run(c),
        Command::Splat(c) => splat::run(c),
        Command::Synth(a) => synth::run(a),
        Command::Uv(c) => uv::run(c),
    }
}
