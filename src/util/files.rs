//! File helpers the commands share.

use std::path::Path;

use crate::error::{Error, Result};

/// Removes the plain files (and links) directly in `dir` whose names `owns` accepts; a
/// missing folder has none. Returns how many were removed.
pub fn clear_matching(dir: &Path, owns: &dyn Fn(&str) -> bool) -> Result<usize> {
    let entries = match std::fs::read_dir(dir) {
        Ok(e) => e,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(0),
        Err(e) => return Err(Error::io(dir, e)),
    };
    let mut n = 0;
    for entry in entries {
        let entry = entry.map_err(|e| Error::io(dir, e))?;
        let path = entry.path();
        let Some(name) = entry.file_name().to_str().map(str::to_owned) else {
            continue;
        };
        let ty = entry.file_type().map_err(|e| Error::io(&path, e))?;
        if ty.is_dir() || !owns(&name) {
            continue;
        }
        std::fs::remove_file(&path).map_err(|e| Error::io(&path, e))?;
        n += 1;
    }
    Ok(n)
}

/// Writes `bytes` to `path` through a temporary file beside it and a rename, so that a
/// reader never sees a half-written file and an interrupted write leaves the old one.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let tmp = path.with_file_name(format!(".{name}.partial"));
    std::fs::write(&tmp, bytes).map_err(|e| Error::io(&tmp, e))?;
    std::fs::rename(&tmp, path).map_err(|e| Error::io(path, e))
}

/// Reads `path` as JSON; a parse error names the file and the line.
pub fn read_json(path: &Path) -> Result<serde_json::Value> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    serde_json::from_str(&text).map_err(|e| {
        Error::invalid(
            path.display().to_string(),
            format!("line {}", e.line()),
            e.to_string(),
        )
    })
}
