//! `texavatars eta`: eta codes computed from an export's own images.

use std::path::PathBuf;

use clap::Args;

use crate::device::BackendKind;
use crate::eta::{EtaOptions, Extractor, compute};

/// Arguments of `eta`.
#[derive(Debug, Args)]
pub struct EtaArgs {
    /// The export's root (`transforms_{train,val,test}.json`): every split present is coded,
    /// and the projection is fitted on its training split and saved there as
    /// `eta_projection.safetensors`. A single sequence's export (`transforms.json`, e.g. a
    /// FREE sequence) is coded with `--projection`.
    #[arg(long)]
    pub data: PathBuf,
    /// An extra split to code, NAME=PATH (a `transforms*.json`), e.g. a FREE sequence's
    /// export: `--split free=../FREE_export/transforms.json`. Repeatable.
    #[arg(long = "split", value_parser = super::eval::parse_extra)]
    pub splits: Vec<(String, PathBuf)>,
    /// A camera index whose images the codes see (repeatable; the features of several are
    /// concatenated). Default: the training split's most frontal camera.
    #[arg(long = "camera")]
    pub cameras: Vec<usize>,
    /// Apply this projection instead of fitting one: the training export's
    /// `eta_projection.safetensors` (or a trained run's copy) when coding a FREE export of
    /// the same subject, or another subject's capture that drives this avatar.
    #[arg(long)]
    pub projection: Option<PathBuf>,
    /// Head model that poses the tracked meshes (default: DATA/../head/head.npz when
    /// present, else the embedded head; a FLAME export needs its model with teeth).
    #[arg(long)]
    pub head: Option<PathBuf>,
    /// Overwrite eta files (and a fitted projection) that exist.
    #[arg(long)]
    pub force: bool,
    /// Where the VGG16 runs.
    #[arg(long, value_enum, default_value = "flex")]
    pub backend: BackendKind,
}

/// Runs `eta`.
pub fn run(a: EtaArgs) -> anyhow::Result<()> {
    let device = a.backend.device();
    let extractor = Extractor::load(&device)?;
    let mut opts = EtaOptions::new(&a.data);
    opts.splits = a.splits;
    opts.cameras = a.cameras;
    opts.projection = a.projection;
    opts.head = a.head;
    opts.force = a.force;
    let report = compute(&opts, &extractor, &mut |line| eprintln!("{line}"))?;
    let splits: Vec<String> = report
        .timesteps
        .iter()
        .map(|(n, c)| format!("{n} {c}"))
        .collect();
    println!(
        "eta: wrote {} codes (timesteps per split: {}) from cameras {:?} with the projection {} ({}, {} components{}) in {:.1} s",
        report.written,
        splits.join(", "),
        report.cameras,
        report.projection.display(),
        report.projection_id,
        report.rank,
        if report.fitted {
            ", fitted now on the training split"
        } else {
            ""
        },
        report.seconds
    );
    Ok(())
}
