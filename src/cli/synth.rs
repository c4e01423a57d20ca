//! `texavatars synth`: render the synthetic multi-view benchmark.

use std::path::PathBuf;

use clap::Args;

use crate::head::HeadAsset;
use crate::head::teeth::LipRings;
use crate::synth::{self, SynthConfig};

/// Arguments of `synth`.
#[derive(Debug, Args)]
pub struct SynthArgs {
    /// Output folder (VHAP's NeRSemble export layout). The settings and head are recorded
    /// in OUT/synth/config.json and OUT/head/. Re-running with the same ones resumes the run
    /// (complete timesteps are skipped, not rendered again); with different ones it is
    /// refused, naming the field, unless --force.
    #[arg(long)]
    pub out: PathBuf,
    /// When --out holds a benchmark made with other settings or another head: delete the
    /// files a synth run writes there (images, masks, parameters, transforms, head, synth/;
    /// nothing else) and generate it again.
    #[arg(long)]
    pub force: bool,
    /// JSON settings (see configs/synth.json); defaults when absent.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// A head model `.npz` with its `.obj` (and optional `.json`) next to it; default: the
    /// embedded CC0 head.
    #[arg(long)]
    pub head: Option<PathBuf>,
    /// Add GaussianAvatars' teeth to `--head` (its `.npz` must hold the lip rings
    /// `lip_outside_ring_upper` and `lip_outside_ring_lower`; see docs/captures.md).
    #[arg(long, requires = "head")]
    pub teeth: bool,
}

/// Runs `synth`.
pub fn run(a: SynthArgs) -> anyhow::Result<()> {
    let config = match &a.config {
        Some(p) => SynthConfig::load(p)?,
        None => SynthConfig::default(),
    };
    let what = a
        .config
        .as_ref()
        .map_or_else(|| "synth config".to_string(), |p| p.display().to_string());
    config.check_memory(&what)?;
    let head = match &a.head {
        Some(p) if a.teeth => HeadAsset::load(p, None)?.with_teeth(&LipRings::load(p)?)?,
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
    let s = synth::generate_with(&config, &head, &a.out, a.force, &mut |line| {
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
