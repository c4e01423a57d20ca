//! `study --paired`: where each variant's images differ from the full method's.
//!
//! A variant trained with the full method's first seed starts from the same initialisation
//! and sees the frames in the same order, so comparing its renders with that run's shows
//! what the component changes in the images, and where; the full method's other seeds show
//! the training's own noise. For every finished run of a subject other than its reference
//! (the full method with the study's first seed), [`pair`] renders both at every held-out
//! and FREE frame the study scores and writes where they differ (`eval --against`,
//! [`crate::eval::run`]) into `RUN/paired/`; [`report`] gathers them into
//! `OUT/report/paired.md` and `paired.json`: per subject and run, per split, the PSNR between
//! the two renders and each face region's concentration (its share of the squared
//! difference over its share of the pixels).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::config::{RunSpec, Study, Variant};
use super::run::{finished, run_data, run_dir};
use crate::data::{PathPolicy, Split};
use crate::device::BackendKind;
use crate::error::{Error, Result};
use crate::eval::regions::RegionScore;
use crate::eval::run::{Against, EvalOptions, evaluate};

/// The folder under a run's folder that [`pair`] writes.
pub const PAIRED: &str = "paired";
/// The splits compared: (`metrics.json` key, label).
const SPLITS: [(&str, &str); 2] = [("free", "FREE"), ("test", "held-out")];
/// The regions whose concentration the table gives.
const REGIONS: [&str; 4] = ["stretched", "creases", "mouth", "eyes"];

/// The run a subject's runs are compared with: its full method with the first seed.
pub fn reference(study: &Study, subject: &str) -> RunSpec {
    RunSpec {
        subject: subject.to_string(),
        variant: Variant::Full,
        seed: study.config.seeds.first().copied().unwrap_or(0),
    }
}

/// Renders `run` and its subject's [`reference()`] at every held-out and FREE frame the
/// study scores and writes where they differ into `RUN/paired/` (`against.md`,
/// `metrics.json`, the difference panels). Returns the folder; `None` when `run` is the
/// reference or either has not finished. A run already compared is skipped.
pub fn pair(
    study: &Study,
    out: &Path,
    run: &RunSpec,
    backend: Option<BackendKind>,
    progress: &mut (dyn FnMut(&str) + Send),
) -> Result<Option<PathBuf>> {
    let reference = reference(study, &run.subject);
    if *run == reference || finished(out, run).is_none() || finished(out, &reference).is_none() {
        return Ok(None);
    }
    let dir = run_dir(out, run).join(PAIRED);
    if dir.join("against.md").is_file() {
        return Ok(Some(dir));
    }
    let e = &study.config.eval;
    let opts = EvalOptions {
        data: run_data(study, out, &reference)?,
        run: run_dir(out, &reference).join("train"),
        out: dir.clone(),
        splits: vec![Split::Test, Split::Free],
        extra: Vec::new(),
        head: None,
        lpips: false,
        stride: e.stride,
        panels: e.panels,
        backend: backend.unwrap_or(BackendKind::Flex),
        paths: PathPolicy::InsideRoot,
        tracked: true,
        renders: false,
        against: Some(run_dir(out, run).join("train")),
    };
    evaluate(&opts, &mut |l| {
        progress(&format!("{}: paired: {l}", run.id()))
    })?;
    Ok(Some(dir))
}

/// One compared run.
#[derive(Clone, Debug, Serialize)]
pub struct PairedRun {
    pub id: String,
    pub subject: String,
    pub variant: Variant,
    pub seed: u64,
    /// Split → region → the two renders' difference there.
    pub regions: BTreeMap<String, BTreeMap<String, RegionScore>>,
}

/// What [`report`] gathered.
#[derive(Clone, Debug, Serialize)]
pub struct Paired {
    pub runs: Vec<PairedRun>,
    /// Runs not compared yet (not finished, or `--paired` not run since).
    pub missing: Vec<String>,
    pub markdown: String,
}

#[derive(Deserialize)]
struct File {
    against: Against,
}

/// Gathers every compared run into `OUT/report/paired.md` and `paired.json`.
pub fn report(study: &Study, out: &Path) -> Result<Paired> {
    let mut runs = Vec::new();
    let mut missing = Vec::new();
    for r in study.runs() {
        if r == reference(study, &r.subject) {
            continue;
        }
        let path = run_dir(out, &r).join(PAIRED).join("metrics.json");
        let Ok(text) = std::fs::read_to_string(&path) else {
            missing.push(r.id());
            continue;
        };
        let file: File = serde_json::from_str(&text)
            .map_err(|e| Error::invalid(path.display().to_string(), "against", e.to_string()))?;
        runs.push(PairedRun {
            id: r.id(),
            subject: r.subject.clone(),
            variant: r.variant,
            seed: r.seed,
            regions: file.against.regions,
        });
    }
    let markdown = table(study, &runs);
    let dir = out.join("report");
    std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
    let p = Paired {
        runs,
        missing,
        markdown,
    };
    let path = dir.join("paired.md");
    std::fs::write(&path, &p.markdown).map_err(|e| Error::io(&path, e))?;
    let path = dir.join("paired.json");
    let json = serde_json::to_string_pretty(&p)
        .map_err(|e| Error::invalid("paired.json", "json", e.to_string()))?;
    std::fs::write(&path, json + "\n").map_err(|e| Error::io(&path, e))?;
    Ok(p)
}

/// The compared runs as Markdown: one row per run, per split the PSNR between the renders
/// and the regions' concentrations.
pub fn table(study: &Study, runs: &[PairedRun]) -> String {
    let seed = study.config.seeds.first().copied().unwrap_or(0);
    let mut head = String::from("| subject | run |");
    let mut rule = String::from("|---|---|");
    for (_, label) in SPLITS {
        head += &format!(" {label}: PSNR between the renders |");
        rule += "---|";
        for r in REGIONS {
            head += &format!(" {r} |");
            rule += "---|";
        }
    }
    let mut s = format!(
        "# Where each run's images differ from the full method's (seed {seed})\n\n{head}\n{rule}\n"
    );
    for run in runs {
        let name = if run.variant == Variant::Full {
            format!("{}, seed {}", run.variant.label(), run.seed)
        } else {
            run.variant.label().to_string()
        };
        s += &format!("| {} | {name} |", run.subject);
        for (split, _) in SPLITS {
            let regions = run.regions.get(split);
            let psnr = regions
                .and_then(|r| r.get("all"))
                .and_then(|x| x.psnr)
                .map_or("-".to_string(), |p| format!("{p:.2} dB"));
            s += &format!(" {psnr} |");
            for r in REGIONS {
                let c = regions
                    .and_then(|x| x.get(r))
                    .and_then(RegionScore::concentration)
                    .map_or("-".to_string(), |c| format!("{c:.2}"));
                s += &format!(" {c} |");
            }
        }
        s += "\n";
    }
    s += &format!(
        "\nEach run against its subject's full method with seed {seed}, both rendered at every held-out and FREE frame the study scores, posed with the tracked parameters (`texavatars eval --against`). A region's figure is its concentration: its share of the squared difference between the two renders over its share of the pixels (above 1: they differ more there than on average). A variant trained with seed {seed} differs from the full method through its component; the full method's other seeds show the training's own noise.\n"
    );
    s
}
