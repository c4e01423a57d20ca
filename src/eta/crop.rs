//! The face region of a frame: the square around the tracked head's projection, resampled
//! to a fixed size.
//!
//! Pixel `(i, j)` has its centre at `(i + 0.5, j + 0.5)` ([`crate::camera`]). Output pixel
//! `(i, j)` of an `n x n` crop of box `b` covers `[x0 + i s, x0 + (i + 1) s)` with
//! `x0 = b.cx - b.side / 2` and `s = b.side / n` (same in y); its value is the mean of
//! `k x k` bilinear samples at `x0 + (i + (a + 0.5) / k) s`, `a = 0..k`, with
//! `k = max(1, ceil(s))` (an area filter when the crop shrinks the image). Samples read
//! the image with clamp-free bilinear weights and white ([`crate::data::BACKGROUND`])
//! outside it, the background every export is composited on.

use crate::camera::Camera;
use crate::data::BACKGROUND;

/// How much larger than the head's projected bounding box the square is.
pub const MARGIN: f32 = 1.05;

/// A square region of an image, in pixels (continuous coordinates).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SquareBox {
    /// Centre x.
    pub cx: f32,
    /// Centre y.
    pub cy: f32,
    /// Side length.
    pub side: f32,
}

/// The square around the projection of `vertices` (world space) into `camera`: centred on
/// their bounding box, side [`MARGIN`] times its longer edge. `None` when no vertex is in
/// front of the camera.
pub fn head_box(camera: &Camera, vertices: &[[f32; 3]]) -> Option<SquareBox> {
    let m = &camera.world_to_camera;
    let (mut lo, mut hi) = ([f32::INFINITY; 2], [f32::NEG_INFINITY; 2]);
    for v in vertices {
        let p = |r: usize| m[r][0] * v[0] + m[r][1] * v[1] + m[r][2] * v[2] + m[r][3];
        let z = p(2);
        if z <= 1e-6 {
            continue;
        }
        let u = [
            camera.fx * p(0) / z + camera.cx,
            camera.fy * p(1) / z + camera.cy,
        ];
        for k in 0..2 {
            lo[k] = lo[k].min(u[k]);
            hi[k] = hi[k].max(u[k]);
        }
    }
    if !lo[0].is_finite() {
        return None;
    }
    Some(SquareBox {
        cx: 0.5 * (lo[0] + hi[0]),
        cy: 0.5 * (lo[1] + hi[1]),
        side: MARGIN * (hi[0] - lo[0]).max(hi[1] - lo[1]).max(1.0),
    })
}

/// The `size x size` crop of `b` from an RGB image (see the module docs).
///
/// # Shapes
/// - `rgb`: [height, width, 3] row-major
/// - returns [size, size, 3] row-major
pub fn crop(rgb: &[f32], width: usize, height: usize, b: &SquareBox, size: usize) -> Vec<f32> {
    let step = b.side / size as f32;
    let k = (step.ceil() as usize).max(1);
    let (x0, y0) = (b.cx - 0.5 * b.side, b.cy - 0.5 * b.side);
    let texel = |x: i64, y: i64, c: usize| -> f32 {
        if x < 0 || y < 0 || x >= width as i64 || y >= height as i64 {
            BACKGROUND[c]
        } else {
            rgb[(y as usize * width + x as usize) * 3 + c]
        }
    };
    let bilinear = |x: f32, y: f32, out: &mut [f32; 3]| {
        let (fx, fy) = (x - 0.5, y - 0.5);
        let (ix, iy) = (fx.floor(), fy.floor());
        let (tx, ty) = (fx - ix, fy - iy);
        let (ix, iy) = (ix as i64, iy as i64);
        for (c, o) in out.iter_mut().enumerate() {
            *o += (1.0 - ty) * ((1.0 - tx) * texel(ix, iy, c) + tx * texel(ix + 1, iy, c))
                + ty * ((1.0 - tx) * texel(ix, iy + 1, c) + tx * texel(ix + 1, iy + 1, c));
        }
    };
    let inv = 1.0 / (k * k) as f32;
    let mut out = vec![0.0; size * size * 3];
    for j in 0..size {
        for i in 0..size {
            let mut acc = [0.0f32; 3];
            for a in 0..k {
                for bb in 0..k {
                    let x = x0 + (i as f32 + (bb as f32 + 0.5) / k as f32) * step;
                    let y = y0 + (j as f32 + (a as f32 + 0.5) / k as f32) * step;
                    bilinear(x, y, &mut acc);
                }
            }
            let o = (j * size + i) * 3;
            for c in 0..3 {
                out[o + c] = acc[c] * inv;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_box_holds_the_projected_points() {
        let mut w2c = [[0.0; 4]; 4];
        for (i, row) in w2c.iter_mut().enumerate() {
            row[i] = 1.0;
        }
        w2c[2][3] = 2.0; // the camera 2 units in front of the origin
        let cam = Camera {
            width: 100,
            height: 80,
            fx: 100.0,
            fy: 100.0,
            cx: 50.0,
            cy: 40.0,
            world_to_camera: w2c,
        };
        // At depth 2: x = ±0.2 -> u = 50 ± 10; y = -0.1..0.3 -> v = 35..55.
        let v = [[-0.2, -0.1, 0.0], [0.2, 0.3, 0.0], [0.0, 0.0, -5.0]];
        let b = head_box(&cam, &v).expect("in front");
        assert!(
            (b.cx - 50.0).abs() < 1e-4 && (b.cy - 45.0).abs() < 1e-4,
            "{b:?}"
        );
        assert!((b.side - 20.0 * MARGIN).abs() < 1e-4, "{b:?}");
        assert!(head_box(&cam, &[[0.0, 0.0, -3.0]]).is_none());
    }

    #[test]
    fn an_aligned_crop_copies_pixels_and_pads_with_the_background() {
        // 4 x 3 image with distinct values; a 2x2 box on pixel centres (1..3, 0..2) at
        // size 2 reads pixels (1, 0), (2, 0), (1, 1), (2, 1) exactly.
        let (w, h) = (4, 3);
        let rgb: Vec<f32> = (0..w * h * 3).map(|i| i as f32 / 100.0).collect();
        let b = SquareBox {
            cx: 2.0,
            cy: 1.0,
            side: 2.0,
        };
        let c = crop(&rgb, w, h, &b, 2);
        let px = |x: usize, y: usize| &rgb[(y * w + x) * 3..(y * w + x) * 3 + 3];
        assert_eq!(&c[0..3], px(1, 0));
        assert_eq!(&c[3..6], px(2, 0));
        assert_eq!(&c[6..9], px(1, 1));
        assert_eq!(&c[9..12], px(2, 1));
        // Far outside: the background.
        let out = crop(
            &rgb,
            w,
            h,
            &SquareBox {
                cx: -50.0,
                cy: -50.0,
                side: 2.0,
            },
            2,
        );
        assert!(out.chunks(3).all(|p| p == BACKGROUND));
        // Shrinking by 2: each output pixel is the mean of a 2x2 block.
        let b = SquareBox {
            cx: 2.0,
            cy: 2.0,
            side: 4.0,
        };
        let c = crop(&rgb, w, h, &b, 2);
        let mean = |xs: [(usize, usize); 4], ch: usize| {
            xs.iter().map(|&(x, y)| px(x, y)[ch]).sum::<f32>() / 4.0
        };
        assert!(
            (c[0] - mean([(0, 0), (1, 0), (0, 1), (1, 1)], 0)).abs() < 1e-6,
            "{}",
            c[0]
        );
    }
}
