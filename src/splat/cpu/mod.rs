//! The CPU tile renderer: the same algorithm as the GPU kernels, in plain multi-threaded Rust.
//!
//! Stages (each a function below): [`project`](project::project) every Gaussian →
//! [`bin`] the visible ones into 16x16 tiles, depth-ordered within a tile →
//! [`rasterize`] each tile front to back (rayon, one task per tile) → on the way back,
//! [`rasterize_backward`] each tile back to front into per-intersection gradient slots (no
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
/// - `opacities`: [N]
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
    /// [M]: the Gaussian of each tile intersection; tile-major, depth order within a tile.
    pub gaussian_from_isect: Vec<u32>,
    /// [T]: `[start, end)` into `gaussian_from_isect` per tile (row-major tiles).
    pub tile_ranges: Vec<[u32; 2]>,
}

/// Gradients of the four inputs.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Grads {
    pub means: Vec<f32>,
    pub cov6: Vec<f32>,
    pub colors: Vec<f32>,
    pub opacities: Vec<f32>,
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

/// Bins visible Gaussians into tiles: sorted by (depth, index), then, per band of tile rows
/// in parallel, a stable counting sort by tile, so every tile lists its Gaussians front to
/// back.
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
    // Depth-ordered Gaussians with their tile boxes, compact for the band scans below.
    let boxes: Vec<(u32, [u16; 4])> = keys
        .par_iter()
        .map(|&k| {
            let g = k as u32;
            let b = projections[g as usize].map_or((1, 1, 0, 0), |p| p.pixels.tiles());
            (g, [b.0 as u16, b.1 as u16, b.2 as u16, b.3 as u16])
        })
        .collect();
    let bands: Vec<(u32, u32)> = (0..tiles_y)
        .step_by(BIN_BAND_ROWS as usize)
        .map(|y0| (y0, (y0 + BIN_BAND_ROWS).min(tiles_y)))
        .collect();
    // Pass 1: per-tile counts, band by band.
    let counts: Vec<Vec<u32>> = bands
        .par_iter()
        .map(|band| {
            let first = (band.0 * tiles_x) as usize;
            let mut c = vec![0u32; ((band.1 - band.0) * tiles_x) as usize];
            visit_band(&boxes, *band, tiles_x, |t, _| c[t - first] += 1);
            c
        })
        .collect();
    let mut tile_ranges = Vec::with_capacity(num_tiles);
    let mut total = 0u32;
    for &c in counts.iter().flatten() {
        tile_ranges.push([total, total + c]);
        total += c;
    }
    // Pass 2: each band fills its own contiguous part of the list.
    let mut gaussian_from_isect = vec![0u32; total as usize];
    let mut parts = Vec::with_capacity(bands.len());
    let mut rest: &mut [u32] = &mut gaussian_from_isect;
    for band in &bands {
        let first = (band.0 * tiles_x) as usize;
        let end = (band.1 * tiles_x) as usize;
        let len = (tile_ranges[end - 1][1] - tile_ranges[first][0]) as usize;
        let (head, tail) = rest.split_at_mut(len);
        parts.push((band, head));
        rest = tail;
    }
    parts.into_par_iter().for_each(|(band, part)| {
        let first = (band.0 * tiles_x) as usize;
        let base = tile_ranges[first][0];
        let mut cursor: Vec<u32> = (first..(band.1 * tiles_x) as usize)
            .map(|t| tile_ranges[t][0] - base)
            .collect();
        visit_band(&boxes, *band, tiles_x, |t, g| {
            let c = &mut cursor[t - first];
            part[*c as usize] = g;
            *c += 1;
        });
    });
    Bins {
        gaussian_from_isect,
        tile_ranges,
    }
}

/// Calls `visit(tile, gaussian)` for every tile of the band of tile rows `[y0, y1)` that each
/// Gaussian of `boxes` (depth order, with its inclusive tile box) touches.
fn visit_band(
    boxes: &[(u32, [u16; 4])],
    (y0, y1): (u32, u32),
    tiles_x: u32,
    mut visit: impl FnMut(usize, u32),
) {
    for &(g, [tx0, ty0, tx1, ty1]) in boxes {
        let (ty0, ty1) = ((ty0 as u32).max(y0), (ty1 as u32 + 1).min(y1));
        for ty in ty0..ty1 {
            for tx in tx0 as u32..=tx1 as u32 {
                visit((ty * tiles_x + tx) as usize, g);
            }
        }
    }
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
    };
    grads
        .means
        .par_chunks_mut(3)
        .zip(grads.cov6.par_chunks_mut(6))
        .zip(grads.colors.par_chunks_mut(3))
        .zip(grads.opacities.par_iter_mut())
        .enumerate()
        .with_min_len(1024)
        .for_each(|(i, (((gm, gcov), gcol), gop))| {
            if fwd.projections[i].is_none() {
                return;
            }
            let g2 = &per_gaussian[i];
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
    use crate::splat::demo::Pcg;

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
