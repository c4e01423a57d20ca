//! Layout of the camera parameter buffer every splat kernel reads.
//!
//! The host packs one pinhole camera (OpenCV axes) and the background colour into a small
//! `f32` buffer with [`pack_camera`]; kernels read single entries by the `CAM_*` indices.
//! The field-of-view limits of the EWA Jacobian are precomputed on the host so every
//! kernel (and the CPU renderer, which computes them the same way) clamps identically.
//!
//! # Shapes
//! - camera buffer: `[CAMERA_LEN]` f32.

use super::constants::FOV_MARGIN;

/// Row-major rotation `R` of world-to-camera, entries `CAM_R + 3 * row + col`.
pub const CAM_R: usize = 0;
/// Translation `t` of world-to-camera, entries `CAM_T + i`.
pub const CAM_T: usize = 9;
/// Focal length along x, in pixels.
pub const CAM_FX: usize = 12;
/// Focal length along y, in pixels.
pub const CAM_FY: usize = 13;
/// Principal point x, in pixels.
pub const CAM_CX: usize = 14;
/// Principal point y, in pixels.
pub const CAM_CY: usize = 15;
/// Image width in pixels, as f32.
pub const CAM_WIDTH: usize = 16;
/// Image height in pixels, as f32.
pub const CAM_HEIGHT: usize = 17;
/// Upper clamp of `x / z` in the EWA Jacobian: `(W - cx) / fx + FOV_MARGIN * 0.5 W / fx`.
pub const CAM_LIM_X_POS: usize = 18;
/// Lower clamp of `x / z`, as a positive number: `cx / fx + FOV_MARGIN * 0.5 W / fx`.
pub const CAM_LIM_X_NEG: usize = 19;
/// Upper clamp of `y / z`: `(H - cy) / fy + FOV_MARGIN * 0.5 H / fy`.
pub const CAM_LIM_Y_POS: usize = 20;
/// Lower clamp of `y / z`, as a positive number: `cy / fy + FOV_MARGIN * 0.5 H / fy`.
pub const CAM_LIM_Y_NEG: usize = 21;
/// Background colour, entries `CAM_BG + c` for RGB.
pub const CAM_BG: usize = 22;
/// Number of `f32` in the camera buffer.
pub const CAMERA_LEN: usize = 25;

/// Packs a camera and a background colour into the buffer layout above.
///
/// `size` is `[width, height]` in pixels, `intrinsics` is `[fx, fy, cx, cy]` in pixels and
/// `world_to_camera` the row-major 4x4 OpenCV extrinsic matrix (its last row is not read).
pub fn pack_camera(
    size: [u32; 2],
    intrinsics: [f32; 4],
    world_to_camera: &[[f32; 4]; 4],
    background: [f32; 3],
) -> [f32; CAMERA_LEN] {
    let [width, height] = size;
    let [fx, fy, cx, cy] = intrinsics;
    let mut out = [0.0f32; CAMERA_LEN];
    for row in 0..3 {
        for col in 0..3 {
            out[CAM_R + 3 * row + col] = world_to_camera[row][col];
        }
        out[CAM_T + row] = world_to_camera[row][3];
    }
    let (w, h) = (width as f32, height as f32);
    out[CAM_FX] = fx;
    out[CAM_FY] = fy;
    out[CAM_CX] = cx;
    out[CAM_CY] = cy;
    out[CAM_WIDTH] = w;
    out[CAM_HEIGHT] = h;
    let (lim_x_pos, lim_x_neg) = fov_limits(w, cx, fx);
    let (lim_y_pos, lim_y_neg) = fov_limits(h, cy, fy);
    out[CAM_LIM_X_POS] = lim_x_pos;
    out[CAM_LIM_X_NEG] = lim_x_neg;
    out[CAM_LIM_Y_POS] = lim_y_pos;
    out[CAM_LIM_Y_NEG] = lim_y_neg;
    out[CAM_BG..CAM_BG + 3].copy_from_slice(&background);
    out
}

/// `(lim_pos, lim_neg)` of the tangent clamp along one image axis of `size` pixels with
/// principal point `c` and focal length `f`.
pub fn fov_limits(size: f32, c: f32, f: f32) -> (f32, f32) {
    let margin = FOV_MARGIN * 0.5 * size / f;
    ((size - c) / f + margin, c / f + margin)
}
