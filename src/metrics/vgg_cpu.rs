//! VGG16's convolution stack on the CPU, for the perceptual loss: the forward pass of two
//! images, the L1 distance of their five taps, and the gradient of that distance with respect
//! to the images. The weights are frozen, so no weight gradient is ever formed.
//!
//! Why: through burn's generic ops (flex), one loss evaluation at 138 x 200 (reference pass,
//! render pass, backward) was much slower than PyTorch's, most of the time going to the
//! convolutions' input gradients and the element-wise autodiff steps between them (ReLU
//! masks, pooling, the normalisation). Here everything is in one place on host memory:
//!
//! - maps are channels-last (`[H·W, C]`), so every gather copies runs of `C` floats;
//! - a convolution with at least [`WINOGRAD_MIN_CHANNELS`] channels on both sides (all but
//!   the first) is one of Winograd's minimal filtering algorithms F(m x m, 3x3) (Lavin and
//!   Gray, "Fast Algorithms for Convolutional Neural Networks", 2016): each m x m output
//!   tile is `Aᵀ [(G g Gᵀ) ⊙ (Bᵀ d B)] A` of its α x α input tile `d` (α = m + 2), so a
//!   block of tiles is α² matrix products `M_ξ[tiles, C_out] = V_ξ[tiles, C_in] ·
//!   U_ξ[C_in, C_out]`. F(4x4, 3x3) (36 products per 16 pixels, 4x fewer multiply-adds than
//!   the direct convolution) runs the layers of up to 256 channels; the 512-channel layers
//!   keep F(2x2, 3x3) (16 per 4, 2.25x fewer), whose weights are 2.25x smaller and whose
//!   maps at 138 x 200 (25 x 17, 12 x 8) give F(4x4) too few tiles per product: timed per
//!   layer at 138 x 200 (forward and input gradient), F(4x4) is clearly faster on the 64-
//!   to 256-channel layers, about even on the 25 x 17 maps and slower on the 12 x 8 ones.
//!   The bias and the ReLU are applied in the output transform while the tile is in cache;
//! - the first convolution (3 input channels) keeps the column formulation: one product
//!   per block of pixels, `Y[block, C_out] = col[block, 9·C_in] · W[9·C_in, C_out]`;
//! - the input gradient of a 3x3 convolution (padding 1) is itself a 3x3 convolution of the
//!   masked output gradient with the kernel rotated by 180° and its channel axes swapped,
//!   so the backward runs the same routine with those weights (`u_back`, transformed once;
//!   stored contiguous, because read in place from the forward's with transposed strides
//!   every product would pack them element by element);
//! - the first convolution's input gradient (3 output channels) is the product of the
//!   output gradient with the transposed weights, then a sum over the nine taps
//!   (`conv3x3_input_gradient`);
//! - a 2x2 max-pool's backward sends each output's gradient to the first maximum of its
//!   window (row-major scan, strict `>`: PyTorch's and burn's rule), which is recomputed from
//!   the saved pre-pool map;
//! - the backward passes over each map once: the ReLU's mask is applied in the Winograd
//!   output transform of the input gradient (`Epilogue::ReluMask`), or, where a pool lies
//!   between, in the pool's backward together with the tap's direct gradient
//!   (`pool_relu_backward`); the loss's sum and the taps' gradients are one pass.
//!
//! Thread mapping: a column convolution splits its pixels into blocks (a multiple of
//! rayon's thread count, each column matrix and each output at most `COL_BLOCK` floats) and
//! runs the blocks on rayon, one single-threaded product each. A Winograd convolution does the same with blocks of tile rows
//! (`WINOGRAD_BLOCK` floats of transformed tiles), except on a map small enough to be one
//! block (`WINOGRAD_SHARED`): there the transforms are parallel over tile rows and the α²
//! products over ξ. In the forward pass the two images of a loss evaluation go through
//! each Winograd layer together where the tiles of both fit that shared block
//! (`winograd_many`; conv3 on at 138 x 200): the α² products take the tiles of both, so
//! each `U_ξ` is packed and read once for the pair. Pooling is parallel over output rows,
//! its scan branch-free in vector lanes.
//!
//! The reference twin is burn's own `Conv2d` / `max_pool2d` / `relu` stack
//! ([`crate::metrics::Features`]); `crate::metrics::perceptual`'s tests compare the loss and
//! its image gradient with it on both CPU backends.

use std::mem::MaybeUninit;

use rayon::prelude::*;

use crate::gemm::{matmul_serial, matmul_serial_uninit, matmul_uninit};
use crate::metrics::constants::{IMAGENET_MEAN, IMAGENET_STD};
use crate::metrics::nets::Net;
use crate::metrics::weights::HostWeights;

/// Floats of the larger of one block's column matrix and its output (256 KiB): both stay in
/// the core's L2 cache from the gather through the product to the bias and ReLU. Chosen by
/// timing VGG16's first layer at 138 x 200 with blocks from 64 KiB to 1 MiB: 1 MiB (whose
/// output no longer fits the cache) was clearly slower, 128-256 KiB the fastest.
const COL_BLOCK: usize = 1 << 16;

/// Floats of one thread's Winograd block of transformed input and output tiles (1 MiB):
/// its α² products read and write them, so they should stay in the core's cache. Chosen by
/// timing VGG16's 64-channel layer at 138 x 200 with F(4x4, 3x3) on a machine with 2 MiB of
/// L2 per core (forward and input gradient): 1 MiB was faster than 512 KiB and 2 MiB.
const WINOGRAD_BLOCK: usize = 1 << 18;

/// Floats of transformed tiles up to which a map is one Winograd block shared by all
/// threads (16 MiB: VGG16's maps from conv2 on at 138 x 200; none at 550 x 802).
/// Chosen by timing each layer at 138 x 200 (forward and input gradient): with F(2x2, 3x3)
/// the shared block was faster than per-thread blocks on the maps from conv3 on and slower
/// on the larger maps; with F(4x4, 3x3), whose conv2 maps also fit, a limit of 8 MiB (conv2
/// and conv3 in per-thread blocks) was slower on those layers.
const WINOGRAD_SHARED: usize = 1 << 22;

/// Channels (input and output) from which a convolution runs as Winograd: with 3 input
/// channels the transformed products are too thin to pay for the transforms.
pub const WINOGRAD_MIN_CHANNELS: usize = 16;

/// Channels (the larger of input and output) up to which a Winograd convolution is
/// F(4x4, 3x3); above, F(2x2, 3x3). See [`winograd_for`].
const F4_MAX_CHANNELS: usize = 256;

thread_local! {
    /// The calling thread's buffers for a shared Winograd block (transformed tiles,
    /// products), kept between convolutions: fresh ones would cost their page faults in
    /// every call. A nested call on the same thread finds them taken and uses fresh ones.
    static WINOGRAD_SCRATCH: std::cell::Cell<(Vec<f32>, Vec<f32>)> =
        const { std::cell::Cell::new((Vec::new(), Vec::new())) };
}

/// One of Lavin and Gray's minimal filtering algorithms F(m x m, 3 x 3) ("Fast Algorithms
/// for Convolutional Neural Networks", 2016): output tiles of `m x m` pixels from input
/// tiles of `α x α` (α = m + 2), `Y = Aᵀ [(G g Gᵀ) ⊙ (Bᵀ d B)] A`, with `α²` products per
/// tile.
#[derive(Debug)]
struct Winograd {
    /// Output tile side `m`.
    m: usize,
    /// `Bᵀ`, α x α, row-major. The transforms are written out by hand; the tests check
    /// them against these matrices.
    #[cfg_attr(not(test), allow(dead_code))]
    bt: &'static [f32],
    /// `G`, α x 3, row-major.
    g: &'static [f32],
    /// `Aᵀ`, m x α, row-major (checked like `bt`).
    #[cfg_attr(not(test), allow(dead_code))]
    at: &'static [f32],
}

impl Winograd {
    /// Input tile side α.
    fn alpha(&self) -> usize {
        self.m + 2
    }

    /// Products per tile, α².
    fn products(&self) -> usize {
        self.alpha() * self.alpha()
    }
}

/// F(2x2, 3x3), Lavin and Gray's eq. 7: 16 products per 4 pixels, 2.25x fewer
/// multiply-adds than the direct convolution.
const F2: Winograd = Winograd {
    m: 2,
    #[rustfmt::skip]
    bt: &[
        1.0, 0.0, -1.0, 0.0,
        0.0, 1.0, 1.0, 0.0,
        0.0, -1.0, 1.0, 0.0,
        0.0, 1.0, 0.0, -1.0,
    ],
    #[rustfmt::skip]
    g: &[
        1.0, 0.0, 0.0,
        0.5, 0.5, 0.5,
        0.5, -0.5, 0.5,
        0.0, 0.0, 1.0,
    ],
    #[rustfmt::skip]
    at: &[
        1.0, 1.0, 1.0, 0.0,
        0.0, 1.0, -1.0, -1.0,
    ],
};

/// F(4x4, 3x3) of Lavin and Gray (interpolation points 0, ±1, ±2, ∞): 36 products per 16
/// pixels, 4x fewer multiply-adds than the direct convolution, for larger transforms and
/// larger float32 rounding (the tests hold both algorithms to 1e-5 of the largest value).
const F4: Winograd = Winograd {
    m: 4,
    #[rustfmt::skip]
    bt: &[
        4.0, 0.0, -5.0, 0.0, 1.0, 0.0,
        0.0, -4.0, -4.0, 1.0, 1.0, 0.0,
        0.0, 4.0, -4.0, -1.0, 1.0, 0.0,
        0.0, -2.0, -1.0, 2.0, 1.0, 0.0,
        0.0, 2.0, -1.0, -2.0, 1.0, 0.0,
        0.0, 4.0, 0.0, -5.0, 0.0, 1.0,
    ],
    #[rustfmt::skip]
    g: &[
        1.0 / 4.0, 0.0, 0.0,
        -1.0 / 6.0, -1.0 / 6.0, -1.0 / 6.0,
        -1.0 / 6.0, 1.0 / 6.0, -1.0 / 6.0,
        1.0 / 24.0, 1.0 / 12.0, 1.0 / 6.0,
        1.0 / 24.0, -1.0 / 12.0, 1.0 / 6.0,
        0.0, 0.0, 1.0,
    ],
    #[rustfmt::skip]
    at: &[
        1.0, 1.0, 1.0, 1.0, 1.0, 0.0,
        0.0, 1.0, -1.0, 2.0, -2.0, 0.0,
        0.0, 1.0, 1.0, 4.0, 4.0, 0.0,
        0.0, 1.0, -1.0, 8.0, -8.0, 1.0,
    ],
};

/// Products per tile of the largest [`Winograd`] (F(4x4, 3x3)).
const MAX_PRODUCTS: usize = 36;

/// Output pixels per tile of the largest [`Winograd`].
const MAX_PIXELS: usize = 16;

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
    /// Winograd layer. The input gradient reads them transposed
    /// ([`conv3x3_input_gradient`]).
    w: Vec<f32>,
    /// The Winograd algorithm of this layer; `None` for a column layer.
    winograd: Option<&'static Winograd>,
    /// Winograd-transformed weights `U = G g Gᵀ`, `[α², C_in, C_out]` (ξ = α·a + b); empty
    /// for a column layer.
    u: Vec<f32>,
    /// The input gradient's: those of the kernel rotated by 180° with its channel axes
    /// swapped, `[α², C_out, C_in]`; empty for a column layer.
    u_back: Vec<f32>,
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
                let fwd = column_weights(&w.data, ci, co);
                let winograd = winograd_for(ci, co);
                let (w, u, u_back) = match winograd {
                    Some(kind) => {
                        let back = rotated_column_weights(&w.data, ci, co);
                        let u = winograd_weights(&fwd, ci, co, kind);
                        (Vec::new(), u, winograd_weights(&back, co, ci, kind))
                    }
                    None => (fwd, Vec::new(), Vec::new()),
                };
                Layer {
                    ci,
                    co,
                    pool_before: spec.pool_before.is_some(),
                    tap: spec.tap,
                    w,
                    winograd,
                    u,
                    u_back,
                    bias: b.data.clone(),
                }
            })
            .collect();
        VggCpu { layers }
    }

    /// The five taps of normalised images of one size, layer by layer for all of them
    /// ([`Layer::forward_many`]), and, for image `i` with `keep_all[i]`, every ReLU output.
    fn features(&self, xs: Vec<Map>, keep_all: &[bool]) -> Vec<Activations> {
        let mut acts: Vec<Activations> = xs
            .iter()
            .map(|_| Activations {
                outputs: Vec::with_capacity(self.layers.len()),
            })
            .collect();
        for (l, layer) in self.layers.iter().enumerate() {
            let srcs: Vec<&Map> = if l == 0 {
                xs.iter().collect()
            } else {
                acts.iter().map(|a| &a.outputs[l - 1]).collect()
            };
            let pooled: Vec<Map>;
            let inputs: Vec<&Map> = if layer.pool_before {
                pooled = srcs.iter().map(|m| max_pool(m, layer.ci)).collect();
                pooled.iter().collect()
            } else {
                srcs
            };
            let Some(&&Map { h, w, .. }) = inputs.first() else {
                return acts;
            };
            let data: Vec<&[f32]> = inputs.iter().map(|m| &m.data[..]).collect();
            let ys = layer.forward_many(&data, [h, w]);
            for ((act, data), &keep) in acts.iter_mut().zip(ys).zip(keep_all) {
                // A map that is neither a tap nor wanted by the backward is freed once used.
                if l > 0 && !(keep || self.layers[l - 1].tap) {
                    act.outputs[l - 1].data = Vec::new();
                }
                act.outputs.push(Map { data, h, w });
            }
        }
        acts
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
            let pair = vec![
                normalise(&a[i * plane..][..plane], h, w),
                normalise(&b[i * plane..][..plane], h, w),
            ];
            let [fa, fb]: [Activations; 2] = self
                .features(pair, &keep)
                .try_into()
                .expect("one set of activations per image");
            let mut signs = Vec::with_capacity(taps.len());
            for (t, &l) in taps.iter().enumerate() {
                let (x, y) = (&fa.outputs[l].data, &fb.outputs[l].data);
                counts[t] = n * x.len();
                // One pass: the sum of |x - y| and, when a gradient is wanted, the tap's
                // gradient `sign(x - y) / count`.
                let inv = 1.0 / counts[t].max(1) as f32;
                let chunk = 1 << 14;
                sums[t] += if keep[0] || keep[1] {
                    let len = x.len();
                    let mut g: Vec<f32> = Vec::with_capacity(len);
                    let s = g.spare_capacity_mut()[..len]
                        .par_chunks_mut(chunk)
                        .zip(x.par_chunks(chunk).zip(y.par_chunks(chunk)))
                        .map(|(g, (x, y))| l1_distance(x, y, Some((g, inv))))
                        .sum::<f64>();
                    // SAFETY: `l1_distance` wrote every value of each chunk of `g`.
                    unsafe { g.set_len(len) };
                    signs.push(g);
                    s
                } else {
                    x.par_chunks(chunk)
                        .zip(y.par_chunks(chunk))
                        .map(|(x, y)| l1_distance(x, y, None))
                        .sum::<f64>()
                };
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
        for (fa, fb, signs) in per_image {
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
        // Which of the tap gradients each layer's output takes.
        let mut tap_of = vec![None; self.layers.len()];
        for (t, l) in (0..self.layers.len())
            .filter(|&l| self.layers[l].tap)
            .enumerate()
        {
            tap_of[l] = Some(t);
        }
        for (i, act) in acts.iter().enumerate() {
            let tap = |l: usize| tap_of[l].map(|t| (&saved.tap_grads[i][t][..], scale));
            // `d`: the gradient of layer `l`'s pre-ReLU output, complete (every path from
            // the loss, the ReLU's mask applied); `None` while no tap lies at or below `l`.
            let mut d: Option<Vec<f32>> = None;
            for (l, layer) in self.layers.iter().enumerate().rev() {
                let y = &act.outputs[l];
                if d.is_none()
                    && let Some(g) = tap(l)
                {
                    d = Some(tap_through_relu(g, &y.data));
                }
                let Some(dl) = d.take() else { continue };
                if l == 0 {
                    d = Some(layer.input_gradient(&dl, [y.h, y.w], None));
                    break;
                }
                let pre = &act.outputs[l - 1];
                d = Some(if layer.pool_before {
                    let dx = layer.input_gradient(&dl, [y.h, y.w], None);
                    pool_relu_backward(&dx, [y.h, y.w], pre, layer.ci, tap(l - 1))
                } else {
                    // The ReLU of layer `l - 1` in the transform's epilogue.
                    let mut dx = layer.input_gradient(&dl, [y.h, y.w], Some(&pre.data));
                    if let Some(g) = tap(l - 1) {
                        add_tap_and_mask(&mut dx, g, &pre.data);
                    }
                    dx
                });
            }
            // Through the normalisation, back to channels first.
            let d = d.unwrap_or_else(|| vec![0.0; 3 * plane]);
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

/// Lanes of [`l1_distance`]'s running sums.
const L1_LANES: usize = 8;

/// `Σ |x - y|` in `f64`, and with `g = Some((g, inv))` the tap's gradient `g = sign(x - y) ·
/// inv`, every value of which it writes. The sum runs in [`L1_LANES`] partial sums, so that
/// its adds do not wait for one another (one chain of dependent adds is bound by the add's
/// latency); with eight, what is left is mostly reading the taps.
fn l1_distance(x: &[f32], y: &[f32], mut g: Option<(&mut [MaybeUninit<f32>], f32)>) -> f64 {
    debug_assert_eq!(x.len(), y.len());
    if let Some((g, _)) = &g {
        debug_assert_eq!(g.len(), x.len());
    }
    let mut lanes = [0.0f64; L1_LANES];
    let whole = x.len() / L1_LANES * L1_LANES;
    for (k, (xs, ys)) in x[..whole]
        .chunks_exact(L1_LANES)
        .zip(y[..whole].chunks_exact(L1_LANES))
        .enumerate()
    {
        for l in 0..L1_LANES {
            lanes[l] += (xs[l] - ys[l]).abs() as f64;
        }
        if let Some((g, inv)) = g.as_mut() {
            for (l, g) in g[k * L1_LANES..][..L1_LANES].iter_mut().enumerate() {
                g.write(sign(xs[l] - ys[l]) * *inv);
            }
        }
    }
    let mut rest = 0.0f64;
    for j in whole..x.len() {
        rest += (x[j] - y[j]).abs() as f64;
        if let Some((g, inv)) = g.as_mut() {
            g[j].write(sign(x[j] - y[j]) * *inv);
        }
    }
    lanes.iter().sum::<f64>() + rest
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
    let len = p * co;
    if p == 0 || co == 0 {
        return vec![0.0f32; len];
    }
    let threads = rayon::current_num_threads().max(1);
    let mut blocks = p.div_ceil((COL_BLOCK / k.max(co)).max(1));
    blocks = blocks.div_ceil(threads) * threads;
    // At least as many blocks as threads, so each product runs on one thread.
    let block = p.div_ceil(blocks.min(p));
    // Written whole by the products, never read before: no zeroing pass first.
    let mut out = Vec::with_capacity(len);
    out.spare_capacity_mut()[..len]
        .par_chunks_mut(block * co)
        .enumerate()
        .for_each_init(Vec::new, |col: &mut Vec<f32>, (bi, o)| {
            let np = o.len() / co;
            col.resize(np * k, 0.0);
            im2col(x, [h, w], ci, bi * block, col);
            matmul_serial_uninit([np, co, k], o, col, [k, 1], wm, [co, 1]);
            // SAFETY: the product wrote all `np·co` values of `o`; `f32` and
            // `MaybeUninit<f32>` have one layout.
            let o =
                unsafe { std::slice::from_raw_parts_mut(o.as_mut_ptr().cast::<f32>(), o.len()) };
            if let Some(b) = bias {
                for row in o.chunks_exact_mut(co) {
                    for (v, b) in row.iter_mut().zip(b) {
                        *v = (*v + b).max(0.0);
                    }
                }
            }
        });
    // SAFETY: the blocks cover all `len` values, each written by its product above.
    unsafe { out.set_len(len) };
    out
}

impl Layer {
    /// The convolution, its bias and its ReLU of maps of one size: `[H·W, C_in]` →
    /// `[H·W, C_out]` each. A Winograd layer runs them together where they fit one shared
    /// block ([`winograd_many`]).
    fn forward_many(&self, xs: &[&[f32]], hw: [usize; 2]) -> Vec<Vec<f32>> {
        match self.winograd {
            None => xs
                .iter()
                .map(|x| conv3x3(x, hw, self.ci, &self.w, self.co, Some(&self.bias)))
                .collect(),
            Some(kind) => {
                let epilogue = Epilogue::BiasRelu(&self.bias);
                let weights = (&self.u[..], kind);
                let channels = [self.ci, self.co];
                winograd_many(xs, hw, channels, weights, epilogue, WINOGRAD_SHARED)
            }
        }
    }

    /// The gradient of the convolution's input from that of its output (before the ReLU):
    /// `[H·W, C_out]` → `[H·W, C_in]`; with `relu`, zero where that map (the previous
    /// layer's ReLU output, `[H·W, C_in]`) is not positive.
    fn input_gradient(&self, dy: &[f32], hw: [usize; 2], relu: Option<&[f32]>) -> Vec<f32> {
        let Some(kind) = self.winograd else {
            let mut dx = conv3x3_input_gradient(dy, hw, self.co, &self.w, self.ci);
            if let Some(y) = relu {
                dx.par_iter_mut().zip(y.par_iter()).for_each(|(d, y)| {
                    if *y <= 0.0 {
                        *d = 0.0;
                    }
                });
            }
            return dx;
        };
        let epilogue = relu.map_or(Epilogue::None, Epilogue::ReluMask);
        conv3x3_winograd(dy, hw, [self.co, self.ci], (&self.u_back, kind), epilogue)
    }
}

/// PyTorch's OIHW 3x3 kernel → the column weights `[9·C_in, C_out]` (see [`Layer`]).
fn column_weights(oihw: &[f32], ci: usize, co: usize) -> Vec<f32> {
    let mut fwd = vec![0.0f32; 9 * ci * co];
    for t in 0..9 {
        for i in 0..ci {
            for o in 0..co {
                fwd[(t * ci + i) * co + o] = oihw[(o * ci + i) * 9 + t];
            }
        }
    }
    fwd
}

/// The input gradient of [`conv3x3`] (before its bias and ReLU) with column weights `wm`
/// `[9·C_in, C_out]`: `dy` `[H·W, C_out]` → `[H·W, C_in]`.
///
/// For few input channels (VGG16's first layer, 3): the product
/// `Z[H·W, 9·C_in] = dy · wmᵀ` holds, for each output pixel, what it sends back through
/// each kernel tap, and each input pixel then sums the nine entries that reach it:
/// `dx[q, c] = Σ_(ky,kx) Z[q - (ky - 1, kx - 1), (ky·3 + kx)·C_in + c]`. The column
/// formulation of the same gradient (a convolution of `dy` with the rotated kernel) would
/// gather a `[H·W, 9·C_out]` matrix (64 MiB at 138 x 200) for a product only `C_in` wide.
fn conv3x3_input_gradient(
    dy: &[f32],
    [h, w]: [usize; 2],
    co: usize,
    wm: &[f32],
    ci: usize,
) -> Vec<f32> {
    let p = h * w;
    let k = 9 * ci;
    debug_assert_eq!(dy.len(), p * co);
    debug_assert_eq!(wm.len(), k * co);
    let mut dx = vec![0.0f32; p * ci];
    if p == 0 || ci == 0 {
        return dx;
    }
    // `wm` read as `[C_out, 9·C_in]`: element (o, r) at r·C_out + o. Written whole by the
    // product, never read before: no zeroing pass first.
    let mut z = Vec::with_capacity(p * k);
    matmul_uninit(
        [p, k, co],
        &mut z.spare_capacity_mut()[..p * k],
        dy,
        [co, 1],
        wm,
        [1, co],
    );
    // SAFETY: the product wrote all `p·k` values.
    unsafe { z.set_len(p * k) };
    dx.par_chunks_mut(w * ci).enumerate().for_each(|(qy, row)| {
        for ky in 0..3 {
            // Output row `py = qy + 1 - ky` reads input row `qy` through tap row `ky`.
            let Some(py) = (qy + 1).checked_sub(ky).filter(|&py| py < h) else {
                continue;
            };
            for kx in 0..3 {
                let t = (ky * 3 + kx) * ci;
                for qx in 0..w {
                    let Some(px) = (qx + 1).checked_sub(kx).filter(|&px| px < w) else {
                        continue;
                    };
                    let src = &z[(py * w + px) * k + t..][..ci];
                    for (d, s) in row[qx * ci..][..ci].iter_mut().zip(src) {
                        *d += s;
                    }
                }
            }
        }
    });
    dx
}

/// The Winograd algorithm of a convolution with these channels: none (the column
/// formulation) below [`WINOGRAD_MIN_CHANNELS`], F(4x4, 3x3) up to [`F4_MAX_CHANNELS`],
/// F(2x2, 3x3) above.
fn winograd_for(ci: usize, co: usize) -> Option<&'static Winograd> {
    if ci.min(co) < WINOGRAD_MIN_CHANNELS {
        None
    } else if ci.max(co) <= F4_MAX_CHANNELS {
        Some(&F4)
    } else {
        Some(&F2)
    }
}

/// PyTorch's OIHW 3x3 kernel rotated by 180° with its channel axes swapped, as column
/// weights `[9·C_out, C_in]` (rows ordered (ky, kx, c_out)): the kernel whose convolution
/// is the input gradient.
fn rotated_column_weights(oihw: &[f32], ci: usize, co: usize) -> Vec<f32> {
    let mut back = vec![0.0f32; 9 * co * ci];
    for t in 0..9 {
        for o in 0..co {
            for i in 0..ci {
                back[(t * co + o) * ci + i] = oihw[(o * ci + i) * 9 + 8 - t];
            }
        }
    }
    back
}

/// `U = G g Gᵀ` for every channel pair, from column weights `[9·C_in, C_out]` (rows
/// ordered (ky, kx, c_in)) to `[α², C_in, C_out]`.
fn winograd_weights(w: &[f32], ci: usize, co: usize, kind: &Winograd) -> Vec<f32> {
    let a = kind.alpha();
    let mut u = vec![0.0f32; a * a * ci * co];
    let mut g = [0.0f32; 9];
    let mut gg = vec![0.0f32; a * 3];
    for i in 0..ci {
        for o in 0..co {
            for (t, v) in g.iter_mut().enumerate() {
                *v = w[(t * ci + i) * co + o];
            }
            // G g, α x 3.
            for (r, row) in gg.chunks_exact_mut(3).enumerate() {
                for (kx, v) in row.iter_mut().enumerate() {
                    *v = (0..3).map(|ky| kind.g[r * 3 + ky] * g[ky * 3 + kx]).sum();
                }
            }
            // (G g) Gᵀ.
            for r in 0..a {
                for c in 0..a {
                    let v: f32 = (0..3).map(|kx| gg[r * 3 + kx] * kind.g[c * 3 + kx]).sum();
                    u[((r * a + c) * ci + i) * co + o] = v;
                }
            }
        }
    }
    u
}

/// A 3x3 convolution (padding 1, stride 1) as Winograd F(m x m, 3x3) of a channels-last
/// map `x` `[H·W, C_in]` with `[c_in, c_out] = channels`, and its [`Epilogue`]. `u` is
/// [`winograd_weights`]' `[α², C_in, C_out]` for `kind`. Returns `[H·W, C_out]`.
///
/// Three steps: the input transform `V = Bᵀ d B` of every α x α input tile, α² products
/// `M_ξ = V_ξ U_ξ`, and the output transform `Aᵀ M A` (with its epilogue) into the m x m
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
    weights: (&[f32], &Winograd),
    epilogue: Epilogue,
) -> Vec<f32> {
    winograd_mapped(x, hw, channels, weights, epilogue, WINOGRAD_SHARED)
}

/// What the output transform does to each output pixel after `Aᵀ M A`, while the pixel is
/// in registers.
#[derive(Clone, Copy, Debug)]
enum Epilogue<'a> {
    /// Nothing.
    None,
    /// Adds this bias `[C_out]` and applies the ReLU (a forward convolution).
    BiasRelu(&'a [f32]),
    /// Zero where this map `[H·W, C_out]`, a ReLU's output, is not positive: an input
    /// gradient carried on through the ReLU that produced the convolution's input.
    ReluMask(&'a [f32]),
}

/// [`conv3x3_winograd`] with the shared-block limit as an argument (tests take either
/// mapping with it).
fn winograd_mapped(
    x: &[f32],
    hw: [usize; 2],
    channels: [usize; 2],
    weights: (&[f32], &Winograd),
    epilogue: Epilogue,
    shared: usize,
) -> Vec<f32> {
    let mut out = winograd_many(&[x], hw, channels, weights, epilogue, shared);
    out.pop().unwrap_or_default()
}

/// [`winograd_mapped`] of several maps of the same size with the same weights (the two
/// images of a loss evaluation): where their transformed tiles fit one shared block
/// together, the α² products take the tiles of all of them, so each `U_ξ` is packed and
/// read from memory once for all (VGG16's 512-channel layers read 16 MiB of weights per
/// map: on the 12 x 8 maps of conv5 at 138 x 200 the products were bound by that). A
/// [`Epilogue::ReluMask`] belongs to one map, so it takes one map.
fn winograd_many(
    xs: &[&[f32]],
    [h, w]: [usize; 2],
    [ci, co]: [usize; 2],
    (u, kind): (&[f32], &Winograd),
    epilogue: Epilogue,
    shared: usize,
) -> Vec<Vec<f32>> {
    debug_assert!(xs.iter().all(|x| x.len() == h * w * ci));
    debug_assert_eq!(u.len(), kind.products() * ci * co);
    if let Epilogue::ReluMask(y) = epilogue {
        assert_eq!(xs.len(), 1, "Winograd: a ReLU mask belongs to one map");
        assert_eq!(y.len(), h * w * co, "Winograd: ReLU mask shape");
    }
    if h == 0 || w == 0 || co == 0 {
        return vec![vec![0.0f32; h * w * co]; xs.len()];
    }
    // Written, never read, before every pixel is written (each belongs to one tile): no
    // zeroing pass first.
    let len = h * w * co;
    let mut outs: Vec<Vec<f32>> = xs.iter().map(|_| Vec::with_capacity(len)).collect();
    let mut dst: Vec<_> = outs
        .iter_mut()
        .map(|o| &mut o.spare_capacity_mut()[..len])
        .collect();
    winograd_tiles(xs, [h, w], [ci, co], (u, kind), epilogue, shared, &mut dst);
    for o in &mut outs {
        // SAFETY: `winograd_tiles` wrote all `len` values of each `dst` (see
        // `write_tile_row`).
        unsafe { o.set_len(len) };
    }
    outs
}

/// [`winograd_many`]'s work on its uninitialised outputs `outs` (`[H·W, C_out]` each, one
/// per map of `xs`), every value of which it writes.
#[allow(clippy::too_many_arguments)]
fn winograd_tiles(
    xs: &[&[f32]],
    [h, w]: [usize; 2],
    [ci, co]: [usize; 2],
    (u, kind): (&[f32], &Winograd),
    epilogue: Epilogue,
    shared: usize,
    outs: &mut [&mut [MaybeUninit<f32>]],
) {
    let (m, a, n) = (kind.m, kind.alpha(), kind.products());
    let (tiles_h, tiles_w) = (h.div_ceil(m), w.div_ceil(m));
    let zero = vec![0.0f32; ci];
    // Transforms one α x α input tile (map `i`, tile row `ty`, column `tx`) into `vt`
    // `[α², C_in]`.
    let transform = |i: usize, ty: usize, tx: usize, vt: &mut [f32], t: &mut [f32]| {
        let x = xs[i];
        let mut d: [&[f32]; MAX_PRODUCTS] = [&zero[..]; MAX_PRODUCTS];
        for dy in 0..a {
            let sy = m * ty + dy;
            if sy == 0 || sy > h {
                continue;
            }
            for dx in 0..a {
                let sx = m * tx + dx;
                if sx == 0 || sx > w {
                    continue;
                }
                let s = ((sy - 1) * w + sx - 1) * ci;
                d[dy * a + dx] = &x[s..s + ci];
            }
        }
        input_transform(kind, &d[..n], vt, t, ci);
    };
    // `U_ξ` as the `[C_in, C_out]` right-hand side of product ξ.
    let weights = |xi: usize| &u[xi * ci * co..][..ci * co];
    let row_floats = tiles_w * n * (ci + co);
    let maps = xs.len();
    if maps > 1 && tiles_h * row_floats > shared / maps {
        // Too large to share one block: map by map.
        for (x, out) in xs.iter().zip(outs.iter_mut()) {
            let weights = (u, kind);
            winograd_tiles(
                &[x],
                [h, w],
                [ci, co],
                weights,
                epilogue,
                shared,
                &mut [out],
            );
        }
        return;
    }
    if maps * tiles_h * row_floats <= shared {
        // Tiles of map `i` from `i · per_map` on.
        let per_map = tiles_h * tiles_w;
        let nt = maps * per_map;
        // Empty when a call further up this thread holds them: then they grow fresh.
        let (mut v, mut mm) = WINOGRAD_SCRATCH.take();
        v.resize(nt * n * ci, 0.0);
        mm.resize(nt * n * co, 0.0);
        // V: [tile, ξ, C_in], one task per tile row.
        v.par_chunks_mut(tiles_w * n * ci)
            .enumerate()
            .for_each_init(Vec::new, |t: &mut Vec<f32>, (r, vr)| {
                t.resize(n * ci, 0.0);
                for (tx, vt) in vr.chunks_exact_mut(n * ci).enumerate() {
                    transform(r / tiles_h, r % tiles_h, tx, vt, t);
                }
            });
        // M: [ξ, tile, C_out], one task per ξ.
        mm.par_chunks_mut(nt * co).enumerate().for_each(|(xi, mx)| {
            matmul_serial(
                [nt, co, ci],
                mx,
                [co, 1],
                false,
                &v[xi * ci..],
                [n * ci, 1],
                weights(xi),
                [co, 1],
            );
        });
        let products = &mm[..];
        for (i, out) in outs.iter_mut().enumerate() {
            out.par_chunks_mut(m * w * co).enumerate().for_each_init(
                Vec::new,
                |s: &mut Vec<f32>, (ty, group)| {
                    s.resize((m * a + m) * co, 0.0);
                    let at = ty * m * w * co;
                    let first = i * per_map + ty * tiles_w;
                    write_tile_row(kind, (group, at), [w, co], s, epilogue, |tx, xi| {
                        &products[(xi * nt + first + tx) * co..][..co]
                    });
                },
            );
        }
        WINOGRAD_SCRATCH.set((v, mm));
        return;
    }
    let threads = rayon::current_num_threads().max(1);
    let mut blocks = tiles_h.div_ceil((WINOGRAD_BLOCK / row_floats).max(1));
    blocks = blocks.div_ceil(threads) * threads;
    let rows = tiles_h.div_ceil(blocks.min(tiles_h));
    // In blocks, map by map (one map here: several share a block or went one by one above).
    for (i, out) in outs.iter_mut().enumerate() {
        out.par_chunks_mut(m * rows * w * co)
            .enumerate()
            .for_each_init(
                || (Vec::new(), Vec::new(), Vec::new()),
                |(v, mm, s): &mut (Vec<f32>, Vec<f32>, Vec<f32>), (bi, o)| {
                    let nt = (o.len() / (w * co)).div_ceil(m) * tiles_w;
                    v.resize(nt * n * ci, 0.0);
                    mm.resize(nt * n * co, 0.0);
                    s.resize((n * ci).max((m * a + m) * co), 0.0);
                    // V: [tile, ξ, C_in].
                    for (t, vt) in v.chunks_exact_mut(n * ci).enumerate() {
                        transform(i, bi * rows + t / tiles_w, t % tiles_w, vt, s);
                    }
                    // M: [tile, ξ, C_out].
                    for xi in 0..n {
                        matmul_serial(
                            [nt, co, ci],
                            &mut mm[xi * co..],
                            [n * co, 1],
                            false,
                            &v[xi * ci..],
                            [n * ci, 1],
                            weights(xi),
                            [co, 1],
                        );
                    }
                    for (r, group) in o.chunks_mut(m * w * co).enumerate() {
                        let mr = &mm[r * tiles_w * n * co..];
                        let at = (bi * rows + r) * m * w * co;
                        write_tile_row(kind, (group, at), [w, co], s, epilogue, |tx, xi| {
                            &mr[(tx * n + xi) * co..][..co]
                        });
                    }
                },
            );
    }
}

/// The output transform of one row of tiles into `group`, the (up to `m`) output rows it
/// covers (`[rows·W, C_out]`, starting at float `at` of the output map), every value of
/// which it writes; `product(tx, ξ)` is tile `tx`'s product `ξ` (`[C_out]`), and `s` is
/// scratch of `(m·α + m)·C_out` floats.
fn write_tile_row<'a>(
    kind: &Winograd,
    (group, at): (&mut [MaybeUninit<f32>], usize),
    [w, co]: [usize; 2],
    s: &mut [f32],
    epilogue: Epilogue,
    product: impl Fn(usize, usize) -> &'a [f32],
) {
    let m = kind.m;
    let len = group.len();
    let mut rows: Vec<_> = group
        .chunks_mut(w * co)
        .map(|r| r.chunks_exact_mut(co))
        .collect();
    // The mask's pixels under `group`, split alike.
    let mut masks: Vec<_> = match epilogue {
        Epilogue::ReluMask(y) => y[at..][..len]
            .chunks(w * co)
            .map(|r| r.chunks_exact(co))
            .collect(),
        _ => Vec::new(),
    };
    let bias = match epilogue {
        Epilogue::BiasRelu(b) => Some(b),
        _ => None,
    };
    // Every pixel of the group is one of the m x m of exactly one tile `tx`.
    for tx in 0..w.div_ceil(m) {
        let mut y: TilePixels = std::array::from_fn(|_| None);
        let mut mask = [None; MAX_PIXELS];
        for r in 0..m {
            for q in 0..m {
                if let Some(it) = rows.get_mut(r) {
                    y[r * m + q] = it.next();
                }
                if let Some(it) = masks.get_mut(r) {
                    mask[r * m + q] = it.next();
                }
            }
        }
        let mt: [&[f32]; MAX_PRODUCTS] = std::array::from_fn(|xi| {
            if xi < kind.products() {
                product(tx, xi)
            } else {
                &[]
            }
        });
        output_transform(kind, &mt[..kind.products()], (y, mask), s, (co, bias));
    }
}

/// Defines `$name`, which runs `$generic` (an `#[inline(always)]` function of the same
/// arguments) compiled for AVX2 where the CPU has it, detected at run time, and as compiled
/// for the baseline otherwise. The element-wise passes of this file (the Winograd
/// transforms, pooling) are plain loops over channel vectors that the compiler vectorises
/// for the lanes it may use; this gives them AVX2's.
macro_rules! with_avx2 {
    ($(#[$doc:meta])* fn $name:ident = $generic:ident($($arg:ident: $ty:ty),* $(,)?)) => {
        $(#[$doc])*
        fn $name($($arg: $ty),*) {
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx2")]
                fn avx2($($arg: $ty),*) {
                    $generic($($arg),*)
                }
                if std::arch::is_x86_feature_detected!("avx2") {
                    // SAFETY: the CPU supports AVX2 (checked just above).
                    return unsafe { avx2($($arg),*) };
                }
            }
            $generic($($arg),*)
        }
    };
}

with_avx2! {
    /// `V = Bᵀ d B` of one α x α tile of channel vectors `d` (row-major, each `c` long) into
    /// `v` `[α², c]` for `kind`; `t` is scratch of `α²·c` floats. The transforms are written
    /// out per algorithm (the tests check them against [`Winograd`]'s matrices): every step is
    /// one pass over channel vectors, in AVX2's lanes where the CPU has them.
    fn input_transform = input_transform_generic(
        kind: &Winograd,
        d: &[&[f32]],
        v: &mut [f32],
        t: &mut [f32],
        c: usize
    )
}

#[inline(always)]
fn input_transform_generic(kind: &Winograd, d: &[&[f32]], v: &mut [f32], t: &mut [f32], c: usize) {
    if kind.m == 2 {
        input_transform_f2(d, v, t, c);
    } else {
        input_transform_f4(d, v, t, c);
    }
}

/// [`input_transform`] for F(2x2, 3x3), with Lavin and Gray's `Bᵀ` rows (1, 0, -1, 0),
/// (0, 1, 1, 0), (0, -1, 1, 0), (0, 1, 0, -1): each entry a sum or a difference of two.
#[inline(always)]
fn input_transform_f2(d: &[&[f32]], v: &mut [f32], t: &mut [f32], c: usize) {
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
#[inline(always)]
fn sum_or_difference(o: &mut [f32], a: &[f32], b: &[f32], add: bool) {
    let pairs = o.iter_mut().zip(a).zip(b);
    if add {
        pairs.for_each(|((o, a), b)| *o = a + b);
    } else {
        pairs.for_each(|((o, a), b)| *o = a - b);
    }
}

/// [`input_transform`] for F(4x4, 3x3): each 1-D step reads six channel vectors and writes
/// six in one pass ([`bt_f4`]).
#[inline(always)]
fn input_transform_f4(d: &[&[f32]], v: &mut [f32], t: &mut [f32], c: usize) {
    // t = Bᵀ d, stored column by column: t[(col·6 + r)·c ..] = (Bᵀ d)[r][col].
    for (col, tc) in t[..36 * c].chunks_exact_mut(6 * c).enumerate() {
        let d: [&[f32]; 6] = std::array::from_fn(|k| d[k * 6 + col]);
        bt_f4(d, tc, c);
    }
    // V = t B, row by row: V[r][col] = (Bᵀ (row r of t)ᵀ)[col].
    let t = &t[..36 * c];
    for (r, vr) in v[..36 * c].chunks_exact_mut(6 * c).enumerate() {
        let row: [&[f32]; 6] = std::array::from_fn(|col| &t[(col * 6 + r) * c..][..c]);
        bt_f4(row, vr, c);
    }
}

/// `o[k] = Σ_j Bᵀ[k][j] d[j]` for F(4x4, 3x3)'s `Bᵀ`, element-wise over `c` channels; `o`
/// holds the six results one after another.
#[inline(always)]
fn bt_f4(d: [&[f32]; 6], o: &mut [f32], c: usize) {
    let [d0, d1, d2, d3, d4, d5] = d.map(|d| &d[..c]);
    let (o0, rest) = o[..6 * c].split_at_mut(c);
    let (o1, rest) = rest.split_at_mut(c);
    let (o2, rest) = rest.split_at_mut(c);
    let (o3, rest) = rest.split_at_mut(c);
    let (o4, o5) = rest.split_at_mut(c);
    for j in 0..c {
        let (a0, a1, a2, a3, a4, a5) = (d0[j], d1[j], d2[j], d3[j], d4[j], d5[j]);
        o0[j] = 4.0 * a0 - 5.0 * a2 + a4;
        o1[j] = -4.0 * (a1 + a2) + a3 + a4;
        o2[j] = 4.0 * (a1 - a2) - a3 + a4;
        o3[j] = 2.0 * (a3 - a1) - a2 + a4;
        o4[j] = 2.0 * (a1 - a3) - a2 + a4;
        o5[j] = 4.0 * a1 - 5.0 * a3 + a5;
    }
}

/// `o[k] = Σ_j Aᵀ[k][j] m[j]` for F(4x4, 3x3)'s `Aᵀ` (4 x 6), element-wise over `c`
/// channels; `o` holds the four results one after another.
#[inline(always)]
fn at_f4(m: [&[f32]; 6], o: &mut [f32], c: usize) {
    let [m0, m1, m2, m3, m4, m5] = m.map(|m| &m[..c]);
    let (o0, rest) = o[..4 * c].split_at_mut(c);
    let (o1, rest) = rest.split_at_mut(c);
    let (o2, o3) = rest.split_at_mut(c);
    for j in 0..c {
        let (a0, a1, a2, a3, a4, a5) = (m0[j], m1[j], m2[j], m3[j], m4[j], m5[j]);
        let (sum12, dif12) = (a1 + a2, a1 - a2);
        let (sum34, dif34) = (a3 + a4, a3 - a4);
        o0[j] = a0 + sum12 + sum34;
        o1[j] = dif12 + 2.0 * dif34;
        o2[j] = sum12 + 4.0 * sum34;
        o3[j] = dif12 + 8.0 * dif34 + a5;
    }
}

/// The output pixels of one tile, row-major, each `C_out` values; `None` past the map's
/// edge (and past the tile's `m²`).
type TilePixels<'a> = [Option<&'a mut [MaybeUninit<f32>]>; MAX_PIXELS];

with_avx2! {
    /// `Y = Aᵀ M A` of one tile's α² products `m` (each `c` long) into its m x m output pixels
    /// `y` (row-major; `None` past the map's edge) for `kind`, plus `bias` and the ReLU when
    /// given, or zero where the pixel's `mask` (when given) is not positive ([`write_pixel`]).
    /// `s` is scratch of `(m·α + m)·c` floats. Written out per algorithm, as
    /// [`input_transform`].
    fn output_transform = output_transform_generic(
        kind: &Winograd,
        m: &[&[f32]],
        pixels: (TilePixels, [Option<&[f32]>; MAX_PIXELS]),
        s: &mut [f32],
        channels: (usize, Option<&[f32]>)
    )
}

#[inline(always)]
fn output_transform_generic(
    kind: &Winograd,
    m: &[&[f32]],
    (y, mask): (TilePixels, [Option<&[f32]>; MAX_PIXELS]),
    s: &mut [f32],
    (c, bias): (usize, Option<&[f32]>),
) {
    let (mo, a) = (kind.m, kind.alpha());
    let (s, tmp) = s[..(mo * a + mo) * c].split_at_mut(mo * a * c);
    // s = Aᵀ M, stored column by column: s[(col·m + r)·c ..] = (Aᵀ M)[r][col].
    for (col, sc) in s.chunks_exact_mut(mo * c).enumerate() {
        let column = |j: usize| m[j * a + col];
        if mo == 2 {
            at_f2(std::array::from_fn(column), sc, c);
        } else {
            at_f4(std::array::from_fn(column), sc, c);
        }
    }
    let s = &*s;
    let mut y = y.into_iter();
    let mut mask = mask.into_iter();
    for r in 0..mo {
        // Row r of Y = s A: tmp[q] = Y[r][q].
        let row = |col: usize| &s[(col * mo + r) * c..][..c];
        if mo == 2 {
            at_f2(std::array::from_fn(row), tmp, c);
        } else {
            at_f4(std::array::from_fn(row), tmp, c);
        }
        for v in tmp.chunks_exact(c) {
            if let Some(out) = y.next().flatten() {
                write_pixel(out, v, bias, mask.next().flatten());
            } else {
                mask.next();
            }
        }
    }
}

/// `o[k] = Σ_j Aᵀ[k][j] m[j]` for F(2x2, 3x3)'s `Aᵀ` rows (1, 1, 1, 0), (0, 1, -1, -1),
/// element-wise over `c` channels; `o` holds the two results one after another.
#[inline(always)]
fn at_f2(m: [&[f32]; 4], o: &mut [f32], c: usize) {
    let [m0, m1, m2, m3] = m.map(|m| &m[..c]);
    let (o0, o1) = o[..2 * c].split_at_mut(c);
    for j in 0..c {
        o0[j] = m0[j] + m1[j] + m2[j];
        o1[j] = m1[j] - m2[j] - m3[j];
    }
}

/// One output pixel `out` from its value `v`: plus `bias` and the ReLU when given, else
/// zero where `mask` (when given) is not positive, else `v`.
#[inline(always)]
fn write_pixel(
    out: &mut [MaybeUninit<f32>],
    v: &[f32],
    bias: Option<&[f32]>,
    mask: Option<&[f32]>,
) {
    let out = &mut out[..v.len()];
    match (bias, mask) {
        (Some(bias), _) => out.iter_mut().zip(v).zip(bias).for_each(|((o, v), z)| {
            o.write((v + z).max(0.0));
        }),
        (None, Some(mask)) => out.iter_mut().zip(v).zip(mask).for_each(|((o, v), y)| {
            o.write(if *y > 0.0 { *v } else { 0.0 });
        }),
        (None, None) => out.iter_mut().zip(v).for_each(|(o, v)| {
            o.write(*v);
        }),
    }
}

/// `m` replaced by `v` where `v` is larger or NaN: one step of the pooling window's scan
/// (row-major, strict `>`, NaN taken; PyTorch's and burn's rule), branch-free so that it
/// runs in vector lanes.
#[inline(always)]
fn takes(v: f32, m: f32) -> bool {
    v > m || v.is_nan()
}

/// 2x2 max-pool with stride 2 (odd trailing rows and columns dropped, as PyTorch's default
/// `ceil_mode=False`) of a channels-last map with `c` channels.
fn max_pool(x: &Map, c: usize) -> Map {
    let (ho, wo) = (x.h / 2, x.w / 2);
    let mut data = vec![0.0f32; ho * wo * c];
    if ho > 0 && wo > 0 {
        let row = x.w * c;
        data.par_chunks_mut(wo * c)
            .enumerate()
            .for_each(|(oy, out)| {
                let (x0, x1) = x.data[2 * oy * row..][..2 * row].split_at(row);
                pool_row(out, [x0, x1], c);
            });
    }
    Map { data, h: ho, w: wo }
}

with_avx2! {
    /// One output row of [`max_pool`] from the two input rows under it, in AVX2's lanes where
    /// the CPU has them (the scan's comparisons are data-dependent: as branches they are
    /// mispredicted about half the time).
    fn pool_row = pool_row_generic(out: &mut [f32], x: [&[f32]; 2], c: usize)
}

#[inline(always)]
fn pool_row_generic(out: &mut [f32], [x0, x1]: [&[f32]; 2], c: usize) {
    for (ox, o) in out.chunks_exact_mut(c).enumerate() {
        let (i, j) = (2 * ox * c, (2 * ox + 1) * c);
        let (v00, v01, v10, v11) = (&x0[i..][..c], &x0[j..][..c], &x1[i..][..c], &x1[j..][..c]);
        for (o, (((&a, &b), &p), &q)) in o.iter_mut().zip(v00.iter().zip(v01).zip(v10).zip(v11)) {
            let m = if takes(b, a) { b } else { a };
            let m = if takes(p, m) { p } else { m };
            *o = if takes(q, m) { q } else { m };
        }
    }
}

/// The backward of [`max_pool`] and of the ReLU whose output `x` it pooled: `dy`
/// `[H_o·W_o, C]` → the gradient of the ReLU's input, `[H·W, C]` as `x`. Each output's
/// gradient goes to the first maximum of its window; with `tap` (`(g, scale)`), `scale·g`
/// (`[H·W, C]`, the loss's direct gradient of `x`) is added; then the ReLU's mask (zero
/// where `x` is not positive) is applied. One pass over the map.
fn pool_relu_backward(
    dy: &[f32],
    [ho, wo]: [usize; 2],
    x: &Map,
    c: usize,
    tap: Option<(&[f32], f32)>,
) -> Vec<f32> {
    let mut dx = vec![0.0f32; x.h * x.w * c];
    if dx.is_empty() {
        return dx;
    }
    let row = x.w * c;
    // Each task owns the two input rows under one output row (one row at an odd end).
    dx.par_chunks_mut(2 * row)
        .enumerate()
        .for_each(|(oy, rows)| {
            let base = oy * 2 * row;
            let xs = &x.data[base..][..rows.len()];
            let ts = tap.map(|(t, scale)| (&t[base..][..rows.len()], scale));
            // Pixels no window covers (an odd last row or column) get the tap's share.
            // (Without a tap they keep the zeros they start with.)
            let rest = |d: &mut [f32], at: usize| {
                if let Some((t, scale)) = ts {
                    let n = d.len();
                    add_tap_and_mask_serial(d, (&t[at..][..n], scale), &xs[at..][..n]);
                }
            };
            if oy < ho {
                let (r0, r1) = rows.split_at_mut(row);
                let g = &dy[oy * wo * c..][..wo * c];
                let tr = ts.map(|(t, scale)| (t.split_at(row), scale));
                pool_backward_rows([r0, r1], xs.split_at(row), g, tr, c);
                if 2 * wo < x.w {
                    rest(&mut rows[2 * wo * c..row], 2 * wo * c);
                    rest(&mut rows[row + 2 * wo * c..], row + 2 * wo * c);
                }
            } else {
                rest(rows, 0);
            }
        });
    dx
}

/// A tap's direct gradient under two input rows of [`pool_relu_backward`]: the rows' tap
/// gradients and their scale.
type TapRows<'a> = Option<((&'a [f32], &'a [f32]), f32)>;

with_avx2! {
    /// The `2·W_o` covered pixels of the two input rows `d` under one output row of
    /// [`pool_relu_backward`] (`x` the ReLU's output there, `g` the output row's gradient
    /// `[W_o·C]`), in AVX2's lanes where the CPU has them: written branch-free, as
    /// [`pool_row`].
    fn pool_backward_rows = pool_backward_rows_generic(
        d: [&mut [f32]; 2],
        x: (&[f32], &[f32]),
        g: &[f32],
        tap: TapRows,
        c: usize
    )
}

#[inline(always)]
fn pool_backward_rows_generic(
    d: [&mut [f32]; 2],
    x: (&[f32], &[f32]),
    g: &[f32],
    tap: TapRows,
    c: usize,
) {
    match tap {
        Some((t, scale)) => pool_backward_windows::<true>(d, x, (t, scale), g, c),
        // `t` is not read without a tap.
        None => pool_backward_windows::<false>(d, x, (x, 0.0), g, c),
    }
}

#[inline(always)]
fn pool_backward_windows<const TAP: bool>(
    [d0, d1]: [&mut [f32]; 2],
    (x0, x1): (&[f32], &[f32]),
    ((t0, t1), scale): ((&[f32], &[f32]), f32),
    g: &[f32],
    c: usize,
) {
    for (ox, g) in g.chunks_exact(c).enumerate() {
        let (i, j) = (2 * ox * c, (2 * ox + 1) * c);
        let (d00, d01) = d0[i..j + c].split_at_mut(c);
        let (d10, d11) = d1[i..j + c].split_at_mut(c);
        let (v00, v01, v10, v11) = (&x0[i..][..c], &x0[j..][..c], &x1[i..][..c], &x1[j..][..c]);
        let (t00, t01, t10, t11) = (&t0[i..][..c], &t0[j..][..c], &t1[i..][..c], &t1[j..][..c]);
        // The gradient `s` a pixel gets from the window, then the tap's share and the ReLU's
        // mask, as `add_tap_and_mask` (with a tap) or the plain mask (without) apply them.
        let out = |s: f32, v: f32, t: f32| {
            if TAP {
                if v > 0.0 { s + scale * t } else { 0.0 }
            } else if v <= 0.0 {
                0.0
            } else {
                s
            }
        };
        for ch in 0..c {
            let (a, b, p, q) = (v00[ch], v01[ch], v10[ch], v11[ch]);
            // The scan of `pool_row`: which of the four is the first maximum.
            let c1 = takes(b, a);
            let m = if c1 { b } else { a };
            let c2 = takes(p, m);
            let m = if c2 { p } else { m };
            let c3 = takes(q, m);
            let gv = g[ch];
            let pick = |k: bool| if k { gv } else { 0.0 };
            d00[ch] = out(pick(!(c1 | c2 | c3)), a, t00[ch]);
            d01[ch] = out(pick(c1 & !(c2 | c3)), b, t01[ch]);
            d10[ch] = out(pick(c2 & !c3), p, t10[ch]);
            d11[ch] = out(pick(c3), q, t11[ch]);
        }
    }
}

/// `d = (d + scale·g)` where `y > 0`, zero elsewhere: a tap's direct gradient added to the
/// gradient of a ReLU's output `y`, carried through the ReLU.
fn add_tap_and_mask(d: &mut [f32], (g, scale): (&[f32], f32), y: &[f32]) {
    const CHUNK: usize = 1 << 14;
    d.par_chunks_mut(CHUNK)
        .zip(g.par_chunks(CHUNK).zip(y.par_chunks(CHUNK)))
        .for_each(|(d, (g, y))| add_tap_and_mask_serial(d, (g, scale), y));
}

/// `scale·g` where `y > 0`, zero elsewhere: [`add_tap_and_mask`] onto a zero gradient,
/// written into a fresh map without zeroing it first.
fn tap_through_relu((g, scale): (&[f32], f32), y: &[f32]) -> Vec<f32> {
    debug_assert_eq!(g.len(), y.len());
    let mut d = Vec::with_capacity(y.len());
    g.par_iter()
        .zip(y)
        .with_min_len(1 << 14)
        .map(|(g, y)| if *y > 0.0 { scale * g } else { 0.0 })
        .collect_into_vec(&mut d);
    d
}

/// [`add_tap_and_mask`] on the calling thread.
fn add_tap_and_mask_serial(d: &mut [f32], (g, scale): (&[f32], f32), y: &[f32]) {
    for ((d, g), y) in d.iter_mut().zip(g).zip(y) {
        *d = if *y > 0.0 { *d + scale * g } else { 0.0 };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The lanes and the rest of [`l1_distance`] against one plain `f64` sum and the sign
    /// rule (0 where equal), on lengths below, at and above a multiple of [`L1_LANES`].
    #[test]
    fn l1_distance_matches_a_plain_sum() {
        for len in [0, 5, L1_LANES, 8 * L1_LANES + 3, 1000] {
            let x: Vec<f32> = (0..len)
                .map(|i| ((i * 37 % 11) as f32 - 5.0) * 0.3)
                .collect();
            let mut y: Vec<f32> = (0..len)
                .map(|i| ((i * 13 % 7) as f32 - 3.0) * 0.5)
                .collect();
            if len > 2 {
                y[2] = x[2];
            }
            let want: f64 = x.iter().zip(&y).map(|(a, b)| (a - b).abs() as f64).sum();
            let inv = 0.25;
            let mut g = vec![MaybeUninit::new(f32::NAN); len];
            let with = l1_distance(&x, &y, Some((&mut g, inv)));
            let without = l1_distance(&x, &y, None);
            assert!(
                (with - want).abs() <= 1e-9 * want.max(1.0),
                "{len}: {with} vs {want}"
            );
            assert_eq!(with, without);
            for (j, g) in g.iter().enumerate() {
                // SAFETY: `l1_distance` wrote every value (all were initialised anyway).
                let g = unsafe { g.assume_init() };
                let d = x[j] - y[j];
                let want = if d > 0.0 {
                    inv
                } else if d < 0.0 {
                    -inv
                } else {
                    0.0
                };
                assert_eq!(g, want, "{len}: gradient {j}");
            }
        }
    }

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

    /// On a small map, and on one of several blocks of [`COL_BLOCK`] (VGG16's first layer's
    /// channels: blocks of `COL_BLOCK / 64` pixels, the last one shorter).
    #[test]
    fn column_convolution_matches_direct_loops() {
        for (h, w, ci, co) in [(5, 7, 3, 4), (23, 101, 3, 64)] {
            assert!(
                co < 64 || h * w > 2 * COL_BLOCK / co,
                "the second map spans blocks"
            );
            let x = values(h * w * ci, 1);
            let oihw = values(co * ci * 9, 2);
            let bias = values(co, 3);
            let fwd = column_weights(&oihw, ci, co);
            let y = conv3x3(&x, [h, w], ci, &fwd, co, Some(&bias));
            let want = direct(&x, [h, w], ci, &oihw, co, &bias);
            assert_eq!(y.len(), want.len());
            for (a, b) in y.iter().zip(&want) {
                assert!((a - b).abs() < 1e-5, "{h}x{w}: {a} vs {b}");
            }
        }
    }

    /// The input gradient of a 3x3 convolution (padding 1) by direct loops: every output
    /// pixel `p` sends `dy[p, o] · W[o, i, ky, kx]` to the input pixel its tap read,
    /// `p + (ky - 1, kx - 1)`.
    fn direct_input_gradient(
        dy: &[f32],
        [h, w]: [usize; 2],
        co: usize,
        oihw: &[f32],
        ci: usize,
    ) -> Vec<f32> {
        let mut dx = vec![0.0f64; h * w * ci];
        for py in 0..h {
            for px in 0..w {
                for ky in 0..3 {
                    for kx in 0..3 {
                        let (qy, qx) = (py + ky, px + kx);
                        if qy < 1 || qy > h || qx < 1 || qx > w {
                            continue;
                        }
                        let q = (qy - 1) * w + qx - 1;
                        for o in 0..co {
                            for i in 0..ci {
                                dx[q * ci + i] += dy[(py * w + px) * co + o] as f64
                                    * oihw[((o * ci + i) * 3 + ky) * 3 + kx] as f64;
                            }
                        }
                    }
                }
            }
        }
        dx.into_iter().map(|v| v as f32).collect()
    }

    /// The column layers' input gradient (product with the transposed weights, then the
    /// sum over the taps) against the direct loops, on maps narrower and shorter than the
    /// kernel too.
    #[test]
    fn column_input_gradient_matches_direct_loops() {
        for (h, w, ci, co) in [(5, 7, 3, 4), (1, 1, 3, 8), (2, 5, 1, 3), (6, 3, 4, 16)] {
            let oihw = values(co * ci * 9, 2);
            let dy = values(h * w * co, 3);
            let dx = conv3x3_input_gradient(&dy, [h, w], co, &column_weights(&oihw, ci, co), ci);
            let want = direct_input_gradient(&dy, [h, w], co, &oihw, ci);
            let e = max_rel(&dx, &want);
            assert!(e < 1e-6, "{h}x{w} {co}->{ci}: {e}");
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

    /// Winograd F(2x2, 3x3) and F(4x4, 3x3) against the direct loops: the forward (with bias
    /// and ReLU) and, with the rotated kernel's weights, the input gradient, plain and
    /// through a ReLU's mask, in both thread mappings. Sizes that are not multiples of the
    /// tile give partial tiles at the right and bottom edges; with per-thread blocks the
    /// maps split into several blocks of tile rows.
    #[test]
    fn winograd_matches_direct_loops() {
        for kind in [&F2, &F4] {
            for (h, w, ci, co) in [
                (5, 7, 16, 24),
                (6, 4, 17, 16),
                (1, 1, 16, 16),
                (9, 3, 32, 16),
                (2, 2, 16, 20),
                (11, 13, 16, 16),
            ] {
                let x = values(h * w * ci, 4);
                let oihw = values(co * ci * 9, 5);
                let bias = values(co, 6);
                let u = winograd_weights(&column_weights(&oihw, ci, co), ci, co, kind);
                let back = rotated_column_weights(&oihw, ci, co);
                let u_back = winograd_weights(&back, co, ci, kind);
                let want_y = direct(&x, [h, w], ci, &oihw, co, &bias);
                let x2 = values(h * w * ci, 14);
                let want_y2 = direct(&x2, [h, w], ci, &oihw, co, &bias);
                let dy = values(h * w * co, 7);
                let want_dx = direct_input_gradient(&dy, [h, w], co, &oihw, ci);
                // A ReLU output for the mask: `values` is negative about half the time.
                let relu = values(h * w * ci, 10);
                let masked: Vec<f32> = want_dx
                    .iter()
                    .zip(&relu)
                    .map(|(d, y)| if *y > 0.0 { *d } else { 0.0 })
                    .collect();
                let m = kind.m;
                for shared in [0, usize::MAX] {
                    let bias = Epilogue::BiasRelu(&bias);
                    let y = winograd_mapped(&x, [h, w], [ci, co], (&u, kind), bias, shared);
                    let e = max_rel(&y, &want_y);
                    assert!(e < 1e-5, "F{m} forward {h}x{w} {ci}->{co}, {shared}: {e}");
                    // Two maps together: in one shared block (`usize::MAX`), by one
                    // (a limit that fits one map's tiles, not both), or in blocks (0).
                    let one = (h.div_ceil(m) * w.div_ceil(m)) * kind.products() * (ci + co);
                    for limit in [shared, one] {
                        let ys =
                            winograd_many(&[&x, &x2], [h, w], [ci, co], (&u, kind), bias, limit);
                        for (y, want) in ys.iter().zip([&want_y, &want_y2]) {
                            let e = max_rel(y, want);
                            assert!(e < 1e-5, "F{m} pair {h}x{w} {ci}->{co}, {limit}: {e}");
                        }
                    }
                    let back = (&u_back[..], kind);
                    let dx = winograd_mapped(&dy, [h, w], [co, ci], back, Epilogue::None, shared);
                    let e = max_rel(&dx, &want_dx);
                    assert!(
                        e < 1e-5,
                        "F{m} input gradient {h}x{w} {co}->{ci}, {shared}: {e}"
                    );
                    let mask = Epilogue::ReluMask(&relu);
                    let dx = winograd_mapped(&dy, [h, w], [co, ci], back, mask, shared);
                    assert!(dx.iter().zip(&relu).all(|(d, y)| *y > 0.0 || *d == 0.0));
                    let e = max_rel(&dx, &masked);
                    assert!(
                        e < 1e-5,
                        "F{m} masked gradient {h}x{w} {co}->{ci}, {shared}: {e}"
                    );
                }
            }
        }
        // The public entry point takes the same path as one of the two.
        let (ci, co) = (16, 16);
        let x = values(9 * 7 * ci, 8);
        let u = winograd_weights(&values(9 * ci * co, 9), ci, co, &F4);
        let none = Epilogue::None;
        assert_eq!(
            conv3x3_winograd(&x, [9, 7], [ci, co], (&u, &F4), none),
            winograd_mapped(&x, [9, 7], [ci, co], (&u, &F4), none, usize::MAX)
        );
    }

    /// `Bᵀ d B` and `Aᵀ M A` by the matrices of Lavin and Gray (the [`Winograd`]
    /// constants), in float64, per channel.
    fn by_matrices(mat: &[f32], rows: usize, a: usize, x: &[Vec<f32>], c: usize) -> Vec<Vec<f64>> {
        // Y = mat · X · matᵀ for each channel, X a x a.
        let mut y = vec![vec![0.0f64; c]; rows * rows];
        for ch in 0..c {
            for r in 0..rows {
                for q in 0..rows {
                    let mut acc = 0.0f64;
                    for i in 0..a {
                        for j in 0..a {
                            acc += mat[r * a + i] as f64
                                * x[i * a + j][ch] as f64
                                * mat[q * a + j] as f64;
                        }
                    }
                    y[r * rows + q][ch] = acc;
                }
            }
        }
        y
    }

    /// The written-out transforms of F(2x2, 3x3) and F(4x4, 3x3) against Lavin and Gray's
    /// matrices (`Bᵀ`, `Aᵀ` of [`F2`] and [`F4`]).
    #[test]
    fn transforms_match_the_matrices() {
        // 37 channels: AVX2's 8-lane vectors (four of them) and a remainder; with 5 only the
        // remainder loop ran.
        let c = 37;
        for kind in [&F2, &F4] {
            let (m, a) = (kind.m, kind.alpha());
            let x: Vec<Vec<f32>> = (0..a * a).map(|k| values(c, 20 + k)).collect();
            let want_v = by_matrices(kind.bt, a, a, &x, c);
            let d: Vec<&[f32]> = x.iter().map(|v| &v[..]).collect();
            let mut v = vec![0.0f32; a * a * c];
            let mut t = vec![0.0f32; a * a * c];
            input_transform(kind, &d, &mut v, &mut t, c);
            for (k, want) in want_v.iter().enumerate() {
                for (ch, w) in want.iter().enumerate() {
                    let got = v[k * c + ch] as f64;
                    assert!((got - w).abs() < 1e-4, "F{m} V[{k}][{ch}]: {got} vs {w}");
                }
            }
            let want_y = by_matrices(kind.at, m, a, &x, c);
            let mut y = vec![MaybeUninit::new(f32::NAN); m * m * c];
            let mut pixels: TilePixels = std::array::from_fn(|_| None);
            for (p, chunk) in y.chunks_exact_mut(c).enumerate() {
                pixels[p] = Some(chunk);
            }
            let mut s = vec![0.0f32; (m * a + m) * c];
            output_transform(kind, &d, (pixels, [None; MAX_PIXELS]), &mut s, (c, None));
            for (k, want) in want_y.iter().enumerate() {
                for (ch, w) in want.iter().enumerate() {
                    // SAFETY: `y` was made initialised (NaN); a pixel left unwritten fails.
                    let got = unsafe { y[k * c + ch].assume_init() } as f64;
                    assert!((got - w).abs() < 1e-4, "F{m} Y[{k}][{ch}]: {got} vs {w}");
                }
            }
        }
    }

    /// The algorithm per layer: VGG16's 64- to 256-channel layers F(4x4, 3x3), its
    /// 512-channel ones F(2x2, 3x3), the first the column formulation.
    #[test]
    fn winograd_choice_per_layer() {
        assert!(winograd_for(3, 64).is_none());
        assert_eq!(winograd_for(64, 64).map(|k| k.m), Some(4));
        assert_eq!(winograd_for(128, 256).map(|k| k.m), Some(4));
        assert_eq!(winograd_for(256, 512).map(|k| k.m), Some(2));
        assert_eq!(winograd_for(512, 512).map(|k| k.m), Some(2));
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
        let dx = pool_relu_backward(&[10.0, 20.0], [1, 2], &x, 1, None);
        assert_eq!(
            dx,
            [10.0, 0.0, 0.0, 0.0, 0.0, 0.0, 20.0, 0.0, 0.0, 0.0, 0.0, 0.0]
        );
    }

    /// The fused backward against its three steps done one by one: pooling's backward (the
    /// first maximum), the tap's gradient added (or not), the ReLU's mask; odd height and
    /// width (the dropped last row and column get only the tap's share), ties, zeros and
    /// negatives; two channels, and nineteen (vector lanes and a remainder).
    #[test]
    fn pool_relu_backward_matches_its_steps() {
        for (h, w, c) in [(5, 5, 2), (4, 7, 19)] {
            let data: Vec<f32> = values(h * w * c, 11)
                .into_iter()
                .enumerate()
                .map(|(i, v)| {
                    if i % 7 == 0 {
                        0.0
                    } else if i % 5 == 0 {
                        0.25
                    } else {
                        v
                    }
                })
                .collect();
            let x = Map { data, h, w };
            let (ho, wo) = (h / 2, w / 2);
            let dy = values(ho * wo * c, 12);
            let tap = values(h * w * c, 13);
            let scale = -0.5;
            let mut pooled = vec![0.0f32; h * w * c];
            let mut max = vec![0.0f32; ho * wo * c];
            for oy in 0..ho {
                for ox in 0..wo {
                    for ch in 0..c {
                        let at = |dy: usize, dx: usize| ((2 * oy + dy) * w + 2 * ox + dx) * c + ch;
                        let mut best = at(0, 0);
                        for (dy, dx) in [(0, 1), (1, 0), (1, 1)] {
                            if x.data[at(dy, dx)] > x.data[best] {
                                best = at(dy, dx);
                            }
                        }
                        pooled[best] += dy[(oy * wo + ox) * c + ch];
                        max[(oy * wo + ox) * c + ch] = x.data[best];
                    }
                }
            }
            assert_eq!(max_pool(&x, c).data, max, "{h}x{w}x{c}");
            for with_tap in [true, false] {
                let mut want = pooled.clone();
                for ((d, t), y) in want.iter_mut().zip(&tap).zip(&x.data) {
                    let t = if with_tap { scale * t } else { 0.0 };
                    *d = if *y > 0.0 { *d + t } else { 0.0 };
                }
                let t = with_tap.then_some((&tap[..], scale));
                let got = pool_relu_backward(&dy, [ho, wo], &x, c, t);
                assert_eq!(got, want, "{h}x{w}x{c}, tap {with_tap}");
            }
        }
    }

    /// A NaN in a window is its maximum and takes its gradient, as in PyTorch's CPU kernel
    /// (aten/src/ATen/native/cpu/MaxPoolKernel.cpp, `cpu_max_pool`: `(val > maxval) ||
    /// std::isnan(val)`), in the vector path (eight channels) as in the scalar one.
    #[test]
    fn pooling_takes_a_nan() {
        let c = 9;
        let mut data = vec![1.0f32; 4 * c];
        for ch in 0..c {
            data[c + ch] = f32::NAN;
            data[2 * c + ch] = 3.0;
        }
        let x = Map { data, h: 2, w: 2 };
        assert!(max_pool(&x, c).data.iter().all(|v| v.is_nan()));
        let dx = pool_relu_backward(&[2.0; 9], [1, 1], &x, c, None);
        for ch in 0..c {
            assert_eq!(
                [dx[ch], dx[c + ch], dx[2 * c + ch], dx[3 * c + ch]],
                [0.0, 2.0, 0.0, 0.0]
            );
        }
    }
}
