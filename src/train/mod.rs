//! Training an avatar on a VHAP export (method §6) through burn's `Learner`.
//!
//! - The model burn trains is [`AvatarTraining`]: the [`Avatar`] and
//!   its objective ([`loss`]); [`step`] implements `TrainStep` (render, objective,
//!   backward) and `InferenceStep` (the same without VGG, on the held-out camera).
//! - The paper counts iterations, burn counts epochs: one burn epoch is one checkpoint
//!   interval ([`loader`]), so burn's checkpointer writes `OUT/checkpoint/{model,optim,
//!   scheduler}-E.bpk` every `checkpoint_every` iterations and `--resume` continues from the
//!   newest complete one, with the same frames the uninterrupted run would have used.
//! - Two learning rates (6e-4 for the decoders, 4e-4 for Exp2Code and the view encoder):
//!   burn 0.22 has parameter groups: a `ModuleLrScheduler` with a constant base rate and a
//!   group (`ParamGroup::from_any_predicates(["exp2code", "view_encoder"])`, matched against
//!   each parameter's module path) at the other rate. Adam keeps its moments per parameter,
//!   so the groups share nothing but the hyper-parameters (beta1, beta2, eps 1e-15).
//! - Metrics (the objective, each term, PSNR) are burn metrics ([`metrics`]): logged by
//!   burn under `OUT/train/epoch-E/` and `OUT/valid/epoch-E/`, printed by [`progress`].
//!
//! - Stops: a signal (SIGINT, SIGTERM), `stop_after` or a non-finite loss or gradient stop a
//!   run without losing work or saving a broken avatar ([`stop`], [`signals`]); one run per
//!   folder at a time ([`lock`]).
//!
//! Seeds: the device is seeded with the config's seed before the networks are built, and the
//! frame order is a function of the seed and the iteration.

pub mod config;
pub mod constants;
pub mod loader;
pub mod lock;
pub mod loss;
pub mod metrics;
pub mod progress;
pub mod signals;
pub mod step;
pub mod stop;

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use burn::lr_scheduler::module_lr_scheduler::{ModuleLrScheduler, ModuleLrSchedulerConfig};
use burn::module::{Module, ParamGroup};
use burn::optim::{AdamConfig, ModuleOptimizer};
use burn::train::checkpoint::{Checkpoint, KeepLastNCheckpoints};
use burn::train::{Learner, SupervisedTraining};

pub use config::{NetSpec, TrainConfig};
pub use loader::{FrameLoader, Schedule, TrainBatch};
pub use loss::{LossTerms, LossWeights, objective};
pub use metrics::{Term, TermMetric};
pub use progress::ProgressPrinter;
pub use step::{AvatarTraining, Objective, StepOutput};
pub use stop::{Fault, IterationRecord, StopControl};

use crate::data::{HeadDataset, PathPolicy, Split};
use crate::device::BackendKind;
use crate::error::{Error, Result};
use crate::head::HeadAsset;
use crate::metrics::VggPerceptual;
use crate::model::{Avatar, AvatarConfig};
use constants::{ENCODER_MODULES, KEEP_CHECKPOINTS};

/// File names inside the output folder.
pub mod files {
    /// The resolved training config of the run (read back by `--resume`).
    pub const CONFIG: &str = "train_config.json";
    /// The avatar's config (networks and ablations), for loading the trained avatar.
    pub const AVATAR_CONFIG: &str = "avatar.json";
    /// The trained avatar's parameters (burnpack), written when the run ends.
    pub const AVATAR: &str = "avatar.bpk";
    /// burn's checkpoint folder.
    pub const CHECKPOINTS: &str = "checkpoint";
    /// The subject's shape and static offsets the avatar was trained with (VHAP's canonical
    /// parameter file).
    pub const IDENTITY: &str = crate::data::identity::CANONICAL;
}

/// How to run [`train`].
#[derive(Clone, Debug)]
pub struct TrainOptions {
    /// The VHAP export's split folder (`transforms_{train,val}.json`), e.g. `OUT/union` of
    /// `texavatars synth`.
    pub data: PathBuf,
    /// Output folder (checkpoints, logs, the trained avatar).
    pub out: PathBuf,
    /// Continue from the newest complete checkpoint in `out`.
    pub resume: bool,
    /// Overrides the config's backend.
    pub backend: Option<BackendKind>,
    /// The head the data was made with; `None`: `data/../head/head.npz` when it exists (a
    /// `texavatars synth` output), else the embedded default head.
    pub head: Option<HeadAsset>,
    /// Install burn's application logger (`out/experiment.log`); it is process-global, so
    /// library callers that train several times may turn it off.
    pub app_log: bool,
    /// Stop after this many iterations of this process, with a checkpoint (the run's count
    /// continues with `--resume`; tests use it to interrupt a run).
    pub stop_after: Option<usize>,
    /// Stop on SIGINT / SIGTERM with a checkpoint ([`signals`]); the command line turns it
    /// on, library callers may leave the process's signals alone.
    pub handle_signals: bool,
    /// Stops the run from elsewhere ([`StopControl::request`]); `None`: a private one.
    pub stop: Option<StopControl>,
    /// Start afresh even when `out` holds a run or a finished avatar: train's own files
    /// there are removed first ([`OWNED`]).
    pub force: bool,
    /// Where the dataset's files may live ([`PathPolicy`]; `--allow-outside-paths`).
    pub paths: PathPolicy,
}

impl TrainOptions {
    /// Defaults: no resume, the config's backend, the head found next to the data, burn's
    /// application log on.
    pub fn new(data: impl Into<PathBuf>, out: impl Into<PathBuf>) -> Self {
        TrainOptions {
            data: data.into(),
            out: out.into(),
            resume: false,
            backend: None,
            head: None,
            app_log: true,
            stop_after: None,
            handle_signals: false,
            stop: None,
            force: false,
            paths: PathPolicy::InsideRoot,
        }
    }
}

/// What a [`train`] call did.
#[derive(Debug)]
pub struct TrainReport {
    /// The global iteration this process started at (0 unless resumed).
    pub start_iteration: usize,
    /// The global iteration reached (the run's total unless stopped early).
    pub end_iteration: usize,
    /// The trained avatar (on the inner, non-autodiff device).
    pub avatar: Avatar,
    /// Gaussians of the avatar.
    pub gaussians: usize,
    /// Wall time of this process's training.
    pub seconds: f64,
    /// Where the trained avatar is written (`out/avatar.bpk`); only a complete run writes it.
    pub avatar_path: PathBuf,
    /// Whether the run reached its last iteration (else it stopped with a checkpoint).
    pub complete: bool,
}

/// What `train` writes into its output folder, removed by [`TrainOptions::force`].
pub const OWNED: [&str; 8] = [
    files::CONFIG,
    files::AVATAR_CONFIG,
    files::AVATAR,
    files::CHECKPOINTS,
    files::IDENTITY,
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

/// The head of `options`: given, or `data/../head/head.npz`, or the embedded default.
fn find_head(options: &TrainOptions) -> Result<HeadAsset> {
    if let Some(h) = &options.head {
        return Ok(h.clone());
    }
    let next_to_data = options.data.join("..").join("head").join("head.npz");
    if next_to_data.is_file() {
        HeadAsset::load(&next_to_data, None)
    } else {
        HeadAsset::embedded()
    }
}

fn write(path: &Path, text: &str) -> Result<()> {
    std::fs::write(path, text).map_err(|e| Error::io(path, e))
}

/// The learning rates: `lr_decoders` for every parameter, `lr_encoders` for those under
/// [`ENCODER_MODULES`].
pub fn lr_scheduler(config: &TrainConfig) -> ModuleLrScheduler {
    ModuleLrSchedulerConfig::new(config.lr_decoders.into())
        .with_group(
            ParamGroup::from_any_predicates(ENCODER_MODULES.to_vec()),
            config.lr_encoders,
        )
        .init()
        .expect("constant learning rates are valid")
}

/// Adam with the config's betas and epsilon.
pub fn optimizer(config: &TrainConfig) -> ModuleOptimizer {
    AdamConfig::new()
        .with_beta_1(config.adam_beta1 as f32)
        .with_beta_2(config.adam_beta2 as f32)
        .with_epsilon(config.adam_eps as f32)
        .init()
}

/// Trains the avatar of `config` on `options.data` (see the module documentation), writes
/// `out/avatar.bpk` and returns the trained avatar.
///
/// A resumed run restores the optimiser state on burn's `Device::default()` first (burn
/// 0.22); set `BURN_DEVICE` to the run's backend to keep a CPU run off wgpu (the `train`
/// command does).
///
/// Before anything runs, the data is checked against the avatar (the posed meshes' vertex
/// count) and, when the VGG loss is on, the VGG16 weights must be installed (`texavatars
/// weights install`). The net config's expression width is set to the head model's (the
/// loader pads or truncates every frame's coefficients to it).
pub fn train(config: &TrainConfig, options: &TrainOptions) -> Result<TrainReport> {
    let mut config = config.clone();
    config.validate("train config")?;
    let head = find_head(options)?;
    if let NetSpec::Inline(net) = &mut config.net
        && net.condition.expression != head.model.num_expr
    {
        eprintln!(
            "train: the head model has {} expression coefficients; net.condition.expression {} -> {}",
            head.model.num_expr, net.condition.expression, head.model.num_expr
        );
        net.condition.expression = head.model.num_expr;
    }
    let avatar_config: AvatarConfig = config.avatar()?;

    // Every frame's files, before anything is written or removed (issue 15.5).
    let model = Arc::new(head.model.clone());
    let checking = Instant::now();
    let train_set = Arc::new(HeadDataset::open_with(
        &options.data,
        Split::Train,
        model.clone(),
        options.paths,
    )?);
    if train_set.is_empty() {
        return Err(Error::invalid(
            train_set.transforms_path().display().to_string(),
            "frames",
            "the training split has no frames",
        ));
    }
    let checked = train_set.check_files()?;
    let val_file = options.data.join(Split::Val.file_name());
    let val_set = if config.val_frames > 0 && val_file.is_file() {
        let v = HeadDataset::open_with(&options.data, Split::Val, model.clone(), options.paths)?;
        v.check_files()?;
        Some(Arc::new(v))
    } else {
        None
    };
    eprintln!(
        "train: checked {} frames and {} timesteps{} in {:.1} s",
        checked.frames,
        checked.timesteps,
        match &val_set {
            Some(v) => format!(" (and {} validation frames)", v.len()),
            None => String::new(),
        },
        checking.elapsed().as_secs_f64()
    );

    let out = &options.out;
    let ckpt_dir = out.join(files::CHECKPOINTS);
    // One run per folder at a time, for the run's whole life (crate::train::lock).
    let _lock = lock::RunLock::acquire(out)?;

    // Scratch files of writes a killed run never finished.
    for dir in [out.clone(), ckpt_dir.clone()] {
        let n = remove_stale_tmp(&dir)?;
        if n > 0 {
            eprintln!(
                "train: removed {n} unfinished temporary file(s) in {}",
                dir.display()
            );
        }
    }

    // Resume: the saved config must describe the same run.
    let checkpoint = if options.resume {
        let saved = TrainConfig::load(&out.join(files::CONFIG))?;
        if let Err(field) = saved.resumable_as(&config) {
            return Err(Error::invalid(
                out.join(files::CONFIG).display().to_string(),
                field,
                "differs from the given config; a resumed run must train the same avatar with \
                 the same schedule (only iterations, val_frames, log_every and backend may change)",
            ));
        }
        let c = latest_checkpoint(&ckpt_dir);
        if c.is_none() {
            eprintln!(
                "train: --resume: no complete checkpoint in {}; starting from iteration 0",
                ckpt_dir.display()
            );
        }
        c
    } else {
        let finished = out.join(files::AVATAR).exists();
        if latest_checkpoint(&ckpt_dir).is_some() || finished {
            if !options.force {
                return Err(Error::invalid(
                    out.display().to_string(),
                    if finished { "avatar.bpk" } else { "checkpoint" },
                    "already holds a training run; pass --resume to continue it, --force to \
                     replace it, or choose another --out",
                ));
            }
            for name in OWNED {
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

    let backend = options.backend.unwrap_or(config.backend);
    let device = backend.autodiff_device();
    let avatar = avatar_config.init_seeded(config.seed, &head.mesh, &device)?;
    // One frame through the checks the step cannot report (it may only panic).
    let probe = train_set.load_item(0)?;
    if probe.vertices.len() != avatar.num_vertices() {
        return Err(Error::invalid(
            train_set.transforms_path().display().to_string(),
            "flame_param_path",
            format!(
                "posed meshes have {} vertices, the avatar's UV mesh {}",
                probe.vertices.len(),
                avatar.num_vertices()
            ),
        ));
    }
    let vgg = if config.ablations.vgg {
        let v = VggPerceptual::load(&device)
            .map_err(|e| {
                Error::invalid(
                    "train config",
                    "ablations.vgg",
                    format!(
                        "the VGG loss needs the VGG16 weights: {e} (or set ablations.vgg to false)"
                    ),
                )
            })?
            .no_grad();
        Some(Arc::new(v))
    } else {
        None
    };
    let stop = options.stop.clone().unwrap_or_default();
    let training = AvatarTraining {
        avatar,
        objective: Objective {
            weights: config.loss.clone(),
            vgg,
            vgg_from: config.vgg_from(),
            guard: Some(stop.clone()),
        },
    };
    let gaussians = training.avatar.num_gaussians();

    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    write(&out.join(files::CONFIG), &config.to_json())?;
    // The subject the avatar is trained on, for eval and driving (crate::data::identity).
    train_set
        .identity()
        .save(&head.model, &out.join(files::IDENTITY))?;
    write(
        &out.join(files::AVATAR_CONFIG),
        &(serde_json::to_string_pretty(&avatar_config).expect("serialises") + "\n"),
    )?;

    let schedule = Schedule {
        seed: config.seed,
        per_epoch: config.checkpoint_every,
        total: config.iterations,
        batch_size: config.batch_size,
        resume: resume_at,
    };
    let start_epoch = checkpoint.unwrap_or(0);
    let start_iteration = schedule.iterations_of(start_epoch).start;
    // A run stopped in its last interval has its remaining iterations in one more epoch.
    let epochs = schedule
        .epochs()
        .max(start_epoch + usize::from(start_iteration < schedule.total));
    let end_iteration = schedule.iterations_of(epochs.saturating_sub(1)).end;
    if let Some(n) = options.stop_after {
        stop.stop_before(start_iteration + n);
    }
    let _signals = if options.handle_signals {
        Some(signals::SignalGuard::install(&stop)?)
    } else {
        None
    };
    eprintln!(
        "train: {} frames, {} Gaussians (R = S = {}), {} backend, iterations {start_iteration}..{end_iteration} of {}, VGG from iteration {}",
        train_set.len(),
        gaussians,
        avatar_config.net.uv_res,
        format!("{backend:?}").to_lowercase(),
        schedule.total,
        if config.ablations.vgg {
            config.vgg_from().to_string()
        } else {
            "never".into()
        }
    );

    // Validation: the held-out camera's frames when the export has them.
    let valid_loader = if let Some(val_set) = val_set {
        let val_indices = FrameLoader::spread(val_set.len(), config.val_frames);
        FrameLoader::fixed(val_set, val_indices, &device.clone().inner())
            .with_stop(stop.clone(), None)
    } else {
        if config.val_frames > 0 {
            eprintln!("train: no {}: no validation", val_file.display());
        }
        FrameLoader::fixed(train_set.clone(), Vec::new(), &device.clone().inner())
    };
    let train_loader = FrameLoader::training(train_set, schedule.clone(), start_epoch, &device)
        .with_stop(stop.clone(), Some(ckpt_dir.clone()));

    let mut builder = SupervisedTraining::new(out, Arc::new(train_loader), Arc::new(valid_loader))
        .metrics((
            TermMetric::new(Term::Loss),
            TermMetric::new(Term::L1),
            TermMetric::new(Term::DSsim),
            TermMetric::new(Term::Vgg),
        ))
        .metrics((
            TermMetric::new(Term::Position),
            TermMetric::new(Term::Scale),
            TermMetric::new(Term::Psnr),
        ))
        .with_default_checkpointers()
        .with_checkpointing_strategy(KeepLastNCheckpoints::new(KEEP_CHECKPOINTS))
        .renderer(Box::new(
            ProgressPrinter::new(schedule.clone(), config.log_every).with_stop(stop.clone()),
        ))
        .with_interrupter(stop.interrupter.clone())
        .num_epochs(epochs);
    if !options.app_log {
        builder = builder.with_application_logger(None);
    }
    if let Some(c) = checkpoint {
        builder = builder.checkpoint(c);
    }
    let learner = Learner::new(training, optimizer(&config), lr_scheduler(&config));
    let t0 = Instant::now();
    let result = builder.launch(learner);
    let seconds = t0.elapsed().as_secs_f64();
    remove_stale_tmp(&ckpt_dir)?;
    let resume_hint = format!(
        "resume with `texavatars train --data {} --config CONFIG --out {} --resume`",
        options.data.display(),
        out.display()
    );
    if let Some(fault) = stop.take_fault() {
        let values: Vec<String> = fault
            .values
            .iter()
            .map(|(n, v)| format!("{n} {v:.6}"))
            .collect();
        let kept = match latest_checkpoint(&ckpt_dir) {
            Some(c) => format!(
                "the last good checkpoint is {c} (iteration {}); lower the learning rates and {resume_hint}",
                checkpoint_iteration(&schedule, &ckpt_dir, c)
            ),
            None => "no checkpoint was written yet".into(),
        };
        return Err(Error::invalid(
            "training",
            format!("iteration {}", fault.iteration),
            format!(
                "not finite: {} ({}); stopped without saving this state: {kept}",
                fault.culprits().join(", "),
                values.join(", ")
            ),
        ));
    }
    if let Some((iteration, e)) = stop.take_data_error() {
        let kept = match latest_checkpoint(&ckpt_dir) {
            Some(c) => format!(
                "checkpoint {c} in {} holds iterations 0..{}; fix the file and {resume_hint}",
                ckpt_dir.display(),
                checkpoint_iteration(&schedule, &ckpt_dir, c)
            ),
            None => "no checkpoint was written yet; fix the file and start again".into(),
        };
        return Err(Error::invalid(
            "training",
            format!("iteration {iteration}"),
            format!("a frame could not be read: {e}; {kept}"),
        ));
    }
    if let Some(e) = result.error {
        return Err(Error::invalid(
            out.display().to_string(),
            "training",
            format!("stopped by an error: {e}"),
        ));
    }
    let reached = stop
        .stopped_at()
        .unwrap_or(end_iteration)
        .min(end_iteration);
    let complete = reached == schedule.total;
    let avatar = result.model.avatar;
    let avatar_path = out.join(files::AVATAR);
    if complete {
        avatar.clone().save_file(&avatar_path).map_err(|e| {
            Error::invalid(avatar_path.display().to_string(), "save", e.to_string())
        })?;
    } else {
        let saved = match latest_checkpoint(&ckpt_dir) {
            Some(c) => format!(
                "checkpoint {c} in {} holds iterations 0..{}",
                ckpt_dir.display(),
                checkpoint_iteration(&schedule, &ckpt_dir, c)
            ),
            None => "no checkpoint was written".into(),
        };
        let message = format!(
            "train: stopped at iteration {reached} of {}; {saved}; {resume_hint}",
            schedule.total
        );
        if let Some(signal) = stop.signal() {
            return Err(Error::Stopped {
                signal,
                message: format!("{} ({message})", signals::name(signal)),
            });
        }
        eprintln!("{message}");
    }
    Ok(TrainReport {
        start_iteration,
        end_iteration: reached,
        avatar,
        gaussians,
        seconds,
        avatar_path,
        complete,
    })
}

/// The global iterations checkpoint `c` (1-based) holds: its [`IterationRecord`] when it
/// was taken in the middle of an interval, else the end of interval `c`.
pub fn checkpoint_iteration(schedule: &Schedule, ckpt_dir: &Path, c: usize) -> usize {
    match IterationRecord::load(ckpt_dir, c) {
        Ok(Some(r)) => r.iteration,
        _ => (c * schedule.per_epoch).min(schedule.total),
    }
}
