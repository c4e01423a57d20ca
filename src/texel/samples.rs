//! The S x S sample grid: one Gaussian per kept sample.
//!
//! Samples sit at `linspace(-1, 1, S)` on both axes and read the `R x R` texel maps with
//! bilinear interpolation, `align_corners = False` and zero padding (`grid_sample`'s
//! defaults): grid `x` maps to the continuous texel column `((x + 1) R - 1) / 2`. A sample
//! is kept when the bilinearly sampled validity exceeds [`KEEP_VALIDITY`]. Order: row-major
//! over the grid, `y` (that is `v`) outer.

use crate::error::{Error, Result};
use crate::mesh::UvMesh;
use crate::texel::layout::{UvLayout, coverage};

/// A sample is kept when its bilinearly sampled validity exceeds this (the paper's 0.99):
/// samples straddling the layout's border would blend in undefined texels.
pub const KEEP_VALIDITY: f32 = 0.99;

/// Kept samples with their bilinear taps into the texel maps, and, for the "w/o Global UV"
/// ablation, the face each sample falls in.
///
/// # Shapes
/// - `grid_index`: `[N]` index `b * S + a` of the sample in the full grid
/// - `uv`: `[N]`
/// - `taps`: [N, 4] texel indices (`j * R + i`) of the 4 neighbours: (i0, j0), (i0+1, j0),
///   (i0, j0+1), (i0+1, j0+1); taps outside the map have weight 0 and index 0
/// - `weights`: [N, 4] bilinear weights
/// - `face`, `bary`: `[N]` the face containing the sample's UV point (lowest index wins) and
///   its barycentrics; where no face contains the point (kept samples at the layout's
///   border), the face of the heaviest valid tap with barycentrics extrapolated to the point
#[derive(Clone, Debug, PartialEq)]
pub struct SampleGrid {
    pub size: usize,
    pub res: usize,
    pub grid_index: Vec<u32>,
    pub uv: Vec<[f32; 2]>,
    pub taps: Vec<[u32; 4]>,
    pub weights: Vec<[f32; 4]>,
    pub face: Vec<u32>,
    pub bary: Vec<[f32; 3]>,
}

/// `linspace(-1, 1, s)[k]` (torch's: a single point is -1).
fn linspace(k: usize, s: usize) -> f64 {
    if s == 1 {
        -1.0
    } else {
        -1.0 + 2.0 * k as f64 / (s - 1) as f64
    }
}

/// Bilinear taps at grid coordinate `(gx, gy)` on an `r x r` map.
pub fn bilinear_taps(gx: f64, gy: f64, r: usize) -> ([u32; 4], [f32; 4]) {
    let ix = ((gx + 1.0) * r as f64 - 1.0) / 2.0;
    let iy = ((gy + 1.0) * r as f64 - 1.0) / 2.0;
    let (x0, y0) = (ix.floor(), iy.floor());
    let (fx, fy) = (ix - x0, iy - y0);
    let mut taps = [0u32; 4];
    let mut weights = [0.0f32; 4];
    for (k, (dx, dy)) in [(0, 0), (1, 0), (0, 1), (1, 1)].into_iter().enumerate() {
        let (x, y) = (x0 + dx as f64, y0 + dy as f64);
        let w = if dx == 1 { fx } else { 1.0 - fx } * if dy == 1 { fy } else { 1.0 - fy };
        if x >= 0.0 && y >= 0.0 && x < r as f64 && y < r as f64 {
            taps[k] = (y as usize * r + x as usize) as u32;
            weights[k] = w as f32;
        }
    }
    (taps, weights)
}

impl SampleGrid {
    /// The kept samples of an `size x size` grid over `layout`.
    pub fn new(mesh: &UvMesh, layout: &UvLayout, size: usize) -> Result<Self> {
        if size == 0 {
            return Err(Error::invalid("sample grid", "size", "must be at least 1"));
        }
        let r = layout.res;
        let validity = layout.validity();
        // Sample points in UV: u = (x + 1) / 2, a regular grid from 0 with step 1/(S-1).
        let step = if size == 1 {
            1.0
        } else {
            1.0 / (size - 1) as f64
        };
        let at_sample = coverage(mesh, size, 0.0, step);
        let mut g = SampleGrid {
            size,
            res: r,
            grid_index: Vec::new(),
            uv: Vec::new(),
            taps: Vec::new(),
            weights: Vec::new(),
            face: Vec::new(),
            bary: Vec::new(),
        };
        for b in 0..size {
            let gy = linspace(b, size);
            for a in 0..size {
                let gx = linspace(a, size);
                let (taps, weights) = bilinear_taps(gx, gy, r);
                let valid: f32 = taps
                    .iter()
                    .zip(&weights)
                    .map(|(&t, &w)| w * validity[t as usize])
                    .sum();
                if valid <= KEEP_VALIDITY {
                    continue;
                }
                let k = b * size + a;
                let uv = [((gx + 1.0) / 2.0) as f32, ((gy + 1.0) / 2.0) as f32];
                let (face, bary) = match at_sample.face[k] {
                    Some(f) => (f, at_sample.bary[k]),
                    None => {
                        // The heaviest valid tap's face, barycentrics extrapolated.
                        let best = (0..4)
                            .filter(|&q| {
                                layout.face[taps[q] as usize].is_some() && weights[q] > 0.0
                            })
                            .max_by(|&p, &q| weights[p].total_cmp(&weights[q]))
                            .and_then(|q| layout.face[taps[q] as usize])
                            .ok_or_else(|| {
                                Error::invalid(
                                    "sample grid",
                                    "validity",
                                    "kept sample with no valid tap",
                                )
                            })?;
                        (best, extrapolated_bary(mesh, best, uv))
                    }
                };
                g.grid_index.push(k as u32);
                g.uv.push(uv);
                g.taps.push(taps);
                g.weights.push(weights);
                g.face.push(face);
                g.bary.push(bary);
            }
        }
        Ok(g)
    }

    /// Number of kept samples (Gaussians).
    pub fn len(&self) -> usize {
        self.grid_index.len()
    }

    /// True when no sample is kept.
    pub fn is_empty(&self) -> bool {
        self.grid_index.is_empty()
    }
}

/// Barycentrics of `uv` with respect to face `f`'s UV triangle (any sign).
fn extrapolated_bary(mesh: &UvMesh, f: u32, uv: [f32; 2]) -> [f32; 3] {
    let [a, b, c] = mesh.uv_faces[f as usize].map(|t| {
        let p = mesh.uvs[t as usize];
        [p[0] as f64, p[1] as f64]
    });
    let (u, v) = (uv[0] as f64, uv[1] as f64);
    let area = (b[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (b[1] - a[1]);
    if area == 0.0 {
        return [1.0 / 3.0; 3];
    }
    let w0 = ((b[0] - u) * (c[1] - v) - (c[0] - u) * (b[1] - v)) / area;
    let w1 = ((c[0] - u) * (a[1] - v) - (a[0] - u) * (c[1] - v)) / area;
    [w0 as f32, w1 as f32, (1.0 - w0 - w1) as f32]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// grid_sample(align_corners=False) at the corners and centre of a 4x4 map.
    #[test]
    fn taps_follow_grid_sample() {
        // x = -1: continuous column -0.5, half of it outside (zero padding).
        let (t, w) = bilinear_taps(-1.0, -1.0, 4);
        assert_eq!(t[3], 0);
        assert_eq!(w, [0.0, 0.0, 0.0, 0.25]);
        // Centre: column 1.5, row 1.5.
        let (t, w) = bilinear_taps(0.0, 0.0, 4);
        assert_eq!(t, [5, 6, 9, 10]);
        assert_eq!(w, [0.25; 4]);
        // x = -0.75 hits the centre of column 0 exactly.
        let (t, w) = bilinear_taps(-0.75, -0.75, 4);
        assert_eq!((t[0], w[0]), (0, 1.0));
    }

    #[test]
    fn samples_need_valid_neighbourhoods() {
        // One triangle covering the lower-left half of UV space.
        let m = UvMesh {
            uvs: vec![[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]],
            positions: vec![[0.0; 3]; 3],
            faces: vec![[0, 1, 2]],
            uv_faces: vec![[0, 1, 2]],
        };
        let layout = UvLayout::new(&m, 16).expect("layout");
        let g = SampleGrid::new(&m, &layout, 16).expect("grid");
        assert!(!g.is_empty() && g.len() < 16 * 16 / 2);
        let v = layout.validity();
        for k in 0..g.len() {
            let s: f32 = (0..4)
                .map(|q| g.weights[k][q] * v[g.taps[k][q] as usize])
                .sum();
            assert!(s > KEEP_VALIDITY);
            assert_eq!(g.face[k], 0);
            let uv = g.uv[k];
            let b = g.bary[k];
            assert!((b[1] - uv[0]).abs() < 1e-5 && (b[2] - uv[1]).abs() < 1e-5);
        }
    }
}
