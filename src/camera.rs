//! One pinhole camera type and its conventions.
//!
//! - Extrinsics: `world_to_camera` is a 4x4 row-major matrix in OpenCV axes (x right, y down,
//!   z forward). A world point `p` maps to camera space as `R p + t` with `R` the upper-left
//!   3x3 block and `t` the last column.
//! - Intrinsics in pixels: `u = fx x / z + cx`, `v = fy y / z + cy`.
//! - Pixel `(i, j)` (column `i`, row `j`) has its centre at `(i + 0.5, j + 0.5)`.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};

/// A pinhole camera with OpenCV axes.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Camera {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Focal length along x, in pixels.
    pub fx: f32,
    /// Focal length along y, in pixels.
    pub fy: f32,
    /// Principal point x, in pixels.
    pub cx: f32,
    /// Principal point y, in pixels.
    pub cy: f32,
    /// World-to-camera transform, row-major, OpenCV axes.
    pub world_to_camera: [[f32; 4]; 4],
}

/// A camera together with the background colour of a render, as stored in the fixtures'
/// `camera.json`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraFile {
    /// The camera.
    #[serde(flatten)]
    pub camera: Camera,
    /// Background colour (RGB). White when absent.
    #[serde(default = "white")]
    pub background: [f32; 3],
}

fn white() -> [f32; 3] {
    [1.0; 3]
}

impl Camera {
    /// A pinhole camera of `width` x `height` pixels with vertical field of view
    /// `fov_y_degrees`, square pixels, the principal point at the image centre, and the
    /// world-to-camera transform `world_to_camera` (OpenCV axes).
    pub fn from_fov(
        width: u32,
        height: u32,
        fov_y_degrees: f32,
        world_to_camera: [[f32; 4]; 4],
    ) -> Self {
        let f = 0.5 * height as f32 / (0.5 * fov_y_degrees.to_radians()).tan();
        Camera {
            width,
            height,
            fx: f,
            fy: f,
            cx: 0.5 * width as f32,
            cy: 0.5 * height as f32,
            world_to_camera,
        }
    }

    /// Rotation block (row-major) of the world-to-camera transform.
    pub fn rotation(&self) -> [[f32; 3]; 3] {
        let m = &self.world_to_camera;
        [
            [m[0][0], m[0][1], m[0][2]],
            [m[1][0], m[1][1], m[1][2]],
            [m[2][0], m[2][1], m[2][2]],
        ]
    }

    /// Translation column of the world-to-camera transform.
    pub fn translation(&self) -> [f32; 3] {
        let m = &self.world_to_camera;
        [m[0][3], m[1][3], m[2][3]]
    }

    /// Camera centre in world coordinates: `-R^T t`.
    pub fn position(&self) -> [f32; 3] {
        let r = self.rotation();
        let t = self.translation();
        let mut c = [0.0f32; 3];
        for (k, ck) in c.iter_mut().enumerate() {
            *ck = -(r[0][k] * t[0] + r[1][k] * t[1] + r[2][k] * t[2]);
        }
        c
    }

    /// Checks that the camera can be rendered with: positive size and focal lengths, finite
    /// values everywhere, and a last row of `[0, 0, 0, 1]`. `what` names the source in errors.
    pub fn validate(&self, what: &str) -> Result<()> {
        let field = |f: &str, why: String| Error::invalid(what, f, why);
        if self.width == 0 || self.height == 0 {
            return Err(field(
                "width/height",
                format!("must be positive, got {}x{}", self.width, self.height),
            ));
        }
        for (name, v) in [
            ("fx", self.fx),
            ("fy", self.fy),
            ("cx", self.cx),
            ("cy", self.cy),
        ] {
            if !v.is_finite() {
                return Err(field(name, format!("must be finite, got {v}")));
            }
        }
        if self.fx <= 0.0 || self.fy <= 0.0 {
            return Err(field(
                "fx/fy",
                format!("must be positive, got {} and {}", self.fx, self.fy),
            ));
        }
        if self
            .world_to_camera
            .iter()
            .flatten()
            .any(|v| !v.is_finite())
        {
            return Err(field("world_to_camera", "has a non-finite entry".into()));
        }
        if let Some(why) = rotation_problem(&self.world_to_camera) {
            return Err(field("world_to_camera", why));
        }
        let last = self.world_to_camera[3];
        if last != [0.0, 0.0, 0.0, 1.0] {
            return Err(field(
                "world_to_camera",
                format!("last row must be [0, 0, 0, 1], got {last:?}"),
            ));
        }
        Ok(())
    }
}

/// Largest deviation of `R^T R` from the identity (and of `det R` from 1) accepted for the
/// rotation part of a camera matrix: exports store six or more significant digits, so a
/// real rotation is off by about 1e-6; a scaled, sheared or singular matrix (which renders
/// nothing, or a distorted head, without an error) by far more.
pub const ROTATION_TOLERANCE: f32 = 1e-3;

/// Why the upper-left 3x3 of `m` is not a rotation (`None` when it is one, within
/// [`ROTATION_TOLERANCE`]).
pub fn rotation_problem(m: &[[f32; 4]; 4]) -> Option<String> {
    let r = |i: usize, j: usize| f64::from(m[i][j]);
    let mut worst = 0.0f64;
    for a in 0..3 {
        for b in 0..3 {
            let dot: f64 = (0..3).map(|k| r(k, a) * r(k, b)).sum();
            worst = worst.max((dot - f64::from(u8::from(a == b))).abs());
        }
    }
    let det = r(0, 0) * (r(1, 1) * r(2, 2) - r(1, 2) * r(2, 1))
        - r(0, 1) * (r(1, 0) * r(2, 2) - r(1, 2) * r(2, 0))
        + r(0, 2) * (r(1, 0) * r(2, 1) - r(1, 1) * r(2, 0));
    let tol = f64::from(ROTATION_TOLERANCE);
    if worst > tol || (det - 1.0).abs() > tol {
        Some(format!(
            "the 3x3 part is not a rotation (|R^T R - I| = {worst:.2e}, det = {det:.4}); \
             a camera matrix must be a rigid transform"
        ))
    } else {
        None
    }
}

impl CameraFile {
    /// Reads a `camera.json` (the fixtures' format) and validates it.
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let file: CameraFile = serde_json::from_str(&text).map_err(|e| {
            Error::invalid(
                path.display().to_string(),
                "json",
                format!("not a camera file: {e}"),
            )
        })?;
        file.camera.validate(&path.display().to_string())?;
        if file.background.iter().any(|v| !v.is_finite()) {
            return Err(Error::invalid(
                path.display().to_string(),
                "background",
                "must be finite".to_string(),
            ));
        }
        Ok(file)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cam() -> Camera {
        Camera {
            width: 4,
            height: 3,
            fx: 10.0,
            fy: 10.0,
            cx: 2.0,
            cy: 1.5,
            world_to_camera: [
                [0.0, -1.0, 0.0, 1.0],
                [1.0, 0.0, 0.0, 2.0],
                [0.0, 0.0, 1.0, 3.0],
                [0.0, 0.0, 0.0, 1.0],
            ],
        }
    }

    #[test]
    fn position_inverts_extrinsics() {
        let c = cam();
        let p = c.position();
        let r = c.rotation();
        let t = c.translation();
        for row in 0..3 {
            let v = r[row][0] * p[0] + r[row][1] * p[1] + r[row][2] * p[2] + t[row];
            assert!(v.abs() < 1e-6, "camera centre must map to the origin");
        }
    }

    #[test]
    fn validate_rejects_bad_values() {
        let mut c = cam();
        assert!(c.validate("x").is_ok());
        c.fx = f32::NAN;
        let e = c.validate("cam.json").unwrap_err().to_string();
        assert!(e.contains("cam.json") && e.contains("fx"), "{e}");
        let mut c = cam();
        c.width = 0;
        assert!(c.validate("x").is_err());
        let mut c = cam();
        c.world_to_camera[3][0] = 1.0;
        assert!(c.validate("x").is_err());
        // Singular, scaled and mirrored 3x3 parts are not rotations (issue 15: a singular
        // camera rotation used to train on blank renders).
        for (i, j, v) in [(0, 1, 0.0), (1, 1, 2.0), (2, 2, -1.0)] {
            let mut c = cam();
            c.world_to_camera[i][j] = v;
            let e = c.validate("cam.json").unwrap_err().to_string();
            assert!(
                e.contains("world_to_camera") && e.contains("not a rotation"),
                "{e}"
            );
        }
    }

    #[test]
    fn load_reports_missing_and_malformed_files() {
        let dir = std::env::temp_dir().join(format!("texavatars-cam-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let missing = dir.join("missing.json");
        let e = CameraFile::load(&missing).unwrap_err().to_string();
        assert!(e.contains("missing.json"), "{e}");
        let bad = dir.join("bad.json");
        std::fs::write(&bad, "{\"width\": 3").unwrap();
        let e = CameraFile::load(&bad).unwrap_err().to_string();
        assert!(e.contains("bad.json"), "{e}");
        let good = dir.join("good.json");
        std::fs::write(&good, serde_json::to_string(&cam()).unwrap()).unwrap();
        let f = CameraFile::load(&good).unwrap();
        assert_eq!(f.background, [1.0; 3]);
        assert_eq!(f.camera, cam());
    }
}
