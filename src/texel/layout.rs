//! UV layout maps: which face covers each texel centre, with its vertices and barycentrics.
//!
//! # Axis convention
//! Texel `(i, j)` of an `R x R` map has its centre at `uv = ((i + 0.5) / R, (j + 0.5) / R)`:
//! column `i` runs along `u`, row `j` along `v`, and maps are stored row-major with index
//! `j * R + i`. OBJ's `v` points up, so row 0 is the *bottom* of the texture; this matches
//! `grid_sample`, where `y = -1` reads row 0. Images written for people (`uv inspect`) are
//! flipped vertically so that they look like the texture (`v` up). The sample grid uses the
//! same convention: a sample at grid `(x, y)` sits at `uv = ((x + 1) / 2, (y + 1) / 2)`.

use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::mesh::UvMesh;

/// Per-point coverage of a regular grid of UV points by the mesh's UV triangles.
#[derive(Clone, Debug, PartialEq)]
pub struct Coverage {
    /// Covering face per point; `None` where no face covers it.
    pub face: Vec<Option<u32>>,
    /// Barycentrics of the point in its face (zero where uncovered).
    pub bary: Vec<[f32; 3]>,
}

/// Finds, for every point `uv = (origin + i * step, origin + j * step)`, `i, j < n`
/// (index `j * n + i`), the lowest-index face whose UV triangle contains it (edges
/// included) and its barycentrics. Faces with a zero-area UV triangle cover nothing.
pub fn coverage(mesh: &UvMesh, n: usize, origin: f64, step: f64) -> Coverage {
    // Rows are independent: each row finds its covering faces by scanning the faces whose
    // v-range contains it, lowest index first.
    let tri_uv = |f: usize| -> [[f64; 2]; 3] {
        mesh.uv_faces[f].map(|t| {
            let uv = mesh.uvs[t as usize];
            [uv[0] as f64, uv[1] as f64]
        })
    };
    // Faces bucketed by the rows they may touch.
    let mut rows: Vec<Vec<u32>> = vec![Vec::new(); n];
    for f in 0..mesh.faces.len() {
        let t = tri_uv(f);
        let (lo, hi) = t
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| {
                (lo.min(p[1]), hi.max(p[1]))
            });
        let j0 = ((lo - origin) / step).ceil().max(0.0);
        let j1 = ((hi - origin) / step).floor().min(n as f64 - 1.0);
        // Also skips NaN bounds.
        if j0.partial_cmp(&j1).is_none_or(|o| o.is_gt()) {
            continue;
        }
        for row in rows.iter_mut().take(j1 as usize + 1).skip(j0 as usize) {
            row.push(f as u32);
        }
    }
    type Row = (Vec<Option<u32>>, Vec<[f32; 3]>);
    let per_row: Vec<Row> = rows
        .par_iter()
        .enumerate()
        .map(|(j, faces)| {
            let v = origin + j as f64 * step;
            let mut face = vec![None; n];
            let mut bary = vec![[0.0f32; 3]; n];
            for &f in faces {
                let [a, b, c] = tri_uv(f as usize);
                let area = (b[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (b[1] - a[1]);
                if area == 0.0 || !area.is_finite() {
                    continue;
                }
                let (lo, hi) = [a[0], b[0], c[0]]
                    .iter()
                    .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &x| {
                        (lo.min(x), hi.max(x))
                    });
                let i0 = ((lo - origin) / step).ceil().max(0.0);
                let i1 = ((hi - origin) / step).floor().min(n as f64 - 1.0);
                if i0.partial_cmp(&i1).is_none_or(|o| o.is_gt()) {
                    continue;
                }
                for i in i0 as usize..=i1 as usize {
                    if face[i].is_some() {
                        continue;
                    }
                    let u = origin + i as f64 * step;
                    // Edge functions, normalised by the signed area: the barycentrics.
                    let w0 = ((b[0] - u) * (c[1] - v) - (c[0] - u) * (b[1] - v)) / area;
                    let w1 = ((c[0] - u) * (a[1] - v) - (a[0] - u) * (c[1] - v)) / area;
                    let w2 = 1.0 - w0 - w1;
                    if w0 >= 0.0 && w1 >= 0.0 && w2 >= 0.0 {
                        face[i] = Some(f);
                        bary[i] = [w0 as f32, w1 as f32, w2 as f32];
                    }
                }
            }
            (face, bary)
        })
        .collect();
    let mut out = Coverage {
        face: Vec::with_capacity(n * n),
        bary: Vec::with_capacity(n * n),
    };
    for (f, b) in per_row {
        out.face.extend(f);
        out.bary.extend(b);
    }
    out
}

/// The UV layout of a topology at resolution `R`, computed once.
///
/// # Shapes
/// - `face`, `bary`: [R * R] (row-major, see the module doc)
/// - `verts`: [R * R] the covering face's three position indices (zero where invalid)
#[derive(Clone, Debug, PartialEq)]
pub struct UvLayout {
    pub res: usize,
    pub face: Vec<Option<u32>>,
    pub verts: Vec<[u32; 3]>,
    pub bary: Vec<[f32; 3]>,
}

impl UvLayout {
    /// Covers the `res x res` texel centres with `mesh`'s UV triangles.
    pub fn new(mesh: &UvMesh, res: usize) -> Result<Self> {
        if res == 0 {
            return Err(Error::invalid("uv layout", "res", "must be at least 1"));
        }
        let c = coverage(mesh, res, 0.5 / res as f64, 1.0 / res as f64);
        let verts = c
            .face
            .iter()
            .map(|f| f.map_or([0; 3], |f| mesh.faces[f as usize]))
            .collect();
        Ok(UvLayout {
            res,
            face: c.face,
            verts,
            bary: c.bary,
        })
    }

    /// 1.0 where a face covers the texel, else 0.0.
    pub fn validity(&self) -> Vec<f32> {
        self.face
            .iter()
            .map(|f| f32::from(u8::from(f.is_some())))
            .collect()
    }

    /// Number of covered texels.
    pub fn valid_count(&self) -> usize {
        self.face.iter().filter(|f| f.is_some()).count()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One triangle per entry, UVs given, positions irrelevant.
    fn uv_mesh(tris: &[[[f32; 2]; 3]]) -> UvMesh {
        let mut m = UvMesh::default();
        for (f, t) in tris.iter().enumerate() {
            for uv in t {
                m.uvs.push(*uv);
                m.positions.push([uv[0], uv[1], 0.0]);
            }
            let b = 3 * f as u32;
            m.faces.push([b, b + 1, b + 2]);
            m.uv_faces.push([b, b + 1, b + 2]);
        }
        m
    }

    /// OBJ's v points up, and row j of a map holds v = (j + 0.5) / R: a triangle in the
    /// top-left corner of the texture (small u, large v) covers high rows and low columns.
    #[test]
    fn uv_axis_convention() {
        let m = uv_mesh(&[[[0.0, 1.0], [0.0, 0.5], [0.5, 1.0]]]);
        let l = UvLayout::new(&m, 8).expect("layout");
        let covered: Vec<(usize, usize)> = (0..64)
            .filter(|&t| l.face[t].is_some())
            .map(|t| (t % 8, t / 8))
            .collect();
        assert!(!covered.is_empty());
        assert!(covered.iter().all(|&(i, j)| i < 4 && j >= 4), "{covered:?}");
        // The texel centre (0.0625, 0.9375) is texel (0, 7).
        assert_eq!(l.face[7 * 8], Some(0));
        let b = l.bary[7 * 8];
        let uv: Vec<f32> = (0..2)
            .map(|c| b[0] * [0.0, 1.0][c] + b[1] * [0.0, 0.5][c] + b[2] * [0.5, 1.0][c])
            .collect();
        assert!((uv[0] - 0.0625).abs() < 1e-6 && (uv[1] - 0.9375).abs() < 1e-6);
    }

    #[test]
    fn lowest_face_index_wins_on_overlap() {
        let big = [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]];
        let m = uv_mesh(&[[[0.0, 0.0], [0.6, 0.0], [0.0, 0.6]], big]);
        let l = UvLayout::new(&m, 16).expect("layout");
        // Texel (1, 1) at uv (0.09, 0.09) lies in both: face 0.
        assert_eq!(l.face[16 + 1], Some(0));
        // Texel (10, 2) lies only in the big one.
        assert_eq!(l.face[2 * 16 + 10], Some(1));
        // Texel (15, 15) in neither.
        assert_eq!(l.face[255], None);
        // Swapping the order flips the winner.
        let m2 = uv_mesh(&[big, [[0.0, 0.0], [0.6, 0.0], [0.0, 0.6]]]);
        assert_eq!(UvLayout::new(&m2, 16).expect("layout").face[17], Some(0));
    }
}
