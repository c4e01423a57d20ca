//! Errors per region of the face: where an avatar's error lies, so that a difference between
//! two avatars can be traced to the part of the method that should cause it.
//!
//! Every scored image's pixels are labelled by the face of the posed mesh (the frame's
//! tracked or refined vertices, those the avatar is driven with) that covers them
//! ([`crate::mesh::raster::rasterize`]), and each face belongs to regions:
//!
//! | region | pixels |
//! |---|---|
//! | `all` | the whole image (what PSNR scores) |
//! | `background` | no face covers them (floaters, missing hair, silhouette errors) |
//! | `skin` | faces outside the mouth and eyes sets |
//! | `mouth` | faces touching the `lips`, `teeth_*` or `tongue` vertex sets ([`HeadMeta`](crate::head::HeadMeta)) |
//! | `eyes` | faces touching the `eye_l` or `eye_r` sets |
//! | `stretched` | the tenth of the faces most stretched against the subject's neutral head |
//! | `creases` | the tenth of the faces whose frame jumps most to a neighbour's |
//!
//! - *stretched*: the face's strain `max |ln σ|` over the singular values σ of its in-plane
//!   deformation from the subject's neutral mesh (zero expression and pose) to the frame's,
//!   from the two triangles' first fundamental forms (eigenvalues of `G_rest⁻¹ G_posed` are
//!   σ²). The deformations a similarity `k R` cannot follow and the Jacobian `J_F` does
//!   (method.md §4, "w/o Jacobian").
//! - *creases*: the largest relative jump `‖J_F − J_G‖ / ‖J_F‖` (Frobenius) to an
//!   edge-neighbour G, with `J_F = [e1 | e2 | n / sqrt|n|]` of the posed face (method.md
//!   §4): where piecewise frames are most discontinuous, what Global UV's blending across
//!   borders smooths ("w/o Global UV").
//!
//! - *shear* (not a region; `triangles` in `metrics.json`): the face's `ln(σ1 / σ2)`, its
//!   principal stretches' log ratio against the neutral head: zero for a similarity (which
//!   `k R` follows exactly), and the log of the aspect change only the Jacobian follows. Its
//!   distribution over the covered pixels says how much the Jacobian can change an image.
//!
//! Both tenths are taken over all faces of the frame (the 90th percentile of the frame's
//! values; a face stretched by less than [`MIN_STRAIN`] is never `stretched`), fixed before
//! any score was seen. Regions may overlap (`stretched`, `creases`
//! cut across the others). A region's PSNR is that of its pixels' squared error pooled over
//! the split's images; `error_share` is its part of the split's total squared error, to read
//! against `pixel_share`.

use std::collections::{BTreeMap, HashMap};

use serde::{Deserialize, Serialize};

use crate::camera::Camera;
use crate::error::Result;
use crate::head::{HeadAsset, HeadPose, lbs};
pub use crate::mesh::raster::Coverage;

/// The regions, in report order.
pub const REGIONS: [&str; 7] = [
    "all",
    "background",
    "skin",
    "mouth",
    "eyes",
    "stretched",
    "creases",
];

/// The share of faces in `stretched` and in `creases` (the top tenth).
pub const TOP_SHARE: f64 = 0.1;
/// A face stretched by less than 1 % (`max |ln σ|` < 0.01) is not `stretched`, top tenth or
/// not (at the neutral pose nothing is).
pub const MIN_STRAIN: f64 = 0.01;

/// Width of a [`ShearHistogram`] bin (`ln(σ1 / σ2)`).
pub const SHEAR_BIN: f64 = 0.005;
/// Bins of a [`ShearHistogram`]; the last one is open (shears of 2 and more).
const SHEAR_BINS: usize = 400;
/// The shear [`TriangleCoverage::shear_over_10pct`] counts pixels above: principal
/// stretches that differ by more than 10 %.
pub const SHEAR_10PCT: f64 = 0.095_310_179_804_324_87; // ln 1.1

const MOUTH_SETS: [&str; 4] = ["lips", "teeth_upper", "teeth_lower", "tongue"];
const EYE_SETS: [&str; 2] = ["eye_l", "eye_r"];

/// Bit of each region in a face's or pixel's mask (the index in [`REGIONS`]).
fn bit(name: &str) -> u8 {
    1 << REGIONS
        .iter()
        .position(|r| *r == name)
        .expect("known region")
}

/// Labels pixels with regions for one subject.
pub struct RegionLabeler {
    faces: Vec<[u32; 3]>,
    /// Static regions (skin, mouth, eyes) of each face.
    face_static: Vec<u8>,
    /// Edge-neighbours of each face.
    neighbours: Vec<Vec<u32>>,
    /// The subject's neutral mesh: first fundamental form `[E, F, G]` of each face.
    rest_metric: Vec<[f64; 3]>,
}

impl RegionLabeler {
    /// For `head`'s mesh and the subject `identity` (shape and static offsets of `neutral`;
    /// its expression and pose are ignored).
    pub fn new(head: &HeadAsset, neutral: &HeadPose) -> Result<Self> {
        let faces = head.mesh.faces.clone();
        let v = head.model.num_vertices();
        let member = |sets: &[&str]| -> Vec<bool> {
            let mut m = vec![false; v];
            for s in sets {
                for (i, x) in head.meta.mask(s, v).into_iter().enumerate() {
                    m[i] |= x;
                }
            }
            m
        };
        let (mouth, eyes) = (member(&MOUTH_SETS), member(&EYE_SETS));
        let touches = |m: &[bool], f: &[u32; 3]| f.iter().any(|&i| m[i as usize]);
        let face_static = faces
            .iter()
            .map(|f| {
                if touches(&eyes, f) {
                    bit("eyes")
                } else if touches(&mouth, f) {
                    bit("mouth")
                } else {
                    bit("skin")
                }
            })
            .collect();
        let mut by_edge: HashMap<(u32, u32), Vec<u32>> = HashMap::new();
        for (k, f) in faces.iter().enumerate() {
            for e in 0..3 {
                let (a, b) = (f[e], f[(e + 1) % 3]);
                by_edge
                    .entry((a.min(b), a.max(b)))
                    .or_default()
                    .push(k as u32);
            }
        }
        let mut neighbours = vec![Vec::new(); faces.len()];
        for fs in by_edge.values() {
            for &a in fs {
                for &b in fs {
                    if a != b {
                        neighbours[a as usize].push(b);
                    }
                }
            }
        }
        let rest = HeadPose {
            shape: neutral.shape.clone(),
            static_offset: neutral.static_offset.clone(),
            ..Default::default()
        };
        let rest_vertices = lbs(&head.model, &rest)?;
        let rest_metric = faces.iter().map(|f| metric(&rest_vertices, f)).collect();
        Ok(RegionLabeler {
            faces,
            face_static,
            neighbours,
            rest_metric,
        })
    }

    /// Region bits of every face for the posed `vertices` ([`REGIONS`] order).
    pub fn face_regions(&self, vertices: &[[f32; 3]]) -> Vec<u8> {
        let strain: Vec<f64> = self
            .faces
            .iter()
            .zip(&self.rest_metric)
            .map(|(f, r)| strain(r, &metric(vertices, f)))
            .collect();
        let jac: Vec<[f64; 9]> = self.faces.iter().map(|f| jacobian(vertices, f)).collect();
        let crease: Vec<f64> = jac
            .iter()
            .zip(&self.neighbours)
            .map(|(j, ns)| {
                let norm = j.iter().map(|x| x * x).sum::<f64>().sqrt();
                ns.iter()
                    .map(|&g| {
                        let d = j.iter().zip(&jac[g as usize]);
                        d.map(|(a, b)| (a - b) * (a - b)).sum::<f64>().sqrt()
                    })
                    .fold(0.0, f64::max)
                    / norm.max(1e-12)
            })
            .collect();
        let (s_cut, c_cut) = (top_cut(&strain), top_cut(&crease));
        self.face_static
            .iter()
            .enumerate()
            .map(|(k, &m)| {
                let mut m = m;
                if strain[k] >= s_cut && strain[k] >= MIN_STRAIN {
                    m |= bit("stretched");
                }
                if crease[k] >= c_cut && crease[k] > 0.0 {
                    m |= bit("creases");
                }
                m
            })
            .collect()
    }

    /// Each face's shear `ln(σ1 / σ2)` for the posed `vertices` (see the module docs; 0 for
    /// a degenerate face).
    pub fn face_shear(&self, vertices: &[[f32; 3]]) -> Vec<f64> {
        self.faces
            .iter()
            .zip(&self.rest_metric)
            .map(|(f, r)| log_stretches(r, &metric(vertices, f)).map_or(0.0, |(a, b)| a - b))
            .collect()
    }

    /// Region bits of every pixel of `camera`'s image `[H * W]`, `all` included, the
    /// image's visible faces and the pixels they cover (pixels per visible triangle), and
    /// its covered pixels by their face's shear.
    pub fn label(
        &self,
        camera: &Camera,
        vertices: &[[f32; 3]],
    ) -> (Vec<u8>, Coverage, ShearHistogram) {
        let per_face = self.face_regions(vertices);
        let shear = self.face_shear(vertices);
        let frags = crate::mesh::raster::rasterize(camera, vertices, &self.faces);
        let mut hist = ShearHistogram::default();
        for f in frags.face.iter().flatten() {
            hist.add(shear[*f as usize]);
        }
        let labels = frags
            .face
            .iter()
            .map(|f| {
                bit("all")
                    | match f {
                        Some(f) => per_face[*f as usize],
                        None => bit("background"),
                    }
            })
            .collect();
        (labels, frags.coverage(), hist)
    }
}

/// First fundamental form `[e1·e1, e1·e2, e2·e2]` of a face.
fn metric(v: &[[f32; 3]], f: &[u32; 3]) -> [f64; 3] {
    let p = f.map(|i| v[i as usize].map(f64::from));
    let e1: [f64; 3] = std::array::from_fn(|a| p[1][a] - p[0][a]);
    let e2: [f64; 3] = std::array::from_fn(|a| p[2][a] - p[0][a]);
    let dot = |a: &[f64; 3], b: &[f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    [dot(&e1, &e1), dot(&e1, &e2), dot(&e2, &e2)]
}

/// `max |ln σ|` of the in-plane deformation between two faces' first fundamental forms
/// (0 for a degenerate face).
fn strain(rest: &[f64; 3], posed: &[f64; 3]) -> f64 {
    log_stretches(rest, posed).map_or(0.0, |(a, b)| a.abs().max(b.abs()))
}

/// `(ln σ1, ln σ2)`, `σ1 ≥ σ2` the principal stretches of the in-plane deformation between
/// two faces' first fundamental forms; `None` for a degenerate face.
fn log_stretches(rest: &[f64; 3], posed: &[f64; 3]) -> Option<(f64, f64)> {
    let [a, b, d] = *rest;
    let det_r = a * d - b * b;
    if det_r.is_nan() || det_r <= 1e-24 {
        return None;
    }
    // M = G_rest⁻¹ G_posed; its eigenvalues are σ².
    let inv = [d / det_r, -b / det_r, a / det_r];
    let [p, q, s] = *posed;
    let m00 = inv[0] * p + inv[1] * q;
    let m01 = inv[0] * q + inv[1] * s;
    let m10 = inv[1] * p + inv[2] * q;
    let m11 = inv[1] * q + inv[2] * s;
    let tr = m00 + m11;
    let det = m00 * m11 - m01 * m10;
    let disc = (tr * tr / 4.0 - det).max(0.0).sqrt();
    let (l1, l2) = (tr / 2.0 + disc, tr / 2.0 - disc);
    if l2.is_nan() || l2 <= 0.0 {
        return None;
    }
    Some((0.5 * l1.ln(), 0.5 * l2.ln()))
}

/// Pixels counted by their face's shear `ln(σ1 / σ2)`, in bins of [`SHEAR_BIN`].
#[derive(Clone, Debug, PartialEq)]
pub struct ShearHistogram(Vec<u64>);

impl Default for ShearHistogram {
    fn default() -> Self {
        ShearHistogram(vec![0; SHEAR_BINS])
    }
}

impl ShearHistogram {
    /// Counts one pixel.
    pub fn add(&mut self, shear: f64) {
        let k = (shear.max(0.0) / SHEAR_BIN) as usize;
        self.0[k.min(SHEAR_BINS - 1)] += 1;
    }

    /// Adds another histogram's counts.
    pub fn merge(&mut self, other: &ShearHistogram) {
        for (a, b) in self.0.iter_mut().zip(&other.0) {
            *a += b;
        }
    }

    /// Pixels counted.
    pub fn count(&self) -> u64 {
        self.0.iter().sum()
    }

    /// The `q` quantile, as the upper edge of its bin (0 when empty).
    pub fn quantile(&self, q: f64) -> f64 {
        let n = self.count();
        if n == 0 {
            return 0.0;
        }
        let want = (q * n as f64).ceil().max(1.0) as u64;
        let mut seen = 0;
        for (k, &c) in self.0.iter().enumerate() {
            seen += c;
            if seen >= want {
                return (k + 1) as f64 * SHEAR_BIN;
            }
        }
        SHEAR_BINS as f64 * SHEAR_BIN
    }

    /// The share of pixels whose bin lies wholly above `x`.
    pub fn share_above(&self, x: f64) -> f64 {
        let n = self.count();
        if n == 0 {
            return 0.0;
        }
        let first = ((x / SHEAR_BIN).ceil() as usize).min(SHEAR_BINS);
        self.0[first..].iter().sum::<u64>() as f64 / n as f64
    }
}

/// `J_F = [e1 | e2 | n / sqrt|n|]` of a posed face, row-major.
fn jacobian(v: &[[f32; 3]], f: &[u32; 3]) -> [f64; 9] {
    let p = f.map(|i| v[i as usize].map(f64::from));
    let e1: [f64; 3] = std::array::from_fn(|a| p[1][a] - p[0][a]);
    let e2: [f64; 3] = std::array::from_fn(|a| p[2][a] - p[0][a]);
    let n = [
        e1[1] * e2[2] - e1[2] * e2[1],
        e1[2] * e2[0] - e1[0] * e2[2],
        e1[0] * e2[1] - e1[1] * e2[0],
    ];
    let s = (n.iter().map(|x| x * x).sum::<f64>().sqrt())
        .sqrt()
        .max(1e-12);
    std::array::from_fn(|k| {
        let (r, c) = (k / 3, k % 3);
        [e1[r], e2[r], n[r] / s][c]
    })
}

/// The value at or above which the top [`TOP_SHARE`] of `values` lie.
fn top_cut(values: &[f64]) -> f64 {
    if values.is_empty() {
        return f64::INFINITY;
    }
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let k = ((v.len() as f64) * (1.0 - TOP_SHARE)).floor() as usize;
    v[k.min(v.len() - 1)]
}

/// One region's pooled error over a split.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct RegionScore {
    /// Pixels over the split's images.
    pub pixels: u64,
    /// Mean squared error per channel.
    pub mse: f64,
    /// `-10 log10(mse)` (dB; `null` for an empty region).
    pub psnr: Option<f64>,
    /// Its pixels' share of the split's pixels.
    pub pixel_share: f64,
    /// Its share of the split's total squared error.
    pub error_share: f64,
}

impl RegionScore {
    /// Its share of the squared error over its share of the pixels (above 1: the error
    /// concentrates here); `None` for a region without pixels.
    pub fn concentration(&self) -> Option<f64> {
        (self.pixel_share > 0.0).then(|| self.error_share / self.pixel_share)
    }
}

/// How large the mesh's triangles are in a split's scored images: what decides how many
/// pixels the per-face parts of the method (the Jacobian, Global UV's blending) can act on.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TriangleCoverage {
    /// Images counted.
    pub images: u64,
    /// Visible faces per image (drawn at one pixel or more), the mean over the images.
    pub visible_faces: f64,
    /// Pixels the mesh covers per image, the mean over the images.
    pub covered_pixels: f64,
    /// Pixels per visible triangle: the covered pixels over the visible faces, pooled over
    /// the images.
    pub pixels_per_triangle: f64,
    /// The covered pixels' face shear `ln(σ1 / σ2)` against the neutral head (the module
    /// docs), pooled over the images: median, 90th and 99th percentile (bin width
    /// [`SHEAR_BIN`]).
    #[serde(default)]
    pub shear_median: f64,
    #[serde(default)]
    pub shear_p90: f64,
    #[serde(default)]
    pub shear_p99: f64,
    /// The share of covered pixels whose face's principal stretches differ by more than
    /// 10 % (`σ1 / σ2 > 1.1`).
    #[serde(default)]
    pub shear_over_10pct: f64,
}

/// Accumulates squared errors per split and region, and the triangles' coverage.
#[derive(Default)]
pub struct RegionTally {
    sums: BTreeMap<String, [(u64, f64); REGIONS.len()]>,
    coverage: BTreeMap<String, (u64, Coverage, ShearHistogram)>,
}

impl RegionTally {
    /// Adds one image: `gt` and `render` `[H * W * 3]`, `labels` `[H * W]` from
    /// [`RegionLabeler::label`].
    pub fn add(&mut self, split: &str, gt: &[f32], render: &[f32], labels: &[u8]) {
        let s = self
            .sums
            .entry(split.to_string())
            .or_insert([(0, 0.0); REGIONS.len()]);
        for (p, &m) in labels.iter().enumerate() {
            let e: f64 = (0..3)
                .map(|c| {
                    let d = f64::from(gt[p * 3 + c].clamp(0.0, 1.0))
                        - f64::from(render[p * 3 + c].clamp(0.0, 1.0));
                    d * d
                })
                .sum();
            for (r, slot) in s.iter_mut().enumerate() {
                if m & (1 << r) != 0 {
                    slot.0 += 1;
                    slot.1 += e;
                }
            }
        }
    }

    /// Adds one image's [`Coverage`] and [`ShearHistogram`] (from [`RegionLabeler::label`]).
    pub fn add_coverage(&mut self, split: &str, c: Coverage, shear: &ShearHistogram) {
        let (n, sum, hist) = self.coverage.entry(split.to_string()).or_default();
        *n += 1;
        sum.visible_faces += c.visible_faces;
        sum.covered_pixels += c.covered_pixels;
        hist.merge(shear);
    }

    /// The triangles' coverage per split.
    pub fn coverage(&self) -> BTreeMap<String, TriangleCoverage> {
        self.coverage
            .iter()
            .map(|(split, (n, sum, hist))| {
                let images = (*n).max(1) as f64;
                let c = TriangleCoverage {
                    images: *n,
                    visible_faces: sum.visible_faces as f64 / images,
                    covered_pixels: sum.covered_pixels as f64 / images,
                    pixels_per_triangle: sum.pixels_per_face(),
                    shear_median: hist.quantile(0.5),
                    shear_p90: hist.quantile(0.9),
                    shear_p99: hist.quantile(0.99),
                    shear_over_10pct: hist.share_above(SHEAR_10PCT),
                };
                (split.clone(), c)
            })
            .collect()
    }

    /// The scores per split and region.
    pub fn scores(&self) -> BTreeMap<String, BTreeMap<String, RegionScore>> {
        self.sums
            .iter()
            .map(|(split, s)| {
                let (all_px, all_err) = s[0];
                let regions = REGIONS
                    .iter()
                    .zip(s)
                    .map(|(name, &(px, err))| {
                        let mse = if px > 0 { err / (3 * px) as f64 } else { 0.0 };
                        let score = RegionScore {
                            pixels: px,
                            mse,
                            psnr: (px > 0).then(|| -10.0 * mse.max(1e-12).log10()),
                            pixel_share: px as f64 / all_px.max(1) as f64,
                            error_share: if all_err > 0.0 { err / all_err } else { 0.0 },
                        };
                        (name.to_string(), score)
                    })
                    .collect();
                (split.clone(), regions)
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn strain_of_known_deformations() {
        let rest = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
        let f = [0, 1, 2];
        let r = metric(&rest, &f);
        // A rotation and a translation: no strain.
        let moved = [[1.0, 2.0, 3.0], [1.0, 3.0, 3.0], [1.0, 2.0, 2.0]];
        assert!(strain(&r, &metric(&moved, &f)).abs() < 1e-9);
        // Stretched by 2 along x: ln 2.
        let x2 = [[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
        assert!((strain(&r, &metric(&x2, &f)) - 2f64.ln()).abs() < 1e-6);
        // Squeezed to a half along y: |ln 0.5|.
        let y5 = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.5, 0.0]];
        assert!((strain(&r, &metric(&y5, &f)) - 2f64.ln()).abs() < 1e-6);
        // A shear x += y by 1: σ = golden ratio and its inverse.
        let sh = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0]];
        let phi = (1.0 + 5f64.sqrt()) / 2.0;
        assert!((strain(&r, &metric(&sh, &f)) - phi.ln()).abs() < 1e-6);
        // Degenerate faces give 0, not NaN.
        let flat = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]];
        assert_eq!(strain(&metric(&flat, &f), &r), 0.0);
        assert_eq!(strain(&r, &metric(&flat, &f)), 0.0);
    }

    #[test]
    fn shear_is_what_a_similarity_cannot_follow() {
        let rest = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
        let f = [0, 1, 2];
        let r = metric(&rest, &f);
        let shear = |v: &[[f32; 3]]| {
            let (a, b) = log_stretches(&r, &metric(v, &f)).expect("stretches");
            a - b
        };
        // Scaled by 3 and rotated: a similarity, no shear.
        let big = [[0.0, 0.0, 0.0], [0.0, 3.0, 0.0], [-3.0, 0.0, 0.0]];
        assert!(shear(&big).abs() < 1e-9);
        // Stretched by 2 along x: ln 2.
        let x2 = [[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
        assert!((shear(&x2) - 2f64.ln()).abs() < 1e-6);
        // x += y: σ1 / σ2 = φ².
        let sh = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0]];
        let phi = (1.0 + 5f64.sqrt()) / 2.0;
        assert!((shear(&sh) - 2.0 * phi.ln()).abs() < 1e-6);
        assert!((SHEAR_10PCT - 1.1f64.ln()).abs() < 1e-15);
    }

    #[test]
    fn shear_histogram_quantiles() {
        let mut h = ShearHistogram::default();
        assert_eq!((h.quantile(0.5), h.share_above(0.0)), (0.0, 0.0));
        // 90 pixels at 0.001 (bin 0), 10 at 0.2 (bin 40), 1 beyond the last bin.
        for _ in 0..90 {
            h.add(0.001);
        }
        for _ in 0..10 {
            h.add(0.2);
        }
        let mut other = ShearHistogram::default();
        other.add(5.0);
        h.merge(&other);
        assert_eq!(h.count(), 101);
        assert_eq!(h.quantile(0.5), SHEAR_BIN);
        assert!((h.quantile(0.95) - 41.0 * SHEAR_BIN).abs() < 1e-12);
        assert!((h.quantile(1.0) - 2.0).abs() < 1e-12);
        assert!((h.share_above(SHEAR_10PCT) - 11.0 / 101.0).abs() < 1e-12);
    }

    #[test]
    fn jacobian_is_method_md_section_4() {
        let v = [[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
        let j = jacobian(&v, &[0, 1, 2]);
        // e1 = (2,0,0), e2 = (0,1,0), n = (0,0,2), n / sqrt|n| = (0,0,sqrt 2).
        let want = [2.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 2f64.sqrt()];
        for (a, b) in j.iter().zip(want) {
            assert!((a - b).abs() < 1e-12);
        }
    }

    #[test]
    fn top_cut_takes_a_tenth() {
        let v: Vec<f64> = (0..100).map(f64::from).collect();
        assert_eq!(top_cut(&v), 90.0);
        assert_eq!(v.iter().filter(|&&x| x >= top_cut(&v)).count(), 10);
        assert_eq!(top_cut(&[]), f64::INFINITY);
    }

    #[test]
    fn tally_pools_squared_errors_per_region() {
        let mut t = RegionTally::default();
        // Two pixels: one background with error 0.1 per channel, one skin, exact.
        let gt = [0.5, 0.5, 0.5, 0.2, 0.2, 0.2];
        let render = [0.6, 0.6, 0.6, 0.2, 0.2, 0.2];
        let labels = [bit("all") | bit("background"), bit("all") | bit("skin")];
        t.add("free", &gt, &render, &labels);
        let s = &t.scores()["free"];
        assert_eq!(s["all"].pixels, 2);
        assert!((s["all"].mse - 0.005).abs() < 1e-6);
        assert!((s["background"].psnr.expect("psnr") - 20.0).abs() < 1e-4);
        assert!((s["background"].error_share - 1.0).abs() < 1e-12);
        assert_eq!(s["skin"].error_share, 0.0);
        assert_eq!(s["skin"].pixel_share, 0.5);
        assert_eq!(s["mouth"].psnr, None);
    }

    #[test]
    fn labels_cover_the_embedded_head() {
        let head = HeadAsset::embedded().expect("head");
        let labeler = RegionLabeler::new(&head, &HeadPose::default()).expect("labeler");
        // At the neutral pose nothing is stretched; the creases' tenth is there.
        let rest = lbs(&head.model, &HeadPose::default()).expect("lbs");
        let m = labeler.face_regions(&rest);
        let count = |name: &str| m.iter().filter(|&&x| x & bit(name) != 0).count();
        assert_eq!(count("stretched"), 0);
        let n = m.len();
        assert!(count("creases") >= n / 10 && count("creases") <= n / 10 + 5);
        assert!(count("mouth") > 100 && count("eyes") > 100, "{m:?}");
        assert_eq!(count("skin") + count("mouth") + count("eyes"), n);
        // Opening the jaw stretches faces (a tenth of them) around the mouth.
        let open = HeadPose {
            jaw: [0.3, 0.0, 0.0],
            ..Default::default()
        };
        let m = labeler.face_regions(&lbs(&head.model, &open).expect("lbs"));
        let stretched_mouth = m
            .iter()
            .filter(|&&x| x & bit("stretched") != 0 && x & bit("mouth") != 0)
            .count();
        assert!(stretched_mouth > 0);
    }
}
