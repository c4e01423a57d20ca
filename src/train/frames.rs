//! Opening a run's training and validation frames, every frame's files checked first.

use std::sync::Arc;
use std::time::Instant;

use super::options::TrainOptions;
use crate::data::{HeadDataset, Split};
use crate::error::{Error, Result};

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
    crate::data::eta::announce(train_set.frames(), Split::Train.name())?;
    let val_file = options.data.join(Split::Val.file_name());
    let val_set = if val_frames > 0 && val_file.is_file() {
        let v = HeadDataset::open_with(&options.data, Split::Val, model, options.paths)?;
        v.check_files()?;
        crate::data::eta::announce(v.frames(), Split::Val.name())?;
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
