//! 3x3 convolutions (padding 1, stride 1) of channels-last maps (`[H·W, C]`) as Winograd's
//! minimal filtering algorithms F(m x m, 3x3) (Lavin and Gray, "Fast Algorithms for
//! Convolutional Neural Networks", 2016): each m x m output tile is `Aᵀ [(G g Gᵀ) ⊙ (Bᵀ d
//! B)] A` of its α x α input tile `d` (α = m + 2), so a block of tiles is α² matrix
//! products `M_ξ[tiles, C_out] = V_ξ[tiles, C_in] · U_ξ[C_in, C_out]`.
//!
//! - F(4x4, 3x3) (36 products per 16 pixels, 4x fewer multiply-adds than the direct
//!   convolution) runs convolutions of up to [`F4_MAX_CHANNELS`] channels; wider ones keep
//!   F(2x2, 3x3) (16 per 4, 2.25x fewer), whose weights are 2.25x smaller and whose small
//!   maps give F(4x4) too few tiles per product ([`winograd_for`]);
//! - an [`Epilogue`] is applied in the output transform while the tile is in cache: the
//!   bias and the ReLU of a forward convolution, or a ReLU's mask on an input gradient;
//! - the input gradient of such a convolution is itself one, of the output gradient with
//!   the kernel rotated by 180° and its channel axes swapped ([`rotated_column_weights`]),
//!   so the backward runs the same routine with those weights.
//!
//! Thread mapping: a map small enough to be one block ([`WINOGRAD_SHARED`] floats of
//! transformed tiles) runs the transforms parallel over tile rows and the α² products over
//! ξ; a larger one is cut into blocks of tile rows (`WINOGRAD_BLOCK` floats, a multiple of
//! the thread count), each block all three steps on one thread. Several maps of one size
//! with the same weights go through together where their tiles fit the shared block
//! ([`winograd_many`]), so each `U_ξ` is packed and read once for all.
//!
//! The reference twin is the direct loop of [`crate::conv3x3`]'s tests; the tests also
//! check the hand-written transforms against the algorithms' matrices.

use std::mem::MaybeUninit;

use rayon::prelude::*;

use crate::gemm::matmul;
use crate::simd::with_avx2;

/// Floats of one thread's Winograd block of transformed input and output tiles (1 MiB):
/// its α² products read and write them, so they should stay in the core's cache. Chosen by
/// timing VGG16's 64-channel layer at 138 x 200 with F(4x4, 3x3) on a machine with 2 MiB of
/// L2 per core (forward and input gradient): 1 MiB was faster than 512 KiB and 2 MiB.
pub const WINOGRAD_BLOCK: usize = 1 << 18;

/// Floats of transformed tiles up to which a map is one Winograd block shared by all
/// threads (16 MiB: VGG16's maps from conv2 on at 138 x 200; none at 550 x 802).
/// Chosen by timing each layer at 138 x 200 (forward and input gradient): with F(2x2, 3x3)
/// the shared block was faster than per-thread blocks on the maps from conv3 on and slower
/// on the larger maps; with F(4x4, 3x3), whose conv2 maps also fit, a limit of 8 MiB (conv2
/// and conv3 in per-thread blocks) was slower on those layers.
pub const WINOGRAD_SHARED: usize = 1 << 22;

/// Channels (input and output) from which a convolution runs as Winograd: with 3 input
/// channels the transformed products are too thin to pay for the transforms.
pub const WINOGRAD_MIN_CHANNELS: usize = 16;

/// Channels (the larger of input and output) up to which a Winograd convolution is
/// F(4x4, 3x3); above, F(2x2, 3x3). See [`winograd_for`].
pub const F4_MAX_CHANNELS: usize = 256;

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
pub struct Winograd {
    /// Output tile side `m`.
    pub m: usize,
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

/// The Winograd algorithm of a convolution with these channels: none (the column
/// formulation) below [`WINOGRAD_MIN_CHANNELS`], F(4x4, 3x3) up to [`F4_MAX_CHANNELS`],
/// F(2x2, 3x3) above.
pub fn winograd_for(ci: usize, co: usize) -> Option<&'static Winograd> {
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
pub fn rotated_column_weights(oihw: &[f32], ci: usize, co: usize) -> Vec<f32> {
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
pub fn winograd_weights(w: &[f32], ci: usize, co: usize, kind: &Winograd) -> Vec<f32> {
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
pub fn conv3x3_winograd(
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
pub enum Epilogue<'a> {
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

/// `winograd_mapped` of several maps of the same size with the same weights (the two
/// images of a loss evaluation): where their transformed tiles fit one shared block
/// together, the α² products take the tiles of all of them, so each `U_ξ` is packed and
/// read from memory once for all (VGG16's 512-channel layers read 16 MiB of weights per
/// map: on the 12 x 8 maps of conv5 at 138 x 200 the products were bound by that). A
/// [`Epilogue::ReluMask`] belongs to one map, so it takes one map.
pub fn winograd_many(
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
            matmul::<false>(
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
                        matmul::<false>(
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::conv3x3::column_weights;
    use crate::conv3x3::reference::*;

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
}
