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

/// Result with [`Error`].
pub type Result<T> = std::result::Result<T, Error>;
