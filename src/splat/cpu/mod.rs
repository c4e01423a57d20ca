//! The CPU tile renderer: the same algorithm as the GPU kernels, in plain multi-threaded Rust.
//!
//! Stages (each a function below): [`project`](project::project) every Gaussian →
//! [`bin`] the visible ones into 16x16 tiles, depth-ordered within a tile →
//! [`rasterize`] each tile front to back (rayon, one task per tile) → on the way back,
//! [`rasterize_backward`] each tile back to front into per-intersection gradient slots (no
//! atomics, deterministic) → sum the slots per Gaussian → [`project::project_backward`].

pub mod project;

use rayon::prelude::*;

use crate::camera::Camera;
use crate::splat::constants::{ALPHA_MAX, ALPHA_MIN, TILE_SIZE, TRANSMITTANCE_MIN};
pub use project::{PixelBox, ProjCamera, Projection, Splat2d, Splat2dGrad};

/// Slack on the cheap `sigma > sigma_cut` rejection: `exp(-0.01) < 1`, so a pixel rejected
/// this way has alpha below the threshold whatever the rounding of `exp`.
const SIGMA_CUT_SLACK: f32 = 0.01;

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

/// Bins visible Gaussians into tiles: sorted by (depth, index), then a stable counting sort
/// by tile, so every tile lists its Gaussians front to back.
pub fn bin(projections: &[Option<Projection>], cam: &ProjCamera) -> Bins {
    let (tiles_x, tiles_y) = cam.tiles();
    let num_tiles = (tiles_x * tiles_y) as usize;
    let mut order: Vec<u32> = (0..projections.len() as u32)
        .filter(|&i| projections[i as usize].is_some())
        .collect();
    let depth = |i: u32| projections[i as usize].map_or(0.0, |p| p.depth);
    order.par_sort_unstable_by(|&i, &j| depth(i).total_cmp(&depth(j)).then(i.cmp(&j)));

    let mut counts = vec![0u32; num_tiles];
    for p in projections.iter().flatten() {
        let (tx0, ty0, tx1, ty1) = p.pixels.tiles();
        for ty in ty0..=ty1 {
            for tx in tx0..=tx1 {
                counts[(ty * tiles_x + tx) as usize] += 1;
            }
        }
    }
    let mut tile_ranges = Vec::with_capacity(num_tiles);
    let mut total = 0u32;
    for &c in &counts {
        tile_ranges.push([total, total + c]);
        total += c;
    }
    let mut cursor: Vec<u32> = tile_ranges.iter().map(|r| r[0]).collect();
    let mut gaussian_from_isect = vec![0u32; total as usize];
    for &g in &order {
        let Some(p) = projections[g as usize] else {
            continue;
        };
        let (tx0, ty0, tx1, ty1) = p.pixels.tiles();
        for ty in ty0..=ty1 {
            for tx in tx0..=tx1 {
                let t = (ty * tiles_x + tx) as usize;
                gaussian_from_isect[cursor[t] as usize] = g;
                cursor[t] += 1;
            }
        }
    }
    Bins {
        gaussian_from_isect,
        tile_ranges,
    }
}

/// Pixel rectangle `[x0, x1) x [y0, y1)` of tile `t`.
fn tile_rect(cam: &ProjCamera, t: usize) -> (u32, u32, u32, u32) {
    let (tiles_x, _) = cam.tiles();
    let (tx, ty) = (t as u32 % tiles_x, t as u32 / tiles_x);
    let x0 = tx * TILE_SIZE;
    let y0 = ty * TILE_SIZE;
    (
        x0,
        y0,
        (x0 + TILE_SIZE).min(cam.width),
        (y0 + TILE_SIZE).min(cam.height),
    )
}

/// The part of a Gaussian's pixel box inside a tile rectangle, as an inclusive range.
fn clip(b: &PixelBox, rect: (u32, u32, u32, u32)) -> Option<(u32, u32, u32, u32)> {
    let x0 = b.x0.max(rect.0);
    let y0 = b.y0.max(rect.1);
    let x1 = b.x1.min(rect.2 - 1);
    let y1 = b.y1.min(rect.3 - 1);
    (x0 <= x1 && y0 <= y1).then_some((x0, y0, x1, y1))
}

/// Alpha of splat `s` at the pixel centre `(px, py)`, and the quantities its backward needs;
/// `None` where the Gaussian is skipped (sigma < 0, alpha < 1/255).
#[inline(always)]
fn alpha_at(s: &Splat2d, px: f32, py: f32) -> Option<Alpha> {
    let dx = px - s.u;
    let dy = py - s.v;
    let sigma = 0.5 * (s.a * dx * dx + s.c * dy * dy) + s.b * dx * dy;
    if sigma.is_nan() || sigma < 0.0 || sigma > s.sigma_cut + SIGMA_CUT_SLACK {
        return None;
    }
    let g = (-sigma).exp();
    let raw = s.opacity * g;
    let alpha = raw.min(ALPHA_MAX);
    (alpha >= ALPHA_MIN).then_some(Alpha {
        alpha,
        g,
        clamped: raw > ALPHA_MAX,
        dx,
        dy,
    })
}

struct Alpha {
    alpha: f32,
    /// `exp(-sigma)`.
    g: f32,
    clamped: bool,
    dx: f32,
    dy: f32,
}

/// Per-tile result of the forward pass.
struct TileOut {
    rgbt: Vec<[f32; 4]>,
    last: Vec<u32>,
}

fn rasterize_tile(
    cam: &ProjCamera,
    projections: &[Option<Projection>],
    bins: &Bins,
    background: [f32; 3],
    t: usize,
) -> TileOut {
    let rect = tile_rect(cam, t);
    let tw = (rect.2 - rect.0) as usize;
    let th = (rect.3 - rect.1) as usize;
    let n = tw * th;
    let mut trans = vec![1.0f32; n];
    let mut color = vec![[0.0f32; 3]; n];
    let mut done = vec![false; n];
    let mut last = vec![0u32; n];
    let mut remaining = n;
    let [start, end] = bins.tile_ranges[t];
    for k in start..end {
        if remaining == 0 {
            break;
        }
        let g = bins.gaussian_from_isect[k as usize] as usize;
        let Some(p) = projections[g] else { continue };
        let Some((x0, y0, x1, y1)) = clip(&p.pixels, rect) else {
            continue;
        };
        let s = &p.splat;
        for py in y0..=y1 {
            let row = (py - rect.1) as usize * tw;
            for px in x0..=x1 {
                let i = row + (px - rect.0) as usize;
                if done[i] {
                    continue;
                }
                let Some(a) = alpha_at(s, px as f32 + 0.5, py as f32 + 0.5) else {
                    continue;
                };
                let next = trans[i] * (1.0 - a.alpha);
                if next < TRANSMITTANCE_MIN {
                    done[i] = true;
                    remaining -= 1;
                    continue;
                }
                let w = a.alpha * trans[i];
                for (acc, c) in color[i].iter_mut().zip(s.rgb) {
                    *acc += w * c;
                }
                trans[i] = next;
                last[i] = k - start + 1;
            }
        }
    }
    let rgbt = (0..n)
        .map(|i| {
            let t = trans[i];
            [
                color[i][0] + t * background[0],
                color[i][1] + t * background[1],
                color[i][2] + t * background[2],
                t,
            ]
        })
        .collect();
    TileOut { rgbt, last }
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
    let tiles: Vec<TileOut> = (0..bins.tile_ranges.len())
        .into_par_iter()
        .map(|t| rasterize_tile(cam, projections, bins, background, t))
        .collect();
    let mut out = vec![0.0f32; w * h * 4];
    let mut last = vec![0u32; w * h];
    for (t, tile) in tiles.iter().enumerate() {
        let rect = tile_rect(cam, t);
        let tw = (rect.2 - rect.0) as usize;
        for (i, (rgbt, l)) in tile.rgbt.iter().zip(&tile.last).enumerate() {
            let px = rect.0 as usize + i % tw;
            let py = rect.1 as usize + i / tw;
            let o = py * w + px;
            out[4 * o..4 * o + 4].copy_from_slice(rgbt);
            last[o] = *l;
        }
    }
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

#[allow(clippy::too_many_arguments)]
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
    let tw = (rect.2 - rect.0) as usize;
    let th = (rect.3 - rect.1) as usize;
    let n = tw * th;
    let mut trans = vec![0.0f32; n];
    let mut after = vec![0.0f32; n];
    let mut grad = vec![[0.0f32; 3]; n];
    let mut last = vec![0u32; n];
    let mut max_last = 0;
    for i in 0..n {
        let px = rect.0 as usize + i % tw;
        let py = rect.1 as usize + i / tw;
        let o = py * w + px;
        let t_final = fwd.out[4 * o + 3];
        let g = [grad_out[4 * o], grad_out[4 * o + 1], grad_out[4 * o + 2]];
        let g_t = grad_out[4 * o + 3];
        trans[i] = t_final;
        // d out / d alpha_i picks up -T_final/(1 - alpha_i) from the background and from the
        // transmittance output; seed the running "after" sum with both.
        after[i] = t_final * (g[0] * background[0] + g[1] * background[1] + g[2] * background[2])
            + g_t * t_final;
        grad[i] = g;
        last[i] = fwd.last[o];
        max_last = max_last.max(last[i]);
    }
    let [start, _] = fwd.bins.tile_ranges[t];
    for k in (0..max_last).rev() {
        let g_idx = fwd.bins.gaussian_from_isect[(start + k) as usize] as usize;
        let Some(p) = fwd.projections[g_idx] else {
            continue;
        };
        let Some((x0, y0, x1, y1)) = clip(&p.pixels, rect) else {
            continue;
        };
        let s = &p.splat;
        let mut acc = Splat2dGrad::default();
        for py in y0..=y1 {
            let row = (py - rect.1) as usize * tw;
            for px in x0..=x1 {
                let i = row + (px - rect.0) as usize;
                if k >= last[i] {
                    continue;
                }
                let Some(a) = alpha_at(s, px as f32 + 0.5, py as f32 + 0.5) else {
                    continue;
                };
                let g = grad[i];
                let one_minus = 1.0 - a.alpha;
                let t_i = trans[i] / one_minus;
                let gc = g[0] * s.rgb[0] + g[1] * s.rgb[1] + g[2] * s.rgb[2];
                let w = a.alpha * t_i;
                for (acc, gc) in acc.rgb.iter_mut().zip(g) {
                    *acc += gc * w;
                }
                let d_alpha = t_i * gc - after[i] / one_minus;
                after[i] += gc * w;
                trans[i] = t_i;
                if !a.clamped {
                    acc.opacity += d_alpha * a.g;
                    let d_sigma = -d_alpha * a.alpha;
                    acc.a += d_sigma * 0.5 * a.dx * a.dx;
                    acc.b += d_sigma * a.dx * a.dy;
                    acc.c += d_sigma * 0.5 * a.dy * a.dy;
                    // d = pixel - mean, so d sigma / d u = -(a dx + b dy).
                    acc.u -= d_sigma * (s.a * a.dx + s.b * a.dy);
                    acc.v -= d_sigma * (s.b * a.dx + s.c * a.dy);
                }
            }
        }
        slots[k as usize] = acc;
    }
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
