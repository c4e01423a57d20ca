//! `texavatars eval`: score a trained avatar on the evaluation splits.

use std::path::PathBuf;

use clap::Args;

use crate::data::Split;
use crate::device::BackendKind;
use crate::eval::run::{EvalOptions, evaluate};

/// Arguments of `eval`.
#[derive(Debug, Args)]
pub struct EvalArgs {
    /// The export's split folder (e.g. `out/synth/union`).
    #[arg(long)]
    pub data: PathBuf,
    /// The training run's folder (`texavatars train --out`).
    #[arg(long)]
    pub run: PathBuf,
    /// Output folder (metrics.json, table.md, images/).
    #[arg(long)]
    pub out: PathBuf,
    /// Splits, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "val,test,free")]
    pub splits: Vec<Split>,
    /// Skip LPIPS (no pretrained weights needed).
    #[arg(long)]
    pub no_lpips: bool,
    /// Evaluate every k-th frame of each split.
    #[arg(long, default_value_t = 1)]
    pub stride: usize,
    /// Ground truth | render | error panels written per split.
    #[arg(long, default_value_t = 8)]
    pub panels: usize,
    /// Where to compute (flex is the fast CPU backend for the networks).
    #[arg(long, value_enum, default_value = "flex")]
    pub backend: BackendKind,
}

/// Runs `eval`.
pub fn run(a: EvalArgs) -> anyhow::Result<()> {
    let opts = EvalOptions {
        data: a.data,
        run: a.run,
        out: a.out.clone(),
        splits: a.splits,
        lpips: !a.no_lpips,
        stride: a.stride,
        panels: a.panels,
        backend: a.backend,
    };
    let report = evaluate(&opts, &mut |l| eprintln!("eval: {l}"))?;
    println!("{}", report.table);
    println!(
        "wrote {}/metrics.json, table.md, images/ in {:.1} s",
        a.out.display(),
        report.seconds
    );
    Ok(())
}
