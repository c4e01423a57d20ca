//! The training configuration (`configs/train_*.json`).

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::constants::*;
use super::loss::LossWeights;
use crate::device::BackendKind;
use crate::error::{Error, Result};
use crate::model::{Ablations, AvatarConfig, NetConfig};

/// The networks of a training config: a net config file (relative paths are relative to the
/// training config's folder) or the config itself.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum NetSpec {
    /// A JSON file as `configs/cpu.json`.
    File(PathBuf),
    /// The sizes inline.
    Inline(NetConfig),
}

/// Everything a training run needs besides its data (method §6; defaults: the paper's
/// optimiser and objective, [`super::constants`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainConfig {
    /// The networks. Its expression width is taken from the head model of the data.
    pub net: NetSpec,
    /// Ablation switches (all on: the full method).
    #[serde(default)]
    pub ablations: Ablations,
    /// Optimiser steps of the whole run (the paper: 600k).
    pub iterations: usize,
    /// Frames per step (the paper: 1).
    #[serde(default = "one")]
    pub batch_size: usize,
    /// Learning rate of both decoders (6e-4).
    #[serde(default = "lr_decoders")]
    pub lr_decoders: f64,
    /// Learning rate of Exp2Code and the view encoder (4e-4).
    #[serde(default = "lr_encoders")]
    pub lr_encoders: f64,
    /// Adam's epsilon (1e-15).
    #[serde(default = "adam_eps")]
    pub adam_eps: f64,
    /// Adam's beta1 (0.9).
    #[serde(default = "adam_beta1")]
    pub adam_beta1: f64,
    /// Adam's beta2 (0.999).
    #[serde(default = "adam_beta2")]
    pub adam_beta2: f64,
    /// Fraction of `iterations` after which the VGG loss is on (0.5).
    #[serde(default = "vgg_start")]
    pub vgg_start: f64,
    /// Loss weights and thresholds.
    #[serde(default)]
    pub loss: LossWeights,
    /// Iterations between checkpoints (one burn epoch each; a validation pass follows).
    pub checkpoint_every: usize,
    /// Frames of the validation split (the held-out camera) evaluated at each checkpoint,
    /// spread evenly over it; 0 skips validation.
    #[serde(default = "val_frames")]
    pub val_frames: usize,
    /// Iterations between progress lines (0: none).
    #[serde(default = "log_every")]
    pub log_every: usize,
    /// Seed of the initial weights and of the frame order.
    #[serde(default)]
    pub seed: u64,
    /// Where tensors live (`--backend` overrides it).
    #[serde(default = "flex")]
    pub backend: BackendKind,
}

fn one() -> usize {
    1
}
fn lr_decoders() -> f64 {
    LR_DECODERS
}
fn lr_encoders() -> f64 {
    LR_ENCODERS
}
fn adam_eps() -> f64 {
    ADAM_EPS
}
fn adam_beta1() -> f64 {
    ADAM_BETA1
}
fn adam_beta2() -> f64 {
    ADAM_BETA2
}
fn vgg_start() -> f64 {
    VGG_START
}
fn val_frames() -> usize {
    4
}
fn log_every() -> usize {
    10
}
fn flex() -> BackendKind {
    BackendKind::Flex
}

impl TrainConfig {
    /// A config with the paper's optimiser and objective for `net`.
    pub fn new(net: NetConfig, iterations: usize, checkpoint_every: usize) -> Self {
        TrainConfig {
            net: NetSpec::Inline(net),
            ablations: Ablations::default(),
            iterations,
            batch_size: 1,
            lr_decoders: LR_DECODERS,
            lr_encoders: LR_ENCODERS,
            adam_eps: ADAM_EPS,
            adam_beta1: ADAM_BETA1,
            adam_beta2: ADAM_BETA2,
            vgg_start: VGG_START,
            loss: LossWeights::default(),
            checkpoint_every,
            val_frames: val_frames(),
            log_every: log_every(),
            seed: 0,
            backend: BackendKind::Flex,
        }
    }

    /// Reads a JSON config, loads a referenced net config (so the result is
    /// self-contained: [`NetSpec::Inline`]) and validates it.
    pub fn load(path: &Path) -> Result<Self> {
        let what = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let mut c: TrainConfig = serde_json::from_str(&text).map_err(|e| {
            Error::invalid(
                &what,
                format!("line {} column {}", e.line(), e.column()),
                e.to_string(),
            )
        })?;
        if let NetSpec::File(f) = &c.net {
            let f = if f.is_relative() {
                path.parent().unwrap_or(Path::new(".")).join(f)
            } else {
                f.clone()
            };
            c.net = NetSpec::Inline(NetConfig::load(&f)?);
        }
        c.validate(&what)?;
        Ok(c)
    }

    /// The network config (an error for an unresolved [`NetSpec::File`]; [`TrainConfig::load`]
    /// resolves it).
    pub fn net_config(&self) -> Result<&NetConfig> {
        match &self.net {
            NetSpec::Inline(n) => Ok(n),
            NetSpec::File(f) => Err(Error::invalid(
                "train config",
                "net",
                format!("{} is not loaded (use TrainConfig::load)", f.display()),
            )),
        }
    }

    /// The avatar these settings train.
    pub fn avatar(&self) -> Result<AvatarConfig> {
        Ok(AvatarConfig::new(self.net_config()?.clone()).with_ablations(self.ablations))
    }

    /// The first (0-based) iteration with the VGG loss: `ceil(vgg_start * iterations)`.
    pub fn vgg_from(&self) -> usize {
        (self.vgg_start * self.iterations as f64).ceil() as usize
    }

    /// Pretty JSON.
    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).expect("a TrainConfig serialises") + "\n"
    }

    /// Checks ranges; `what` names the source in errors.
    pub fn validate(&self, what: &str) -> Result<()> {
        let bad = |field: &str, why: &str| Err(Error::invalid(what, field, why));
        if let NetSpec::Inline(n) = &self.net {
            n.validate(what)?;
        }
        if self.iterations == 0 {
            return bad("iterations", "must be at least 1");
        }
        if self.batch_size == 0 {
            return bad("batch_size", "must be at least 1");
        }
        if self.checkpoint_every == 0 {
            return bad("checkpoint_every", "must be at least 1");
        }
        for (field, lr) in [
            ("lr_decoders", self.lr_decoders),
            ("lr_encoders", self.lr_encoders),
        ] {
            if !(lr.is_finite() && lr >= 0.0) {
                return bad(field, "must be a finite learning rate >= 0");
            }
        }
        if !(self.adam_eps.is_finite() && self.adam_eps > 0.0) {
            return bad("adam_eps", "must be > 0");
        }
        for (field, b) in [
            ("adam_beta1", self.adam_beta1),
            ("adam_beta2", self.adam_beta2),
        ] {
            if !(0.0..1.0).contains(&b) {
                return bad(field, "must be in [0, 1)");
            }
        }
        if !(0.0..=1.0).contains(&self.vgg_start) {
            return bad("vgg_start", "must be a fraction in [0, 1]");
        }
        let l = &self.loss;
        let weights = [l.l1, l.dssim, l.vgg, l.position, l.scale];
        if weights.iter().any(|w| !(w.is_finite() && *w >= 0.0)) {
            return bad("loss", "weights must be finite and >= 0");
        }
        Ok(())
    }

    /// Whether `other` trains the same run (everything but `iterations`, `val_frames`,
    /// `log_every` and `backend` equal): a run may be resumed with a longer schedule, a
    /// different validation size, progress interval or backend. Returns the first field that
    /// differs.
    pub fn resumable_as(&self, other: &TrainConfig) -> std::result::Result<(), &'static str> {
        let norm = |c: &TrainConfig| TrainConfig {
            iterations: 0,
            val_frames: 0,
            log_every: 0,
            backend: BackendKind::Flex,
            ..c.clone()
        };
        let (a, b) = (norm(self), norm(other));
        if a == b {
            return Ok(());
        }
        Err(if a.net != b.net {
            "net"
        } else if a.ablations != b.ablations {
            "ablations"
        } else if a.checkpoint_every != b.checkpoint_every {
            "checkpoint_every"
        } else if a.seed != b.seed {
            "seed"
        } else if a.batch_size != b.batch_size {
            "batch_size"
        } else {
            "optimiser or loss settings"
        })
    }
}
