//! `texavatars synth`: render the synthetic multi-view benchmark.

use std::path::PathBuf;

use clap::Args;

use crate::error::Error;
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
    #[arg(long, required_unless_present = "analyse")]
    pub out: Option<PathBuf>,
    /// The subject to render: 0 (default) is the head's mean shape with the original
    /// appearance; K > 0 another shape and appearance. One export folder per subject.
    /// Overrides the config's `subject`.
    #[arg(long)]
    pub subject: Option<usize>,
    /// Analyse an existing export instead of rendering one: print how much of the true
    /// wrinkle activations (DIR/*/truth/) a cross-validated ridge regression explains from
    /// the tracked expression coefficients and their squares (flame_param/), from the true
    /// ones, and from eta (eta/), and the tracking error; also written to
    /// DIR/synth/analysis.json.
    #[arg(long, value_name = "DIR", conflicts_with_all = ["out", "force", "config", "head", "teeth", "subject"])]
    pub analyse: Option<PathBuf>,
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
    if let Some(dir) = &a.analyse {
        let r = synth::analysis::analyse(dir)?;
        print!("{}", r.text());
        let path = dir.join("synth/analysis.json");
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent).map_err(|e| Error::io(parent, e))?;
        }
        let json = serde_json::to_string_pretty(&r)
            .map_err(|e| Error::invalid("analysis", "json", e.to_string()))?;
        std::fs::write(&path, json).map_err(|e| Error::io(&path, e))?;
        println!("wrote {}", path.display());
        return Ok(());
    }
    let Some(out) = a.out.clone() else {
        return Err(Error::invalid("synth", "--out", "required (or --analyse DIR)").into());
    };
    let mut config = match &a.config {
        Some(p) => SynthConfig::load(p)?,
        None => SynthConfig::default(),
    };
    let what = a
        .config
        .as_ref()
        .map_or_else(|| "synth config".to_string(), |p| p.display().to_string());
    if let Some(k) = a.subject {
        config.subject = k;
        config.validate(&format!("{what} with --subject {k}"))?;
    }
    config.check_memory(&what)?;
    let head = match &a.head {
        Some(p) if a.teeth => HeadAsset::load(p, None)?.with_teeth(&LipRings::load(p)?)?,
        Some(p) => HeadAsset::load(p, None)?,
        None => HeadAsset::embedded()?,
    };
    eprintln!(
        "synth: subject {}, {}x{} images, {} cameras, {} frames per sequence + {} FREE, into {}",
        config.subject,
        config.width,
        config.height,
        config.cameras,
        config.frames_per_sequence,
        config.free_frames,
        out.display()
    );
    let s = synth::generate_with(&config, &head, &out, a.force, &mut |line| {
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
