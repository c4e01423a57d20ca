//! `texavatars eval`: score a trained avatar on the evaluation splits.

use std::path::PathBuf;

use clap::Args;

use crate::data::{PathPolicy, Split};
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
    /// Splits of `--data`, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "val,test,free")]
    pub splits: Vec<Split>,
    /// An extra split, NAME=PATH: any VHAP export of the subject (`PATH` a
    /// `transforms*.json`), e.g. `--split free=../FREE_export/transforms.json`. Repeatable.
    #[arg(long = "split", value_parser = parse_extra)]
    pub extra: Vec<(String, PathBuf)>,
    /// The head model the avatar was trained with (`.npz`, its `.obj` next to it). Default:
    /// `DATA/../head/head.npz` when present, else the embedded head.
    #[arg(long)]
    pub head: Option<PathBuf>,
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
    /// Read dataset files that lie outside the dataset's folder (by default only files in
    /// it, or in a sibling VHAP export it combines, are read).
    #[arg(long)]
    pub allow_outside_paths: bool,
}

/// Runs `eval`.
pub fn run(a: EvalArgs) -> anyhow::Result<()> {
    let opts = EvalOptions {
        data: a.data,
        run: a.run,
        out: a.out.clone(),
        splits: a.splits,
        extra: a.extra,
        head: a.head,
        lpips: !a.no_lpips,
        stride: a.stride,
        panels: a.panels,
        backend: a.backend,
        paths: if a.allow_outside_paths {
            PathPolicy::Anywhere
        } else {
            PathPolicy::InsideRoot
        },
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

/// Parses `NAME=PATH` of `--split`.
fn parse_extra(s: &str) -> Result<(String, PathBuf), String> {
    let (name, path) = s
        .split_once('=')
        .ok_or_else(|| format!("{s:?}: expected NAME=PATH/transforms.json"))?;
    let name = name.trim();
    if name.is_empty()
        || !name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || "_-".contains(c))
    {
        return Err(format!(
            "{name:?}: a split name is letters, digits, '_' and '-' (it names a folder)"
        ));
    }
    let path = PathBuf::from(path);
    if !path.is_file() {
        return Err(format!("{}: no such file", path.display()));
    }
    Ok((name.to_string(), path))
}
