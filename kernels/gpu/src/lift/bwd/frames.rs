//! Backward of the per-face frames: one thread per face, writing the gradient of each of
//! the face's three corners (summed per vertex afterwards by a CSR gather).
//!
//! # Shapes
//! - `vertices`: `[V, 3]`, `faces`: `[F, 3]` u32, `dframes`: `[F, 9]`,
//!   `dcorners`: `[F, 3, 3]` (corner, coordinate).

use cubecl::prelude::*;

use crate::lift::math::{face_frame_backward, load_m3};
use crate::lift::transform::face_vertices;

/// See the module documentation.
#[cube(launch_unchecked)]
pub fn face_frames_backward(
    vertices: &[f32],
    faces: &[u32],
    dframes: &[f32],
    dcorners: &mut [f32],
    num_faces: u32,
    #[comptime] scaled_rotation: bool,
) {
    let f = ABSOLUTE_POS as u32;
    if f >= num_faces {
        terminate!();
    }
    let fi = f as usize;
    let t = face_vertices(vertices, faces, fi);
    let g = face_frame_backward(t.v0, t.v1, t.v2, load_m3(dframes, fi * 9), scaled_rotation);
    let base = fi * 9;
    dcorners[base] = g.d0.x;
    dcorners[base + 1] = g.d0.y;
    dcorners[base + 2] = g.d0.z;
    dcorners[base + 3] = g.d1.x;
    dcorners[base + 4] = g.d1.y;
    dcorners[base + 5] = g.d1.z;
    dcorners[base + 6] = g.d2.x;
    dcorners[base + 7] = g.d2.y;
    dcorners[base + 8] = g.d2.z;
}
