//! Training an avatar on a VHAP export (method §6) through burn's `Learner`.
//!
//! - The model burn trains is [`AvatarTraining`]: the [`Avatar`](crate::models::texavatars::Avatar) and
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
//! - The run itself is [`train`] ([`run`]): it opens and checks the frames ([`frames`]),
//!   readies the output folder ([`folder`]: its files, the checkpoint to resume from,
//!   `--force`), builds the optimiser and learning rates ([`optim`]) and hands the model to
//!   burn's learner ([`launch`]); [`options`] holds how to run it and what it reports.
//!
//! Seeds: the device is seeded with the config's seed before the networks are built, and the
//! frame order is a function of the seed and the iteration.

pub mod config;
pub mod constants;
pub mod folder;
pub mod frames;
pub mod gaussianavatars;
pub mod launch;
pub mod loader;
pub mod lock;
pub mod loss;
pub mod metrics;
pub mod optim;
pub mod options;
pub mod progress;
pub mod refine;
pub mod run;
pub mod signals;
pub mod step;
pub mod stop;

pub use config::{NetSpec, TrainConfig};
pub use folder::{OWNED, RunFolder, files, latest_checkpoint, prepare_folder, remove_stale_tmp};
pub use frames::open_frames;
pub use launch::{Launch, Launched, checkpoint_iteration};
pub use loader::{FrameLoader, Schedule, TrainBatch};
pub use loss::{LossTerms, LossWeights, objective};
pub use metrics::{Term, TermMetric};
pub use optim::{lr_scheduler, optimizer};
pub use options::{TrainOptions, TrainReport};
pub use progress::ProgressPrinter;
pub use run::train;
pub use step::{AvatarTraining, Objective, StepOutput};
pub use stop::{Fault, IterationRecord, StopControl};
