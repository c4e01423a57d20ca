//! `texavatars synth`: render the synthetic multi-view benchmark.

use std::path::PathBuf;

use clap::Args;

use crate::head::HeadAsset;
use crate::synth::{self, SynthConfig};

/// Arguments of `synth`.
#[derive(Debug, Args)]
pub struct SynthArgs {
    /// Output folder (VHAP's NeRSemble export layout; an existing run is resumed).
    #[arg(long)]
    pub out: PathBuf,
    /// JSON settings (see configs/synth.json); defaults when absent.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// A head model `.npz` with its `.obj` (and optional `.json`) next to it; default: the
    /// embedded CC0 head.
    #[arg(long)]
    pub head: Option<PathBuf>,
}

/// Runs `synth`.
pub fn run(a: SynthArgs) -> anyhow::Result<()> {
    let config = match &a.config {
        Some(p) => SynthConfig::load(p)?,
        None => SynthConfig::default(),
    };
    let head = match &a.head {
        Some(p) => HeadAsset::load(p, None)?,
        None => HeadAsset::embedded()?,
    };
    eprintln!(
        "synth: {}x{} images, {} cameras, {} frames per sequence + {} FREE, into {}",
        config.width,
        config.height,
        config.cameras,
        config.frames_per_sequence,
        config.free_frames,
        a.out.display()
    );
    let s = synth::generate(&config, &head, &a.out, &mut |line| {
        eprintln!("synth: {line}")
    })?;
    println!(
        "{} sequences, {} timesteps x {} cameras = {} images ({} timesteps rendered, {} already there) in {:.1} s; {:.1} MB on disk; splits train/val/test/free: {:?} frames",
        s.sequences,
        s.timesteps,
        s.cameras,
        s.images,
        s.rendered_timesteps,
        s.skipped_timesteps,
        s.seconds,
        s.bytes as f64 / 1e6,
        s.split_frames
    );
    Ok(())
}
