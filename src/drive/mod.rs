//! Driving a trained avatar: motions (a dataset split, another subject's FLAME parameters,
//! or keyframed curves), the cameras it is seen from, rendering frames and videos, exporting
//! per-frame 3DGS PLY files, and the frame-rate benchmark; [`outputs`] says which files of
//! an output folder each command owns (and clears before writing).

pub mod cameras;
pub mod export;
pub mod fps;
pub mod motion;
pub mod outputs;
pub mod render;

pub use cameras::{CameraPath, View, cameras};
pub use export::{ExportStats, HostGaussians, to_ply};
pub use motion::{Curves, Identity, Motion, MotionFrame, MotionKind};
pub use render::{RenderOptions, RenderReport, render_frame, render_frame_in_view, render_motion};
