//! The training configuration (`configs/train_*.json`).

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::constants::*;
use super::loss::LossWeights;
use crate::data::crop::CropSize;
use crate::device::BackendKind;
use crate::error::{Error, Result};
use crate::limits;
use crate::models::texavatars::{Ablations, AvatarConfig, NetConfig};

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
    /// Learning rate of the refined expressions (FLAME refinement, 1e-3).
    #[serde(default = "lr_flame_expr")]
    pub lr_flame_expr: f64,
    /// Learning rate of the refined rotations (1e-5).
    #[serde(default = "lr_flame_pose")]
    pub lr_flame_pose: f64,
    /// Learning rate of the refined translations (1e-6).
    #[serde(default = "lr_flame_translation")]
    pub lr_flame_translation: f64,
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
    /// Score a window of each training frame instead of the whole frame: each step renders
    /// and scores a `width x height` window placed uniformly at random in its frame (drawn
    /// from the seed and the iteration, so a resumed run draws the same windows), while the
    /// decoders and the lifting still produce every Gaussian. Validation, `eval` and every
    /// other command use whole frames. Absent (the default): whole frames, as the paper.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub crop: Option<CropSize>,
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
fn lr_flame_expr() -> f64 {
    LR_FLAME_EXPR
}
fn lr_flame_pose() -> f64 {
    LR_FLAME_POSE
}
fn lr_flame_translation() -> f64 {
    LR_FLAME_TRANSLATION
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

/// Sizes of a net config that [`NetConfig::validate`] and the memory estimate compute with
/// unchecked arithmetic: the condition's width (a sum) and the view encoder's input side
/// (`8` shifted by the stages before the view and the view encoder's layers). A hostile
/// config overflowing them is refused here, by [`TrainConfig::load`], before either runs.
fn check_net_sizes(what: &str, n: &NetConfig) -> Result<()> {
    let c = &n.condition;
    if c.expression
        .checked_add(c.pose)
        .and_then(|d| d.checked_add(c.eta))
        .is_none()
    {
        return Err(Error::invalid(
            what,
            "condition",
            "expression + pose + eta overflows",
        ));
    }
    // Sides up to 8 * 2^32; `uv_res` itself allows far fewer stages.
    let shifts = n.appearance.before_view.len() + n.view.channels.len();
    if shifts > 32 {
        return Err(Error::invalid(
            what,
            "appearance.before_view/view.channels",
            format!(
                "{shifts} stages in all: the view encoder's input side 8 * 2^{shifts} is \
                 beyond any image"
            ),
        ));
    }
    Ok(())
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
            lr_flame_expr: LR_FLAME_EXPR,
            lr_flame_pose: LR_FLAME_POSE,
            lr_flame_translation: LR_FLAME_TRANSLATION,
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
            crop: None,
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
        match &c.net {
            NetSpec::File(f) => {
                let f = if f.is_relative() {
                    path.parent().unwrap_or(Path::new(".")).join(f)
                } else {
                    f.clone()
                };
                // A regular file only: a FIFO or a device (`/dev/zero`) would never end.
                if std::fs::metadata(&f).is_ok_and(|m| !m.is_file()) {
                    return Err(Error::invalid(
                        &what,
                        "net",
                        format!("{} is not a regular file", f.display()),
                    ));
                }
                let text = std::fs::read_to_string(&f).map_err(|e| Error::io(&f, e))?;
                let net_what = f.display().to_string();
                let n: NetConfig = serde_json::from_str(&text).map_err(|e| {
                    Error::invalid(
                        &net_what,
                        format!("line {} column {}", e.line(), e.column()),
                        e.to_string(),
                    )
                })?;
                // As `NetConfig::load` does, with the sizes checked first.
                check_net_sizes(&net_what, &n)?;
                n.validate(&net_what)?;
                c.net = NetSpec::Inline(n);
            }
            NetSpec::Inline(n) => check_net_sizes(&what, n)?,
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

    /// Checks ranges, the caps of [`limits::BATCH_SIZE`] and [`limits::UV_RES`], and the
    /// memory of a training step without the frames' images
    /// ([`TrainConfig::memory_estimate`] with `None`: the image size is the data's) against
    /// the budget; `what` names the source in errors.
    pub fn validate(&self, what: &str) -> Result<()> {
        let bad = |field: &str, why: &str| Err(Error::invalid(what, field, why));
        if let NetSpec::Inline(n) = &self.net {
            limits::check_size(what, "net.uv_res", n.uv_res, &limits::UV_RES)?;
            n.validate(what)?;
        }
        if self.iterations == 0 {
            return bad("iterations", "must be at least 1");
        }
        if self.batch_size == 0 {
            return bad("batch_size", "must be at least 1");
        }
        limits::check_size(what, "batch_size", self.batch_size, &limits::BATCH_SIZE)?;
        if self.checkpoint_every == 0 {
            return bad("checkpoint_every", "must be at least 1");
        }
        for (field, lr) in [
            ("lr_decoders", self.lr_decoders),
            ("lr_encoders", self.lr_encoders),
            ("lr_flame_expr", self.lr_flame_expr),
            ("lr_flame_pose", self.lr_flame_pose),
            ("lr_flame_translation", self.lr_flame_translation),
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
        if let Some(crop) = &self.crop {
            crop.validate(what)?;
        }
        let l = &self.loss;
        let weights = [l.l1, l.dssim, l.vgg, l.position, l.scale];
        if weights.iter().any(|w| !(w.is_finite() && *w >= 0.0)) {
            return bad("loss", "weights must be finite and >= 0");
        }
        if let Some(e) = self.memory_estimate(None) {
            let field = if self.batch_size > 1 {
                "batch_size"
            } else {
                "net"
            };
            limits::check_estimate(what, field, &e)?;
        }
        Ok(())
    }

    /// The memory of a training run (within 2x; `None` for an unresolved
    /// [`NetSpec::File`]): the parameters with their gradients and Adam's two moments, and
    /// per frame of a batch the networks' activations kept for the backward pass (every
    /// layer's output three times: pre-activation, activation, gradient) with the largest
    /// transposed convolution's column buffer (forward and backward), the lifting's
    /// per-texel attributes and gradients (64 floats per texel of R^2) and the Gaussians
    /// (one per texel at most, [`limits::GAUSSIAN_BYTES`] forward and again backward).
    /// With `image_pixels` (the frames' width x height) it adds per frame the rasterizer's
    /// forward and backward buffers, the ground truth, L1 and SSIM maps (512 B per pixel; of
    /// the crop's window when the run crops) and,
    /// with the VGG loss on, VGG16's activations of render and target (4.5 KiB per pixel).
    pub fn memory_estimate(&self, image_pixels: Option<u64>) -> Option<limits::Estimate> {
        let NetSpec::Inline(n) = &self.net else {
            return None;
        };
        let sat = |f: &[usize]| limits::product(&f.iter().map(|&x| x as u64).collect::<Vec<_>>());
        let base = crate::models::texavatars::constants::BASE_RES;
        // Parameters and per-frame activations and column buffers, in floats.
        #[derive(Default)]
        struct Count {
            params: u64,
            acts: u64,
            col: u64,
        }
        impl Count {
            fn add(&mut self, params: u64, acts: u64) {
                self.params = self.params.saturating_add(params);
                self.acts = self.acts.saturating_add(acts);
            }
        }
        let mut k = Count::default();
        k.add(
            sat(&[n.condition.dim(), n.code_channels, base, base]),
            sat(&[n.code_channels, base, base]),
        );
        // A transposed convolution (4x4, stride 2) from `c_in` at `side` to `c_out` at twice
        // the side; returns the new side.
        let up = |k: &mut Count, c_in: usize, c_out: usize, side: usize| {
            let out = side.saturating_mul(2);
            let bias = if n.untied_bias {
                sat(&[c_out, out, out])
            } else {
                c_out as u64
            };
            k.add(
                sat(&[c_in, c_out, 16]).saturating_add(bias),
                sat(&[c_out, out, out]),
            );
            k.col = k.col.max(sat(&[c_in, 16, side, side]));
            out
        };
        let (mut c, mut side) = (n.code_channels, base);
        for &g in &n.geometry {
            side = up(&mut k, c, g, side);
            c = g;
        }
        let (mut c, mut side) = (n.code_channels, base);
        for &a in &n.appearance.before_view {
            side = up(&mut k, c, a, side);
            c = a;
        }
        c = c.saturating_add(n.view.channels.last().copied().unwrap_or(0));
        for &m in &n.appearance.mid {
            k.add(sat(&[c, m, 9]), sat(&[m, side, side]));
            c = m;
        }
        for &a in &n.appearance.after_view {
            side = up(&mut k, c, a, side);
            c = a;
        }
        let sq = n.view.square_res;
        k.add(0, sat(&[6, sq, sq]));
        let (mut c, mut side) = (6usize, n.view_input_res());
        for &v in &n.view.channels {
            side /= 2;
            k.add(sat(&[c, v, 9]), sat(&[v, side, side]));
            c = v;
        }
        let Count { params, acts, col } = k;
        let r = n.uv_res;
        let batch = self.batch_size as u64;
        let per_frame = acts
            .saturating_mul(3)
            .saturating_add(col.saturating_mul(2))
            .saturating_add(sat(&[r, r, 64]))
            .saturating_mul(4)
            .saturating_add(limits::product(&[
                r as u64,
                r as u64,
                2 * limits::GAUSSIAN_BYTES,
            ]));
        let mut e = limits::Estimate::new()
            .add(
                format!("{params} parameters with gradients and Adam moments"),
                params.saturating_mul(16),
            )
            .add(
                format!("activations of {batch} frame(s) at R_uv {r}"),
                per_frame.saturating_mul(batch),
            );
        if let Some(px) = image_pixels {
            // A crop scores (and renders) its window only.
            let px = self
                .crop
                .map_or(px, |c| px.min(u64::from(c.width) * u64::from(c.height)));
            let vgg = self.ablations.vgg && self.loss.vgg > 0.0;
            let per_px: u64 = 512 + if vgg { 4608 } else { 0 };
            e = e.add(
                format!("images of {batch} frame(s)"),
                limits::product(&[px, per_px, batch]),
            );
        }
        Some(e)
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
        } else if a.crop != b.crop {
            "crop"
        } else {
            "optimiser or loss settings"
        })
    }
}
