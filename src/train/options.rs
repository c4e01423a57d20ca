//! How to run [`train`](super::train) ([`TrainOptions`]) and what a run did
//! ([`TrainReport`]).

use std::path::PathBuf;

use super::stop::StopControl;
use crate::data::PathPolicy;
use crate::device::BackendKind;
use crate::head::HeadAsset;
use crate::models::texavatars::Avatar;

/// How to run [`train`](super::train).
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
    /// Stop on SIGINT / SIGTERM with a checkpoint ([`signals`](super::signals)); the command
    /// line turns it on, library callers may leave the process's signals alone.
    pub handle_signals: bool,
    /// Stops the run from elsewhere ([`StopControl::request`]); `None`: a private one.
    pub stop: Option<StopControl>,
    /// Start afresh even when `out` holds a run or a finished avatar: train's own files
    /// there are removed first ([`OWNED`](super::OWNED)).
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

/// What a [`train`](super::train) call did.
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
