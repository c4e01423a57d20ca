//! VGG16's convolution stack on the CPU, for the perceptual loss: the forward pass of two
//! images, the L1 distance of their five taps, and the gradient of that distance with respect
//! to the images. The weights are frozen, so no weight gradient is ever formed.
//!
//! Why: through burn's generic ops (flex), one loss evaluation at 138 x 200 (reference pass,
//! render pass, backward) took about twice PyTorch's time, most of it in the convolutions'
//! input gradients and the element-wise autodiff steps between them (ReLU masks, pooling,
//! the normalisation). Here everything is in one place on host memory:
//!
//! - maps are channels-last (`[H·W, C]`), so every gather copies runs of `C` floats;
//! - a convolution with at least [`WINOGRAD_MIN_CHANNELS`] channels on both sides (all but
//!   the first) is Winograd's minimal filtering F(2x2, 3x3) (Lavin and Gray, "Fast
//!   Algorithms for Convolutional Neural Networks", 2016): each 2x2 output tile is
//!   `Aᵀ [(G g Gᵀ) ⊙ (Bᵀ d B)] A` of its 4x4 input tile `d`, so a block of tiles is 16
//!   matrix products `M_ξ[tiles, C_out] = V_ξ[tiles, C_in] · U_ξ[C_in, C_out]`: 16 products
//!   per 4 pixels instead of 36, 2.25x fewer multiply-adds. The bias and the ReLU are
//!   applied in the output transform while the tile is in cache;
//! - the first convolution (3 input channels) keeps the column formulation: one product
//!   per block of pixels, `Y[block, C_out] = col[block, 9·C_in] · W[9·C_in, C_out]`;
//! - the input gradient of a 3x3 convolution (padding 1) is itself a 3x3 convolution of the
//!   masked output gradient with the kernel rotated by 180° and its channel axes swapped
//!   (`w_back`), so the backward runs the same routine; for Winograd, rotating `g` by 180°
//!   swaps rows 0 and 3 of `G` (`G J = P G`), so the backward's `U` is the forward's with
//!   indices 0 and 3 of both tile axes swapped and the channel axes transposed: the same
//!   16 matrices read with other strides, no second copy;
//! - a 2x2 max-pool's backward sends each output's gradient to the first maximum of its
//!   window (row-major scan, strict `>`: PyTorch's and burn's rule), which is recomputed from
//!   the saved pre-pool map.
//!
//! Thread mapping: a column convolution splits its pixels into blocks (a multiple of
//! rayon's thread count, each column matrix at most `COL_BLOCK` floats) and runs the blocks
//! on rayon, one single-threaded product each; with one block, its product runs on all
//! threads instead. A Winograd convolution does the same with blocks of tile rows
//! (`WINOGRAD_BLOCK` floats of transformed tiles), except on a map small enough to be one
//! block (`WINOGRAD_SHARED`): there the transforms are parallel over tile rows and the 16
//! products over ξ. Pooling is parallel over output rows.
//!
//! The reference twin is burn's own `Conv2d` / `max_pool2d` / `relu` stack
//! ([`crate::metrics::Features`]); `crate::metrics::perceptual`'s tests compare the loss and
//! its image gradient with it on both CPU backends.

use rayon::prelude::*;

use crate::gemm::{matmul, matmul_serial};
use crate::metrics::constants::{IMAGENET_MEAN, IMAGENET_STD};
use crate::metrics::nets::Net;
use crate::metrics::weights::HostWeights;

/// Floats of one block's column matrix (4 MiB): large enough that the product's packing of
/// the weights is paid over many pixels, small enough to stay in the last-level cache.
const COL_BLOCK: usize = 1 << 20;

/// Floats of one thread's Winograd block of transformed input and output tiles (2 MiB):
/// its 16 products read and write them, so they should stay in the core's cache.
const WINOGRAD_BLOCK: usize = 1 << 19;

/// Floats of transformed tiles up to which a map is one Winograd block shared by all
/// threads (16 MiB: VGG16's maps from conv3 on at 138 x 200; none at 550 x 802).
/// Measured per layer at 138 x 200 on the development machine (forward and input
/// gradient): on these deep maps the shared block was 2-60% faster than per-thread blocks,
/// on the larger maps 13-45% slower.
const WINOGRAD_SHARED: usize = 1 << 22;

/// Channels (input and output) from which a convolution runs as Winograd F(2x2, 3x3): with
/// 3 input channels the 16 transformed products are too thin to pay for the transforms.
pub const WINOGRAD_MIN_CHANNELS: usize = 16;

thread_local! {
    /// The calling thread's buffers for a shared Winograd block (transformed tiles,
    /// products), kept between convolutions: fresh ones would cost their page faults in
    /// every call. A nested call on the same thread finds them taken and uses fresh ones.
    static WINOGRAD_SCRATCH: std::cell::Cell<(Vec<f32>, Vec<f32>)> =
        const { std::cell::Cell::new((Vec::new(), Vec::new())) };
}

/// Winograd F(2x2, 3x3)'s filter transform `G` (4x3), after Lavin and Gray (2016), eq. 7.
const WINOGRAD_G: [[f32; 3]; 4] = [
    [1.0, 0.0, 0.0],
    [0.5, 0.5, 0.5],
    [0.5, -0.5, 0.5],
    [0.0, 0.0, 1.0],
];

/// One 3x3 convolution (padding 1, stride 1), in the column or the Winograd formulation.
#[derive(Debug)]
struct Layer {
    ci: usize,
    co: usize,
    /// A 2x2 max-pool (stride 2) on this convolution's input.
    pool_before: bool,
    /// Whether this convolution's ReLU output is one of the five taps.
    tap: bool,
    /// Forward weights `[9·C_in, C_out]`, rows ordered (ky, kx, c_in); empty for a
    /// Winograd layer.
    w: Vec<f32>,
    /// Input-gradient weights `[9·C_out, C_in]`, rows ordered (ky, kx, c_out): the kernel
    /// rotated by 180°; empty for a Winograd layer.
    w_back: Vec<f32>,
    /// Winograd-transformed weights `U = G g Gᵀ`, `[16, C_in, C_out]` (ξ = 4·a + b); empty
    /// for a column layer.
    u: Vec<f32>,
    bias: Vec<f32>,
}

/// torchvision's VGG16 `features[:30]` prepared for the CPU (see the module docs).
#[derive(Debug)]
pub struct VggCpu {
    layers: Vec<Layer>,
}

/// A channels-last map: `data[(y·w + x)·c + channel]`.
#[derive(Clone, Debug)]
struct Map {
    data: Vec<f32>,
    h: usize,
    w: usize,
}

/// What the backward pass of one image needs: every convolution's ReLU output.
#[derive(Debug)]
struct Activations {
    outputs: Vec<Map>,
}

/// The state the perceptual loss keeps for its backward pass (see [`VggCpu::loss`]).
#[derive(Debug)]
pub struct Saved {
    n: usize,
    h: usize,
    w: usize,
    /// Per image, the activations of the images whose gradient is wanted (`a`, `b`).
    acts: [Vec<Activations>; 2],
    /// Per image and tap, `sign(fa - fb) / count_tap`.
    tap_grads: Vec<Vec<Vec<f32>>>,
}

impl VggCpu {
    /// Prepares VGG16's weights (PyTorch's OIHW layout) for the CPU passes.
    ///
    /// # Panics
    /// If `host` is not VGG16 or its shapes are not [`Net::convs`]'.
    pub fn new(host: &HostWeights) -> Self {
        assert_eq!(host.net, Net::Vgg16, "the CPU perceptual network is VGG16");
        let layers = Net::Vgg16
            .convs()
            .iter()
            .zip(&host.convs)
            .map(|(spec, (w, b))| {
                assert!(
                    spec.kernel == 3 && spec.stride == 1 && spec.padding == 1,
                    "VGG16 convolutions are 3x3, stride 1, padding 1"
                );
                assert!(matches!(spec.pool_before, None | Some((2, 2))));
                let (ci, co) = (spec.in_channels, spec.out_channels);
                assert_eq!(w.shape, [co, ci, 3, 3], "VGG16 kernel shape");
                assert_eq!(b.shape, [co], "VGG16 bias shape");
                let (fwd, back) = column_weights(&w.data, ci, co);
                let winograd = ci >= WINOGRAD_MIN_CHANNELS && co >= WINOGRAD_MIN_CHANNELS;
                let (w, w_back, u) = if winograd {
                    (Vec::new(), Vec::new(), winograd_weights(&fwd, ci, co))
                } else {
                    (fwd, back, Vec::new())
                };
                Layer {
                    ci,
                    co,
                    pool_before: spec.pool_before.is_some(),
                    tap: spec.tap,
                    w,
                    w_back,
                    u,
                    bias: b.data.clone(),
                }
            })
            .collect();
        VggCpu { layers }
    }

    /// The five taps of one normalised image (and, with `keep_all`, every ReLU output).
    fn features(&self, x: Map, keep_all: bool) -> Activations {
        let mut outputs: Vec<Map> = Vec::with_capacity(self.layers.len());
        for (l, layer) in self.layers.iter().enumerate() {
            let src = if l == 0 { &x } else { &outputs[l - 1] };
            let pooled;
            let input = if layer.pool_before {
                pooled = max_pool(src, layer.ci);
                &pooled
            } else {
                src
            };
            let y = Map {
                data: layer.forward(&input.data, [input.h, input.w]),
                h: input.h,
                w: input.w,
            };
            // A map that is neither a tap nor wanted by the backward is freed once used.
            if l > 0 && !(keep_all || self.layers[l - 1].tap) {
                outputs[l - 1].data = Vec::new();
            }
            outputs.push(y);
        }
        Activations { outputs }
    }

    /// The perceptual loss of [`crate::metrics::VggPerceptual::forward`]: the sum over the
    /// five taps of the mean absolute difference of the VGG16 features of `a` and `b`
    /// (images in [0, 1], normalised with the ImageNet statistics first), and the state of
    /// [`VggCpu::backward`]: it holds what the gradient of input `k` (0: `a`, 1: `b`) needs
    /// when `keep[k]`, and nothing otherwise.
    ///
    /// # Shapes
    /// - `a`, `b`: `[N, 3, H, W]` row-major (channels first, as burn holds them)
    pub fn loss(
        &self,
        a: &[f32],
        b: &[f32],
        [n, h, w]: [usize; 3],
        keep: [bool; 2],
    ) -> (f64, Saved) {
        assert_eq!(a.len(), n * 3 * h * w, "perceptual loss: image a");
        assert_eq!(b.len(), n * 3 * h * w, "perceptual loss: image b");
        let taps: Vec<usize> = (0..self.layers.len())
            .filter(|&i| self.layers[i].tap)
            .collect();
        let mut sums = vec![0.0f64; taps.len()];
        let mut counts = vec![0usize; taps.len()];
        let mut per_image = Vec::with_capacity(n);
        for i in 0..n {
            let plane = 3 * h * w;
            let fa = self.features(normalise(&a[i * plane..][..plane], h, w), keep[0]);
            let fb = self.features(normalise(&b[i * plane..][..plane], h, w), keep[1]);
            let mut signs = Vec::with_capacity(taps.len());
            for (t, &l) in taps.iter().enumerate() {
                let (x, y) = (&fa.outputs[l].data, &fb.outputs[l].data);
                counts[t] = n * x.len();
                sums[t] += x
                    .par_chunks(1 << 14)
                    .zip(y.par_chunks(1 << 14))
                    .map(|(x, y)| {
                        x.iter()
                            .zip(y)
                            .map(|(p, q)| (p - q).abs() as f64)
                            .sum::<f64>()
                    })
                    .sum::<f64>();
                if keep[0] || keep[1] {
                    signs.push(
                        x.par_iter()
                            .zip(y.par_iter())
                            .map(|(p, q)| sign(p - q))
                            .collect::<Vec<f32>>(),
                    );
                }
            }
            per_image.push((keep[0].then_some(fa), keep[1].then_some(fb), signs));
        }
        let loss = sums
            .iter()
            .zip(&counts)
            .map(|(s, &c)| s / c.max(1) as f64)
            .sum();
        let mut acts = [Vec::new(), Vec::new()];
        let mut tap_grads = Vec::with_capacity(n);
        for (fa, fb, mut signs) in per_image {
            for (s, &c) in signs.iter_mut().zip(&counts) {
                let inv = 1.0 / c.max(1) as f32;
                s.par_iter_mut().for_each(|v| *v *= inv);
            }
            tap_grads.push(signs);
            acts[0].extend(fa);
            acts[1].extend(fb);
        }
        let saved = Saved {
            n,
            h,
            w,
            acts,
            tap_grads,
        };
        (loss, saved)
    }

    /// The gradient of `grad · loss` with respect to input `k` (0: `a`, 1: `b`), `[N, 3, H,
    /// W]` row-major; `None` when [`VggCpu::loss`] did not keep that input's state.
    pub fn backward(&self, saved: &Saved, k: usize, grad: f32) -> Option<Vec<f32>> {
        let acts = &saved.acts[k];
        if acts.len() != saved.n {
            return None;
        }
        // d|fa - fb| / dfb = -sign(fa - fb).
        let scale = if k == 0 { grad } else { -grad };
        let (h, w) = (saved.h, saved.w);
        let plane = h * w;
        let mut out = vec![0.0f32; saved.n * 3 * plane];
        for (i, act) in acts.iter().enumerate() {
            let mut taps = saved.tap_grads[i].iter().rev();
            let mut dy: Option<Vec<f32>> = None;
            for (l, layer) in self.layers.iter().enumerate().rev() {
                let y = &act.outputs[l];
                if layer.tap
                    && let Some(g) = taps.next()
                {
                    let d = dy.get_or_insert_with(|| vec![0.0; g.len()]);
                    d.par_iter_mut()
                        .zip(g.par_iter())
                        .for_each(|(d, g)| *d += scale * g);
                }
                let Some(mut d) = dy.take() else { continue };
                // Through the ReLU: the gradient passes where the output is positive.
                d.par_iter_mut().zip(y.data.par_iter()).for_each(|(d, y)| {
                    if *y <= 0.0 {
                        *d = 0.0;
                    }
                });
                let dx = layer.input_gradient(&d, [y.h, y.w]);
                dy = Some(if layer.pool_before {
                    let pre = &act.outputs[l - 1];
                    max_pool_backward(&dx, [y.h, y.w], pre, layer.ci)
                } else {
                    dx
                });
            }
            // Through the normalisation, back to channels first.
            let d = dy.unwrap_or_else(|| vec![0.0; 3 * plane]);
            let o = &mut out[i * 3 * plane..][..3 * plane];
            for c in 0..3 {
                let inv = 1.0 / IMAGENET_STD[c];
                for p in 0..plane {
                    o[c * plane + p] = d[p * 3 + c] * inv;
                }
            }
        }
        Some(out)
    }
}

/// `sign(x)` with `sign(0) = 0` (the subgradient burn's `abs` uses).
fn sign(x: f32) -> f32 {
    if x > 0.0 {
        1.0
    } else if x < 0.0 {
        -1.0
    } else {
        0.0
    }
}

/// One channels-first RGB image in [0, 1] → channels-last, ImageNet-normalised.
fn normalise(img: &[f32], h: usize, w: usize) -> Map {
    let plane = h * w;
    let mut data = vec![0.0f32; 3 * plane];
    for c in 0..3 {
        let (m, inv) = (IMAGENET_MEAN[c], 1.0 / IMAGENET_STD[c]);
        for p in 0..plane {
            data[p * 3 + c] = (img[c * plane + p] - m) * inv;
        }
    }
    Map { data, h, w }
}

/// Gathers the column matrix of pixels `p0 .. p0 + np` of a channels-last map `x` [H·W, C]
/// for a 3x3 kernel with padding 1: `col[(p - p0)·9C + (ky·3 + kx)·C + c] = x[y+ky-1,
/// x+kx-1, c]`, zero outside the map.
fn im2col(x: &[f32], [h, w]: [usize; 2], c: usize, p0: usize, col: &mut [f32]) {
    let k = 9 * c;
    for (r, row) in col.chunks_exact_mut(k).enumerate() {
        let (py, px) = ((p0 + r) / w, (p0 + r) % w);
        for ky in 0..3 {
            let sy = py + ky;
            for kx in 0..3 {
                let sx = px + kx;
                let dst = &mut row[(ky * 3 + kx) * c..][..c];
                if sy >= 1 && sy <= h && sx >= 1 && sx <= w {
                    let s = ((sy - 1) * w + (sx - 1)) * c;
                    dst.copy_from_slice(&x[s..s + c]);
                } else {
                    dst.fill(0.0);
                }
            }
        }
    }
}

/// A 3x3 convolution (padding 1, stride 1) of a channels-last map `x` `[H·W, C_in]` with
/// weights `wm` `[9·C_in, C_out]`; with `bias`, the bias is added and the ReLU applied.
/// Returns `[H·W, C_out]`.
fn conv3x3(
    x: &[f32],
    [h, w]: [usize; 2],
    ci: usize,
    wm: &[f32],
    co: usize,
    bias: Option<&[f32]>,
) -> Vec<f32> {
    let p = h * w;
    let k = 9 * ci;
    debug_assert_eq!(x.len(), p * ci);
    debug_assert_eq!(wm.len(), k * co);
    let mut out = vec![0.0f32; p * co];
    if p == 0 || co == 0 {
        return out;
    }
    let threads = rayon::current_num_threads().max(1);
    let mut blocks = p.div_ceil((COL_BLOCK / k).max(1));
    blocks = blocks.div_ceil(threads) * threads;
    let block = p.div_ceil(blocks.min(p));
    let one_block = block >= p;
    out.par_chunks_mut(block * co).enumerate().for_each_init(
        Vec::new,
        |col: &mut Vec<f32>, (bi, o)| {
            let np = o.len() / co;
            col.resize(np * k, 0.0);
            im2col(x, [h, w], ci, bi * block, col);
            let product = if one_block { matmul } else { matmul_serial };
            product([np, co, k], o, [co, 1], false, col, [k, 1], wm, [co, 1]);
            if let Some(b) = bias {
                for row in o.chunks_exact_mut(co) {
                    for (v, b) in row.iter_mut().zip(b) {
                        *v = (*v + b).max(0.0);
                    }
                }
            }
        },
    );
    out
}

impl Layer {
    /// The convolution, its bias and its ReLU: `[H·W, C_in]` → `[H·W, C_out]`.
    fn forward(&self, x: &[f32], hw: [usize; 2]) -> Vec<f32> {
        if self.u.is_empty() {
            conv3x3(x, hw, self.ci, &self.w, self.co, Some(&self.bias))
        } else {
            conv3x3_winograd(x, hw, [self.ci, self.co], &self.u, false, Some(&self.bias))
        }
    }

    /// The gradient of the convolution's input from that of its output (before the ReLU):
    /// `[H·W, C_out]` → `[H·W, C_in]`.
    fn input_gradient(&self, dy: &[f32], hw: [usize; 2]) -> Vec<f32> {
        if self.u.is_empty() {
            conv3x3(dy, hw, self.co, &self.w_back, self.ci, None)
        } else {
            conv3x3_winograd(dy, hw, [self.co, self.ci], &self.u, true, None)
        }
    }
}

/// PyTorch's OIHW 3x3 kernel → the column weights (forward `[9·C_in, C_out]`, input
/// gradient `[9·C_out, C_in]` with the kernel rotated by 180°; see [`Layer`]).
fn column_weights(oihw: &[f32], ci: usize, co: usize) -> (Vec<f32>, Vec<f32>) {
    let at = |o: usize, i: usize, ky: usize, kx: usize| oihw[((o * ci + i) * 3 + ky) * 3 + kx];
    let mut fwd = vec![0.0f32; 9 * ci * co];
    let mut back = vec![0.0f32; 9 * co * ci];
    for ky in 0..3 {
        for kx in 0..3 {
            let t = ky * 3 + kx;
            for i in 0..ci {
                for o in 0..co {
                    fwd[(t * ci + i) * co + o] = at(o, i, ky, kx);
                    back[(t * co + o) * ci + i] = at(o, i, 2 - ky, 2 - kx);
                }
            }
        }
    }
    (fwd, back)
}

/// `U = G g Gᵀ` for every channel pair, from column weights `[9·C_in, C_out]` (rows
/// ordered (ky, kx, c_in)) to `[16, C_in, C_out]`.
fn winograd_weights(w: &[f32], ci: usize, co: usize) -> Vec<f32> {
    let mut u = vec![0.0f32; 16 * ci * co];
    for i in 0..ci {
        for o in 0..co {
            let g = |ky: usize, kx: usize| w[((ky * 3 + kx) * ci + i) * co + o];
            for (a, ga) in WINOGRAD_G.iter().enumerate() {
                for (b, gb) in WINOGRAD_G.iter().enumerate() {
                    let mut s = 0.0f32;
                    for (ky, gay) in ga.iter().enumerate() {
                        for (kx, gbx) in gb.iter().enumerate() {
                            s += gay * g(ky, kx) * gbx;
                        }
                    }
                    u[((a * 4 + b) * ci + i) * co + o] = s;
                }
            }
        }
    }
    u
}

/// The index of `U` that the 180°-rotated kernel's transform takes at tile position `ξ`:
/// rows 0 and 3 of `G` swap on both axes (see the module docs).
fn rotated(xi: usize) -> usize {
    let flip = |a: usize| match a {
        0 => 3,
        3 => 0,
        a => a,
    };
    flip(xi / 4) * 4 + flip(xi % 4)
}

/// A 3x3 convolution (padding 1, stride 1) as Winograd F(2x2, 3x3) of a channels-last map
/// `x` `[H·W, C_in]` with `[c_in, c_out] = channels`; with `bias`, the bias is added and
/// the ReLU applied. `u` is [`winograd_weights`]' `[16, C_in, C_out]`, or, with `rotate`,
/// the forward layer's `[16, C_out, C_in]` read as its 180°-rotated, channel-swapped kernel
/// (the input gradient). Returns `[H·W, C_out]`.
///
/// Three steps: the input transform `V = Bᵀ d B` of every 4x4 input tile, 16 products
/// `M_ξ = V_ξ U_ξ`, and the output transform `Aᵀ M A` (with bias and ReLU) into the 2x2
/// pixels each tile covers. Two thread mappings:
/// - a map whose transformed tiles fit [`WINOGRAD_SHARED`] floats (the deep, small maps)
///   is one block on all threads: transforms parallel over tile rows, the products
///   parallel over ξ, so each `U_ξ` (up to 1 MiB) is packed once and the products are as
///   tall as the map has tiles;
/// - a larger map is cut into blocks of tile rows, [`WINOGRAD_BLOCK`] floats at most and a
///   multiple of the thread count, each block all three steps on one thread, so its tiles
///   stay in that core's cache.
fn conv3x3_winograd(
    x: &[f32],
    hw: [usize; 2],
    channels: [usize; 2],
    u: &[f32],
    rotate: bool,
    bias: Option<&[f32]>,
) -> Vec<f32> {
    winograd_mapped(x, hw, channels, (u, rotate), bias, WINOGRAD_SHARED)
}

/// [`conv3x3_winograd`] with the shared-block limit as an argument (tests take either
/// mapping with it).
fn winograd_mapped(
    x: &[f32],
    [h, w]: [usize; 2],
    [ci, co]: [usize; 2],
    (u, rotate): (&[f32], bool),
    bias: Option<&[f32]>,
    shared: usize,
) -> Vec<f32> {
    debug_assert_eq!(x.len(), h * w * ci);
    debug_assert_eq!(u.len(), 16 * ci * co);
    let mut out = vec![0.0f32; h * w * co];
    if h == 0 || w == 0 || co == 0 {
        return out;
    }
    let (tiles_h, tiles_w) = (h.div_ceil(2), w.div_ceil(2));
    let zero = vec![0.0f32; ci];
    // Transforms one 4x4 input tile (tile row `ty`, column `tx`) into `vt` `[16, C_in]`.
    let transform = |ty: usize, tx: usize, vt: &mut [f32], t: &mut [f32]| {
        let mut d: [&[f32]; 16] = [&zero[..]; 16];
        for dy in 0..4 {
            let sy = 2 * ty + dy;
            if sy == 0 || sy > h {
                continue;
            }
            for dx in 0..4 {
                let sx = 2 * tx + dx;
                if sx == 0 || sx > w {
                    continue;
                }
                let s = ((sy - 1) * w + sx - 1) * ci;
                d[dy * 4 + dx] = &x[s..s + ci];
            }
        }
        input_transform(&d, vt, t, ci);
    };
    // `U_ξ` and its strides as the `[C_in, C_out]` right-hand side of product ξ.
    let weights = |xi: usize| {
        if rotate {
            (&u[rotated(xi) * ci * co..][..ci * co], [1, ci])
        } else {
            (&u[xi * ci * co..][..ci * co], [co, 1])
        }
    };
    let row_floats = tiles_w * 16 * (ci + co);
    if tiles_h * row_floats <= shared {
        let nt = tiles_h * tiles_w;
        // Empty when a call further up this thread holds them: then they grow fresh.
        let (mut v, mut m) = WINOGRAD_SCRATCH.take();
        v.resize(nt * 16 * ci, 0.0);
        m.resize(nt * 16 * co, 0.0);
        // V: [tile, ξ, C_in], one task per tile row.
        v.par_chunks_mut(tiles_w * 16 * ci)
            .enumerate()
            .for_each_init(Vec::new, |t: &mut Vec<f32>, (ty, vr)| {
                t.resize(16 * ci, 0.0);
                for (tx, vt) in vr.chunks_exact_mut(16 * ci).enumerate() {
                    transform(ty, tx, vt, t);
                }
            });
        // M: [ξ, tile, C_out], one task per ξ.
        m.par_chunks_mut(nt * co).enumerate().for_each(|(xi, mx)| {
            let (ux, strides) = weights(xi);
            matmul_serial(
                [nt, co, ci],
                mx,
                [co, 1],
                false,
                &v[xi * ci..],
                [16 * ci, 1],
                ux,
                strides,
            );
        });
        let products = &m;
        out.par_chunks_mut(2 * w * co).enumerate().for_each_init(
            || (Vec::new(), Vec::new()),
            |(mt, s): &mut (Vec<f32>, Vec<f32>), (ty, pair)| {
                s.resize(8 * co, 0.0);
                write_tile_row(pair, [w, co], [mt, s], bias, |tx, mt| {
                    for xi in 0..16 {
                        let at = (xi * nt + ty * tiles_w + tx) * co;
                        mt.extend_from_slice(&products[at..][..co]);
                    }
                });
            },
        );
        WINOGRAD_SCRATCH.set((v, m));
        return out;
    }
    let threads = rayon::current_num_threads().max(1);
    let mut blocks = tiles_h.div_ceil((WINOGRAD_BLOCK / row_floats).max(1));
    blocks = blocks.div_ceil(threads) * threads;
    let rows = tiles_h.div_ceil(blocks.min(tiles_h));
    out.par_chunks_mut(2 * rows * w * co)
        .enumerate()
        .for_each_init(
            || (Vec::new(), Vec::new(), Vec::new(), Vec::new()),
            |(v, m, s, mt): &mut (Vec<f32>, Vec<f32>, Vec<f32>, Vec<f32>), (bi, o)| {
                let nt = (o.len() / (w * co)).div_ceil(2) * tiles_w;
                v.resize(nt * 16 * ci, 0.0);
                m.resize(nt * 16 * co, 0.0);
                s.resize(16 * ci.max(co), 0.0);
                // V: [tile, ξ, C_in].
                for (t, vt) in v.chunks_exact_mut(16 * ci).enumerate() {
                    transform(bi * rows + t / tiles_w, t % tiles_w, vt, s);
                }
                // M: [tile, ξ, C_out].
                for xi in 0..16 {
                    let (ux, strides) = weights(xi);
                    matmul_serial(
                        [nt, co, ci],
                        &mut m[xi * co..],
                        [16 * co, 1],
                        false,
                        &v[xi * ci..],
                        [16 * ci, 1],
                        ux,
                        strides,
                    );
                }
                for (r, pair) in o.chunks_mut(2 * w * co).enumerate() {
                    let m = &m[r * tiles_w * 16 * co..];
                    write_tile_row(pair, [w, co], [mt, s], bias, |tx, mt| {
                        mt.extend_from_slice(&m[tx * 16 * co..][..16 * co]);
                    });
                }
            },
        );
    out
}

/// The output transform of one row of tiles into `pair`, the (one or two) output rows it
/// covers (`[rows·W, C_out]`); `gather(tx, mt)` puts tile `tx`'s products `[16, C_out]`
/// into `mt`, and `s` is [`output_transform`]'s scratch.
fn write_tile_row(
    pair: &mut [f32],
    [w, co]: [usize; 2],
    [mt, s]: [&mut Vec<f32>; 2],
    bias: Option<&[f32]>,
    gather: impl Fn(usize, &mut Vec<f32>),
) {
    let (top, bottom) = pair.split_at_mut((w * co).min(pair.len()));
    let mut top = top.chunks_exact_mut(co);
    let mut bottom = bottom.chunks_exact_mut(co);
    for tx in 0..w.div_ceil(2) {
        let y = [top.next(), top.next(), bottom.next(), bottom.next()];
        mt.clear();
        gather(tx, mt);
        output_transform(mt, y, s, co, bias);
    }
}

/// `V = Bᵀ d B` of one 4x4 tile of channel vectors `d` (row-major, each `c` long) into
/// `v` `[16, c]`, with Lavin and Gray's `Bᵀ` rows (1, 0, -1, 0), (0, 1, 1, 0),
/// (0, -1, 1, 0), (0, 1, 0, -1). `t` is scratch of `16·c` floats. Every step is one
/// element-wise pass over channel vectors, so it runs in SIMD lanes.
fn input_transform(d: &[&[f32]; 16], v: &mut [f32], t: &mut [f32], c: usize) {
    // t = Bᵀ d, row by row of the result (each a 4-vector of columns).
    let (t, v) = (&mut t[..16 * c], &mut v[..16 * c]);
    let mut rows = t.chunks_exact_mut(4 * c);
    for (r, (p, q)) in [(0, 2), (1, 2), (2, 1), (1, 3)].into_iter().enumerate() {
        let tr = rows.next().expect("four rows");
        for col in 0..4 {
            let (a, b) = (&d[p * 4 + col][..c], &d[q * 4 + col][..c]);
            sum_or_difference(&mut tr[col * c..][..c], a, b, r == 1);
        }
    }
    // V = t B: the same combination along each row.
    for (tr, vr) in t.chunks_exact(4 * c).zip(v.chunks_exact_mut(4 * c)) {
        let col = |k: usize| &tr[k * c..][..c];
        for (k, o) in vr.chunks_exact_mut(c).enumerate() {
            let (p, q) = [(0, 2), (1, 2), (2, 1), (1, 3)][k];
            sum_or_difference(o, col(p), col(q), k == 1);
        }
    }
}

/// `o = a + b` with `add`, `o = a - b` without, element-wise.
fn sum_or_difference(o: &mut [f32], a: &[f32], b: &[f32], add: bool) {
    let pairs = o.iter_mut().zip(a).zip(b);
    if add {
        pairs.for_each(|((o, a), b)| *o = a + b);
    } else {
        pairs.for_each(|((o, a), b)| *o = a - b);
    }
}

/// `Y = Aᵀ M A` of one tile's products `m` `[16, c]` (Lavin and Gray's `Aᵀ` rows
/// (1, 1, 1, 0), (0, 1, -1, -1)) into the 2x2 output pixels `y` (row-major, each `c` long;
/// `None` past the map's edge), plus `bias` and the ReLU when given. `s` is scratch of
/// `8·c` floats.
fn output_transform(
    m: &[f32],
    y: [Option<&mut [f32]>; 4],
    s: &mut [f32],
    c: usize,
    bias: Option<&[f32]>,
) {
    let (m, s) = (&m[..16 * c], &mut s[..8 * c]);
    let row = |r: usize, k: usize| &m[(r * 4 + k) * c..][..c];
    // s = Aᵀ M (2 x 4 vectors).
    for (k, o) in s.chunks_exact_mut(c).enumerate() {
        let (r, col) = (k / 4, k % 4);
        let (a, b, d) = if r == 0 {
            (row(0, col), row(1, col), row(2, col))
        } else {
            (row(1, col), row(2, col), row(3, col))
        };
        if r == 0 {
            o.iter_mut()
                .zip(a)
                .zip(b)
                .zip(d)
                .for_each(|(((o, a), b), d)| *o = a + b + d);
        } else {
            o.iter_mut()
                .zip(a)
                .zip(b)
                .zip(d)
                .for_each(|(((o, a), b), d)| *o = a - b - d);
        }
    }
    // Y = s A.
    for (k, out) in y.into_iter().enumerate() {
        let Some(out) = out else { continue };
        let (r, col) = (k / 2, k % 2);
        let sv = |j: usize| &s[(r * 4 + j) * c..][..c];
        let (a, b, d) = if col == 0 {
            (sv(0), sv(1), sv(2))
        } else {
            (sv(1), sv(2), sv(3))
        };
        let sgn = if col == 0 { 1.0 } else { -1.0 };
        let out = &mut out[..c];
        match bias {
            Some(bias) => out
                .iter_mut()
                .zip(a)
                .zip(b)
                .zip(d)
                .zip(&bias[..c])
                .for_each(|((((o, a), b), d), z)| {
                    let v = if col == 0 { a + b + d } else { a - b - d };
                    *o = (v + z).max(0.0);
                }),
            None => out
                .iter_mut()
                .zip(a)
                .zip(b)
                .zip(d)
                .for_each(|(((o, a), b), d)| *o = a + sgn * (b + d)),
        }
    }
}

/// 2x2 max-pool with stride 2 (odd trailing rows and columns dropped, as PyTorch's default
/// `ceil_mode=False`) of a channels-last map with `c` channels.
fn max_pool(x: &Map, c: usize) -> Map {
    let (ho, wo) = (x.h / 2, x.w / 2);
    let mut data = vec![0.0f32; ho * wo * c];
    if ho > 0 && wo > 0 {
        data.par_chunks_mut(wo * c)
            .enumerate()
            .for_each(|(oy, row)| {
                for ox in 0..wo {
                    let o = &mut row[ox * c..][..c];
                    let at = |dy: usize, dx: usize| ((2 * oy + dy) * x.w + 2 * ox + dx) * c;
                    o.copy_from_slice(&x.data[at(0, 0)..][..c]);
                    for (dy, dx) in [(0, 1), (1, 0), (1, 1)] {
                        for (m, v) in o.iter_mut().zip(&x.data[at(dy, dx)..][..c]) {
                            if *v > *m || v.is_nan() {
                                *m = *v;
                            }
                        }
                    }
                }
            });
    }
    Map { data, h: ho, w: wo }
}

/// The backward of [`max_pool`]: `dy` `[H_o·W_o, C]` → the gradient of the pre-pool map
/// `x`, each output's gradient sent to the first maximum of its window.
fn max_pool_backward(dy: &[f32], [ho, wo]: [usize; 2], x: &Map, c: usize) -> Vec<f32> {
    let mut dx = vec![0.0f32; x.h * x.w * c];
    if ho == 0 || wo == 0 {
        return dx;
    }
    // Each task owns the two input rows under one output row.
    dx.par_chunks_mut(2 * x.w * c)
        .take(ho)
        .enumerate()
        .for_each(|(oy, rows)| {
            for ox in 0..wo {
                for ch in 0..c {
                    let at = |dy: usize, dx: usize| ((2 * oy + dy) * x.w + 2 * ox + dx) * c + ch;
                    let mut best = (0, 0);
                    let mut m = x.data[at(0, 0)];
                    for (dy, dx) in [(0, 1), (1, 0), (1, 1)] {
                        let v = x.data[at(dy, dx)];
                        if v > m || v.is_nan() {
                            m = v;
                            best = (dy, dx);
                        }
                    }
                    rows[(best.0 * x.w + 2 * ox + best.1) * c + ch] += dy[(oy * wo + ox) * c + ch];
                }
            }
        });
    dx
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A direct (loop) 3x3 convolution, channels-last, OIHW weights.
    fn direct(
        x: &[f32],
        [h, w]: [usize; 2],
        ci: usize,
        oihw: &[f32],
        co: usize,
        bias: &[f32],
    ) -> Vec<f32> {
        let mut y = vec![0.0f32; h * w * co];
        for py in 0..h {
            for px in 0..w {
                for o in 0..co {
                    let mut s = bias[o] as f64;
                    for ky in 0..3 {
                        for kx in 0..3 {
                            let (sy, sx) = (py + ky, px + kx);
                            if sy < 1 || sy > h || sx < 1 || sx > w {
                                continue;
                            }
                            for i in 0..ci {
                                s += x[((sy - 1) * w + sx - 1) * ci + i] as f64
                                    * oihw[((o * ci + i) * 3 + ky) * 3 + kx] as f64;
                            }
                        }
                    }
                    y[(py * w + px) * co + o] = (s as f32).max(0.0);
                }
            }
        }
        y
    }

    fn values(n: usize, seed: usize) -> Vec<f32> {
        (0..n)
            .map(|i| (((i * 7919 + seed * 104_729) % 1000) as f32 / 500.0) - 1.0)
            .collect()
    }

    #[test]
    fn column_convolution_matches_direct_loops() {
        let (h, w, ci, co) = (5, 7, 3, 4);
        let x = values(h * w * ci, 1);
        let oihw = values(co * ci * 9, 2);
        let bias = values(co, 3);
        let (fwd, _) = column_weights(&oihw, ci, co);
        let y = conv3x3(&x, [h, w], ci, &fwd, co, Some(&bias));
        let want = direct(&x, [h, w], ci, &oihw, co, &bias);
        for (a, b) in y.iter().zip(&want) {
            assert!((a - b).abs() < 1e-5, "{a} vs {b}");
        }
    }

    /// The largest difference relative to the largest magnitude of `want`.
    fn max_rel(got: &[f32], want: &[f32]) -> f32 {
        assert_eq!(got.len(), want.len());
        let scale = want.iter().fold(1e-12f32, |m, v| m.max(v.abs()));
        got.iter()
            .zip(want)
            .fold(0.0f32, |m, (a, b)| m.max((a - b).abs() / scale))
    }

    /// Winograd against the direct loops (forward, with bias and ReLU) and, read as the
    /// rotated kernel, against the column formulation's input gradient (itself checked
    /// against the loops above), in both thread mappings. Odd sizes give partial tiles at
    /// the right and bottom edges; with per-thread blocks the maps split into several
    /// blocks of tile rows.
    #[test]
    fn winograd_matches_direct_loops_and_columns() {
        for (h, w, ci, co) in [
            (5, 7, 16, 24),
            (6, 4, 17, 16),
            (1, 1, 16, 16),
            (9, 3, 32, 16),
            (2, 2, 16, 20),
        ] {
            let x = values(h * w * ci, 4);
            let oihw = values(co * ci * 9, 5);
            let bias = values(co, 6);
            let (fwd, back) = column_weights(&oihw, ci, co);
            let u = winograd_weights(&fwd, ci, co);
            let want_y = direct(&x, [h, w], ci, &oihw, co, &bias);
            let dy = values(h * w * co, 7);
            let want_dx = conv3x3(&dy, [h, w], co, &back, ci, None);
            for shared in [0, usize::MAX] {
                let y = winograd_mapped(&x, [h, w], [ci, co], (&u, false), Some(&bias), shared);
                let e = max_rel(&y, &want_y);
                assert!(e < 1e-5, "forward {h}x{w} {ci}->{co}, {shared}: {e}");
                let dx = winograd_mapped(&dy, [h, w], [co, ci], (&u, true), None, shared);
                let e = max_rel(&dx, &want_dx);
                assert!(e < 1e-5, "input gradient {h}x{w} {co}->{ci}, {shared}: {e}");
            }
        }
        // The public entry point takes the same path as one of the two.
        let (ci, co) = (16, 16);
        let x = values(9 * 7 * ci, 8);
        let u = winograd_weights(&values(9 * ci * co, 9), ci, co);
        assert_eq!(
            conv3x3_winograd(&x, [9, 7], [ci, co], &u, false, None),
            winograd_mapped(&x, [9, 7], [ci, co], (&u, false), None, usize::MAX)
        );
    }

    #[test]
    fn pooling_takes_the_first_maximum_and_drops_odd_edges() {
        // One channel, 3 x 4: the last row is dropped; window 0 has a tie (first wins).
        let x = Map {
            data: vec![2.0, 2.0, 0.0, 1.0, 1.0, 0.0, 5.0, 3.0, 9.0, 9.0, 9.0, 9.0],
            h: 3,
            w: 4,
        };
        let y = max_pool(&x, 1);
        assert_eq!((y.h, y.w), (1, 2));
        assert_eq!(y.data, [2.0, 5.0]);
        let dx = max_pool_backward(&[10.0, 20.0], [1, 2], &x, 1);
        assert_eq!(
            dx,
            [10.0, 0.0, 0.0, 0.0, 0.0, 0.0, 20.0, 0.0, 0.0, 0.0, 0.0, 0.0]
        );
    }
}
