//! An exclusive lock on a run folder, held for a training run's whole life, so that two
//! `train` runs can never write the same folder (which left a mixed, unloadable avatar).
//!
//! The lock is the operating system's advisory file lock (`flock` on Linux, through
//! [`std::fs::File::try_lock`]) on `RUN/train.lock`. The kernel releases it when the holding
//! process ends, however it ends (kill -9 included), so a stale lock from a dead process never
//! blocks a new run. The file holds the holder's pid, for the message; it stays in the folder
//! after the run (removing it would race with a process that opened it).

use std::fs::{File, OpenOptions, TryLockError};
use std::io::{Read, Seek, Write};
use std::path::{Path, PathBuf};

use crate::error::{Error, Result};

/// The lock file's name inside a run folder.
pub const LOCK_FILE: &str = "train.lock";

/// A held lock; dropping it releases the lock.
#[derive(Debug)]
pub struct RunLock {
    _file: File,
    path: PathBuf,
}

impl RunLock {
    /// Locks `dir` (created if missing), or fails naming the process that holds it.
    pub fn acquire(dir: &Path) -> Result<Self> {
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
        let path = dir.join(LOCK_FILE);
        let mut file = OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)
            .map_err(|e| Error::io(&path, e))?;
        match file.try_lock() {
            Ok(()) => {
                let pid = std::process::id();
                file.set_len(0)
                    .and_then(|()| file.rewind())
                    .and_then(|()| writeln!(file, "{pid}"))
                    .map_err(|e| Error::io(&path, e))?;
                Ok(RunLock { _file: file, path })
            }
            Err(TryLockError::WouldBlock) => {
                let mut text = String::new();
                let _ = file.read_to_string(&mut text);
                let holder = match text.trim().parse::<u32>() {
                    Ok(pid) => format!("process {pid}"),
                    Err(_) => "another process".to_string(),
                };
                Err(Error::invalid(
                    dir.display().to_string(),
                    "lock",
                    format!(
                        "{holder} is training in this folder ({} is locked); wait for it to \
                         end or choose another --out",
                        path.display()
                    ),
                ))
            }
            Err(TryLockError::Error(e)) => Err(Error::io(&path, e)),
        }
    }

    /// The lock file.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_second_lock_names_the_holder_and_a_dead_holder_blocks_nothing() {
        let dir = std::env::temp_dir().join(format!("texavatars-lock-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let held = RunLock::acquire(&dir).expect("first");
        let text = std::fs::read_to_string(held.path()).expect("read");
        assert_eq!(text.trim(), std::process::id().to_string());
        // flock locks belong to the open file: a second open in this process conflicts too.
        let e = RunLock::acquire(&dir).expect_err("held").to_string();
        assert!(
            e.contains(&format!("process {}", std::process::id())) && e.contains("lock"),
            "{e}"
        );
        drop(held);
        // A file left by a process that died (here: released) does not block.
        std::fs::write(dir.join(LOCK_FILE), "999999999\n").expect("stale");
        let again = RunLock::acquire(&dir).expect("stale lock file, no holder");
        drop(again);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
