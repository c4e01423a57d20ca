//! The CPU tile renderer: the same algorithm as the GPU kernels, in plain multi-threaded Rust.
//!
//! Stages (each a function below): [`project`](project::project) every Gaussian →
//! [`bin`] the visible ones into 16x16 tiles, depth-ordered within a tile →
//! [`rasterize`] each tile front to back (rayon, one task per tile) → on the way back,
//! [`backward`] walks each tile back to front into per-intersection gradient slots (no
//! atomics, deterministic) → sum the slots per Gaussian → [`project::project_backward`].

pub mod lanes;
pub mod project;

use rayon::prelude::*;

use crate::camera::Camera;
use crate::splat::constants::TILE_SIZE;
use lanes::{TileBackward, TileForward, TileRect};
pub use project::{PixelBox, ProjCamera, Projection, Splat2d, Splat2dGrad};

/// Borrowed Gaussian attributes, row-major.
///
/// # Shapes
/// - `means`: [N, 3]
/// - `cov6`: [N, 6] (xx, xy, xz, yy, yz, zz)
/// - `colors`: [N, 3]
/// - `opacities`: `[N]`
#[derive(Clone, Copy, Debug)]
pub struct Scene<'a> {
    pub means: &'a [f32],
    pub cov6: &'a [f32],
    pub colors: &'a [f32],
    pub opacities: &'a [f32],
}

impl Scene<'_> {
    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.opacities.len()
    }

    /// True when there are no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.opacities.is_empty()
    }

    fn check(&self) {
        let n = self.len();
        assert_eq!(self.means.len(), 3 * n, "means must be [N, 3]");
        assert_eq!(self.cov6.len(), 6 * n, "cov6 must be [N, 6]");
        assert_eq!(self.colors.len(), 3 * n, "colors must be [N, 3]");
    }
}

/// Everything the forward pass produces and the backward pass reads.
#[derive(Clone, Debug, Default)]
pub struct Forward {
    /// [H, W, 4]: RGB and final transmittance.
    pub out: Vec<f32>,
    /// Per Gaussian: its projection, `None` when culled.
    pub projections: Vec<Option<Projection>>,
    /// Tile bins.
    pub bins: Bins,
    /// [H, W]: per pixel, one past the last composited intersection, relative to its tile's
    /// range start.
    pub last: Vec<u32>,
}

/// Gaussians binned into tiles.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Bins {
    /// `[M]`: the Gaussian of each tile intersection; tile-major, depth order within a tile.
    pub gaussian_from_isect: Vec<u32>,
    /// `[T]`: `[start, end)` into `gaussian_from_isect` per tile (row-major tiles).
    pub tile_ranges: Vec<[u32; 2]>,
}

/// Gradients of the four inputs, and `screen` `[N, 2]`: of each projected centre (u, v) in
/// pixels.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Grads {
    pub means: Vec<f32>,
    pub cov6: Vec<f32>,
    pub colors: Vec<f32>,
    pub opacities: Vec<f32>,
    pub screen: Vec<f32>,
}

/// Projects every Gaussian (in parallel).
pub fn project_all(scene: &Scene, cam: &ProjCamera) -> Vec<Option<Projection>> {
    (0..scene.len())
        .into_par_iter()
        .with_min_len(1024)
        .map(|i| {
            project::project(
                cam,
                &scene.means[3 * i..3 * i + 3],
                &scene.cov6[6 * i..6 * i + 6],
                &scene.colors[3 * i..3 * i + 3],
                scene.opacities[i],
            )
        })
        .collect()
}

/// Tile rows per binning band: bands are binned in parallel, each scanning every Gaussian.
const BIN_BAND_ROWS: u32 = 8;

/// A Gaussian as the band scans see it: index, inclusive tile box, and its ellipse.
#[derive(Clone, Copy)]
struct Binned {
    g: u32,
    tiles: [u16; 4],
    ellipse: TileEllipse,
}

/// The ellipse `sigma(d) = (a dx² + 2 b dx dy + c dy²) / 2 <= cut` of a projected
/// Gaussian (`d` from its mean), for [`TileEllipse::row_tiles`].
#[derive(Clone, Copy)]
struct TileEllipse {
    u: f32,
    v: f32,
    /// `b / a` and `1 / a`.
    b_a: f32,
    inv_a: f32,
    /// `a c - b²` (> 0) and `2 a cut`: the chord at `dy` is `sqrt(2 a cut - det dy²) / a`
    /// either side of `-b dy / a`.
    det: f32,
    two_a_cut: f32,
    /// Half the ellipse's height, and the `dy` of its leftmost point (the rightmost is at
    /// `-dy_left`).
    half_height: f32,
    dy_left: f32,
}

/// Slack on the tile test's cut, in units of sigma (the per-pixel test adds
/// [`lanes::SIGMA_CUT_SLACK`]; this is more, so rounding never drops a reached tile).
const TILE_TEST_SLACK: f32 = 0.05;

impl TileEllipse {
    fn new(p: &Projection) -> Self {
        let s = &p.splat;
        let cut = s.sigma_cut + lanes::SIGMA_CUT_SLACK + TILE_TEST_SLACK;
        let det = s.a * s.c - s.b * s.b;
        let half_width = (2.0 * s.c * cut / det).sqrt();
        TileEllipse {
            u: s.u,
            v: s.v,
            b_a: s.b / s.a,
            inv_a: 1.0 / s.a,
            det,
            two_a_cut: 2.0 * s.a * cut,
            half_height: (2.0 * s.a * cut / det).sqrt(),
            dy_left: s.b * half_width / s.c,
        }
    }

    /// The tile columns of tile row `ty`, within `[tx0, tx1]`, whose pixel centres the
    /// ellipse may reach: the ellipse's x-range over the band of the row's pixel-centre
    /// heights, whose ends lie at the band's clamp of the leftmost and rightmost points.
    /// `None` when the band misses the ellipse; non-finite values keep the whole row.
    fn row_tiles(&self, ty: u32, tx0: u32, tx1: u32) -> Option<(u32, u32)> {
        let y0 = (ty * TILE_SIZE) as f32 + 0.5 - self.v;
        // `max` and `min` drop a NaN height, so `lo` and `hi` are finite (the clamps below
        // need that).
        let (lo, hi) = (
            y0.max(-self.half_height),
            (y0 + (TILE_SIZE - 1) as f32).min(self.half_height),
        );
        if lo > hi {
            return None;
        }
        let x_at = |dy: f32, side: f32| {
            let chord = (self.two_a_cut - self.det * dy * dy).max(0.0).sqrt() * self.inv_a;
            -self.b_a * dy + side * chord
        };
        let left = self.u + x_at(self.dy_left.clamp(lo, hi), -1.0);
        let right = self.u + x_at((-self.dy_left).clamp(lo, hi), 1.0);
        if !(left.is_finite() && right.is_finite()) {
            return Some((tx0, tx1));
        }
        if right < 0.5 {
            return None;
        }
        // Pixel columns with centres in [left, right], as tiles.
        let first = ((left - 0.5).ceil().max(0.0) as u32 / TILE_SIZE).max(tx0);
        let last = ((right - 0.5).floor() as u32 / TILE_SIZE).min(tx1);
        (first <= last).then_some((first, last))
    }
}

/// Bins visible Gaussians into tiles: sorted by (depth, index), then, per band of tile rows
/// in parallel, a stable counting sort by tile, so every tile lists its Gaussians front to
/// back. A Gaussian whose box spans several tile rows and columns is only listed, row by
/// row, in the tiles its ellipse reaches (`TileEllipse::row_tiles`; a tilted ellipse
/// leaves box corners empty); one whose box is a single row or column of tiles reaches all
/// of them.
pub fn bin(projections: &[Option<Projection>], cam: &ProjCamera) -> Bins {
    let (tiles_x, tiles_y) = cam.tiles();
    let num_tiles = (tiles_x * tiles_y) as usize;
    // Sort keys: depth bits (positive floats order like their bits), then the index, so the
    // order is total and the unstable sort deterministic.
    let mut keys: Vec<u64> = projections
        .par_iter()
        .enumerate()
        .filter_map(|(i, p)| p.map(|p| ((p.depth.to_bits() as u64) << 32) | i as u64))
        .collect();
    keys.par_sort_unstable();
    // Depth-ordered Gaussians with their tile boxes and ellipses, compact for the band
    // scans below (the keys only hold visible Gaussians).
    let boxes: Vec<Binned> = keys
        .par_iter()
        .filter_map(|&k| {
            let g = k as u32;
            let p = projections[g as usize].as_ref()?;
            let b = p.pixels.tiles();
            Some(Binned {
                g,
                tiles: [b.0 as u16, b.1 as u16, b.2 as u16, b.3 as u16],
                ellipse: TileEllipse::new(p),
            })
        })
        .collect();
    let bands: Vec<(u32, u32)> = (0..tiles_y)
        .step_by(BIN_BAND_ROWS as usize)
        .map(|y0| (y0, (y0 + BIN_BAND_ROWS).min(tiles_y)))
        .collect();
    // Pass 1: each band's runs of tiles (depth order) and its per-tile counts.
    let runs: Vec<(Vec<Run>, Vec<u32>)> = bands
        .par_iter()
        .map(|band| {
            let first = (band.0 * tiles_x) as usize;
            let runs = band_runs(&boxes, *band);
            let mut c = vec![0u32; ((band.1 - band.0) * tiles_x) as usize];
            for r in &runs {
                let row = (r.ty as u32 * tiles_x) as usize - first;
                for tx in r.first..=r.last {
                    c[row + tx as usize] += 1;
                }
            }
            (runs, c)
        })
        .collect();
    let mut tile_ranges = Vec::with_capacity(num_tiles);
    let mut total = 0u32;
    for &c in runs.iter().flat_map(|(_, c)| c) {
        tile_ranges.push([total, total + c]);
        total += c;
    }
    // Pass 2: each band fills its own contiguous part of the list.
    let mut gaussian_from_isect = vec![0u32; total as usize];
    let mut parts = Vec::with_capacity(bands.len());
    let mut rest: &mut [u32] = &mut gaussian_from_isect;
    for (band, (band_runs, _)) in bands.iter().zip(&runs) {
        let first = (band.0 * tiles_x) as usize;
        let end = (band.1 * tiles_x) as usize;
        let len = (tile_ranges[end - 1][1] - tile_ranges[first][0]) as usize;
        let (head, tail) = rest.split_at_mut(len);
        parts.push((band, band_runs, head));
        rest = tail;
    }
    parts.into_par_iter().for_each(|(band, band_runs, part)| {
        let first = (band.0 * tiles_x) as usize;
        let base = tile_ranges[first][0];
        let mut cursor: Vec<u32> = (first..(band.1 * tiles_x) as usize)
            .map(|t| tile_ranges[t][0] - base)
            .collect();
        for r in band_runs {
            let row = (r.ty as u32 * tiles_x) as usize - first;
            for tx in r.first..=r.last {
                let c = &mut cursor[row + tx as usize];
                part[*c as usize] = r.g;
                *c += 1;
            }
        }
    });
    Bins {
        gaussian_from_isect,
        tile_ranges,
    }
}

/// A Gaussian's tiles in one tile row: columns `first..=last` of row `ty`.
struct Run {
    g: u32,
    ty: u16,
    first: u16,
    last: u16,
}

/// The runs of tiles that each Gaussian of `boxes` (depth order) touches in the band of tile
/// rows `[y0, y1)`, in depth order: its tile box, less the tiles its ellipse misses.
fn band_runs(boxes: &[Binned], (y0, y1): (u32, u32)) -> Vec<Run> {
    let mut runs = Vec::new();
    for b in boxes {
        let [tx0, ty0, tx1, ty1] = b.tiles.map(u32::from);
        let test = tx1 > tx0 && ty1 > ty0;
        for ty in ty0.max(y0)..(ty1 + 1).min(y1) {
            let row = if test {
                b.ellipse.row_tiles(ty, tx0, tx1)
            } else {
                Some((tx0, tx1))
            };
            if let Some((first, last)) = row {
                runs.push(Run {
                    g: b.g,
                    ty: ty as u16,
                    first: first as u16,
                    last: last as u16,
                });
            }
        }
    }
    runs
}

/// Pixel rectangle of tile `t`.
fn tile_rect(cam: &ProjCamera, t: usize) -> TileRect {
    let (tiles_x, _) = cam.tiles();
    let (tx, ty) = (t as u32 % tiles_x, t as u32 / tiles_x);
    let x0 = tx * TILE_SIZE;
    let y0 = ty * TILE_SIZE;
    TileRect {
        x0,
        y0,
        x1: (x0 + TILE_SIZE).min(cam.width),
        y1: (y0 + TILE_SIZE).min(cam.height),
    }
}

fn tile_forward_baseline(
    rect: TileRect,
    projections: &[Option<Projection>],
    isects: &[u32],
) -> TileForward {
    lanes::tile_forward_generic(rect, projections, isects)
}

/// The same code compiled for AVX2 (8-wide vectors).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn tile_forward_avx2(
    rect: TileRect,
    projections: &[Option<Projection>],
    isects: &[u32],
) -> TileForward {
    lanes::tile_forward_generic(rect, projections, isects)
}

fn tile_forward(rect: TileRect, projections: &[Option<Projection>], isects: &[u32]) -> TileForward {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU supports AVX2 (checked just above).
        return unsafe { tile_forward_avx2(rect, projections, isects) };
    }
    tile_forward_baseline(rect, projections, isects)
}

fn tile_backward_baseline(
    rect: TileRect,
    st: &mut TileBackward,
    projections: &[Option<Projection>],
    isects: &[u32],
    slots: &mut [Splat2dGrad],
) {
    lanes::tile_backward_generic(rect, st, projections, isects, slots)
}

/// The same code compiled for AVX2 (8-wide vectors).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn tile_backward_avx2(
    rect: TileRect,
    st: &mut TileBackward,
    projections: &[Option<Projection>],
    isects: &[u32],
    slots: &mut [Splat2dGrad],
) {
    lanes::tile_backward_generic(rect, st, projections, isects, slots)
}

fn tile_backward(
    rect: TileRect,
    st: &mut TileBackward,
    projections: &[Option<Projection>],
    isects: &[u32],
    slots: &mut [Splat2dGrad],
) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU supports AVX2 (checked just above).
        return unsafe { tile_backward_avx2(rect, st, projections, isects, slots) };
    }
    tile_backward_baseline(rect, st, projections, isects, slots)
}

/// Composites every tile front to back (one rayon task per tile).
///
/// Returns `out` [H, W, 4] (RGB, final transmittance) and `last` [H, W].
pub fn rasterize(
    cam: &ProjCamera,
    projections: &[Option<Projection>],
    bins: &Bins,
    background: [f32; 3],
) -> (Vec<f32>, Vec<u32>) {
    let (w, h) = (cam.width as usize, cam.height as usize);
    let tiles: Vec<TileForward> = bins
        .tile_ranges
        .par_iter()
        .enumerate()
        .map(|(t, &[start, end])| {
            let isects = &bins.gaussian_from_isect[start as usize..end as usize];
            tile_forward(tile_rect(cam, t), projections, isects)
        })
        .collect();
    let mut out = vec![0.0f32; w * h * 4];
    let mut last = vec![0u32; w * h];
    let (tiles_x, _) = cam.tiles();
    out.par_chunks_mut(4 * w)
        .zip(last.par_chunks_mut(w))
        .enumerate()
        .for_each(|(py, (out_row, last_row))| {
            let ty = py / TILE_SIZE as usize;
            let ly = py % TILE_SIZE as usize;
            for tx in 0..tiles_x as usize {
                let t = ty * tiles_x as usize + tx;
                let (tile, rect) = (&tiles[t], tile_rect(cam, t));
                for px in rect.x0 as usize..rect.x1 as usize {
                    let (sp, l) = lanes::span_lane(px - rect.x0 as usize, ly);
                    let tr = tile.trans[sp][l];
                    out_row[4 * px..4 * px + 4].copy_from_slice(&[
                        tile.color[0][sp][l] + tr * background[0],
                        tile.color[1][sp][l] + tr * background[1],
                        tile.color[2][sp][l] + tr * background[2],
                        tr,
                    ]);
                    last_row[px] = tile.last[sp][l];
                }
            }
        });
    (out, last)
}

/// Forward pass: projection, binning and compositing.
pub fn forward(scene: &Scene, camera: &Camera, background: [f32; 3]) -> Forward {
    scene.check();
    let cam = ProjCamera::new(camera);
    let projections = project_all(scene, &cam);
    let bins = bin(&projections, &cam);
    let (out, last) = rasterize(&cam, &projections, &bins, background);
    Forward {
        out,
        projections,
        bins,
        last,
    }
}

fn rasterize_tile_backward(
    cam: &ProjCamera,
    fwd: &Forward,
    background: [f32; 3],
    grad_out: &[f32],
    t: usize,
    slots: &mut [Splat2dGrad],
) {
    let rect = tile_rect(cam, t);
    let w = cam.width as usize;
    let mut st = TileBackward::new();
    for py in rect.y0..rect.y1 {
        let ly = (py - rect.y0) as usize;
        for px in rect.x0..rect.x1 {
            let (sp, l) = lanes::span_lane((px - rect.x0) as usize, ly);
            let o = py as usize * w + px as usize;
            let t_final = fwd.out[4 * o + 3];
            let g = [grad_out[4 * o], grad_out[4 * o + 1], grad_out[4 * o + 2]];
            let g_t = grad_out[4 * o + 3];
            st.trans[sp][l] = t_final;
            // d out / d alpha_i picks up -T_final/(1 - alpha_i) from the background and from
            // the transmittance output; seed the running "after" sum with both.
            st.after[sp][l] = t_final
                * (g[0] * background[0] + g[1] * background[1] + g[2] * background[2])
                + g_t * t_final;
            for (ch, gc) in g.into_iter().enumerate() {
                st.grad[ch][sp][l] = gc;
            }
            st.last[sp][l] = fwd.last[o];
        }
    }
    let [start, end] = fwd.bins.tile_ranges[t];
    let isects = &fwd.bins.gaussian_from_isect[start as usize..end as usize];
    tile_backward(rect, &mut st, &fwd.projections, isects, slots);
}

/// Backward pass. `grad_out` is [H, W, 4]: gradients of the loss w.r.t. RGB and the final
/// transmittance. Culled Gaussians get zero gradients.
pub fn backward(
    scene: &Scene,
    camera: &Camera,
    background: [f32; 3],
    fwd: &Forward,
    grad_out: &[f32],
) -> Grads {
    scene.check();
    let cam = ProjCamera::new(camera);
    let (w, h) = (cam.width as usize, cam.height as usize);
    assert_eq!(grad_out.len(), w * h * 4, "grad_out must be [H, W, 4]");
    let m = fwd.bins.gaussian_from_isect.len();
    let mut slots = vec![Splat2dGrad::default(); m];
    // Split the slots into one disjoint chunk per tile (tile ranges are contiguous).
    let mut chunks = Vec::with_capacity(fwd.bins.tile_ranges.len());
    let mut rest: &mut [Splat2dGrad] = &mut slots;
    for r in &fwd.bins.tile_ranges {
        let (head, tail) = rest.split_at_mut((r[1] - r[0]) as usize);
        chunks.push(head);
        rest = tail;
    }
    chunks
        .into_par_iter()
        .enumerate()
        .for_each(|(t, chunk)| rasterize_tile_backward(&cam, fwd, background, grad_out, t, chunk));

    let n = scene.len();
    let mut per_gaussian = vec![Splat2dGrad::default(); n];
    for (slot, &g) in slots.iter().zip(&fwd.bins.gaussian_from_isect) {
        per_gaussian[g as usize].add(slot);
    }
    let mut grads = Grads {
        means: vec![0.0; 3 * n],
        cov6: vec![0.0; 6 * n],
        colors: vec![0.0; 3 * n],
        opacities: vec![0.0; n],
        screen: vec![0.0; 2 * n],
    };
    grads
        .means
        .par_chunks_mut(3)
        .zip(grads.cov6.par_chunks_mut(6))
        .zip(grads.colors.par_chunks_mut(3))
        .zip(grads.opacities.par_iter_mut())
        .zip(grads.screen.par_chunks_mut(2))
        .enumerate()
        .with_min_len(1024)
        .for_each(|(i, ((((gm, gcov), gcol), gop), gscreen))| {
            if fwd.projections[i].is_none() {
                return;
            }
            let g2 = &per_gaussian[i];
            gscreen.copy_from_slice(&[g2.u, g2.v]);
            let (dm, dc) = project::project_backward(
                &cam,
                &scene.means[3 * i..3 * i + 3],
                &scene.cov6[6 * i..6 * i + 6],
                g2,
            );
            gm.copy_from_slice(&dm);
            gcov.copy_from_slice(&dc);
            gcol.copy_from_slice(&g2.rgb);
            *gop = g2.opacity;
        });
    grads
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::util::rng::Pcg;

    /// Random splats around a 16x16 tile at (32, 16), some partly outside it.
    fn splats(n: usize, seed: u64) -> Vec<Option<Projection>> {
        let mut rng = Pcg::new(seed);
        (0..n)
            .map(|i| {
                if i % 17 == 5 {
                    return None;
                }
                let (u, v) = (28.0 + 24.0 * rng.uniform(), 12.0 + 24.0 * rng.uniform());
                let (sx, sy) = (0.5 + 4.0 * rng.uniform(), 0.5 + 4.0 * rng.uniform());
                let rho = 0.9 * (2.0 * rng.uniform() - 1.0);
                let det = sx * sx * sy * sy * (1.0 - rho * rho);
                let (a, b, c) = (sy * sy / det, -rho * sx * sy / det, sx * sx / det);
                let opacity = 0.05 + 0.94 * rng.uniform();
                let sigma_cut = (255.0 * opacity).ln();
                let (rx, ry) = ((2.0 * sigma_cut).sqrt() * sx, (2.0 * sigma_cut).sqrt() * sy);
                let lo = |c: f32, r: f32| (c - r - 0.5).ceil().max(0.0) as u32;
                let hi = |c: f32, r: f32| (c + r - 0.5).floor().max(0.0) as u32;
                Some(Projection {
                    splat: Splat2d {
                        u,
                        v,
                        a,
                        b,
                        c,
                        opacity,
                        rgb: [rng.uniform(), rng.uniform(), rng.uniform()],
                        sigma_cut,
                    },
                    depth: 1.0 + i as f32,
                    pixels: PixelBox {
                        x0: lo(u, rx),
                        y0: lo(v, ry),
                        x1: hi(u, rx),
                        y1: hi(v, ry),
                    },
                })
            })
            .collect()
    }

    /// The tile rows' column ranges hold every tile with a pixel centre inside the ellipse
    /// (brute force over each tile's 256 centres), and they do drop the empty corners of
    /// tilted ellipses.
    #[test]
    fn tile_rows_keep_every_reached_tile() {
        let mut rng = Pcg::new(21);
        let (mut dropped, mut kept) = (0, 0);
        for _ in 0..3000 {
            let (sx, sy) = (0.5 + 30.0 * rng.uniform(), 0.5 + 30.0 * rng.uniform());
            let rho = 0.999 * (2.0 * rng.uniform() - 1.0);
            let det = sx * sx * sy * sy * (1.0 - rho * rho);
            let opacity = 0.01 + 0.99 * rng.uniform();
            let p = Projection {
                splat: Splat2d {
                    u: 64.0 * rng.uniform(),
                    v: 64.0 * rng.uniform(),
                    a: sy * sy / det,
                    b: -rho * sx * sy / det,
                    c: sx * sx / det,
                    opacity,
                    rgb: [0.5; 3],
                    sigma_cut: (255.0 * opacity).ln(),
                },
                depth: 1.0,
                pixels: PixelBox {
                    x0: 0,
                    y0: 0,
                    x1: 63,
                    y1: 63,
                },
            };
            let (s, e) = (&p.splat, TileEllipse::new(&p));
            let cut = s.sigma_cut + lanes::SIGMA_CUT_SLACK;
            for ty in 0..4 {
                let row = e.row_tiles(ty, 0, 3);
                for tx in 0..4 {
                    let reached = (0..TILE_SIZE * TILE_SIZE).any(|k| {
                        let dx = (tx * TILE_SIZE + k % TILE_SIZE) as f32 + 0.5 - s.u;
                        let dy = (ty * TILE_SIZE + k / TILE_SIZE) as f32 + 0.5 - s.v;
                        0.5 * (s.a * dx * dx + 2.0 * s.b * dx * dy + s.c * dy * dy) <= cut
                    });
                    let listed = row.is_some_and(|(a, b)| (a..=b).contains(&tx));
                    assert!(listed || !reached, "{s:?}: tile ({tx}, {ty}) dropped");
                    if listed {
                        kept += 1;
                    } else {
                        dropped += 1;
                    }
                }
            }
        }
        assert!(
            dropped > 1000 && kept > 1000,
            "{dropped} dropped, {kept} kept"
        );
    }

    /// The dispatched (AVX2 where the CPU has it) and the baseline builds of the tile loops
    /// agree, so the path CI's CPU does not take is tested too.
    #[test]
    fn baseline_and_dispatched_tiles_agree() {
        let projections = splats(300, 3);
        let isects: Vec<u32> = (0..projections.len() as u32).collect();
        // A full tile and an edge tile (13 x 9 pixels).
        for rect in [
            TileRect {
                x0: 32,
                y0: 16,
                x1: 48,
                y1: 32,
            },
            TileRect {
                x0: 32,
                y0: 16,
                x1: 45,
                y1: 25,
            },
        ] {
            let a = tile_forward(rect, &projections, &isects);
            let b = tile_forward_baseline(rect, &projections, &isects);
            assert_eq!(a.last, b.last);
            assert!(a.last.iter().flatten().any(|&l| l > 0));
            for (x, y) in a.trans.iter().flatten().zip(b.trans.iter().flatten()) {
                assert!((x - y).abs() <= 1e-6, "{x} vs {y}");
            }
            for (x, y) in a
                .color
                .iter()
                .flatten()
                .flatten()
                .zip(b.color.iter().flatten().flatten())
            {
                assert!((x - y).abs() <= 1e-6, "{x} vs {y}");
            }
            let mut st = [TileBackward::new(), TileBackward::new()];
            let mut rng = Pcg::new(9);
            for sp in 0..lanes::SPANS {
                for l in 0..lanes::LANES {
                    let g = [rng.uniform(), rng.uniform(), rng.uniform()];
                    for s in &mut st {
                        s.trans[sp][l] = a.trans[sp][l];
                        s.after[sp][l] = 0.3 * a.trans[sp][l];
                        s.last[sp][l] = a.last[sp][l];
                        for (grad, g) in s.grad.iter_mut().zip(g) {
                            grad[sp][l] = g;
                        }
                    }
                }
            }
            let [s0, s1] = &mut st;
            let mut ga = vec![Splat2dGrad::default(); isects.len()];
            let mut gb = ga.clone();
            tile_backward(rect, s0, &projections, &isects, &mut ga);
            tile_backward_baseline(rect, s1, &projections, &isects, &mut gb);
            let close = |x: f32, y: f32| (x - y).abs() <= 1e-4 * (1.0 + x.abs().max(y.abs()));
            assert!(ga.iter().any(|g| g.opacity != 0.0));
            for (x, y) in ga.iter().zip(&gb) {
                let (x, y) = (
                    [
                        x.u, x.v, x.a, x.b, x.c, x.opacity, x.rgb[0], x.rgb[1], x.rgb[2],
                    ],
                    [
                        y.u, y.v, y.a, y.b, y.c, y.opacity, y.rgb[0], y.rgb[1], y.rgb[2],
                    ],
                );
                assert!(
                    x.iter().zip(&y).all(|(&p, &q)| close(p, q)),
                    "{x:?} vs {y:?}"
                );
            }
        }
    }
}
