//! The splits of a VHAP export: which `transforms_*.json` a dataset reads.

use std::fmt;
use std::str::FromStr;

use crate::error::{Error, Result};

/// A split of a VHAP / GaussianAvatars export.
///
/// `train`, `val` and `test` are VHAP's; `free` (free-viewpoint renders, same format) is this
/// project's addition.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Split {
    /// `transforms_train.json`.
    Train,
    /// `transforms_val.json`.
    Val,
    /// `transforms_test.json`.
    Test,
    /// `transforms_free.json`.
    Free,
}

impl Split {
    /// Every split, in the order above.
    pub const ALL: [Split; 4] = [Split::Train, Split::Val, Split::Test, Split::Free];

    /// The split's name: `train`, `val`, `test` or `free`.
    pub fn name(self) -> &'static str {
        match self {
            Split::Train => "train",
            Split::Val => "val",
            Split::Test => "test",
            Split::Free => "free",
        }
    }

    /// The split's file name inside the dataset root, e.g. `transforms_train.json`.
    pub fn file_name(self) -> &'static str {
        match self {
            Split::Train => "transforms_train.json",
            Split::Val => "transforms_val.json",
            Split::Test => "transforms_test.json",
            Split::Free => "transforms_free.json",
        }
    }
}

impl fmt::Display for Split {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Split {
    type Err = Error;

    /// Parses a split name as [`Split::name`] writes it (lower case).
    fn from_str(s: &str) -> Result<Self> {
        Split::ALL
            .into_iter()
            .find(|split| split.name() == s)
            .ok_or_else(|| {
                Error::invalid(
                    "dataset split",
                    "split",
                    format!("{s:?} is not one of train, val, test, free"),
                )
            })
    }
}
