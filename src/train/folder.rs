//! The run's output folder: the names of the files a run writes ([`files`], [`OWNED`]),
//! finding the newest complete checkpoint and making the folder ready for a run (locked,
//! scratch files removed, resumed or replaced: [`prepare_folder`]).

use std::path::{Path, PathBuf};

use burn::train::checkpoint::Checkpoint;

use super::lock;
use super::options::TrainOptions;
use super::stop::IterationRecord;
use crate::error::{Error, Result};

pub use crate::models::texavatars::files;

/// What `train` writes into its output folder, removed by [`TrainOptions::force`].
pub const OWNED: [&str; 11] = [
    files::CONFIG,
    crate::data::refined::REFINED_NPZ,
    crate::data::refined::REFINED_INDEX,
    files::AVATAR_CONFIG,
    files::AVATAR,
    files::CHECKPOINTS,
    files::IDENTITY,
    crate::eta::projection::FILE_NAME,
    "train",
    "valid",
    "experiment.log",
];

/// Removes `*.tmp` files in `dir` (not below): scratch files of writes that a killed process
/// never finished (burn's checkpoint store writes `<name>.<pid>-<n>.tmp` and renames it).
/// Call only while holding the run's lock, when no writer can be running.
pub fn remove_stale_tmp(dir: &Path) -> Result<usize> {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return Ok(0);
    };
    let mut n = 0;
    for e in entries.flatten() {
        let p = e.path();
        if p.extension().is_some_and(|x| x == "tmp") && p.is_file() {
            std::fs::remove_file(&p).map_err(|err| Error::io(&p, err))?;
            n += 1;
        }
    }
    Ok(n)
}

/// The newest epoch of `dir` (burn's checkpoint folder) whose model, optimiser and
/// scheduler records all exist and parse; a partly written newest one (a run killed while
/// saving) is skipped for the one before.
pub fn latest_checkpoint(dir: &Path) -> Option<usize> {
    let mut epochs: Vec<usize> = std::fs::read_dir(dir)
        .ok()?
        .flatten()
        .filter_map(|e| {
            let name = e.file_name().into_string().ok()?;
            name.strip_prefix("model-")?
                .strip_suffix(".bpk")?
                .parse()
                .ok()
        })
        .collect();
    epochs.sort_unstable();
    epochs.into_iter().rev().find(|&e| {
        let p = |name: &str| dir.join(format!("{name}-{e}.bpk"));
        burn::store::ModuleRecord::load(p("model")).is_ok()
            && <burn::optim::OptimizerRecord as Checkpoint>::load(p("optim")).is_ok()
            && <burn::lr_scheduler::LrSchedulerRecord as Checkpoint>::load(p("scheduler")).is_ok()
    })
}

/// A run's output folder, locked and made ready by [`prepare_folder`].
pub struct RunFolder {
    /// Held for the run's whole life ([`lock`]).
    pub lock: lock::RunLock,
    /// `OUT/checkpoint`.
    pub ckpt_dir: PathBuf,
    /// The checkpoint (1-based burn epoch) a resumed run starts from.
    pub checkpoint: Option<usize>,
    /// The checkpoint and the global iteration it holds, when it was taken in the middle of
    /// an interval ([`IterationRecord`]).
    pub resume_at: Option<(usize, usize)>,
}

/// Locks `options.out` (one run per folder), removes scratch files of killed writes, and
/// either finds the checkpoint to resume from (after `check_saved` has compared the saved
/// config with this run's) or refuses a folder that holds a run unless `--force`, which
/// removes the `owned` files first. `finished` is the file a complete run writes.
pub fn prepare_folder(
    options: &TrainOptions,
    owned: &[&str],
    finished: &str,
    check_saved: impl FnOnce() -> Result<()>,
) -> Result<RunFolder> {
    let out = &options.out;
    let ckpt_dir = out.join(files::CHECKPOINTS);
    let lock = lock::RunLock::acquire(out)?;
    for dir in [out.clone(), ckpt_dir.clone()] {
        let n = remove_stale_tmp(&dir)?;
        if n > 0 {
            eprintln!(
                "train: removed {n} unfinished temporary file(s) in {}",
                dir.display()
            );
        }
    }
    let checkpoint = if options.resume {
        check_saved()?;
        let c = latest_checkpoint(&ckpt_dir);
        if c.is_none() {
            eprintln!(
                "train: --resume: no complete checkpoint in {}; starting from iteration 0",
                ckpt_dir.display()
            );
        }
        c
    } else {
        let done = out.join(finished).exists();
        if latest_checkpoint(&ckpt_dir).is_some() || done {
            if !options.force {
                return Err(Error::invalid(
                    out.display().to_string(),
                    if done { finished } else { "checkpoint" },
                    "already holds a training run; pass --resume to continue it, --force to \
                     replace it, or choose another --out",
                ));
            }
            for name in owned {
                let p = out.join(name);
                let r = if p.is_dir() {
                    std::fs::remove_dir_all(&p)
                } else if p.exists() {
                    std::fs::remove_file(&p)
                } else {
                    Ok(())
                };
                r.map_err(|e| Error::io(&p, e))?;
            }
            eprintln!(
                "train: --force: removed the earlier run in {}",
                out.display()
            );
        }
        None
    };
    // Records of checkpoints that were never written; the newest's, when it was taken in the
    // middle of an interval (a stopped run).
    IterationRecord::remove_after(&ckpt_dir, checkpoint.unwrap_or(0))?;
    let resume_at = match checkpoint {
        Some(c) => IterationRecord::load(&ckpt_dir, c)?.map(|r| (c, r.iteration)),
        None => None,
    };
    Ok(RunFolder {
        lock,
        ckpt_dir,
        checkpoint,
        resume_at,
    })
}
