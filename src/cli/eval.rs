//! `texavatars eval`: score a trained avatar on the evaluation splits.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use clap::Args;
use serde::Serialize;

use crate::data::{PathPolicy, Split};
use crate::device::BackendKind;
use crate::error::Error;
use crate::eval::run::{EvalOptions, evaluate};
use crate::eval::{Means, combine_subjects, paper_table};

/// Arguments of `eval`.
#[derive(Debug, Args)]
pub struct EvalArgs {
    /// The export's split folder (e.g. `out/synth/union`).
    #[arg(long, required_unless_present = "combine")]
    pub data: Option<PathBuf>,
    /// The training run's folder (`texavatars train --out`).
    #[arg(long, required_unless_present = "combine")]
    pub run: Option<PathBuf>,
    /// Output folder (metrics.json, table.md, images/).
    #[arg(long)]
    pub out: PathBuf,
    /// Combine earlier evaluations of several subjects instead of evaluating: each DIR is
    /// an `eval --out` folder (its metrics.json); writes OUT/table.md and OUT/metrics.json
    /// with, per split, the mean over the subjects of their means and the standard
    /// deviation over the subjects. Repeatable (one per subject).
    #[arg(long, value_name = "DIR", conflicts_with_all = ["data", "run", "extra", "head"])]
    pub combine: Vec<PathBuf>,
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
    /// Score ceil(n / k) of each split's n images, spread evenly over its timesteps and
    /// cameras (1: all).
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
    /// Pose every frame with its tracked FLAME parameters, ignoring the run's refined ones
    /// (by default the training timesteps, i.e. the novel-view split, use the refined ones,
    /// as GaussianAvatars does).
    #[arg(long)]
    pub tracked: bool,
    /// A second run of the same subject: render it at every scored frame too and write
    /// against.md, where the two runs' renders differ per face region (both posed with the
    /// tracked parameters), and a difference panel per panel frame.
    #[arg(long, value_name = "RUN")]
    pub against: Option<PathBuf>,
}

/// Runs `eval`.
pub fn run(a: EvalArgs) -> anyhow::Result<()> {
    if !a.combine.is_empty() {
        return combine(&a.combine, &a.out);
    }
    let (Some(data), Some(run)) = (a.data, a.run) else {
        return Err(
            Error::invalid("eval", "--data/--run", "required (or --combine DIR ...)").into(),
        );
    };
    let opts = EvalOptions {
        data,
        run,
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
        tracked: a.tracked,
        renders: false,
        against: a.against,
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

/// The subjects' means combined (`eval --combine`).
#[derive(Serialize)]
struct Combined {
    subjects: Vec<PathBuf>,
    means: BTreeMap<String, Means>,
    table: String,
}

/// `eval --combine DIR ... --out OUT`: reads each DIR/metrics.json's means, combines them
/// over the subjects and writes OUT/metrics.json and OUT/table.md.
fn combine(dirs: &[PathBuf], out: &Path) -> anyhow::Result<()> {
    let mut subjects = Vec::with_capacity(dirs.len());
    for d in dirs {
        let path = d.join("metrics.json");
        let what = path.display().to_string();
        let text = std::fs::read_to_string(&path).map_err(|e| Error::io(&path, e))?;
        let json: serde_json::Value = serde_json::from_str(&text)
            .map_err(|e| Error::invalid(&what, format!("line {}", e.line()), e.to_string()))?;
        let means: BTreeMap<String, Means> =
            serde_json::from_value(json.get("means").cloned().unwrap_or_default())
                .map_err(|e| Error::invalid(&what, "means", e.to_string()))?;
        if means.is_empty() {
            return Err(Error::invalid(&what, "means", "no split was evaluated").into());
        }
        subjects.push(means);
    }
    let means = combine_subjects(&subjects);
    let table = paper_table(&means);
    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    let c = Combined {
        subjects: dirs.to_vec(),
        means,
        table,
    };
    let json = serde_json::to_string_pretty(&c)
        .map_err(|e| Error::invalid("evaluation", "json", e.to_string()))?;
    let path = out.join("metrics.json");
    std::fs::write(&path, json).map_err(|e| Error::io(&path, e))?;
    let path = out.join("table.md");
    std::fs::write(&path, &c.table).map_err(|e| Error::io(&path, e))?;
    println!("{}", c.table);
    println!(
        "wrote {}/metrics.json, table.md ({} subjects)",
        out.display(),
        dirs.len()
    );
    Ok(())
}

/// Parses `NAME=PATH` of `--split`.
pub(crate) fn parse_extra(s: &str) -> Result<(String, PathBuf), String> {
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
