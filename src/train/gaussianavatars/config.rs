//! The config of a GaussianAvatars run ([`GaTrainConfig`]): its length and bookkeeping.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::device::BackendKind;
use crate::error::{Error, Result};

/// A GaussianAvatars training run (`configs/train_gaussianavatars.json`): its length and
/// bookkeeping; everything else is GaussianAvatars' ([`crate::train::gaussianavatars::constants`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GaTrainConfig {
    /// Optimiser steps of the run (GaussianAvatars: 600,000); every interval of its
    /// schedule is scaled to it.
    pub iterations: usize,
    /// Iterations between checkpoints (one burn epoch each; a validation pass follows).
    pub checkpoint_every: usize,
    /// SH degree (GaussianAvatars: 3).
    #[serde(default = "three")]
    pub sh_degree: usize,
    /// Validation frames evaluated at each checkpoint (0: none).
    #[serde(default = "four")]
    pub val_frames: usize,
    /// Iterations between progress lines (0: none).
    #[serde(default = "ten")]
    pub log_every: usize,
    /// Seed of the initial colours, the frame order and the split samples.
    #[serde(default)]
    pub seed: u64,
    /// Where tensors live (`--backend` overrides it).
    #[serde(default = "flex")]
    pub backend: BackendKind,
    /// FLAME refinement ([`crate::train::refine`]; GaussianAvatars' default, off with its
    /// `--not_finetune_flame_params`), at GaussianAvatars' learning rates.
    #[serde(default = "yes")]
    pub flame_refinement: bool,
}

fn yes() -> bool {
    true
}
fn three() -> usize {
    3
}
fn four() -> usize {
    4
}
fn ten() -> usize {
    10
}
fn flex() -> BackendKind {
    BackendKind::Flex
}

impl GaTrainConfig {
    /// Reads and validates a config file.
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let c: Self = serde_json::from_str(&text)
            .map_err(|e| Error::invalid(path.display().to_string(), "json", e.to_string()))?;
        c.validate(&path.display().to_string())?;
        Ok(c)
    }

    /// Checks the values (`what` names the source in errors).
    pub fn validate(&self, what: &str) -> Result<()> {
        if self.iterations == 0 {
            return Err(Error::invalid(what, "iterations", "must be at least 1"));
        }
        if self.checkpoint_every == 0 {
            return Err(Error::invalid(
                what,
                "checkpoint_every",
                "must be at least 1",
            ));
        }
        if self.sh_degree > 3 {
            return Err(Error::invalid(
                what,
                "sh_degree",
                format!("{} (0 to 3)", self.sh_degree),
            ));
        }
        Ok(())
    }

    /// Pretty JSON.
    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).expect("serialises") + "\n"
    }

    /// `Err(field)` when a run saved with `self` cannot be resumed as `other` (only
    /// `val_frames`, `log_every` and `backend` may change: the schedule is scaled to
    /// `iterations`).
    pub fn resumable_as(&self, other: &Self) -> std::result::Result<(), &'static str> {
        if self.iterations != other.iterations {
            return Err("iterations");
        }
        if self.checkpoint_every != other.checkpoint_every {
            return Err("checkpoint_every");
        }
        if self.sh_degree != other.sh_degree {
            return Err("sh_degree");
        }
        if self.seed != other.seed {
            return Err("seed");
        }
        if self.flame_refinement != other.flame_refinement {
            return Err("flame_refinement");
        }
        Ok(())
    }
}
