//! VGG16's convolution stack on the CPU, for the perceptual loss: the forward pass of two
//! images, the L1 distance of their five taps, and the gradient of that distance with respect
//! to the images. The weights are frozen, so no weight gradient is ever formed.
//!
//! Why: through burn's generic ops (flex), one loss evaluation at 138 x 200 (reference pass,
//! render pass, backward) was much slower than PyTorch's, most of the time going to the
//! convolutions' input gradients and the element-wise autodiff steps between them (ReLU
//! masks, pooling, the normalisation). Here everything is in one place on host memory, on
//! the ops of `texavatars-cpu`:
//!
//! - maps are channels-last ([`Map`], `[H·W, C]`), so every gather copies runs of `C` floats;
//! - a convolution with at least `WINOGRAD_MIN_CHANNELS` channels on both sides (all but
//!   the first) runs as Winograd's minimal filtering ([`texavatars_cpu::winograd`]): F(4x4,
//!   3x3) on the layers of up to 256 channels, F(2x2, 3x3) on the 512-channel ones, whose
//!   maps at 138 x 200 (25 x 17, 12 x 8) give F(4x4) too few tiles per product (timed per
//!   layer at 138 x 200, forward and input gradient: F(4x4) is clearly faster on the 64- to
//!   256-channel layers, about even on the 25 x 17 maps and slower on the 12 x 8 ones). The
//!   bias and the ReLU are applied in the output transform while the tile is in cache;
//! - the first convolution (3 input channels) keeps the column formulation
//!   ([`texavatars_cpu::conv3x3`]), and its input gradient (3 output channels) is the
//!   product of the output gradient with the transposed weights, then a sum over the nine
//!   taps;
//! - the input gradient of a Winograd layer runs the same routine with the kernel rotated
//!   by 180° and its channel axes swapped (`u_back`, transformed once; stored contiguous,
//!   because read in place from the forward's with transposed strides every product would
//!   pack them element by element);
//! - a 2x2 max-pool's backward sends each output's gradient to the first maximum of its
//!   window ([`texavatars_cpu::pool`]), recomputed from the saved pre-pool map;
//! - the backward passes over each map once: the ReLU's mask is applied in the Winograd
//!   output transform of the input gradient (`Epilogue::ReluMask`), or, where a pool lies
//!   between, in the pool's backward together with the tap's direct gradient
//!   (`pool_relu_backward`); the loss's sum and the taps' gradients are one pass.
//!
//! Thread mapping: as the ops'. In the forward pass the two images of a loss evaluation go
//! through each Winograd layer together where the tiles of both fit the shared block
//! (`winograd_many`; conv3 on at 138 x 200), so each layer's transformed weights are packed
//! and read once for the pair.
//!
//! The reference twin is burn's own `Conv2d` / `max_pool2d` / `relu` stack
//! ([`crate::metrics::Features`]); `crate::metrics::perceptual`'s tests compare the loss and
//! its image gradient with it on both CPU backends.

use std::mem::MaybeUninit;

use rayon::prelude::*;
use texavatars_cpu::conv3x3::{column_weights, conv3x3, conv3x3_input_gradient};
use texavatars_cpu::map::Map;
use texavatars_cpu::pool::{add_tap_and_mask, max_pool, pool_relu_backward, tap_through_relu};
use texavatars_cpu::winograd::{
    Epilogue, WINOGRAD_SHARED, Winograd, conv3x3_winograd, rotated_column_weights, winograd_for,
    winograd_many, winograd_weights,
};

use crate::metrics::constants::{IMAGENET_MEAN, IMAGENET_STD};
use crate::metrics::nets::Net;
use crate::metrics::weights::HostWeights;

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

    /// The five tap maps (channels-last `[H_k·W_k, C_k]`, after their ReLU) of each of
    /// `images`, maps of one size already normalised for the network.
    pub(crate) fn taps(&self, images: Vec<Map>) -> Vec<Vec<Map>> {
        let keep = vec![false; images.len()];
        self.features(images, &keep)
            .into_iter()
            .map(|act| {
                act.outputs
                    .into_iter()
                    .zip(&self.layers)
                    .filter(|(_, layer)| layer.tap)
                    .map(|(map, _)| map)
                    .collect()
            })
            .collect()
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

#[cfg(test)]
mod tests {
    use super::*;
    use texavatars_cpu::winograd::winograd_for;

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
}
