//! Settings of the synthetic benchmark (`configs/synth*.json`); every field has a default,
//! so configs and recorded exports written before a field existed still read (they take
//! the field's default).

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::limits;
use crate::synth::tracking::TrackingNoise;

/// The largest subject index `--subject` takes.
pub const MAX_SUBJECT: usize = 1_000_000;

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
    /// Standard deviation of the noise added to the eta side signal (whose clean values
    /// lie in [-1, 1]).
    pub eta_noise: f32,
    /// How much a fully active wrinkle darkens the albedo.
    pub wrinkle_strength: f32,
    /// Largest head rotation in training frames, radians (yaw; pitch and roll smaller).
    pub train_rotation: f32,
    /// Largest head rotation in the FREE sequence, radians.
    pub free_rotation: f32,
    /// Seed of every random choice.
    pub seed: u64,
    /// The subject rendered (`texavatars synth --subject K`): 0 is the head's mean shape
    /// with the original appearance; others differ in shape and appearance
    /// ([`crate::synth::subject`]).
    pub subject: usize,
    /// Strength of the hidden muscle tension that changes wrinkles independently of the
    /// expression ([`crate::synth::tension`]); 0 makes the activations a function of the
    /// expression coefficients alone.
    pub tension: f32,
    /// Noise of the tracked parameters written to `flame_param/`
    /// ([`crate::synth::tracking`]); the truth goes to `truth/`.
    pub tracking: TrackingNoise,
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
            frames_per_sequence: 12,
            free_frames: 24,
            texture_res: 512,
            eta_noise: 0.05,
            wrinkle_strength: 0.45,
            train_rotation: 0.2,
            free_rotation: 0.5,
            seed: 7,
            subject: 0,
            tension: 1.0,
            tracking: TrackingNoise::default(),
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

    /// Checks ranges, and sizes against their caps ([`crate::limits`]: image sides, cameras,
    /// frames, texture resolution).
    pub fn validate(&self, what: &str) -> Result<()> {
        let bad = |field: &str, why: &str| Err(Error::invalid(what, field, why));
        if self.width < 8 || self.height < 8 {
            return bad("width/height", "images must be at least 8x8");
        }
        limits::check_image_size(what, "", self.width.into(), self.height.into())?;
        limits::check_size(what, "cameras", self.cameras, &limits::CAMERAS)?;
        limits::check_size(
            what,
            "frames_per_sequence",
            self.frames_per_sequence,
            &limits::FRAMES,
        )?;
        limits::check_size(what, "free_frames", self.free_frames, &limits::FRAMES)?;
        limits::check_size(what, "texture_res", self.texture_res, &limits::TEXTURE_RES)?;
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
        if !self.tension.is_finite() || !(0.0..=4.0).contains(&self.tension) {
            return bad("tension", "must be from 0 to 4");
        }
        if self.subject > MAX_SUBJECT {
            return bad("subject", "must be at most 1000000");
        }
        self.tracking.validate(what)
    }

    /// Timesteps of the benchmark: the ten training sequences and the test sequence at
    /// `frames_per_sequence` each, and the FREE sequence.
    pub fn timesteps(&self) -> u64 {
        let seqs = crate::synth::sequences::TRAIN_FAMILIES.len() as u64 + 1;
        (self.frames_per_sequence as u64)
            .saturating_mul(seqs)
            .saturating_add(self.free_frames as u64)
    }

    /// The memory a run takes (within 2x), as (field, part, bytes): `threads` views rendered
    /// at once, each with its supersampled z-buffer and its output images; the baked maps;
    /// the image records of the `transforms_*.json` files.
    fn memory_parts(&self, threads: usize) -> [(&'static str, String, u64); 3] {
        let (w, h, s) = (
            u64::from(self.width),
            u64::from(self.height),
            u64::from(self.supersample),
        );
        let per_view = limits::product(&[w, h, s, s, limits::SYNTH_BYTES_PER_SAMPLE])
            .saturating_add(limits::product(&[w, h, limits::SYNTH_BYTES_PER_SAMPLE]));
        let t = self.texture_res as u64;
        [
            (
                "width/height/supersample",
                format!("{threads} views of {w}x{h} at {s}x{s} supersampling"),
                per_view.saturating_mul(threads as u64),
            ),
            (
                "texture_res",
                format!("{t}x{t} baked maps"),
                limits::product(&[t, t, limits::SYNTH_BYTES_PER_TEXEL]),
            ),
            (
                "frames_per_sequence/free_frames/cameras",
                "image records".to_string(),
                limits::product(&[
                    self.timesteps(),
                    self.cameras as u64,
                    limits::SYNTH_BYTES_PER_IMAGE_RECORD,
                ]),
            ),
        ]
    }

    /// The memory a run with `threads` rendering threads takes (within 2x).
    pub fn memory_estimate(&self, threads: usize) -> limits::Estimate {
        self.memory_parts(threads)
            .into_iter()
            .fold(limits::Estimate::new(), |e, (_, part, b)| e.add(part, b))
    }

    /// [`SynthConfig::memory_estimate`] for this process's thread pool, checked against the
    /// memory budget; the error names the fields of the largest part.
    pub fn check_memory(&self, what: &str) -> Result<()> {
        let parts = self.memory_parts(rayon::current_num_threads());
        let field = parts
            .iter()
            .max_by_key(|p| p.2)
            .map_or("width/height", |p| p.0);
        let e = parts
            .into_iter()
            .fold(limits::Estimate::new(), |e, (_, part, b)| e.add(part, b));
        limits::check_estimate(what, field, &e)
    }
}
