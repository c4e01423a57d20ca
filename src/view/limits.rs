//! The viewer's bounds, with their reasons: what one message, one frame and one client may
//! ask of the server.

use super::protocol::Orbit;
use crate::error::{Error, Result};

/// Largest text message the server reads, bytes. A full request (52 expression values,
/// every pose value, the camera) is under 2 KB; a FLAME head's 100 expressions under 3 KB.
pub const MESSAGE_BYTES: usize = 16 * 1024;

/// Largest WebSocket message the connection accepts at all (larger ones close it); above
/// [`MESSAGE_BYTES`] so that an oversized request still gets an error reply.
pub const SOCKET_MESSAGE_BYTES: usize = 64 * 1024;

/// Image side of a viewer frame, pixels: 2.5 times the paper's 802-pixel frames. A
/// 2048 x 2048 render holds about 400 MB of buffers (`crate::limits::render_bytes`).
pub const MAX_SIDE: u32 = 2048;
/// Smallest image side, pixels (below it a frame shows nothing of use).
pub const MIN_SIDE: u32 = 16;

/// Expression coefficients are refused beyond ±this: 3 standard deviations of FLAME's PCA
/// expressions times 3; beyond it the mesh folds over itself.
pub const EXPRESSION: f32 = 9.0;

/// Orbit distance range, model units (metres for FLAME): from inside the head to far away.
pub const DISTANCE: (f32, f32) = (0.05, 20.0);

/// Vertical field of view range, degrees.
pub const FOV_DEGREES: (f32, f32) = (1.0, 120.0);

/// WebSocket clients served at once; more are refused (HTTP 503). Frames are rendered one
/// at a time, so each client beyond a few only slows the others.
pub const CLIENTS: usize = 8;

/// Messages a client may send per second; more are refused with an error reply. Sliders
/// send at most one per animation frame (60 per second).
pub const MESSAGES_PER_SECOND: u32 = 240;

/// The orbit the page starts from: the synthetic rig's front camera (4 degrees above the
/// face, 1 m, 20 degrees), at NeRSemble's 550 x 802 aspect (the page scales the size to
/// its window).
pub const DEFAULT_ORBIT: Orbit = Orbit {
    yaw: 0.0,
    pitch: 4.0,
    distance: 1.0,
    pan: [0.0, 0.0],
    fov: 20.0,
    width: 550,
    height: 802,
};

/// Checks one image side of a camera against [`MIN_SIDE`]..=[`MAX_SIDE`].
pub fn check_side(field: &str, v: u32) -> Result<()> {
    if (MIN_SIDE..=MAX_SIDE).contains(&v) {
        Ok(())
    } else {
        Err(Error::invalid(
            "request",
            field,
            format!("{v} pixels is outside [{MIN_SIDE}, {MAX_SIDE}]"),
        ))
    }
}
