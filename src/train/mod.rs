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
pub mod refine;
pub mod signals;
pub mod step;
pub mod stop;

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use burn::lr_scheduler::module_lr_scheduler::{ModuleLrScheduler, ModuleLrSchedulerConfig};
use burn::module::{Module, ParamGroup};
use burn::optim::ModuleOptimizer;
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
pub const OWNED: [&str; 10] = [
    files::CONFIG,
    refine::REFINED_NPZ,
    refine::REFINED_INDEX,
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
/// [`ENCODER_MODULES`], and FLAME refinement's three ([`refine`]).
pub fn lr_scheduler(config: &TrainConfig) -> ModuleLrScheduler {
    ModuleLrSchedulerConfig::new(config.lr_decoders.into())
        .with_group(
            ParamGroup::from_any_predicates(ENCODER_MODULES.to_vec()),
            config.lr_encoders,
        )
        .with_group(
            ParamGroup::from_predicate(refine::REFINE_EXPR),
            config.lr_flame_expr,
        )
        .with_group(
            ParamGroup::from_predicate(refine::REFINE_POSE),
            config.lr_flame_pose,
        )
        .with_group(
            ParamGroup::from_predicate(refine::REFINE_TRANSLATION),
            config.lr_flame_translation,
        )
        .init()
        .expect("constant learning rates are valid")
}

/// Adam with the config's betas and epsilon.
pub fn optimizer(config: &TrainConfig) -> ModuleOptimizer {
    texavatars_cpu::adam::FusedAdam {
        beta_1: config.adam_beta1 as f32,
        beta_2: config.adam_beta2 as f32,
        epsilon: config.adam_eps as f32,
    }
    .init()
}

/// The training frames of `options.data` and, when `val_frames > 0` and the export has
/// one, its validation split, each frame's files checked before anything is written or
/// removed (issue 15.5).
pub fn open_frames(
    options: &TrainOptions,
    model: Arc<crate::head::HeadModel>,
    val_frames: usize,
) -> Result<(Arc<HeadDataset>, Option<Arc<HeadDataset>>)> {
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
    let val_set = if val_frames > 0 && val_file.is_file() {
        let v = HeadDataset::open_with(&options.data, Split::Val, model, options.paths)?;
        v.check_files()?;
        Some(Arc::new(v))
    } else {
        if val_frames > 0 {
            eprintln!("train: no {}: no validation", val_file.display());
        }
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
    Ok((train_set, val_set))
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

/// The part of a run burn's learner drives, for any model whose steps take [`TrainBatch`]es
/// and report [`StepOutput`]s.
pub struct Launch {
    /// The run's iterations and checkpoint intervals.
    pub schedule: Schedule,
    /// The checkpoint a resumed run starts from ([`RunFolder::checkpoint`]).
    pub checkpoint: Option<usize>,
    /// Iterations between progress lines.
    pub log_every: usize,
    /// Validation frames per checkpoint.
    pub val_frames: usize,
    /// Stops the run ([`StopControl`]).
    pub stop: StopControl,
    /// The `train` arguments naming the model in resume hints (`""` for TexAvatars,
    /// `" --model gaussianavatars"`).
    pub model_arg: &'static str,
}

/// What [`Launch::run`] hands back: the learner's result, the process's first and last
/// iterations and its wall time.
pub struct Launched<M> {
    pub result: burn::train::LearningResult<M>,
    pub start_iteration: usize,
    pub end_iteration: usize,
    pub seconds: f64,
    /// Signal handlers, released when the run's report is done.
    pub signals: Option<signals::SignalGuard>,
}

impl Launch {
    /// The first burn epoch this process trains, its first iteration, the number of epochs
    /// and the last iteration.
    fn epochs(&self) -> (usize, usize, usize, usize) {
        let start_epoch = self.checkpoint.unwrap_or(0);
        let start_iteration = self.schedule.iterations_of(start_epoch).start;
        // A run stopped in its last interval has its remaining iterations in one more epoch.
        let epochs = self
            .schedule
            .epochs()
            .max(start_epoch + usize::from(start_iteration < self.schedule.total));
        let end_iteration = self.schedule.iterations_of(epochs.saturating_sub(1)).end;
        (start_epoch, start_iteration, epochs, end_iteration)
    }

    /// The first iteration this process trains.
    pub fn start_iteration(&self) -> usize {
        self.epochs().1
    }

    /// Runs burn's learner on `training` (with its optimiser and learning rates) and the
    /// loaders (the objective's terms as burn metrics, checkpoints every interval, progress
    /// lines), after `announce` has printed the run's first line with the iterations it
    /// will train.
    pub fn run<M>(
        &self,
        options: &TrainOptions,
        training: M,
        (optim, lr): (ModuleOptimizer, ModuleLrScheduler),
        sets: (Arc<HeadDataset>, Option<Arc<HeadDataset>>),
        device: &burn::tensor::Device,
        announce: impl FnOnce(usize, usize),
    ) -> Result<Launched<M>>
    where
        M: burn::train::LearnerModel
            + burn::train::TrainStep<Input = TrainBatch, Output = StepOutput>
            + burn::train::InferenceStep<Input = TrainBatch, Output = StepOutput>,
    {
        let (start_epoch, start_iteration, epochs, end_iteration) = self.epochs();
        let stop = &self.stop;
        let ckpt_dir = options.out.join(files::CHECKPOINTS);
        if let Some(n) = options.stop_after {
            stop.stop_before(start_iteration + n);
        }
        let signals = if options.handle_signals {
            Some(signals::SignalGuard::install(stop)?)
        } else {
            None
        };
        announce(start_iteration, end_iteration);
        let (train_set, val_set) = sets;
        // Validation: the held-out camera's frames when the export has them.
        let valid_loader = if let Some(val_set) = val_set {
            let val_indices = FrameLoader::spread(val_set.len(), self.val_frames);
            FrameLoader::fixed(val_set, val_indices, &device.clone().inner())
                .with_stop(stop.clone(), None)
        } else {
            FrameLoader::fixed(train_set.clone(), Vec::new(), &device.clone().inner())
        };
        let train_loader =
            FrameLoader::training(train_set, self.schedule.clone(), start_epoch, device)
                .with_stop(stop.clone(), Some(ckpt_dir));
        let mut builder =
            SupervisedTraining::new(&options.out, Arc::new(train_loader), Arc::new(valid_loader))
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
                    ProgressPrinter::new(self.schedule.clone(), self.log_every)
                        .with_stop(stop.clone()),
                ))
                .with_interrupter(stop.interrupter.clone())
                .num_epochs(epochs);
        if !options.app_log {
            builder = builder.with_application_logger(None);
        }
        if let Some(c) = self.checkpoint {
            builder = builder.checkpoint(c);
        }
        let learner = Learner::new(training, optim, lr);
        let t0 = Instant::now();
        let result = builder.launch(learner);
        Ok(Launched {
            result,
            start_iteration,
            end_iteration,
            seconds: t0.elapsed().as_secs_f64(),
            signals,
        })
    }

    /// After the learner: a non-finite value, a data error or burn's own error become the
    /// run's error (naming the checkpoint to resume from); else the iteration reached and
    /// whether the run is complete.
    pub fn outcome(
        &self,
        options: &TrainOptions,
        error: Option<String>,
        end_iteration: usize,
    ) -> Result<(usize, bool)> {
        let stop = &self.stop;
        let schedule = &self.schedule;
        let out = &options.out;
        let ckpt_dir = out.join(files::CHECKPOINTS);
        remove_stale_tmp(&ckpt_dir)?;
        let resume_hint = resume_hint(options, self.model_arg);
        if let Some(fault) = stop.take_fault() {
            let values: Vec<String> = fault
                .values
                .iter()
                .map(|(n, v)| format!("{n} {v:.6}"))
                .collect();
            let kept = match latest_checkpoint(&ckpt_dir) {
                Some(c) => format!(
                    "the last good checkpoint is {c} (iteration {}); lower the learning rates and {resume_hint}",
                    checkpoint_iteration(schedule, &ckpt_dir, c)
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
                    checkpoint_iteration(schedule, &ckpt_dir, c)
                ),
                None => "no checkpoint was written yet; fix the file and start again".into(),
            };
            return Err(Error::invalid(
                "training",
                format!("iteration {iteration}"),
                format!("a frame could not be read: {e}; {kept}"),
            ));
        }
        if let Some(e) = error {
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
        Ok((reached, reached == schedule.total))
    }

    /// An incomplete run's message (where its work is, how to resume): the run's error when
    /// a signal stopped it, else printed.
    pub fn stopped(&self, options: &TrainOptions, reached: usize) -> Result<()> {
        let ckpt_dir = options.out.join(files::CHECKPOINTS);
        let saved = match latest_checkpoint(&ckpt_dir) {
            Some(c) => format!(
                "checkpoint {c} in {} holds iterations 0..{}",
                ckpt_dir.display(),
                checkpoint_iteration(&self.schedule, &ckpt_dir, c)
            ),
            None => "no checkpoint was written".into(),
        };
        let message = format!(
            "train: stopped at iteration {reached} of {}; {saved}; {}",
            self.schedule.total,
            resume_hint(options, self.model_arg)
        );
        if let Some(signal) = self.stop.signal() {
            return Err(Error::Stopped {
                signal,
                message: format!("{} ({message})", signals::name(signal)),
            });
        }
        eprintln!("{message}");
        Ok(())
    }
}

fn resume_hint(options: &TrainOptions, model_arg: &str) -> String {
    format!(
        "resume with `texavatars train{model_arg} --data {} --config CONFIG --out {} --resume`",
        options.data.display(),
        options.out.display()
    )
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

    let model = Arc::new(head.model.clone());
    let (train_set, val_set) = open_frames(options, model, config.val_frames)?;

    let out = &options.out;
    let folder = prepare_folder(options, &OWNED, files::AVATAR, || {
        let saved = TrainConfig::load(&out.join(files::CONFIG))?;
        saved.resumable_as(&config).map_err(|field| {
            Error::invalid(
                out.join(files::CONFIG).display().to_string(),
                field,
                "differs from the given config; a resumed run must train the same avatar with \
                 the same schedule (only iterations, val_frames, log_every and backend may change)",
            )
        })
    })?;

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
    // The weights are needed only where the schedule reaches the VGG term.
    let vgg = if config.ablations.vgg && config.vgg_from() < config.iterations {
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
    let refine = if config.ablations.flame_refinement {
        let timesteps = refine::Timesteps::of_dataset(&train_set)?;
        Some(refine::FlameRefinement::new(
            &head.model,
            timesteps,
            &device,
        )?)
    } else {
        None
    };
    let training = AvatarTraining {
        avatar,
        refine,
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

    let launch = Launch {
        schedule: Schedule {
            seed: config.seed,
            per_epoch: config.checkpoint_every,
            total: config.iterations,
            batch_size: config.batch_size,
            resume: folder.resume_at,
        },
        checkpoint: folder.checkpoint,
        log_every: config.log_every,
        val_frames: config.val_frames,
        stop,
        model_arg: "",
    };
    let frames = train_set.len();
    let launched = launch.run(
        options,
        training,
        (optimizer(&config), lr_scheduler(&config)),
        (train_set, val_set),
        &device,
        |start, end| {
            eprintln!(
                "train: {frames} frames, {gaussians} Gaussians (R = S = {}), {} backend, iterations {start}..{end} of {}, VGG from iteration {}",
                avatar_config.net.uv_res,
                format!("{backend:?}").to_lowercase(),
                config.iterations,
                if config.ablations.vgg {
                    config.vgg_from().to_string()
                } else {
                    "never".into()
                }
            )
        },
    )?;
    let error = launched.result.error.as_ref().map(|e| e.to_string());
    let (reached, complete) = launch.outcome(options, error, launched.end_iteration)?;
    let model = launched.result.model;
    let avatar = model.avatar;
    let avatar_path = out.join(files::AVATAR);
    if complete {
        if let Some(refine) = &model.refine {
            refine.refined().save(out)?;
        }
        avatar.clone().save_file(&avatar_path).map_err(|e| {
            Error::invalid(avatar_path.display().to_string(), "save", e.to_string())
        })?;
    } else {
        launch.stopped(options, reached)?;
    }
    drop(folder);
    Ok(TrainReport {
        start_iteration: launched.start_iteration,
        end_iteration: reached,
        avatar,
        gaussians,
        seconds: launched.seconds,
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
