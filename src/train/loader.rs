//! burn [`DataLoader`]s over a [`HeadDataset`] that count iterations, not epochs.
//!
//! burn's learner runs in epochs and checkpoints after each one. The paper trains for a
//! number of iterations (600k at batch 1) with no notion of epochs, so one burn "epoch" here
//! is one checkpoint interval: `checkpoint_every` iterations. The training loader hands out
//! the iterations of one interval per [`DataLoader::iter`] call and tags every batch with its
//! global iteration number (the objective switches the VGG loss on by it).
//!
//! Frame order: iteration `i` at batch size `B` takes the frames at positions `i B .. i B +
//! B` of an endless sequence of passes over the dataset, each pass a permutation of all
//! frames drawn from `(seed, pass)`. The order is a pure function of the seed and the
//! iteration, so a resumed run sees exactly the frames the uninterrupted run would have seen.
//!
//! Stops: the training loader ends an epoch early when its [`StopControl`] asks for it
//! (signal, iteration limit), after recording where ([`IterationRecord`]); see
//! [`super::stop`].

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};

use burn::data::dataloader::{DataLoader, DataLoaderIterator, Progress};
use burn::data::dataset::DatasetError;
use burn::tensor::Device;

use super::stop::{IterationRecord, StopControl};
use crate::data::crop::{CropSize, Window};
use crate::data::{HeadBatch, HeadBatcher, HeadDataset};
use crate::util::rng::Pcg;

/// One step's input: a batch and the global (0-based) iteration it belongs to.
#[derive(Clone, Debug)]
pub struct TrainBatch {
    /// The frames.
    pub batch: HeadBatch,
    /// Global iteration, counted from 0 over the whole run (resumes included).
    pub iteration: usize,
}

/// The frame order of the training loader.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Schedule {
    /// Seed of the per-pass permutations.
    pub seed: u64,
    /// Iterations per burn epoch (the checkpoint interval).
    pub per_epoch: usize,
    /// Iterations of the whole run.
    pub total: usize,
    /// Frames per iteration.
    pub batch_size: usize,
    /// `Some((e, n))`: a run resumed from a checkpoint taken in the middle of an interval
    /// ([`IterationRecord`]): its first epoch `e` starts at iteration `n` (before
    /// `e * per_epoch`), so it also trains the rest of the stopped interval.
    pub resume: Option<(usize, usize)>,
    /// Each training frame seen through a random window of this size
    /// ([`crop_window`]); `None`: whole frames.
    pub crop: Option<CropSize>,
}

impl Schedule {
    /// burn epochs of the run: `ceil(total / per_epoch)`.
    pub fn epochs(&self) -> usize {
        self.total.div_ceil(self.per_epoch)
    }

    /// The iterations of (0-based) epoch `e`.
    pub fn iterations_of(&self, e: usize) -> std::ops::Range<usize> {
        let end = ((e + 1) * self.per_epoch).min(self.total);
        let start = match self.resume {
            Some((first, n)) if first == e => n.min(end),
            _ => (e * self.per_epoch).min(self.total),
        };
        start..end
    }
}

/// Permutation of `0..n` for pass `pass` (Fisher-Yates with a PCG seeded by seed and pass).
pub fn pass_order(seed: u64, pass: usize, n: usize) -> Vec<usize> {
    let mut rng = Pcg::new(
        seed ^ (pass as u64)
            .wrapping_add(1)
            .wrapping_mul(0x9E37_79B9_7F4A_7C15),
    );
    let mut order: Vec<usize> = (0..n).collect();
    for i in (1..n).rev() {
        let j = ((rng.next_u32() as u64 * (i as u64 + 1)) >> 32) as usize;
        order.swap(i, j);
    }
    order
}

/// The window of the `k`-th frame of iteration `iteration` that a cropping run
/// ([`Schedule::crop`]) scores: placed uniformly in the frame by a PCG seeded by the seed,
/// the iteration and `k` alone, so a resumed run scores the windows the uninterrupted run
/// would have.
pub fn crop_window(
    crop: &CropSize,
    seed: u64,
    iteration: usize,
    k: usize,
    width: u32,
    height: u32,
) -> Window {
    let stream = (iteration as u64)
        .wrapping_mul(0x9E37_79B9_7F4A_7C15)
        .wrapping_add((k as u64).wrapping_mul(0xD1B5_4A32_D192_ED03));
    let mut rng = Pcg::new(seed ^ stream ^ 0xC807_0000_0000_0000);
    crop.place(width, height, &mut rng)
}

/// Which frames a loader yields.
#[derive(Clone, Debug)]
enum Frames {
    /// Training: iterations of a [`Schedule`]; the next epoch to hand out is shared by every
    /// clone (and every `to_device` copy) of the loader.
    Schedule {
        schedule: Schedule,
        next_epoch: Arc<AtomicUsize>,
    },
    /// Validation: the same frames, one per batch, on every pass.
    Fixed(Arc<Vec<usize>>),
}

/// The data loader of [`super::train`] (training and validation).
#[derive(Clone)]
pub struct FrameLoader {
    dataset: Arc<HeadDataset>,
    frames: Frames,
    device: Device,
    /// Item range of an epoch this loader is restricted to ([`DataLoader::slice`]).
    range: Option<(usize, usize)>,
    /// Ends epochs early when a stop is requested; training loaders also record where in
    /// the checkpoint folder.
    stop: Option<(StopControl, Option<PathBuf>)>,
}

impl std::fmt::Debug for FrameLoader {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FrameLoader")
            .field("dataset", &self.dataset)
            .field("frames", &self.frames)
            .field("range", &self.range)
            .finish()
    }
}

impl FrameLoader {
    /// The training loader of `schedule`; its first [`DataLoader::iter`] call yields (0-based)
    /// epoch `start_epoch` (the number of epochs a resumed run has already done).
    pub fn training(
        dataset: Arc<HeadDataset>,
        schedule: Schedule,
        start_epoch: usize,
        device: &Device,
    ) -> Self {
        FrameLoader {
            dataset,
            frames: Frames::Schedule {
                schedule,
                next_epoch: Arc::new(AtomicUsize::new(start_epoch)),
            },
            device: device.clone(),
            range: None,
            stop: None,
        }
    }

    /// Stops at `stop`'s request: a training loader ends the epoch after the step in progress
    /// (writing an [`IterationRecord`] into `checkpoints` for the checkpoint burn then takes)
    /// and, at the next epoch, sets burn's interrupter; a validation loader yields nothing.
    pub fn with_stop(mut self, stop: StopControl, checkpoints: Option<PathBuf>) -> Self {
        self.stop = Some((stop, checkpoints));
        self
    }

    /// A validation loader over the frames `indices` of `dataset`, one frame per batch.
    pub fn fixed(dataset: Arc<HeadDataset>, indices: Vec<usize>, device: &Device) -> Self {
        FrameLoader {
            dataset,
            frames: Frames::Fixed(Arc::new(indices)),
            device: device.clone(),
            range: None,
            stop: None,
        }
    }

    /// `count` frames spread evenly over `dataset` (all of them when it has fewer).
    pub fn spread(dataset_len: usize, count: usize) -> Vec<usize> {
        let count = count.min(dataset_len);
        (0..count).map(|k| k * dataset_len / count).collect()
    }

    /// Batches of one `iter` call: (global iteration, frame indices) per batch.
    fn plan(&self, epoch: Option<usize>) -> Vec<(usize, Vec<usize>)> {
        let mut plan: Vec<(usize, Vec<usize>)> = match &self.frames {
            Frames::Fixed(indices) => indices
                .iter()
                .enumerate()
                .map(|(k, &i)| (k, vec![i]))
                .collect(),
            Frames::Schedule { schedule, .. } => {
                let n = self.dataset.len();
                let b = schedule.batch_size;
                let mut cached: Option<(usize, Vec<usize>)> = None;
                schedule
                    .iterations_of(epoch.unwrap_or(0))
                    .map(|it| {
                        let frames = (it * b..it * b + b)
                            .map(|pos| {
                                let pass = pos / n;
                                if cached.as_ref().is_none_or(|(p, _)| *p != pass) {
                                    cached = Some((pass, pass_order(schedule.seed, pass, n)));
                                }
                                cached.as_ref().expect("just set").1[pos % n]
                            })
                            .collect();
                        (it, frames)
                    })
                    .collect()
            }
        };
        if let Some((start, end)) = self.range {
            // `slice` counts items; with one batch per iteration that is batches * B.
            let b = self.batch_size();
            plan = plan
                .into_iter()
                .enumerate()
                .filter(|(k, _)| (start..end).contains(&(k * b)))
                .map(|(_, p)| p)
                .collect();
        }
        plan
    }

    fn batch_size(&self) -> usize {
        match &self.frames {
            Frames::Schedule { schedule, .. } => schedule.batch_size,
            Frames::Fixed(_) => 1,
        }
    }
}

struct FrameIter<'a> {
    loader: &'a FrameLoader,
    plan: std::vec::IntoIter<(usize, Vec<usize>)>,
    done: usize,
    total: usize,
    /// burn's 1-based number of this epoch (training loaders only).
    epoch: Option<usize>,
}

impl FrameIter<'_> {
    /// Whether to end the pass here, before `iteration`. A training epoch that trained
    /// something records where it stopped (burn checkpoints it next); a validation pass ends
    /// on a signal only, and never sets burn's interrupter (that would skip the checkpoint).
    fn stops_before(&self, iteration: usize) -> bool {
        let Some((stop, records)) = &self.loader.stop else {
            return false;
        };
        let Some(epoch) = self.epoch else {
            return stop.signal().is_some();
        };
        if !stop.stops_before(iteration) {
            return false;
        }
        if self.done == 0 {
            // Nothing trained in this epoch: no checkpoint for it.
            stop.interrupter.stop(Some("stop requested"));
        } else if let Some(dir) = records {
            let record = IterationRecord {
                checkpoint: epoch,
                iteration,
            };
            if let Err(e) = record.save(dir) {
                // Without the record the checkpoint would claim a whole interval.
                eprintln!("train: {e}; stopping without a checkpoint");
                stop.interrupter
                    .stop(Some("the iteration record could not be written"));
            }
        }
        stop.mark_stopped_at(iteration);
        true
    }
}

impl Iterator for FrameIter<'_> {
    type Item = Result<TrainBatch, DatasetError>;

    fn next(&mut self) -> Option<Self::Item> {
        let (iteration, frames) = self.plan.as_slice().first()?.clone();
        if self.stops_before(iteration) {
            self.plan = Vec::new().into_iter();
            return None;
        }
        let crop = match &self.loader.frames {
            Frames::Schedule { schedule, .. } => schedule.crop.map(|c| (c, schedule.seed)),
            Frames::Fixed(_) => None,
        };
        let items: Result<Vec<_>, _> = frames
            .iter()
            .enumerate()
            .map(|(k, &i)| {
                let item = self.loader.dataset.load_item(i)?;
                Ok::<_, crate::error::Error>(match &crop {
                    Some((c, seed)) => {
                        let (w, h) = (item.camera.width, item.camera.height);
                        crop_window(c, *seed, iteration, k, w, h).apply(item)
                    }
                    None => item,
                })
            })
            .collect();
        if let (Err(e), Some((stop, _)), Some(_)) = (&items, &self.loader.stop, self.epoch) {
            // An unreadable frame: checkpoint what was trained and let `train` report it.
            stop.data_error(iteration, e.to_string());
            if self.stops_before(iteration) {
                self.plan = Vec::new().into_iter();
                return None;
            }
        }
        self.plan.next();
        self.done += frames.len();
        Some(
            items
                .and_then(|items| HeadBatcher.try_batch(items, &self.loader.device))
                .map(|batch| TrainBatch { batch, iteration })
                .map_err(DatasetError::new),
        )
    }
}

impl DataLoaderIterator<TrainBatch> for FrameIter<'_> {
    fn progress(&self) -> Progress {
        Progress {
            items_processed: self.done,
            items_total: self.total,
            unit: Some("frames".to_string()),
        }
    }
}

impl DataLoader<TrainBatch> for FrameLoader {
    fn iter<'a>(&'a self) -> Box<dyn DataLoaderIterator<TrainBatch> + 'a> {
        let epoch = match &self.frames {
            Frames::Schedule { next_epoch, .. } => Some(next_epoch.fetch_add(1, Ordering::SeqCst)),
            Frames::Fixed(_) => None,
        };
        let mut plan = self.plan(epoch);
        if let Some((stop, _)) = &self.stop
            && epoch.is_some()
        {
            // The epoch after a stopped one, or one that may not start: burn ends the run
            // without another checkpoint.
            let first = plan.first().map(|(it, _)| *it);
            let stop_now = first.filter(|&it| stop.stops_before(it));
            if stop.stopped_at().is_some() || stop_now.is_some() {
                stop.interrupter.stop(Some("stop requested"));
                if let Some(it) = stop_now.filter(|_| stop.stopped_at().is_none()) {
                    stop.mark_stopped_at(it);
                }
                plan.clear();
            }
        }
        let total = plan.iter().map(|(_, f)| f.len()).sum();
        Box::new(FrameIter {
            loader: self,
            plan: plan.into_iter(),
            done: 0,
            total,
            epoch: epoch.map(|e| e + 1),
        })
    }

    fn num_items(&self) -> usize {
        match &self.frames {
            Frames::Fixed(indices) => match self.range {
                Some((s, e)) => e.min(indices.len()).saturating_sub(s),
                None => indices.len(),
            },
            Frames::Schedule { schedule, .. } => {
                let all = schedule.per_epoch.min(schedule.total) * schedule.batch_size;
                match self.range {
                    Some((s, e)) => e.min(all).saturating_sub(s),
                    None => all,
                }
            }
        }
    }

    fn to_device(&self, device: &Device) -> Arc<dyn DataLoader<TrainBatch>> {
        let mut l = self.clone();
        l.device = device.clone();
        Arc::new(l)
    }

    fn slice(&self, start: usize, end: usize) -> Arc<dyn DataLoader<TrainBatch>> {
        let mut l = self.clone();
        l.range = Some(match self.range {
            Some((s, _)) => (s + start, s + end),
            None => (start, end),
        });
        Arc::new(l)
    }
}
