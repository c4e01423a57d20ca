//! A CPU triangle rasterizer with a z-buffer, for the synthetic ground truth.
//!
//! Pixel centres at `(x + 0.5, y + 0.5)`, the camera's OpenCV convention (`u = fx x / z + cx`).
//! Per pixel it keeps the nearest face, its camera depth and perspective-correct
//! barycentrics (so UVs and other attributes interpolate correctly under perspective). Both
//! windings are drawn. Triangles with a vertex at or behind [`NEAR`] are skipped (no
//! clipping): the synthetic cameras look at a head well in front of them.

use rayon::prelude::*;

use crate::camera::Camera;

/// Nearest depth drawn.
pub const NEAR: f32 = 1e-3;

/// What the rasterizer leaves per pixel (row-major, `width x height`).
#[derive(Clone, Debug, PartialEq)]
pub struct Fragments {
    pub width: usize,
    pub height: usize,
    /// Camera depth; `f32::INFINITY` where nothing was drawn.
    pub depth: Vec<f32>,
    /// The face drawn; `None` where nothing was drawn.
    pub face: Vec<Option<u32>>,
    /// Perspective-correct barycentrics of the pixel centre in its face.
    pub bary: Vec<[f32; 3]>,
}

/// How many faces a rasterized image shows and how many pixels they cover.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Coverage {
    /// Faces drawn at one pixel or more (the visible faces).
    pub visible_faces: u64,
    /// Pixels some face covers.
    pub covered_pixels: u64,
}

impl Coverage {
    /// Pixels per visible face: `covered_pixels / visible_faces` (0 when nothing is drawn).
    pub fn pixels_per_face(&self) -> f64 {
        if self.visible_faces == 0 {
            0.0
        } else {
            self.covered_pixels as f64 / self.visible_faces as f64
        }
    }
}

impl Fragments {
    /// The visible faces and the pixels they cover.
    pub fn coverage(&self) -> Coverage {
        let mut seen = std::collections::HashSet::new();
        let mut covered = 0;
        for f in self.face.iter().flatten() {
            covered += 1;
            seen.insert(*f);
        }
        Coverage {
            visible_faces: seen.len() as u64,
            covered_pixels: covered,
        }
    }

    /// Interpolates a per-vertex attribute at every covered pixel.
    pub fn interpolate<const C: usize>(
        &self,
        faces: &[[u32; 3]],
        attribute: &[[f32; C]],
    ) -> Vec<Option<[f32; C]>> {
        self.face
            .iter()
            .zip(&self.bary)
            .map(|(f, b)| {
                f.map(|f| {
                    let v = faces[f as usize];
                    std::array::from_fn(|c| {
                        (0..3)
                            .map(|k| b[k] * attribute[v[k] as usize][c])
                            .sum::<f32>()
                    })
                })
            })
            .collect()
    }
}

/// Rasterizes `faces` of `vertices` (world space) seen by `camera`.
pub fn rasterize(camera: &Camera, vertices: &[[f32; 3]], faces: &[[u32; 3]]) -> Fragments {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let m = camera.world_to_camera;
    // Camera-space vertices and their projections.
    let cam: Vec<[f32; 3]> = vertices
        .iter()
        .map(|p| std::array::from_fn(|i| (0..3).map(|k| m[i][k] * p[k]).sum::<f32>() + m[i][3]))
        .collect();
    let screen: Vec<[f32; 2]> = cam
        .iter()
        .map(|p| {
            [
                camera.fx * p[0] / p[2] + camera.cx,
                camera.fy * p[1] / p[2] + camera.cy,
            ]
        })
        .collect();
    // Faces bucketed by the rows they touch, so rows rasterize in parallel.
    let mut rows: Vec<Vec<u32>> = vec![Vec::new(); h];
    for (f, v) in faces.iter().enumerate() {
        // Also skips NaN depths.
        if !v.iter().all(|&i| cam[i as usize][2] > NEAR) {
            continue;
        }
        let ys = v.map(|i| screen[i as usize][1]);
        let lo = (ys.iter().copied().fold(f32::INFINITY, f32::min) - 0.5)
            .ceil()
            .max(0.0);
        let hi = (ys.iter().copied().fold(f32::NEG_INFINITY, f32::max) - 0.5).floor();
        if lo.partial_cmp(&hi).is_none_or(|o| o.is_gt()) || !hi.is_finite() {
            continue;
        }
        for row in rows
            .iter_mut()
            .take((hi as usize + 1).min(h))
            .skip(lo as usize)
        {
            row.push(f as u32);
        }
    }
    type Row = (Vec<f32>, Vec<Option<u32>>, Vec<[f32; 3]>);
    let per_row: Vec<Row> = rows
        .par_iter()
        .enumerate()
        .map(|(y, row_faces)| {
            let mut depth = vec![f32::INFINITY; w];
            let mut face = vec![None; w];
            let mut bary = vec![[0.0f32; 3]; w];
            let py = y as f32 + 0.5;
            for &f in row_faces {
                let v = faces[f as usize];
                let [a, b, c] = v.map(|i| screen[i as usize]);
                let z = v.map(|i| cam[i as usize][2]);
                let area = (b[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (b[1] - a[1]);
                if area == 0.0 || !area.is_finite() {
                    continue;
                }
                let xs = [a[0], b[0], c[0]];
                let lo = (xs.iter().copied().fold(f32::INFINITY, f32::min) - 0.5)
                    .ceil()
                    .max(0.0);
                let hi = (xs.iter().copied().fold(f32::NEG_INFINITY, f32::max) - 0.5)
                    .floor()
                    .min(w as f32 - 1.0);
                if lo.partial_cmp(&hi).is_none_or(|o| o.is_gt()) {
                    continue;
                }
                for x in lo as usize..=hi as usize {
                    let px = x as f32 + 0.5;
                    let w0 = ((b[0] - px) * (c[1] - py) - (c[0] - px) * (b[1] - py)) / area;
                    let w1 = ((c[0] - px) * (a[1] - py) - (a[0] - px) * (c[1] - py)) / area;
                    let w2 = 1.0 - w0 - w1;
                    if w0 < 0.0 || w1 < 0.0 || w2 < 0.0 {
                        continue;
                    }
                    // Perspective-correct: interpolate 1/z in screen space.
                    let inv = [w0 / z[0], w1 / z[1], w2 / z[2]];
                    let s = inv[0] + inv[1] + inv[2];
                    let d = 1.0 / s;
                    if d < depth[x] {
                        depth[x] = d;
                        face[x] = Some(f);
                        bary[x] = inv.map(|v| v / s);
                    }
                }
            }
            (depth, face, bary)
        })
        .collect();
    let mut out = Fragments {
        width: w,
        height: h,
        depth: Vec::with_capacity(w * h),
        face: Vec::with_capacity(w * h),
        bary: Vec::with_capacity(w * h),
    };
    for (d, f, b) in per_row {
        out.depth.extend(d);
        out.face.extend(f);
        out.bary.extend(b);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// 20x20 image, f = 10, principal point at the centre, camera at the origin looking +z.
    fn camera() -> Camera {
        Camera {
            width: 20,
            height: 20,
            fx: 10.0,
            fy: 10.0,
            cx: 10.0,
            cy: 10.0,
            world_to_camera: [
                [1.0, 0.0, 0.0, 0.0],
                [0.0, 1.0, 0.0, 0.0],
                [0.0, 0.0, 1.0, 0.0],
                [0.0, 0.0, 0.0, 1.0],
            ],
        }
    }

    /// A square at depth `z` spanning [-s, s]^2 in x and y (two triangles).
    fn square(z: f32, s: f32, base: u32) -> (Vec<[f32; 3]>, Vec<[u32; 3]>) {
        (
            vec![[-s, -s, z], [s, -s, z], [s, s, z], [-s, s, z]],
            vec![[base, base + 1, base + 2], [base, base + 2, base + 3]],
        )
    }

    #[test]
    fn known_depth_fills_known_pixels() {
        // At depth 2 with f = 10, x in [-0.4, 0.4] maps to u in [8, 12]: pixels 8..=11.
        let (v, f) = square(2.0, 0.4, 0);
        let r = rasterize(&camera(), &v, &f);
        for y in 0..20 {
            for x in 0..20 {
                let i = y * 20 + x;
                let inside = (8..12).contains(&x) && (8..12).contains(&y);
                assert_eq!(r.face[i].is_some(), inside, "pixel ({x}, {y})");
                if inside {
                    assert!((r.depth[i] - 2.0).abs() < 1e-5);
                } else {
                    assert!(r.depth[i].is_infinite());
                }
            }
        }
    }

    #[test]
    fn coverage_counts_visible_faces_and_their_pixels() {
        // The square of `known_depth_fills_known_pixels`: two faces over 4 x 4 pixels.
        let (v, f) = square(2.0, 0.4, 0);
        let c = rasterize(&camera(), &v, &f).coverage();
        assert_eq!(
            c,
            Coverage {
                visible_faces: 2,
                covered_pixels: 16
            }
        );
        assert_eq!(c.pixels_per_face(), 8.0);
        // A face hidden behind the near square is not visible; nothing drawn gives zero.
        let (far_v, far_f) = square(3.0, 0.2, 0);
        let hidden = [v.clone(), far_v].concat();
        let faces = [f.clone(), far_f.iter().map(|t| t.map(|i| i + 4)).collect()].concat();
        assert_eq!(
            rasterize(&camera(), &hidden, &faces)
                .coverage()
                .visible_faces,
            2
        );
        let behind: Vec<[f32; 3]> = v.iter().map(|p| [p[0], p[1], -2.0]).collect();
        let none = rasterize(&camera(), &behind, &f).coverage();
        assert_eq!((none.visible_faces, none.pixels_per_face()), (0, 0.0));
    }

    #[test]
    fn nearer_surfaces_occlude_in_any_order() {
        let (far_v, far_f) = square(3.0, 0.9, 0);
        let (near_v, near_f) = square(2.0, 0.4, 0);
        let shift = |f: &[[u32; 3]]| f.iter().map(|t| t.map(|i| i + 4)).collect::<Vec<_>>();
        let far_first = (
            [far_v.clone(), near_v.clone()].concat(),
            [far_f.clone(), shift(&near_f)].concat(),
        );
        let near_first = ([near_v, far_v].concat(), [near_f, shift(&far_f)].concat());
        for (label, (v, f)) in [("far first", far_first), ("near first", near_first)] {
            let r = rasterize(&camera(), &v, &f);
            // Centre pixel: the near square (depth 2); pixel (7, 10): only the far one.
            assert!((r.depth[10 * 20 + 10] - 2.0).abs() < 1e-5, "{label}");
            assert!((r.depth[10 * 20 + 7] - 3.0).abs() < 1e-5, "{label}");
        }
    }

    #[test]
    fn barycentrics_are_perspective_correct() {
        // A plane slanted in depth: z = 2 + x. Interpolating world x at a pixel must give the
        // x where that pixel's ray meets the plane: x = (u - cx) / f * z, z = 2 + x.
        let v = vec![
            [-0.5, -0.5, 1.5],
            [0.5, -0.5, 2.5],
            [0.5, 0.5, 2.5],
            [-0.5, 0.5, 1.5],
        ];
        let f = vec![[0, 1, 2], [0, 2, 3]];
        let r = rasterize(&camera(), &v, &f);
        let xs: Vec<[f32; 1]> = v.iter().map(|p| [p[0]]).collect();
        let interp = r.interpolate(&f, &xs);
        let y = 10;
        for x in 0..20 {
            let i = y * 20 + x;
            if let Some([wx]) = interp[i] {
                let t = (x as f32 + 0.5 - 10.0) / 10.0;
                // x = t z = t (2 + x)  =>  x = 2 t / (1 - t).
                let want = 2.0 * t / (1.0 - t);
                assert!((wx - want).abs() < 1e-4, "pixel {x}: {wx} vs {want}");
                assert!((r.depth[i] - (2.0 + want)).abs() < 1e-4);
            }
        }
        assert!(
            interp[y * 20..(y + 1) * 20]
                .iter()
                .filter(|v| v.is_some())
                .count()
                > 3
        );
    }
}
