//! Clap commands: thin wrappers that parse, call the library and report.

pub mod splat;

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
    /// The Gaussian rasterizer on its own.
    #[command(subcommand)]
    Splat(splat::SplatCommand),
}

/// Runs a parsed command line.
pub fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Splat(c) => splat::run(c),
    }
}
