//! 2x2 max-pooling (stride 2) of channels-last maps, and its backward fused with the ReLU
//! whose output it pooled: each output's gradient goes to the first maximum of its window
//! (row-major scan, strict `>`, NaN taken: PyTorch's and burn's rule), recomputed from the
//! saved pre-pool map; a tap's direct gradient is added and the ReLU's mask applied in the
//! same pass ([`pool_relu_backward`]).
//!
//! Thread mapping: parallel over output rows; the scan branch-free in vector lanes
//! (AVX2 where the CPU has it).
//!
//! The reference twin is the three steps done one by one (the tests).

use rayon::prelude::*;

use crate::map::Map;
use crate::simd::with_avx2;

/// `m` replaced by `v` where `v` is larger or NaN: one step of the pooling window's scan
/// (row-major, strict `>`, NaN taken; PyTorch's and burn's rule), branch-free so that it
/// runs in vector lanes.
#[inline(always)]
fn takes(v: f32, m: f32) -> bool {
    v > m || v.is_nan()
}

/// 2x2 max-pool with stride 2 (odd trailing rows and columns dropped, as PyTorch's default
/// `ceil_mode=False`) of a channels-last map with `c` channels.
pub fn max_pool(x: &Map, c: usize) -> Map {
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
pub fn pool_relu_backward(
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
pub fn add_tap_and_mask(d: &mut [f32], (g, scale): (&[f32], f32), y: &[f32]) {
    const CHUNK: usize = 1 << 14;
    d.par_chunks_mut(CHUNK)
        .zip(g.par_chunks(CHUNK).zip(y.par_chunks(CHUNK)))
        .for_each(|(d, (g, y))| add_tap_and_mask_serial(d, (g, scale), y));
}

/// `scale·g` where `y > 0`, zero elsewhere: [`add_tap_and_mask`] onto a zero gradient,
/// written into a fresh map without zeroing it first.
pub fn tap_through_relu((g, scale): (&[f32], f32), y: &[f32]) -> Vec<f32> {
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
    use crate::conv3x3::reference::values;

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
