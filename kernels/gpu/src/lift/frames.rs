//! Per-face frames of the posed mesh: one thread per face.
//!
//! # Shapes
//! - `vertices`: `[V, 3]`, `faces`: `[F, 3]` u32, `frames`: `[F, 9]` (row-major 3x3; the
//!   columns are the frame's axes).

use cubecl::prelude::*;

use super::math::{face_frame, store_m3};
use super::transform::face_vertices;

/// See the module documentation.
#[cube(launch_unchecked)]
pub fn face_frames(
    vertices: &[f32],
    faces: &[u32],
    frames: &mut [f32],
    num_faces: u32,
    #[comptime] scaled_rotation: bool,
) {
    let f = ABSOLUTE_POS as u32;
    if f >= num_faces {
        terminate!();
    }
    let fi = f as usize;
    let t = face_vertices(vertices, faces, fi);
    store_m3(
        frames,
        fi * 9,
        face_frame(t.v0, t.v1, t.v2, scaled_rotation),
    );
}
