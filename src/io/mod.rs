//! File formats shared by the commands: `.npy` and `.npz` arrays, PNG images and (read-only,
//! never executed) Python pickles of numpy arrays.

pub mod image;
pub mod npy;
pub mod npz;
pub mod pickle;

use std::path::{Path, PathBuf};

use crate::error::{Error, Result};

/// The files in `dir` whose extension is `ext` (no dot), sorted by path.
pub fn files_with_extension(dir: &Path, ext: &str) -> Result<Vec<PathBuf>> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| Error::io(dir, e))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == ext))
        .collect();
    files.sort();
    Ok(files)
}
