//! Per-face frames of the posed mesh: one thread per face.
//!
//! # Shapes
//! - `vertices`: `[V, 3]`, `faces`: `[F, 3]` u32, `frames`: `[F, 9]` (row-major 3x3; the
//!   columns are the frame's axes).

use cubecl::prelude::*;

use super::math::{face_frame, load3, store_m3};

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
    let v0 = load3(vertices, faces[fi * 3] as usize * 3);
    let v1 = load3(vertices, faces[fi * 3 + 1] as usize * 3);
    let v2 = load3(vertices, faces[fi * 3 + 2] as usize * 3);
    store_m3(frames, fi * 9, face_frame(v0, v1, v2, scaled_rotation));
}
