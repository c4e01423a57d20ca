//! The crate's error type: every error names the file (or source) and the field at fault.

use std::path::{Path, PathBuf};

/// Errors of texavatars. Messages name the file and field so a user can fix the input.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// A file or value was read but its content is unusable.
    #[error("{what}: field `{field}`: {why}")]
    Invalid {
        /// The file or source (a path, or a description such as "splat inputs").
        what: String,
        /// The field, key or tensor at fault.
        field: String,
        /// What is wrong with it.
        why: String,
    },
    /// A run stopped by a signal before its end, its work saved; the process exits with
    /// `128 + signal` (the shell's convention).
    #[error("{message}")]
    Stopped {
        /// The signal's number (2: SIGINT, 15: SIGTERM).
        signal: usize,
        /// What was saved and how to resume.
        message: String,
    },
}

impl Error {
    /// An I/O error on `path`.
    pub fn io(path: &Path, source: std::io::Error) -> Self {
        Error::Io {
            path: path.to_path_buf(),
            source,
        }
    }

    /// An invalid field `field` in `what`.
    pub fn invalid(
        what: impl Into<String>,
        field: impl Into<String>,
        why: impl Into<String>,
    ) -> Self {
        Error::Invalid {
            what: what.into(),
            field: field.into(),
            why: why.into(),
        }
    }
}

impl Error {
    /// The process exit status this error calls for: `128 + signal` for a stopped run, 1
    /// otherwise.
    pub fn exit_code(&self) -> u8 {
        match self {
            Error::Stopped { signal, .. } => exit_code(*signal),
            _ => 1,
        }
    }
}

/// Result with [`Error`].
pub type Result<T> = std::result::Result<T, Error>;

/// The exit status of a process stopped by `signal` (the shell's convention).
pub fn exit_code(signal: usize) -> u8 {
    (128 + signal.min(127)) as u8
}
