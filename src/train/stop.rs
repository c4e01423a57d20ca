//! Stopping a training run before its planned end without losing work or saving a broken
//! avatar: on a signal ([`super::signals`]), at an iteration limit (`--stop-after`, tests), or
//! when a step's loss or gradient is not finite.
//!
//! burn's learner checkpoints only after a whole epoch (one checkpoint interval here, see
//! [`super::loader`]) and writes no checkpoint once its [`Interrupter`] is set. So the two
//! kinds of stop take two routes:
//!
//! - **A requested stop** (signal, iteration limit) ends the current epoch early: the
//!   training loader returns no more batches after the step in progress, the validation
//!   loader none at all, and burn checkpoints the model, the optimiser and the scheduler as
//!   usual. Before that, the loader writes [`IterationRecord`] `checkpoint/iteration-E.json`
//!   ("checkpoint E holds the state after iteration N"): a resumed run continues from
//!   iteration N, with the frames the uninterrupted run would have used. The next epoch's
//!   loader then sets the interrupter, and burn ends the run without another checkpoint.
//!   A frame the loader cannot read (a PNG corrupt past its header, which the up-front
//!   check does not decode) stops the run the same way ([`StopControl::data_error`]).
//! - **A fault** (a non-finite loss term or gradient, checked by every step) sets the
//!   interrupter at once: burn stops after that step and writes no checkpoint, so the
//!   newest checkpoint on disk is the last good state. [`super::train`] reports the
//!   iteration and the terms and saves no avatar.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

use burn::train::Interrupter;
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};

/// No signal received (`StopControl::signal`).
const NO_SIGNAL: usize = 0;
/// No iteration recorded yet (`StopControl::stopped_at`).
const NONE: usize = usize::MAX;

/// A step whose numbers were not finite.
#[derive(Clone, Debug, PartialEq)]
pub struct Fault {
    /// The global (0-based) iteration of the step.
    pub iteration: usize,
    /// Each reported number by name: the loss terms, PSNR and the gradients' L1 norm.
    pub values: Vec<(String, f64)>,
}

impl Fault {
    /// The names of the non-finite values.
    pub fn culprits(&self) -> Vec<&str> {
        self.values
            .iter()
            .filter(|(_, v)| !v.is_finite())
            .map(|(n, _)| n.as_str())
            .collect()
    }
}

/// Shared between the training loader, the step, the signal handler and [`super::train`];
/// clones share their state.
#[derive(Clone)]
pub struct StopControl {
    /// burn's interrupter (given to the learner).
    pub interrupter: Interrupter,
    /// The signal number received, or [`NO_SIGNAL`]; written by the signal handler.
    signal: Arc<AtomicUsize>,
    /// Stop before this global iteration (`usize::MAX`: never).
    limit: Arc<AtomicUsize>,
    /// The first iteration not trained when the loader ended a run early ([`NONE`]: it did
    /// not).
    stopped_at: Arc<AtomicUsize>,
    fault: Arc<Mutex<Option<Fault>>>,
    /// A frame the training loader could not read: the iteration and the error.
    data_error: Arc<Mutex<Option<(usize, String)>>>,
}

impl std::fmt::Debug for StopControl {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("StopControl")
            .field("signal", &self.signal())
            .field("limit", &self.limit.load(Ordering::SeqCst))
            .field("stopped_at", &self.stopped_at.load(Ordering::SeqCst))
            .finish_non_exhaustive()
    }
}

impl Default for StopControl {
    fn default() -> Self {
        StopControl {
            interrupter: Interrupter::new(),
            signal: Arc::new(AtomicUsize::new(NO_SIGNAL)),
            limit: Arc::new(AtomicUsize::new(usize::MAX)),
            stopped_at: Arc::new(AtomicUsize::new(NONE)),
            fault: Arc::new(Mutex::new(None)),
            data_error: Arc::new(Mutex::new(None)),
        }
    }
}

impl StopControl {
    /// A control with nothing requested.
    pub fn new() -> Self {
        Self::default()
    }

    /// The flag a signal handler sets to the signal's number.
    pub fn signal_flag(&self) -> Arc<AtomicUsize> {
        self.signal.clone()
    }

    /// Asks the run to stop as a signal would (`signal` > 0).
    pub fn request(&self, signal: usize) {
        self.signal.store(signal.max(1), Ordering::SeqCst);
    }

    /// The signal received, if any.
    pub fn signal(&self) -> Option<usize> {
        match self.signal.load(Ordering::SeqCst) {
            NO_SIGNAL => None,
            s => Some(s),
        }
    }

    /// Stops the run before global iteration `iteration`.
    pub fn stop_before(&self, iteration: usize) {
        self.limit.store(iteration, Ordering::SeqCst);
    }

    /// Whether the run must not train global iteration `iteration`.
    pub fn stops_before(&self, iteration: usize) -> bool {
        self.signal().is_some() || iteration >= self.limit.load(Ordering::SeqCst)
    }

    /// Records that the loader ended the run before `iteration`.
    pub(crate) fn mark_stopped_at(&self, iteration: usize) {
        self.stopped_at.store(iteration, Ordering::SeqCst);
    }

    /// The first iteration not trained, when the loader ended the run early.
    pub fn stopped_at(&self) -> Option<usize> {
        match self.stopped_at.load(Ordering::SeqCst) {
            NONE => None,
            i => Some(i),
        }
    }

    /// Records a fault (the first one wins) and stops burn at once, without a checkpoint.
    pub fn fault(&self, fault: Fault) {
        if let Ok(mut f) = self.fault.lock()
            && f.is_none()
        {
            *f = Some(fault);
        }
        self.interrupter
            .stop(Some("a loss term or gradient is not finite"));
    }

    /// The recorded fault.
    pub fn take_fault(&self) -> Option<Fault> {
        self.fault.lock().ok().and_then(|mut f| f.take())
    }

    /// Records that a frame of `iteration` could not be read (the first error wins) and asks
    /// the run to stop before that iteration, as a requested stop does: the steps already
    /// trained are checkpointed.
    pub fn data_error(&self, iteration: usize, error: String) {
        if let Ok(mut d) = self.data_error.lock()
            && d.is_none()
        {
            *d = Some((iteration, error));
        }
        let limit = self.limit.load(Ordering::SeqCst).min(iteration);
        self.stop_before(limit);
    }

    /// The recorded data error: the iteration whose frames could not be read, and why.
    pub fn take_data_error(&self) -> Option<(usize, String)> {
        self.data_error.lock().ok().and_then(|mut d| d.take())
    }
}

/// "Checkpoint `checkpoint` holds the state after `iteration` iterations": written for a
/// checkpoint taken in the middle of a checkpoint interval (a stopped run), read by
/// `--resume`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct IterationRecord {
    /// burn's (1-based) checkpoint number.
    pub checkpoint: usize,
    /// Global iterations trained into it.
    pub iteration: usize,
}

impl IterationRecord {
    /// The record's file in the checkpoint folder `dir`.
    pub fn path(dir: &Path, checkpoint: usize) -> PathBuf {
        dir.join(format!("iteration-{checkpoint}.json"))
    }

    /// Writes the record (through a temporary file and a rename).
    pub fn save(&self, dir: &Path) -> Result<()> {
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
        let path = Self::path(dir, self.checkpoint);
        let tmp = path.with_extension("json.tmp");
        let text = serde_json::to_string(self).expect("serialises");
        std::fs::write(&tmp, text).map_err(|e| Error::io(&tmp, e))?;
        std::fs::rename(&tmp, &path).map_err(|e| Error::io(&path, e))
    }

    /// The record of checkpoint `checkpoint` in `dir`, if one was written.
    pub fn load(dir: &Path, checkpoint: usize) -> Result<Option<Self>> {
        let path = Self::path(dir, checkpoint);
        if !path.exists() {
            return Ok(None);
        }
        let text = std::fs::read_to_string(&path).map_err(|e| Error::io(&path, e))?;
        let r: IterationRecord = serde_json::from_str(&text)
            .map_err(|e| Error::invalid(path.display().to_string(), "iteration", e.to_string()))?;
        if r.checkpoint != checkpoint {
            return Err(Error::invalid(
                path.display().to_string(),
                "checkpoint",
                format!(
                    "{} in a file named for checkpoint {checkpoint}",
                    r.checkpoint
                ),
            ));
        }
        Ok(Some(r))
    }

    /// Removes the records of checkpoints after `latest` (written by a run that died before
    /// burn saved the checkpoint they describe; a later checkpoint of that number will be a
    /// whole interval).
    pub fn remove_after(dir: &Path, latest: usize) -> Result<()> {
        let Ok(entries) = std::fs::read_dir(dir) else {
            return Ok(());
        };
        for e in entries.flatten() {
            let name = e.file_name();
            let Some(n) = name
                .to_str()
                .and_then(|n| n.strip_prefix("iteration-")?.strip_suffix(".json"))
                .and_then(|n| n.parse::<usize>().ok())
            else {
                continue;
            };
            if n > latest {
                let p = e.path();
                std::fs::remove_file(&p).map_err(|err| Error::io(&p, err))?;
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_signal_or_the_limit_stops_before_an_iteration() {
        let s = StopControl::new();
        assert!(!s.stops_before(1_000_000));
        s.stop_before(5);
        assert!(!s.stops_before(4));
        assert!(s.stops_before(5));
        let t = StopControl::new();
        let clone = t.clone();
        clone.signal_flag().store(15, Ordering::SeqCst);
        assert_eq!(t.signal(), Some(15));
        assert!(t.stops_before(0));
    }

    #[test]
    fn the_first_fault_is_kept_and_burn_is_interrupted() {
        let s = StopControl::new();
        let f = |i| Fault {
            iteration: i,
            values: vec![("Loss".into(), f64::NAN), ("L1".into(), 0.5)],
        };
        s.fault(f(3));
        s.fault(f(4));
        assert!(s.interrupter.should_stop());
        let got = s.take_fault().unwrap();
        assert_eq!(got.iteration, 3);
        assert_eq!(got.culprits(), vec!["Loss"]);
    }

    #[test]
    fn iteration_records_round_trip_and_stale_ones_are_removed() {
        let dir = std::env::temp_dir().join(format!("texavatars-stop-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        for (c, i) in [(1, 7), (3, 25)] {
            IterationRecord {
                checkpoint: c,
                iteration: i,
            }
            .save(&dir)
            .unwrap();
        }
        assert_eq!(
            IterationRecord::load(&dir, 3).unwrap().unwrap().iteration,
            25
        );
        assert_eq!(IterationRecord::load(&dir, 2).unwrap(), None);
        IterationRecord::remove_after(&dir, 2).unwrap();
        assert_eq!(IterationRecord::load(&dir, 3).unwrap(), None);
        assert!(IterationRecord::load(&dir, 1).unwrap().is_some());
        std::fs::write(IterationRecord::path(&dir, 4), "{\"checkpoint\": 9}").unwrap();
        assert!(IterationRecord::load(&dir, 4).is_err());
        let _ = std::fs::remove_dir_all(&dir);
    }
}
