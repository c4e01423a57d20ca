//! The part of a run burn's `Learner` drives ([`Launch`]): the loaders, metrics,
//! checkpoints and progress lines around any model whose steps take [`TrainBatch`]es, and
//! the run's outcome (errors, stops, resume hints).

use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

use burn::lr_scheduler::module_lr_scheduler::ModuleLrScheduler;
use burn::optim::ModuleOptimizer;
use burn::train::checkpoint::KeepLastNCheckpoints;
use burn::train::{Learner, SupervisedTraining};

use super::constants::KEEP_CHECKPOINTS;
use super::folder::{files, latest_checkpoint, remove_stale_tmp};
use super::loader::{FrameLoader, Schedule, TrainBatch};
use super::metrics::{Term, TermMetric};
use super::options::TrainOptions;
use super::progress::ProgressPrinter;
use super::signals;
use super::step::StepOutput;
use super::stop::{IterationRecord, StopControl};
use crate::data::HeadDataset;
use crate::error::{Error, Result};

/// The part of a run burn's learner drives, for any model whose steps take [`TrainBatch`]es
/// and report [`StepOutput`]s.
pub struct Launch {
    /// The run's iterations and checkpoint intervals.
    pub schedule: Schedule,
    /// The checkpoint a resumed run starts from
    /// ([`RunFolder::checkpoint`](super::RunFolder::checkpoint)).
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

/// The global iterations checkpoint `c` (1-based) holds: its [`IterationRecord`] when it
/// was taken in the middle of an interval, else the end of interval `c`.
pub fn checkpoint_iteration(schedule: &Schedule, ckpt_dir: &Path, c: usize) -> usize {
    match IterationRecord::load(ckpt_dir, c) {
        Ok(Some(r)) => r.iteration,
        _ => (c * schedule.per_epoch).min(schedule.total),
    }
}
