//! VGG16's convolution stack on the CPU, for the perceptual loss: the forward pass of two
//! images, the L1 distance of their five taps, and the gradient of that distance with respect
//! to the images. The weights are frozen, so no weight gradient is ever formed.
//!
//! Why: through burn's generic ops (flex), one loss evaluation at 138 x 200 (reference pass,
//! render pass, backward) took about twice PyTorch's time, most of it in the convolutions'
//! input gradients and the element-wise autodiff steps between them (ReLU masks, pooling,
//! the normalisation). Here everything is in one place on host memory:
//!
//! - maps are channels-last (`[H·W, C]`), so the column matrix of a 3x3 convolution is built
//!   by copying runs of `C` floats, and a convolution is one matrix product per block of
//!   pixels: `Y[block, C_out] = col[block, 9·C_in] · W[9·C_in, C_out]`, with the bias and
//!   the ReLU applied to the block while it is in cache;
//! - the input gradient of a 3x3 convolution (padding 1) is itself a 3x3 convolution of the
//!   masked output gradient with the kernel rotated by 180° and its channel axes swapped
//!   (`w_back`), so the backward runs the same routine;
//! - a 2x2 max-pool's backward sends each output's gradient to the first maximum of its
//!   window (row-major scan, strict `>`: PyTorch's and burn's rule), which is recomputed from
//!   the saved pre-pool map.
//!
//! Thread mapping: every convolution splits its pixels into blocks (a multiple of rayon's
//! thread count, each block's column matrix at most `COL_BLOCK` floats) and runs the blocks
//! on rayon, one single-threaded product each; a convolution with one block runs its product
//! on all threads instead. Pooling is parallel over output rows.
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

/// One 3x3 convolution (padding 1, stride 1) in the column formulation.
#[derive(Debug)]
struct Layer {
    ci: usize,
    co: usize,
    /// A 2x2 max-pool (stride 2) on this convolution's input.
    pool_before: bool,
    /// Whether this convolution's ReLU output is one of the five taps.
    tap: bool,
    /// Forward weights `[9·C_in, C_out]`, rows ordered (ky, kx, c_in).
    w: Vec<f32>,
    /// Input-gradient weights `[9·C_out, C_in]`, rows ordered (ky, kx, c_out): the kernel
    /// rotated by 180°.
    w_back: Vec<f32>,
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
                let oihw = |o: usize, i: usize, ky: usize, kx: usize| {
                    w.data[((o * ci + i) * 3 + ky) * 3 + kx]
                };
                let mut fwd = vec![0.0f32; 9 * ci * co];
                let mut back = vec![0.0f32; 9 * co * ci];
                for ky in 0..3 {
                    for kx in 0..3 {
                        let t = ky * 3 + kx;
                        for i in 0..ci {
                            for o in 0..co {
                                fwd[(t * ci + i) * co + o] = oihw(o, i, ky, kx);
                                back[(t * co + o) * ci + i] = oihw(o, i, 2 - ky, 2 - kx);
                            }
                        }
                    }
                }
                Layer {
                    ci,
                    co,
                    pool_before: spec.pool_before.is_some(),
                    tap: spec.tap,
                    w: fwd,
                    w_back: back,
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
                data: conv3x3(
                    &input.data,
                    [input.h, input.w],
                    layer.ci,
                    &layer.w,
                    layer.co,
                    Some(&layer.bias),
                ),
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
                let dx = conv3x3(&d, [y.h, y.w], layer.co, &layer.w_back, layer.ci, None);
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
        let mut fwd = vec![0.0f32; 9 * ci * co];
        for o in 0..co {
            for i in 0..ci {
                for t in 0..9 {
                    fwd[(t * ci + i) * co + o] = oihw[(o * ci + i) * 9 + t];
                }
            }
        }
        let y = conv3x3(&x, [h, w], ci, &fwd, co, Some(&bias));
        let want = direct(&x, [h, w], ci, &oihw, co, &bias);
        for (a, b) in y.iter().zip(&want) {
            assert!((a - b).abs() < 1e-5, "{a} vs {b}");
        }
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
