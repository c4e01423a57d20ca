//! The cameras a driven avatar is seen from, one per motion frame.
//!
//! - [`CameraPath::Dataset`]: the dataset's own camera `index` at every timestep (a dataset
//!   motion only); by default the middle of the sorted camera indices, which is the frontal
//!   camera of NeRSemble's and the synthetic benchmark's 16-camera arcs (index 8).
//! - [`CameraPath::Orbit`]: a camera swinging `degrees` to either side of the face and back
//!   once over the motion, at `distance` from the first frame's head centre, 4 degrees above
//!   it (the synthetic rig's front camera), world y up, the face looking along +z.
//! - [`CameraPath::Front`]: the orbit's camera held at the front.

use glam::Vec3;

use crate::camera::Camera;
use crate::drive::motion::{Motion, MotionKind};
use crate::error::{Error, Result};
use crate::synth::cameras::look_at;

/// Elevation of the orbit and front cameras, degrees (the synthetic rig's front camera).
const ELEVATION_DEGREES: f32 = 4.0;

/// How the cameras move.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum CameraPath {
    /// The dataset's camera `index` (`None`: the middle index).
    Dataset { index: Option<usize> },
    /// Swing `degrees` either side of the front and back.
    Orbit { degrees: f32 },
    /// Fixed at the front.
    Front,
}

/// Image size and lens of the orbit and front cameras.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct View {
    pub width: u32,
    pub height: u32,
    pub fov_y_degrees: f32,
    /// Distance from the head centre, in the head model's units (metres for FLAME and the
    /// default head).
    pub distance: f32,
}

impl Default for View {
    /// NeRSemble's 550 x 802 with the synthetic rig's lens and distance.
    fn default() -> Self {
        View {
            width: 550,
            height: 802,
            fov_y_degrees: 20.0,
            distance: 1.0,
        }
    }
}

/// One camera per frame of `motion`.
pub fn cameras(motion: &Motion, path: CameraPath, view: &View) -> Result<Vec<Camera>> {
    let what = motion.source.display().to_string();
    match path {
        CameraPath::Dataset { index } => {
            if motion.kind != MotionKind::Dataset {
                return Err(Error::invalid(
                    what,
                    "cameras",
                    "`dataset` cameras need a dataset motion (a transforms_*.json); use `orbit` \
                     or `front`",
                ));
            }
            let all = motion.camera_indices();
            let index = index.unwrap_or(all[all.len() / 2]);
            motion
                .frames
                .iter()
                .map(|f| {
                    f.camera(index).ok_or_else(|| {
                        Error::invalid(
                            &what,
                            format!("timestep {}", f.timestep),
                            format!("no camera {index} (cameras in the file: {all:?})"),
                        )
                    })
                })
                .collect()
        }
        CameraPath::Orbit { degrees } => orbit(motion, degrees, view),
        CameraPath::Front => orbit(motion, 0.0, view),
    }
}

fn orbit(motion: &Motion, degrees: f32, view: &View) -> Result<Vec<Camera>> {
    if view.width == 0 || view.height == 0 {
        return Err(Error::invalid(
            "view",
            "size",
            "width and height must be > 0",
        ));
    }
    if !(view.fov_y_degrees > 0.0 && view.fov_y_degrees < 180.0) {
        return Err(Error::invalid("view", "fov", "must be in (0, 180) degrees"));
    }
    if !(view.distance.is_finite() && view.distance > 0.0) {
        return Err(Error::invalid("view", "distance", "must be > 0"));
    }
    let target = centre(&motion.frames[0].conditioning.vertices);
    let n = motion.frames.len();
    let el = ELEVATION_DEGREES.to_radians();
    Ok((0..n)
        .map(|i| {
            let phase = std::f32::consts::TAU * i as f32 / n.max(1) as f32;
            let az = (degrees * phase.sin()).to_radians();
            let dir = Vec3::new(az.sin() * el.cos(), el.sin(), az.cos() * el.cos());
            Camera::from_fov(
                view.width,
                view.height,
                view.fov_y_degrees,
                look_at(target + view.distance * dir, target),
            )
        })
        .collect())
}

/// Centre of the bounding box of `v`.
pub fn centre(v: &[[f32; 3]]) -> Vec3 {
    let mut lo = Vec3::splat(f32::INFINITY);
    let mut hi = Vec3::splat(f32::NEG_INFINITY);
    for p in v {
        lo = lo.min(Vec3::from(*p));
        hi = hi.max(Vec3::from(*p));
    }
    0.5 * (lo + hi)
}
