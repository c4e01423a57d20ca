//! A window of a frame: the pixels of a rectangle and the camera that sees exactly them.
//!
//! Cropping keeps the frame's geometry: the window `[x0, x0 + w) x [y0, y0 + h)` of a
//! `W x H` image is what a camera with the same focal lengths and rotation, the principal
//! point moved to `(cx - x0, cy - y0)` and `w x h` pixels, renders. A pixel `(x, y)` of the
//! window (centre `x + 0.5`) is pixel `(x0 + x, y0 + y)` of the frame.

use serde::{Deserialize, Serialize};

use crate::camera::Camera;
use crate::data::dataset::HeadItem;
use crate::error::{Error, Result};
use crate::util::rng::Pcg;

/// The size of the window a training step scores (`crop` in a training config).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CropSize {
    /// Pixels across.
    pub width: u32,
    /// Pixels down.
    pub height: u32,
}

/// A window of a frame, in the frame's pixels.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Window {
    pub x0: u32,
    pub y0: u32,
    pub width: u32,
    pub height: u32,
}

impl CropSize {
    /// Smallest side: one 16 x 16 tile of the renderer, and SSIM's 11 x 11 window fits.
    pub const MIN_SIDE: u32 = 16;

    /// Checks the sides (`what` names the config for the error).
    pub fn validate(&self, what: &str) -> Result<()> {
        for (field, v) in [("crop.width", self.width), ("crop.height", self.height)] {
            if v < Self::MIN_SIDE {
                return Err(Error::invalid(
                    what,
                    field,
                    format!("{v} pixels; a crop needs at least {}", Self::MIN_SIDE),
                ));
            }
        }
        Ok(())
    }

    /// Checks that the window fits a `width x height` frame (`what` names the data).
    pub fn check_fits(&self, what: &str, width: u32, height: u32) -> Result<()> {
        if self.width > width || self.height > height {
            return Err(Error::invalid(
                what,
                "crop",
                format!(
                    "a {}x{} crop does not fit the {width}x{height} frames",
                    self.width, self.height
                ),
            ));
        }
        Ok(())
    }

    /// A window of this size placed uniformly at random inside a `width x height` frame
    /// (every position with the window inside the frame equally likely), drawn from `rng`.
    /// A side larger than the frame is clamped to it.
    pub fn place(&self, width: u32, height: u32, rng: &mut Pcg) -> Window {
        let w = self.width.min(width);
        let h = self.height.min(height);
        let pick = |slack: u32, rng: &mut Pcg| -> u32 {
            ((rng.next_u32() as u64 * (slack as u64 + 1)) >> 32) as u32
        };
        let x0 = pick(width - w, rng);
        let y0 = pick(height - h, rng);
        Window {
            x0,
            y0,
            width: w,
            height: h,
        }
    }
}

impl Window {
    /// The camera that renders exactly this window of `camera`'s image.
    pub fn camera(&self, camera: &Camera) -> Camera {
        Camera {
            width: self.width,
            height: self.height,
            cx: camera.cx - self.x0 as f32,
            cy: camera.cy - self.y0 as f32,
            ..*camera
        }
    }

    /// This window of a row-major `[H, W, C]` image of `width` pixels across.
    fn pixels(&self, data: &[f32], width: u32, channels: usize) -> Vec<f32> {
        let row = self.width as usize * channels;
        let mut out = Vec::with_capacity(row * self.height as usize);
        for y in self.y0..self.y0 + self.height {
            let start = (y as usize * width as usize + self.x0 as usize) * channels;
            out.extend_from_slice(&data[start..start + row]);
        }
        out
    }

    /// The frame `item` seen through this window: image, mask and camera cropped, the rest
    /// unchanged.
    ///
    /// # Panics
    /// When the window does not lie inside the item's frame.
    pub fn apply(&self, item: HeadItem) -> HeadItem {
        let (w, h) = (item.camera.width, item.camera.height);
        assert!(
            self.x0 + self.width <= w && self.y0 + self.height <= h,
            "window {self:?} outside a {w}x{h} frame"
        );
        HeadItem {
            image: self.pixels(&item.image, w, 3),
            mask: self.pixels(&item.mask, w, 1),
            camera: self.camera(&item.camera),
            ..item
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera() -> Camera {
        let pose = [
            [1., 0., 0., 0.],
            [0., 1., 0., 0.],
            [0., 0., 1., 2.],
            [0., 0., 0., 1.],
        ];
        let mut c = Camera::from_fov(40, 30, 30.0, pose);
        c.cx = 21.3;
        c.cy = 14.1;
        c
    }

    /// OpenCV's pinhole: `u = fx x / z + cx` in camera coordinates.
    fn project(c: &Camera, p: [f32; 3]) -> (f32, f32) {
        let m = &c.world_to_camera;
        let q: [f32; 3] =
            std::array::from_fn(|r| m[r][0] * p[0] + m[r][1] * p[1] + m[r][2] * p[2] + m[r][3]);
        (c.fx * q[0] / q[2] + c.cx, c.fy * q[1] / q[2] + c.cy)
    }

    #[test]
    fn a_point_lands_on_the_same_frame_pixel() {
        let c = camera();
        let win = Window {
            x0: 7,
            y0: 5,
            width: 20,
            height: 16,
        };
        let wc = win.camera(&c);
        for p in [[0.1f32, -0.2, 0.5], [-0.3, 0.25, 0.9], [0.0, 0.0, 0.0]] {
            let (u, v) = project(&c, p);
            let (wu, wv) = project(&wc, p);
            assert!((u - (wu + 7.0)).abs() < 1e-4 && (v - (wv + 5.0)).abs() < 1e-4);
        }
        assert_eq!((wc.width, wc.height, wc.fx, wc.fy), (20, 16, c.fx, c.fy));
    }

    #[test]
    fn placement_covers_every_position_and_stays_inside() {
        let size = CropSize {
            width: 30,
            height: 28,
        };
        let mut rng = Pcg::new(3);
        let mut seen = [[false; 3]; 11];
        for _ in 0..2000 {
            let w = size.place(40, 30, &mut rng);
            assert!(w.x0 + w.width <= 40 && w.y0 + w.height <= 30);
            seen[w.x0 as usize][w.y0 as usize] = true;
        }
        assert!(seen.iter().flatten().all(|&s| s), "{seen:?}");
        let whole = CropSize {
            width: 64,
            height: 64,
        }
        .place(40, 30, &mut rng);
        assert_eq!(
            (whole.x0, whole.y0, whole.width, whole.height),
            (0, 0, 40, 30)
        );
    }

    #[test]
    fn sides_below_a_tile_are_refused() {
        let e = CropSize {
            width: 8,
            height: 64,
        }
        .validate("cfg.json")
        .unwrap_err()
        .to_string();
        assert!(e.contains("cfg.json") && e.contains("crop.width"), "{e}");
        let e = CropSize {
            width: 64,
            height: 64,
        }
        .check_fits("data", 40, 30)
        .unwrap_err()
        .to_string();
        assert!(e.contains("64x64") && e.contains("40x30"), "{e}");
    }
}
