//! The transposed 2D convolution's passes on host memory (no bias, no groups, no
//! dilation), in the column formulation ([`crate::conv`] is the op): the decoders' layers, up
//! to 512 x 512.
//!
//! - forward, per batch item: `col = Wᵀ · X` ([C_out·k_h·k_w, H·W]), then `col2im`
//!   sums into every output pixel the column entries that land on it;
//! - backward: `dcol = im2col(dY)` (the same index map read the other way), then
//!   `dX = W · dcol` and `dW += X · dcolᵀ`.
//!
//! The index map here (`im2col`, `col2im_plane`) also serves the plain convolution
//! ([`crate::conv2d`]), which reads it the other way.
//!
//! Thread mapping: the products run on rayon through `gemm`; `col2im` is parallel over
//! output channels (each task owns one output plane, so no two tasks write one pixel);
//! `im2col` is parallel over the rows of `dcol`.

use rayon::prelude::*;

use crate::constants::{COLUMN_BLOCK, planes_per_task};
use crate::conv::ConvParams;
use crate::gemm::{GradientSum, matmul, matmul_into_uninit};

/// Stride and padding of the shared index map (height, width): input pixel `i` reaches
/// output `i·stride + k - padding` through kernel tap `k`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct IndexMap {
    pub(crate) stride: [usize; 2],
    pub(crate) padding: [usize; 2],
}

/// The sizes of one call: the transposed convolution's input (`ci` x `h` x `w`) and output
/// (`co` x `ho` x `wo`). [`crate::conv2d`] runs the same index map the other way, with its
/// own output in the input's place and its own input in the output's.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Dims {
    pub(crate) n: usize,
    pub(crate) ci: usize,
    pub(crate) co: usize,
    pub(crate) h: usize,
    pub(crate) w: usize,
    pub(crate) kh: usize,
    pub(crate) kw: usize,
    pub(crate) ho: usize,
    pub(crate) wo: usize,
}

impl Dims {
    pub(crate) fn new(x: &[usize], weight: &[usize], p: &ConvParams) -> Self {
        let [n, ci, h, w] = [x[0], x[1], x[2], x[3]];
        let [co, kh, kw] = [weight[1], weight[2], weight[3]];
        let [ho, wo] = p.output_size([h, w], [kh, kw]).unwrap_or([0, 0]);
        Dims {
            n,
            ci,
            co,
            h,
            w,
            kh,
            kw,
            ho,
            wo,
        }
    }

    /// Input pixels per plane.
    pub(crate) fn p(&self) -> usize {
        self.h * self.w
    }

    /// Rows of the column matrix (C_out · k_h · k_w).
    pub(crate) fn q(&self) -> usize {
        self.co * self.kh * self.kw
    }
}

/// The input index `i` whose output `i·stride + k - pad` is `o`, for every input `i`:
/// returns the input range `[lo, hi)` that lands inside `0..out` for kernel tap `k`.
pub(crate) fn valid_inputs(
    len: usize,
    out: usize,
    stride: usize,
    pad: usize,
    k: usize,
) -> (usize, usize) {
    // o = i·s + k - pad ∈ [0, out)  ⇔  i·s ≥ pad - k  and  i·s < out + pad - k.
    let lo = pad.saturating_sub(k).div_ceil(stride);
    let hi = if out + pad > k {
        (out + pad - k).div_ceil(stride).min(len)
    } else {
        0
    };
    (lo.min(hi), hi)
}

/// Forward on host memory: `x` [N, C_in, H, W], `weight` [C_in, C_out, k_h, k_w], then
/// `epilogue(channel, plane)` on every output plane (for [`crate::conv_bias_act`]'s bias and
/// activation): in the task that scattered it, while
/// it is still in cache, when the column matrix is one block; in a pass of its own after
/// the last block otherwise.
///
/// The input is taken in blocks of [`input_rows_per_block`] rows (all of it for the small
/// layers): per block, `col = Wᵀ · X[:, block]`, then every output row the block reaches
/// gets its share added (neighbouring blocks reach some output rows both), so the blocks
/// run one after another into the zeroed output; the whole-input case writes instead.
pub(crate) fn host_forward_then(
    x: &[f32],
    weight: &[f32],
    d: Dims,
    p: &IndexMap,
    epilogue: impl Fn(usize, &mut [f32]) + Sync,
) -> Vec<f32> {
    host_forward_blocked(
        x,
        weight,
        d,
        p,
        input_rows_per_block(d, COLUMN_BLOCK),
        epilogue,
    )
}

/// Input rows per block of the host passes: as many as keep the block's column matrix
/// within `block` values, at least one and at most the input's height.
fn input_rows_per_block(d: Dims, block: usize) -> usize {
    (block / (d.q() * d.w).max(1)).clamp(1, d.h.max(1))
}

/// [`host_forward_then`] with `rows` input rows per block (the tests set it small).
fn host_forward_blocked(
    x: &[f32],
    weight: &[f32],
    d: Dims,
    p: &IndexMap,
    rows: usize,
    epilogue: impl Fn(usize, &mut [f32]) + Sync,
) -> Vec<f32> {
    let (pp, q, plane) = (d.p(), d.q(), d.ho * d.wo);
    let whole = rows >= d.h;
    let mut out = vec![0.0f32; d.n * d.co * plane];
    with_columns(q * rows * d.w, |col| {
        for b in 0..d.n {
            let xb = &x[b * d.ci * pp..(b + 1) * d.ci * pp];
            let ob = &mut out[b * d.co * plane..(b + 1) * d.co * plane];
            for r0 in (0..d.h).step_by(rows) {
                let r1 = (r0 + rows).min(d.h);
                let n = (r1 - r0) * d.w;
                let col = &mut col[..q * n];
                // col [q, n] = Wᵀ [q, C_in] · X[:, block] [C_in, n]; W is [C_in, q]
                // row-major, the block's pixels are contiguous in every input plane.
                matmul::<true>(
                    [q, n, d.ci],
                    col,
                    [n, 1],
                    false,
                    weight,
                    [1, q],
                    &xb[r0 * d.w..],
                    [pp, 1],
                );
                let col = &*col;
                ob.par_chunks_mut(plane)
                    .enumerate()
                    .with_min_len(planes_per_task(plane))
                    .for_each(|(c, o)| {
                        col2im_rows(col, o, c, d, p, (r0, r1), !whole);
                        if whole {
                            epilogue(c, o);
                        }
                    });
            }
            if !whole {
                ob.par_chunks_mut(plane)
                    .enumerate()
                    .with_min_len(planes_per_task(plane))
                    .for_each(|(c, o)| epilogue(c, o));
            }
        }
    });
    out
}

/// Writes output channel `c`'s plane `o` [H_out, W_out] from its column rows over the whole
/// input: every output pixel is the sum of the column entries that land on it (what was
/// written there before is replaced).
pub(crate) fn col2im_plane(col: &[f32], o: &mut [f32], c: usize, d: Dims, p: &IndexMap) {
    col2im_rows(col, o, c, d, p, (0, d.h), false);
}

/// The share of input rows `r0..r1` in output channel `c`'s plane `o` [H_out, W_out], from
/// the block's column rows (`col` [q, (r1 - r0)·W]): added to the output rows the block
/// reaches with `accumulate`, written into every output row without it (then the block
/// must be the whole input).
///
/// Row by row: output row `oy` takes input row `iy` of tap `ky` when `iy·s_y + ky - p_y = oy`.
/// A tap `kx` sends input columns to the output columns `ix·s_x + kx - p_x`, which step by
/// `s_x`; so the row is summed in `s_x` phase rows (phase `r` holds the output columns
/// `m·s_x + r`), where every tap's contribution is one contiguous, vectorisable add, and
/// the phases are interleaved into `o`'s row once at the end. Adding each tap into `o` with a
/// stride of `s_x` instead is scalar code, one value at a time, and was a large part of the
/// `paper` decoders' forward + backward.
fn col2im_rows(
    col: &[f32],
    o: &mut [f32],
    c: usize,
    d: Dims,
    p: &IndexMap,
    (r0, r1): (usize, usize),
    accumulate: bool,
) {
    let pp = (r1 - r0) * d.w;
    let [sy, sx] = p.stride;
    let [py, px] = p.padding;
    if d.wo == 0 || r0 >= r1 {
        return;
    }
    // The output rows the block reaches: r0·s_y - p_y ..= (r1 - 1)·s_y + k_h - 1 - p_y.
    let (oy0, oy1) = if accumulate {
        (
            (r0 * sy).saturating_sub(py),
            ((r1 - 1) * sy + d.kh).saturating_sub(py).min(d.ho),
        )
    } else {
        (0, d.ho)
    };
    let mw = d.wo.div_ceil(sx);
    let mut phases = vec![0.0f32; sx * mw];
    for (oy, out_row) in o.chunks_exact_mut(d.wo).enumerate().take(oy1).skip(oy0) {
        phases.fill(0.0);
        for ky in 0..d.kh {
            // iy·sy = oy + py - ky, with r0 <= iy < r1.
            let Some(t) = (oy + py).checked_sub(ky) else {
                continue;
            };
            if t % sy != 0 || t / sy < r0 || t / sy >= r1 {
                continue;
            }
            let iy = t / sy - r0;
            for kx in 0..d.kw {
                let (ix0, ix1) = valid_inputs(d.w, d.wo, sx, px, kx);
                if ix0 == ix1 {
                    continue;
                }
                let row = &col[((c * d.kh + ky) * d.kw + kx) * pp..][..pp];
                let src = &row[iy * d.w + ix0..iy * d.w + ix1];
                // Output column of input column ix0; the others follow every sx.
                let ox0 = ix0 * sx + kx - px;
                let at = (ox0 % sx) * mw + ox0 / sx;
                phases[at..at + src.len()]
                    .iter_mut()
                    .zip(src)
                    .for_each(|(a, v)| *a += v);
            }
        }
        interleave(&phases, mw, sx, out_row, accumulate);
    }
}

/// `out[m·s + r] (+)= phases[r·mw + m]` for every output column (added with `accumulate`).
fn interleave(phases: &[f32], mw: usize, s: usize, out: &mut [f32], accumulate: bool) {
    // One loop per mode, not a branch per value in the hot loop.
    if accumulate {
        interleave_with(phases, mw, s, out, |v, x| *v += x);
    } else {
        interleave_with(phases, mw, s, out, |v, x| *v = x);
    }
}

/// [`interleave`] with `put(out value, phase value)`.
fn interleave_with(
    phases: &[f32],
    mw: usize,
    s: usize,
    out: &mut [f32],
    put: impl Fn(&mut f32, f32),
) {
    match s {
        1 => out.iter_mut().zip(phases).for_each(|(v, x)| put(v, *x)),
        2 => {
            let (even, odd) = phases.split_at(mw);
            let mut pairs = out.chunks_exact_mut(2);
            for ((pair, e), o) in (&mut pairs).zip(even).zip(odd) {
                put(&mut pair[0], *e);
                put(&mut pair[1], *o);
            }
            if let [last] = pairs.into_remainder() {
                put(last, even[mw - 1]);
            }
        }
        _ => out
            .iter_mut()
            .enumerate()
            .for_each(|(ox, v)| put(v, phases[(ox % s) * mw + ox / s])),
    }
}

/// Gathers `dcol` [q, P] from one batch item's output gradient `g` [C_out, H_out, W_out].
pub(crate) fn im2col(g: &[f32], dcol: &mut [f32], d: Dims, p: &IndexMap) {
    im2col_rows(g, dcol, d, p, (0, d.h));
}

/// Gathers the block of input rows `r0..r1` of `dcol` ([q, (r1 - r0)·W]) from one batch
/// item's output gradient `g` [C_out, H_out, W_out].
fn im2col_rows(g: &[f32], dcol: &mut [f32], d: Dims, p: &IndexMap, (r0, r1): (usize, usize)) {
    let pp = (r1 - r0) * d.w;
    let plane = d.ho * d.wo;
    let [sy, sx] = p.stride;
    let [py, px] = p.padding;
    dcol.par_chunks_mut(pp)
        .enumerate()
        .with_min_len(planes_per_task(pp))
        .for_each(|(r, row)| {
            let (c, ky, kx) = (r / (d.kh * d.kw), (r / d.kw) % d.kh, r % d.kw);
            let gc = &g[c * plane..(c + 1) * plane];
            let (iy0, iy1) = valid_inputs(d.h, d.ho, sy, py, ky);
            // The valid rows inside the block, counted from its first row.
            let iy1 = iy1.clamp(r0, r1) - r0;
            let iy0 = iy0.clamp(r0, r1) - r0;
            let iy0 = iy0.min(iy1);
            let (ix0, ix1) = valid_inputs(d.w, d.wo, sx, px, kx);
            // Only the entries no tap reaches are zeroed; the rest are written once.
            row[..iy0 * d.w].fill(0.0);
            row[iy1 * d.w..].fill(0.0);
            let ox0 = ix0 * sx + kx - px;
            for iy in iy0..iy1 {
                let oy = (iy + r0) * sy + ky - py;
                let dst = &mut row[iy * d.w..(iy + 1) * d.w];
                dst[..ix0].fill(0.0);
                dst[ix1..].fill(0.0);
                if ix0 == ix1 {
                    continue;
                }
                let src = &gc[oy * d.wo + ox0..(oy + 1) * d.wo];
                let n = ix1 - ix0;
                if sx == 1 {
                    dst[ix0..ix1].copy_from_slice(&src[..n]);
                } else if sx == 2 {
                    // The decoders' stride, written out as pairs so that the compiler
                    // vectorises it (a `step_by(2)` gather compiles to scalar code).
                    let (body, last) = dst[ix0..ix1].split_at_mut(n - 1);
                    body.iter_mut()
                        .zip(src[..2 * (n - 1)].chunks_exact(2))
                        .for_each(|(d, pair)| *d = pair[0]);
                    last[0] = src[2 * (n - 1)];
                } else {
                    dst[ix0..ix1]
                        .iter_mut()
                        .zip(src.iter().step_by(sx))
                        .for_each(|(d, s)| *d = *s);
                }
            }
        });
}

/// Backward on host memory → (dx [N, C_in, H, W], dweight [C_in, C_out, k_h, k_w]), in
/// blocks of input rows as the forward ([`host_forward_then`]): per block, `dcol` from the
/// output gradient, `dX[:, block] = W · dcol` and `dW += X[:, block] · dcolᵀ`.
pub(crate) fn host_backward(
    x: &[f32],
    weight: &[f32],
    g: &[f32],
    d: Dims,
    p: &IndexMap,
) -> (Vec<f32>, Vec<f32>) {
    host_backward_blocked(x, weight, g, d, p, input_rows_per_block(d, COLUMN_BLOCK))
}

/// [`host_backward`] with `rows` input rows per block (the tests set it small).
fn host_backward_blocked(
    x: &[f32],
    weight: &[f32],
    g: &[f32],
    d: Dims,
    p: &IndexMap,
    rows: usize,
) -> (Vec<f32>, Vec<f32>) {
    let (pp, q, plane) = (d.p(), d.q(), d.ho * d.wo);
    let mut dx = Vec::with_capacity(d.n * d.ci * pp);
    let mut dw = GradientSum::new(d.ci, q, d.n * d.p());
    with_columns(q * rows * d.w, |dcol| {
        for b in 0..d.n {
            let gb = &g[b * d.co * plane..(b + 1) * d.co * plane];
            let xb = &x[b * d.ci * pp..(b + 1) * d.ci * pp];
            let dxb = &mut dx.spare_capacity_mut()[b * d.ci * pp..(b + 1) * d.ci * pp];
            for r0 in (0..d.h).step_by(rows) {
                let r1 = (r0 + rows).min(d.h);
                let n = (r1 - r0) * d.w;
                let dcol = &mut dcol[..q * n];
                im2col_rows(gb, dcol, d, p, (r0, r1));
                // dX[:, block] [C_in, n] = W [C_in, q] · dcol [q, n]
                matmul_into_uninit(
                    [d.ci, n, q],
                    &mut dxb[r0 * d.w..],
                    [pp, 1],
                    weight,
                    [q, 1],
                    dcol,
                    [n, 1],
                );
                // dW [C_in, q] += X[:, block] [C_in, n] · dcolᵀ [n, q]
                dw.add(n, &xb[r0 * d.w..], pp, dcol, n);
            }
        }
    });
    // SAFETY: the blocks' products wrote the `C_in·P` values of every batch item.
    unsafe { dx.set_len(d.n * d.ci * pp) };
    (dx, dw.into_row_major())
}

thread_local! {
    /// The calling thread's column buffer, kept between calls ([`with_columns`]).
    static COLUMNS: std::cell::Cell<Vec<f32>> = const { std::cell::Cell::new(Vec::new()) };
}

/// Runs `f` on a column buffer of `len` values whose contents are unspecified (`f` writes
/// before it reads), reused across calls on one thread so the column matrices of every layer
/// and step do not each cost a fresh, zeroed allocation. A nested call gets a buffer of its
/// own.
pub(crate) fn with_columns<R>(len: usize, f: impl FnOnce(&mut [f32]) -> R) -> R {
    let mut buf = COLUMNS.take();
    if buf.len() < len {
        buf.resize(len, 0.0);
    }
    let out = f(&mut buf[..len]);
    COLUMNS.set(buf);
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::check::{host, max_rel, output_and_gradients};
    use crate::conv::ConvKind;
    use crate::conv::tests::{TRANSPOSED, case_shapes};
    use burn::tensor::{Device, Distribution, Tensor};

    /// The passes in blocks of every possible number of input rows (down to one, so that
    /// every block boundary falls between output rows that two blocks share) against burn's
    /// `conv_transpose2d` and its backward on ndarray, on every index map of the op's
    /// transposed cases; the epilogue runs once per plane, after the last block.
    #[test]
    #[allow(deprecated)]
    fn blocks_match_burn() {
        let device = Device::ndarray().autodiff();
        for (i, case) in TRANSPOSED.into_iter().enumerate() {
            let (p, wshape, out) = case_shapes(ConvKind::Transposed, case);
            let (_, _, _, [h, w], n) = case;
            let [ci, co] = [wshape[0], wshape[1]];
            device.seed(100 + i as u64);
            let normal = Distribution::Normal(0.0, 1.0);
            let x = Tensor::<4>::random([n, ci, h, w], normal, &device);
            let wt = Tensor::<4>::random(wshape, normal, &device);
            let g = Tensor::<4>::random(out, normal, &device);
            let options = burn::tensor::ops::ConvTransposeOptions::new(
                p.stride,
                p.padding,
                [0, 0],
                [1, 1],
                1,
            );
            let [y_ref, dx_ref, dw_ref] = output_and_gradients(&x, &wt, &g, |x, w| {
                burn::tensor::module::conv_transpose2d(x, w, None, options.clone())
            });
            let [xs, ws, gs] = [x, wt, g].map(host);
            let d = Dims::new(&[n, ci, h, w], &wshape, &p);
            let (m, plane) = (p.map(), out[2] * out[3]);
            for rows in 1..=h {
                // The epilogue adds 10 + the channel, so a plane it misses or visits twice shows.
                let y = host_forward_blocked(&xs, &ws, d, &m, rows, |c, o: &mut [f32]| {
                    o.iter_mut().for_each(|v| *v += 10.0 + c as f32)
                });
                let y: Vec<f32> = y
                    .iter()
                    .enumerate()
                    .map(|(j, v)| v - 10.0 - ((j / plane) % co) as f32)
                    .collect();
                let (dx, dw) = host_backward_blocked(&xs, &ws, &gs, d, &m, rows);
                for (what, a, b) in [("forward", &y, &y_ref), ("grad x", &dx, &dx_ref)] {
                    let e = max_rel(a, b, 1e-3);
                    assert!(e < 1e-5, "case {i}, {rows} rows: {what} differs by {e}");
                }
                let e = max_rel(&dw, &dw_ref, 1e-3);
                assert!(
                    e < 1e-5,
                    "case {i}, {rows} rows: grad weight differs by {e}"
                );
            }
        }
    }

    /// Blocks of [`COLUMN_BLOCK`] values: the `paper` decoders' last geometry layer (32 to 11
    /// channels, 256 to 512) in blocks of 5 input rows, its first (8 x 8) in one.
    #[test]
    fn rows_per_block() {
        let p = ConvParams::transposed([2, 2], [1, 1]);
        let d = |ci: usize, co: usize, h: usize| Dims::new(&[1, ci, h, h], &[ci, co, 4, 4], &p);
        assert_eq!(input_rows_per_block(d(32, 11, 256), COLUMN_BLOCK), 5);
        assert_eq!(input_rows_per_block(d(256, 256, 8), COLUMN_BLOCK), 8);
        assert_eq!(input_rows_per_block(d(3, 1, 4), 1), 1);
    }

    #[test]
    fn valid_inputs_cover_exactly_the_output() {
        for &(len, out, stride, pad, k) in &[
            (5usize, 10usize, 2usize, 1usize, 0usize),
            (5, 10, 2, 1, 3),
            (3, 7, 3, 2, 4),
            (1, 2, 2, 1, 0),
        ] {
            let (lo, hi) = valid_inputs(len, out, stride, pad, k);
            for i in 0..len {
                let o = (i * stride + k) as isize - pad as isize;
                let inside = o >= 0 && (o as usize) < out;
                assert_eq!(
                    inside,
                    (lo..hi).contains(&i),
                    "{len} {out} {stride} {pad} {k} {i}"
                );
            }
        }
    }
}
