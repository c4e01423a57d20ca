//! Running a study: its data, each run (train then evaluate, resumable), the estimate of
//! the whole study's wall time, and the plan for running it elsewhere.
//!
//! Folders under `OUT`: `data/NAME/` (a `synth` subject's benchmark), `runs/SUBJECT/
//! VARIANT-seedS/{train,eval}/` and `run.json` there once the run is finished (its wall
//! times). A run with `run.json` is skipped; one without continues its training with
//! `--resume` semantics and evaluates again.

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::{Deserialize, Serialize};

use super::config::{RunSpec, Study, Variant};
use crate::data::{PathPolicy, Split};
use crate::device::BackendKind;
use crate::error::{Error, Result};
use crate::eval::run::{EvalOptions, evaluate, head_for};
use crate::head::HeadAsset;
use crate::train::TrainOptions;

/// The file that marks a finished run.
pub const FINISHED: &str = "run.json";

/// What a finished run records.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct RunRecord {
    pub id: String,
    pub variant: Variant,
    pub seed: u64,
    pub iterations: usize,
    /// Wall time of the training this record's process did (a resumed run: its part).
    pub train_seconds: f64,
    /// Iterations this record's process trained in `train_seconds` (a resumed run: its
    /// part); records written before the field existed read as `iterations`.
    #[serde(default)]
    pub trained_iterations: Option<usize>,
    pub eval_seconds: f64,
}

/// A run's folder.
pub fn run_dir(out: &Path, run: &RunSpec) -> PathBuf {
    out.join("runs")
        .join(&run.subject)
        .join(format!("{}-seed{}", run.variant.name(), run.seed))
}

/// The split folder of subject `name`.
pub fn subject_data(study: &Study, out: &Path, name: &str) -> Result<PathBuf> {
    let s = study
        .subject(name)
        .ok_or_else(|| Error::invalid(study.path.display().to_string(), "subjects", name))?;
    Ok(match &s.data {
        Some(d) => d.clone(),
        None => out.join("data").join(&s.name).join("union"),
    })
}

/// The split folder `run` trains and is evaluated on: the subject's
/// ([`subject_data`]), or for [`Variant::ImageEta`] the same folder in the subject's
/// image-eta copy ([`image_eta_root`]).
pub fn run_data(study: &Study, out: &Path, run: &RunSpec) -> Result<PathBuf> {
    let data = subject_data(study, out, &run.subject)?;
    if run.variant != Variant::ImageEta {
        return Ok(data);
    }
    let leaf = data.file_name().unwrap_or_default();
    Ok(image_eta_root(out, &run.subject).join(leaf))
}

/// The image-eta copy of subject `name`'s export: `OUT/data/NAME.image-eta/`, a copy of the
/// folder that holds its split folder (files hard-linked where the file system allows),
/// without its `eta/` folders, whose codes `texavatars eta` then computes from the images.
pub fn image_eta_root(out: &Path, name: &str) -> PathBuf {
    out.join("data").join(format!("{name}.image-eta"))
}

/// The marker of a finished image-eta copy (the `eta` report).
const IMAGE_ETA_DONE: &str = "image-eta.json";

/// Copies `src` into `dst` (hard links, else copies), leaving out folders named `eta` and a
/// fitted projection; what exists in `dst` already is kept.
fn mirror(src: &Path, dst: &Path) -> Result<()> {
    std::fs::create_dir_all(dst).map_err(|e| Error::io(dst, e))?;
    for entry in std::fs::read_dir(src).map_err(|e| Error::io(src, e))? {
        let entry = entry.map_err(|e| Error::io(src, e))?;
        let name = entry.file_name();
        let (from, to) = (entry.path(), dst.join(&name));
        let kind = entry.file_type().map_err(|e| Error::io(&from, e))?;
        if kind.is_dir() {
            if name != "eta" {
                mirror(&from, &to)?;
            }
        } else if name != crate::eta::projection::FILE_NAME
            && !to.exists()
            && std::fs::hard_link(&from, &to).is_err()
        {
            std::fs::copy(&from, &to).map_err(|e| Error::io(&to, e))?;
        }
    }
    Ok(())
}

/// Makes subject `name`'s image-eta copy (see [`image_eta_root`]) unless it is finished.
fn prepare_image_eta(
    study: &Study,
    out: &Path,
    name: &str,
    extractor: &mut Option<crate::eta::Extractor>,
    progress: &mut (dyn FnMut(&str) + Send),
) -> Result<()> {
    let root = image_eta_root(out, name);
    if root.join(IMAGE_ETA_DONE).is_file() {
        return Ok(());
    }
    let data = subject_data(study, out, name)?;
    let parent = data.parent().unwrap_or(Path::new("."));
    mirror(parent, &root)?;
    if extractor.is_none() {
        *extractor = Some(crate::eta::Extractor::load(&BackendKind::Flex.device())?);
    }
    let leaf = data.file_name().unwrap_or_default();
    let mut opts = crate::eta::EtaOptions::new(&root.join(leaf));
    opts.force = true;
    let ex = extractor.as_ref().expect("loaded above");
    let r = crate::eta::compute(&opts, ex, &mut |l| {
        progress(&format!("data {name}.image-eta: {l}"))
    })?;
    let record = serde_json::json!({
        "projection": r.projection,
        "projection_id": r.projection_id,
        "rank": r.rank,
        "cameras": r.cameras,
        "timesteps": r.timesteps,
        "written": r.written,
        "seconds": r.seconds,
    });
    let path = root.join(IMAGE_ETA_DONE);
    std::fs::write(
        &path,
        serde_json::to_string_pretty(&record).expect("serialises") + "\n",
    )
    .map_err(|e| Error::io(&path, e))?;
    progress(&format!(
        "data {name}.image-eta: {} eta codes from cameras {:?} ({} components) in {:.1} s",
        r.written, r.cameras, r.rank, r.seconds
    ));
    Ok(())
}

/// Generates every `synth` subject's benchmark that is not complete yet (the synthetic
/// benchmark skips what is already there), and the image-eta copies when the study has
/// that variant. Run it once before runs start in parallel.
pub fn prepare(study: &Study, out: &Path, progress: &mut (dyn FnMut(&str) + Send)) -> Result<()> {
    let head = HeadAsset::embedded()?;
    for s in &study.config.subjects {
        if let Some(subject) = s.synth {
            let config = crate::synth::SynthConfig {
                subject,
                ..study.synth.clone()
            };
            let dir = out.join("data").join(&s.name);
            let t0 = Instant::now();
            let summary = crate::synth::generate(&config, &head, &dir, &mut |_| {})?;
            progress(&format!(
                "data {}: synthetic subject {subject}, {} images ({} timesteps rendered now) in {:.1} s",
                s.name,
                summary.images,
                summary.rendered_timesteps,
                t0.elapsed().as_secs_f64()
            ));
        } else if let Some(d) = &s.data
            && !d.join(Split::Train.file_name()).is_file()
        {
            return Err(Error::invalid(
                study.path.display().to_string(),
                format!("subjects[{}].data", s.name),
                format!("{} has no {}", d.display(), Split::Train.file_name()),
            ));
        }
    }
    if study.config.variants.contains(&Variant::ImageEta) {
        let mut extractor = None;
        for s in &study.config.subjects {
            prepare_image_eta(study, out, &s.name, &mut extractor, progress)?;
        }
    }
    Ok(())
}

/// The record of a finished run, `None` when it has not finished.
pub fn finished(out: &Path, run: &RunSpec) -> Option<RunRecord> {
    let text = std::fs::read_to_string(run_dir(out, run).join(FINISHED)).ok()?;
    serde_json::from_str(&text).ok()
}

/// Trains and evaluates `run` unless it has finished (then returns its record). Training
/// continues from the run's newest checkpoint when there is one.
pub fn run_one(
    study: &Study,
    out: &Path,
    run: &RunSpec,
    backend: Option<BackendKind>,
    progress: &mut (dyn FnMut(&str) + Send),
) -> Result<RunRecord> {
    if let Some(r) = finished(out, run) {
        return Ok(r);
    }
    let dir = run_dir(out, run);
    let data = run_data(study, out, run)?;
    let eta_done = image_eta_root(out, &run.subject).join(IMAGE_ETA_DONE);
    if run.variant == Variant::ImageEta && !eta_done.is_file() {
        return Err(Error::invalid(
            eta_done.display().to_string(),
            "file",
            "missing: the image-eta copy is not finished; run `texavatars study --prepare` (or the whole study) first",
        ));
    }
    if !data.join(Split::Train.file_name()).is_file() {
        return Err(Error::invalid(
            data.display().to_string(),
            Split::Train.file_name(),
            "missing: run `texavatars study --prepare` (or the whole study) first",
        ));
    }
    let train_dir = dir.join("train");
    let mut options = TrainOptions::new(&data, &train_dir);
    // Continue a run this study started (its config is there); start one that never began.
    options.resume = train_dir.join(crate::train::files::CONFIG).is_file()
        || train_dir
            .join(crate::train::gaussianavatars::ga_files::CONFIG)
            .is_file();
    options.backend = backend;
    options.app_log = false;
    options.handle_signals = true;
    let head = head_for(&data)?;
    options.head = Some(head);
    let t0 = Instant::now();
    let (iterations, trained, complete) = match (study.train_config(run), study.ga_config(run)) {
        (Some(c), _) => {
            let r = crate::train::train(&c, &options)?;
            (
                c.iterations,
                r.end_iteration - r.start_iteration,
                r.complete,
            )
        }
        (None, Some(c)) => {
            let r = crate::train::gaussianavatars::train(&c, &options)?;
            (
                c.iterations,
                r.end_iteration - r.start_iteration,
                r.complete,
            )
        }
        (None, None) => {
            return Err(Error::invalid(
                study.path.display().to_string(),
                "gaussianavatars",
                "missing for the gaussianavatars variant",
            ));
        }
    };
    let train_seconds = t0.elapsed().as_secs_f64();
    if !complete {
        return Err(Error::invalid(
            run.id(),
            "train",
            "stopped before its last iteration; run the study again to continue it",
        ));
    }
    progress(&format!(
        "{}: trained {trained} of {iterations} iterations in {train_seconds:.0} s; evaluating",
        run.id()
    ));
    let eval_seconds = evaluate_run(study, out, run, backend, progress)?;
    let record = RunRecord {
        id: run.id(),
        variant: run.variant,
        seed: run.seed,
        iterations,
        train_seconds,
        trained_iterations: Some(trained),
        eval_seconds,
    };
    let path = dir.join(FINISHED);
    std::fs::write(
        &path,
        serde_json::to_string_pretty(&record).expect("serialises") + "\n",
    )
    .map_err(|e| Error::io(&path, e))?;
    Ok(record)
}

/// Evaluates `run`'s trained avatar into its `eval/` folder (replacing what is there);
/// returns the seconds it took.
fn evaluate_run(
    study: &Study,
    out: &Path,
    run: &RunSpec,
    backend: Option<BackendKind>,
    progress: &mut (dyn FnMut(&str) + Send),
) -> Result<f64> {
    let t1 = Instant::now();
    let dir = run_dir(out, run);
    let e = &study.config.eval;
    let opts = EvalOptions {
        data: run_data(study, out, run)?,
        run: dir.join("train"),
        out: dir.join("eval"),
        splits: vec![Split::Val, Split::Test, Split::Free],
        extra: Vec::new(),
        head: None,
        lpips: e.lpips,
        stride: e.stride,
        panels: e.panels,
        backend: backend.unwrap_or(BackendKind::Flex),
        paths: PathPolicy::InsideRoot,
        tracked: false,
        renders: true,
        against: None,
    };
    evaluate(&opts, &mut |l| {
        progress(&format!("{}: eval: {l}", run.id()))
    })?;
    Ok(t1.elapsed().as_secs_f64())
}

/// Evaluates a finished run again (its training kept), e.g. after `eval` learned a new
/// score; its `run.json` records the new evaluation time. `None` when `run` has not finished.
pub fn reevaluate(
    study: &Study,
    out: &Path,
    run: &RunSpec,
    backend: Option<BackendKind>,
    progress: &mut (dyn FnMut(&str) + Send),
) -> Result<Option<RunRecord>> {
    let Some(mut record) = finished(out, run) else {
        return Ok(None);
    };
    record.eval_seconds = evaluate_run(study, out, run, backend, progress)?;
    let path = run_dir(out, run).join(FINISHED);
    std::fs::write(
        &path,
        serde_json::to_string_pretty(&record).expect("serialises") + "\n",
    )
    .map_err(|e| Error::io(&path, e))?;
    Ok(Some(record))
}

/// Seconds per iteration used by [`estimate`] before any run of the study has finished: a
/// TexAvatars step without the VGG loss on the 2-core reference machine (release build,
/// `flex`, `train_cpu.json`'s networks; docs/performance.md). These reference values are
/// only a first guess: once a run of the same kind has finished, its own seconds per
/// iteration replace them.
pub const REFERENCE_STEP: f64 = 0.082;
/// A TexAvatars step with the VGG loss on the reference machine (s).
pub const REFERENCE_VGG_STEP: f64 = 0.44;
/// A GaussianAvatars step on the reference machine, averaged over a run (s; it grows with
/// densification).
pub const REFERENCE_GA_STEP: f64 = 0.9;
/// One run's evaluation at the demo's stride, with LPIPS, on the reference machine (s).
pub const REFERENCE_EVAL_RUN: f64 = 80.0;

/// Estimated seconds of the runs not finished yet: the finished runs' measured seconds per
/// iteration of the same kind (TexAvatars or GaussianAvatars) when there are some, else the
/// reference machine's ([`REFERENCE_STEP`]).
pub fn estimate(study: &Study, out: &Path) -> (f64, usize) {
    let runs = study.runs();
    let done: Vec<RunRecord> = runs.iter().filter_map(|r| finished(out, r)).collect();
    let per_iteration = |ga: bool| -> Option<f64> {
        let (s, n) = done
            .iter()
            .filter(|r| (r.variant == Variant::Gaussianavatars) == ga)
            .filter_map(|r| {
                let trained = r.trained_iterations.unwrap_or(r.iterations);
                (trained > 0).then(|| r.train_seconds / trained as f64)
            })
            .fold((0.0, 0usize), |(s, n), t| (s + t, n + 1));
        (n > 0).then(|| s / n as f64)
    };
    let eval = if done.is_empty() {
        REFERENCE_EVAL_RUN
    } else {
        done.iter().map(|r| r.eval_seconds).sum::<f64>() / done.len() as f64
    };
    let mut total = 0.0;
    let mut left = 0;
    for r in runs.iter().filter(|r| finished(out, r).is_none()) {
        left += 1;
        total += eval;
        if let Some(c) = study.ga_config(r) {
            total += c.iterations as f64 * per_iteration(true).unwrap_or(REFERENCE_GA_STEP);
        } else if let Some(c) = study.train_config(r) {
            total += match per_iteration(false) {
                Some(s) => c.iterations as f64 * s,
                None => {
                    let vgg = if c.ablations.vgg {
                        c.iterations - c.vgg_from().min(c.iterations)
                    } else {
                        0
                    };
                    (c.iterations - vgg) as f64 * REFERENCE_STEP + vgg as f64 * REFERENCE_VGG_STEP
                }
            };
        }
    }
    (total, left)
}

/// Writes `OUT/plan/commands.txt` (one command line per run) and `OUT/plan/slurm.sh` (a
/// Slurm array over them, after the data step) and returns the command lines. `exe` is the
/// texavatars binary the commands call.
pub fn plan(study: &Study, out: &Path, exe: &str) -> Result<Vec<String>> {
    let runs = study.runs();
    let config = study.path.display().to_string();
    let outs = out.display().to_string();
    let q = |s: &str| shell_quote(s);
    let commands: Vec<String> = (0..runs.len())
        .map(|k| {
            format!(
                "{} study --config {} --out {} --run {k}",
                q(exe),
                q(&config),
                q(&outs)
            )
        })
        .collect();
    let dir = out.join("plan");
    std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
    let write = |name: &str, text: String| -> Result<()> {
        let p = dir.join(name);
        let mut f = std::fs::File::create(&p).map_err(|e| Error::io(&p, e))?;
        f.write_all(text.as_bytes()).map_err(|e| Error::io(&p, e))
    };
    let mut listing = String::new();
    for (c, r) in commands.iter().zip(&runs) {
        listing.push_str(&format!("{c}  # {}\n", r.id()));
    }
    write("commands.txt", listing)?;
    let n = runs.len();
    let slurm = format!(
        "#!/bin/bash\n\
         # texavatars study: {n} independent runs of {config}.\n\
         # First, once (it generates the synthetic subjects' data):\n\
         #   {exe} study --config {config} --out {outs} --prepare\n\
         # then submit this array; every task trains and evaluates one run (a finished run is\n\
         # skipped, an interrupted one resumes), and at the end:\n\
         #   {exe} study --config {config} --out {outs} --collect\n\
         #SBATCH --job-name=texavatars-study\n\
         #SBATCH --array=0-{last}\n\
         #SBATCH --cpus-per-task=2\n\
         #SBATCH --output={outs}/plan/slurm-%A_%a.log\n\
         set -euo pipefail\n\
         {exe} study --config {config} --out {outs} --run \"$SLURM_ARRAY_TASK_ID\"\n",
        last = n.saturating_sub(1),
        exe = q(exe),
        config = q(&config),
        outs = q(&outs),
    );
    write("slurm.sh", slurm)?;
    Ok(commands)
}

/// The `xargs -P` line that runs every run of the plan, `jobs` at a time.
pub fn xargs_line(study: &Study, out: &Path, exe: &str, jobs: usize) -> String {
    let n = study.runs().len();
    format!(
        "{exe} study --config {c} --out {o} --prepare && seq 0 {last} | xargs -P {jobs} -I{{}} \
         {exe} study --config {c} --out {o} --run {{}} && {exe} study --config {c} --out {o} --collect",
        exe = shell_quote(exe),
        c = shell_quote(&study.path.display().to_string()),
        o = shell_quote(&out.display().to_string()),
        last = n.saturating_sub(1),
    )
}

/// `s` as one shell word.
fn shell_quote(s: &str) -> String {
    if !s.is_empty()
        && s.chars()
            .all(|c| c.is_ascii_alphanumeric() || "/._-=:+,".contains(c))
    {
        s.to_string()
    } else {
        format!("'{}'", s.replace('\'', "'\\''"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shell_quote_keeps_plain_words_and_quotes_the_rest() {
        assert_eq!(shell_quote("out/study_1"), "out/study_1");
        assert_eq!(shell_quote("a b"), "'a b'");
        assert_eq!(shell_quote("it's"), "'it'\\''s'");
        assert_eq!(shell_quote(""), "''");
    }

    #[test]
    fn the_estimate_divides_a_resumed_run_s_seconds_by_the_iterations_it_trained() {
        let study = Study::load(Path::new("configs/study_ladder_802.json")).expect("config");
        let runs = study.runs();
        assert_eq!(runs.len(), 5);
        let out = std::env::temp_dir().join(format!("texavatars-estimate-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&out);
        let first = &runs[0];
        assert_eq!(first.variant, Variant::Full);
        let dir = run_dir(&out, first);
        std::fs::create_dir_all(&dir).expect("mkdir");
        let write = |record: &str| std::fs::write(dir.join(FINISHED), record).expect("write");
        // Resumed at iteration 3,000: 100 s for its last 500 iterations, 10 s of eval.
        write(
            r#"{"id": "subject0/full-seed0", "variant": "full", "seed": 0, "iterations": 3500,
                "train_seconds": 100.0, "trained_iterations": 500, "eval_seconds": 10.0}"#,
        );
        let (seconds, left) = estimate(&study, &out);
        assert_eq!(left, 4);
        let ga = 3500.0 * REFERENCE_GA_STEP + 10.0;
        assert!(
            (seconds - (3.0 * (3500.0 * 0.2 + 10.0) + ga)).abs() < 1e-6,
            "{seconds}"
        );
        // A record from before the field: its seconds cover all its iterations.
        write(
            r#"{"id": "subject0/full-seed0", "variant": "full", "seed": 0, "iterations": 3500,
                "train_seconds": 100.0, "eval_seconds": 10.0}"#,
        );
        let (seconds, _) = estimate(&study, &out);
        assert!(
            (seconds - (3.0 * (100.0 + 10.0) + ga)).abs() < 1e-6,
            "{seconds}"
        );
        let _ = std::fs::remove_dir_all(&out);
    }

    #[test]
    fn the_image_eta_copy_leaves_out_eta_folders_and_projections() {
        let dir = std::env::temp_dir().join(format!("texavatars-mirror-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let src = dir.join("src");
        for f in [
            "union/transforms_train.json",
            "seq/flame_param/00000.npz",
            "seq/eta/00000.npy",
        ] {
            let p = src.join(f);
            std::fs::create_dir_all(p.parent().expect("parent")).expect("mkdir");
            std::fs::write(&p, f).expect("write");
        }
        std::fs::write(
            src.join("union").join(crate::eta::projection::FILE_NAME),
            "p",
        )
        .expect("write");
        let dst = dir.join("dst");
        mirror(&src, &dst).expect("mirror");
        assert_eq!(
            std::fs::read_to_string(dst.join("seq/flame_param/00000.npz")).expect("copied"),
            "seq/flame_param/00000.npz"
        );
        assert!(dst.join("union/transforms_train.json").is_file());
        assert!(!dst.join("seq/eta").exists());
        assert!(
            !dst.join("union")
                .join(crate::eta::projection::FILE_NAME)
                .exists()
        );
        // Again: what is there is kept.
        mirror(&src, &dst).expect("again");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
