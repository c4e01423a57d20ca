//! 3x3 convolutions (padding 1, stride 1) of channels-last maps (`[H·W, C]`) in the column
//! formulation: one product per block of pixels, `Y[block, C_out] = col[block, 9·C_in] ·
//! W[9·C_in, C_out]`, and the input gradient for few input channels as one product and a
//! sum over the nine taps ([`conv3x3_input_gradient`]). The perceptual loss's first VGG16
//! layer (3 input channels) runs here; its wider layers run as [`crate::winograd`].
//!
//! Thread mapping: the pixels split into blocks (a multiple of rayon's thread count, each
//! column matrix and each output at most `COL_BLOCK` floats), one single-threaded product
//! per block on rayon.
//!
//! The reference twin is a direct loop over pixels, taps and channels ([`reference`]); the
//! tests compare both passes with it.

use rayon::prelude::*;

use crate::gemm::matmul_uninit;

/// Floats of the larger of one block's column matrix and its output (256 KiB): both stay in
/// the core's L2 cache from the gather through the product to the bias and ReLU. Chosen by
/// timing VGG16's first layer at 138 x 200 with blocks from 64 KiB to 1 MiB: 1 MiB (whose
/// output no longer fits the cache) was clearly slower, 128-256 KiB the fastest.
const COL_BLOCK: usize = 1 << 16;

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
pub fn conv3x3(
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
            matmul_uninit::<false>([np, co, k], o, col, [k, 1], wm, [co, 1]);
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

/// PyTorch's OIHW 3x3 kernel → the column weights `[9·C_in, C_out]`, rows ordered (ky, kx, c_in).
pub fn column_weights(oihw: &[f32], ci: usize, co: usize) -> Vec<f32> {
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
pub fn conv3x3_input_gradient(
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
    matmul_uninit::<true>(
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

/// Plain loops the fast paths are checked against (tests of this crate only).
#[cfg(test)]
pub(crate) mod reference {
    /// A direct (loop) 3x3 convolution, channels-last, OIHW weights.
    pub(crate) fn direct(
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

    /// Deterministic test values in [-1, 1).
    pub(crate) fn values(n: usize, seed: usize) -> Vec<f32> {
        (0..n)
            .map(|i| (((i * 7919 + seed * 104_729) % 1000) as f32 / 500.0) - 1.0)
            .collect()
    }

    /// The input gradient of a 3x3 convolution (padding 1) by direct loops: every output
    /// pixel `p` sends `dy[p, o] · W[o, i, ky, kx]` to the input pixel its tap read,
    /// `p + (ky - 1, kx - 1)`.
    pub(crate) fn direct_input_gradient(
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

    /// The largest difference relative to the largest magnitude of `want`.
    pub(crate) fn max_rel(got: &[f32], want: &[f32]) -> f32 {
        assert_eq!(got.len(), want.len());
        let scale = want.iter().fold(1e-12f32, |m, v| m.max(v.abs()));
        got.iter()
            .zip(want)
            .fold(0.0f32, |m, (a, b)| m.max((a - b).abs() / scale))
    }
}

#[cfg(test)]
mod tests {
    use super::reference::*;
    use super::*;

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
}
