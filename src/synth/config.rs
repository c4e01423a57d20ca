//! Settings of the synthetic benchmark (`configs/synth*.json`); every field has a default.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};

/// What `texavatars synth` generates.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SynthConfig {
    /// Image width in pixels (NeRSemble: 550).
    pub width: u32,
    /// Image height in pixels (NeRSemble: 802).
    pub height: u32,
    /// Supersampling factor per axis (anti-aliasing).
    pub supersample: u32,
    /// Number of cameras on the frontal arc (NeRSemble: 16).
    pub cameras: usize,
    /// The held-out camera of the novel-view split (NeRSemble protocol: 8, the front one).
    pub val_camera: usize,
    /// Camera distance from the head centre, metres.
    pub distance: f32,
    /// Horizontal span of the arc, degrees (cameras spread evenly over it).
    pub arc_degrees: f32,
    /// Vertical field of view, degrees.
    pub fov_y_degrees: f32,
    /// Frames per training and held-out sequence.
    pub frames_per_sequence: usize,
    /// Frames of the FREE sequence.
    pub free_frames: usize,
    /// Resolution of the baked albedo and wrinkle maps.
    pub texture_res: usize,
    /// Standard deviation of the noise added to the eta side signal.
    pub eta_noise: f32,
    /// How much a fully active wrinkle darkens the albedo.
    pub wrinkle_strength: f32,
    /// Largest head rotation in training frames, radians (yaw; pitch and roll smaller).
    pub train_rotation: f32,
    /// Largest head rotation in the FREE sequence, radians.
    pub free_rotation: f32,
    /// Seed of every random choice.
    pub seed: u64,
}

impl Default for SynthConfig {
    fn default() -> Self {
        SynthConfig {
            width: 138,
            height: 200,
            supersample: 3,
            cameras: 16,
            val_camera: 8,
            distance: 1.0,
            arc_degrees: 120.0,
            fov_y_degrees: 20.0,
            frames_per_sequence: 8,
            free_frames: 24,
            texture_res: 512,
            eta_noise: 0.05,
            wrinkle_strength: 0.45,
            train_rotation: 0.2,
            free_rotation: 0.5,
            seed: 7,
        }
    }
}

impl SynthConfig {
    /// Reads a JSON config (missing fields take their defaults).
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let c: SynthConfig = serde_json::from_str(&text).map_err(|e| {
            Error::invalid(
                path.display().to_string(),
                format!("line {} column {}", e.line(), e.column()),
                e.to_string(),
            )
        })?;
        c.validate(&path.display().to_string())?;
        Ok(c)
    }

    /// Checks ranges.
    pub fn validate(&self, what: &str) -> Result<()> {
        let bad = |field: &str, why: &str| Err(Error::invalid(what, field, why));
        if self.width < 8 || self.height < 8 {
            return bad("width/height", "images must be at least 8x8");
        }
        if !(1..=8).contains(&self.supersample) {
            return bad("supersample", "must be 1 to 8");
        }
        if self.cameras < 2 {
            return bad("cameras", "need at least 2 (one is held out)");
        }
        if self.val_camera >= self.cameras {
            return bad("val_camera", "must be a camera index");
        }
        let sane = self.distance.is_finite()
            && self.distance > 0.0
            && self.fov_y_degrees > 1.0
            && self.fov_y_degrees < 170.0;
        if !sane {
            return bad("distance/fov_y_degrees", "distance > 0 and 1 < fov < 170");
        }
        if self.frames_per_sequence < 2 || self.free_frames < 2 {
            return bad("frames_per_sequence/free_frames", "at least 2");
        }
        if self.texture_res < 16 {
            return bad("texture_res", "at least 16");
        }
        if !self.eta_noise.is_finite() || self.eta_noise < 0.0 {
            return bad("eta_noise", "must be >= 0");
        }
        Ok(())
    }
}
