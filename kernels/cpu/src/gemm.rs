//! Row-major matrix products on the CPU through the `gemm` crate (the one burn-flex itself
//! uses), with explicit strides: the column formulations of the CPU convolutions
//! ([`crate::conv_transpose`], [`crate::winograd`]) are built on it.

use std::mem::MaybeUninit;

/// Work (multiply-adds) above which a product is split across rayon's threads.
pub const PARALLEL_WORK: usize = 1 << 16;

/// `dst[m×n] (+)= lhs[m×k] · rhs[k×n]` with explicit (row, column) strides. With
/// `PARALLEL`, on rayon's threads when the work reaches [`PARALLEL_WORK`]; without, on the
/// calling thread only (for products that are already one task of a parallel loop).
///
/// # Panics
/// When a stride addresses past the end of its slice.
#[allow(clippy::too_many_arguments)]
pub fn matmul<const PARALLEL: bool>(
    mnk: [usize; 3],
    dst: &mut [f32],
    dst_strides: [usize; 2],
    accumulate: bool,
    lhs: &[f32],
    lhs_strides: [usize; 2],
    rhs: &[f32],
    rhs_strides: [usize; 2],
) {
    let (d, l, r) = ((dst, dst_strides), (lhs, lhs_strides), (rhs, rhs_strides));
    product(PARALLEL, mnk, d, accumulate, l, r)
}

/// [`matmul`] into a dense row-major `dst` of `m·n` values (strides `[n, 1]`) that need
/// not be initialised: every value is written and none is read. For outputs allocated fresh,
/// where zeroing them first would be one more pass over memory; the caller marks them
/// initialised afterwards (`Vec::set_len`).
///
/// # Panics
/// When `dst` does not have `m·n` values or a stride addresses past the end of its slice.
pub fn matmul_uninit<const PARALLEL: bool>(
    mnk: [usize; 3],
    dst: &mut [MaybeUninit<f32>],
    lhs: &[f32],
    lhs_strides: [usize; 2],
    rhs: &[f32],
    rhs_strides: [usize; 2],
) {
    let [m, n, _] = mnk;
    assert_eq!(dst.len(), m * n, "matmul_uninit: dst is not m x n");
    uninit_product(
        PARALLEL,
        mnk,
        (dst, [n, 1]),
        (lhs, lhs_strides),
        (rhs, rhs_strides),
    );
}

/// [`matmul_uninit`] with explicit `dst` strides: the `m·n` values they address are
/// written and none is read; the others are left as they were (a block of columns of a
/// larger matrix, say).
///
/// # Panics
/// When a stride addresses past the end of its slice.
pub fn matmul_into_uninit(
    mnk: [usize; 3],
    dst: &mut [MaybeUninit<f32>],
    dst_strides: [usize; 2],
    lhs: &[f32],
    lhs_strides: [usize; 2],
    rhs: &[f32],
    rhs_strides: [usize; 2],
) {
    uninit_product(
        true,
        mnk,
        (dst, dst_strides),
        (lhs, lhs_strides),
        (rhs, rhs_strides),
    );
}

/// A matrix operand: its values and its (row, column) strides.
type Operand<'a> = (&'a [f32], [usize; 2]);

/// The product into uninitialised `dst`, on rayon's threads when `parallel`.
fn uninit_product(
    parallel: bool,
    mnk: [usize; 3],
    (dst, dst_strides): (&mut [MaybeUninit<f32>], [usize; 2]),
    (lhs, lhs_strides): Operand,
    (rhs, rhs_strides): Operand,
) {
    let dst = ((dst.as_mut_ptr().cast::<f32>(), dst.len()), dst_strides);
    // SAFETY: `f32` and `MaybeUninit<f32>` have one layout; `product_raw` writes the `m·n`
    // addressed values (inside `dst`, which it asserts) without reading them when
    // `accumulate` is false.
    unsafe {
        product_raw(
            parallel,
            mnk,
            dst,
            false,
            (lhs, lhs_strides),
            (rhs, rhs_strides),
        )
    };
}

/// Summed `k` from which [`GradientSum`] keeps its sum column-major (with at least
/// [`COLUMN_MAJOR_MIN_N`] columns). Chosen on the weight gradients of the `paper` decoders'
/// transposed convolutions: from k = 4096 (128 -> 64 at 64^2) up to k = 65536 (32 -> 11) the
/// column-major sum is much faster; at k = 1024 and below (128 -> 128 at 32^2) its gain
/// does not pay for the final transposition.
pub const COLUMN_MAJOR_MIN_K: usize = 4096;

/// Columns (`n`) from which [`GradientSum`] keeps its sum column-major: with 48 (64 -> 3,
/// k = 16384) the column-major product is slower than the row-major one.
pub const COLUMN_MAJOR_MIN_N: usize = 64;

/// A sum of products `lhs · rhsᵀ` whose two operands both run along `k` (`lhs` [m×k],
/// `rhs` [n×k], a row each per output row and column): the weight gradients of the column
/// convolutions, `X · dcolᵀ` summed over blocks of pixels or batch items.
///
/// With a long `k` it is kept column-major while it sums and transposed once at the end:
/// gemm computes a row-major destination as the transposed problem, which packs `rhs` (the
/// larger operand there) in panels of 64 rows a power-of-two stride apart (cache
/// conflicts); into a column-major destination the same product avoids that packing and is
/// much faster (see [`COLUMN_MAJOR_MIN_K`]).
pub struct GradientSum {
    m: usize,
    n: usize,
    column_major: bool,
    /// The sum: value (r, c) at `c·m + r` when `column_major`, at `r·n + c` otherwise.
    sum: Vec<f32>,
}

impl GradientSum {
    /// A zero `m×n` sum that will take `k_total` values of `k` in all (which picks its
    /// layout).
    pub fn new(m: usize, n: usize, k_total: usize) -> Self {
        Self {
            m,
            n,
            column_major: k_total >= COLUMN_MAJOR_MIN_K && n >= COLUMN_MAJOR_MIN_N,
            sum: vec![0.0; m * n],
        }
    }

    /// Adds `lhs[m×k] · rhs[n×k]ᵀ`, the operands' rows `lhs_row` and `rhs_row` values apart
    /// (their `k` values contiguous).
    ///
    /// # Panics
    /// When a row addresses past the end of its slice.
    pub fn add(&mut self, k: usize, lhs: &[f32], lhs_row: usize, rhs: &[f32], rhs_row: usize) {
        let (m, n) = (self.m, self.n);
        let dst_strides = if self.column_major { [1, m] } else { [n, 1] };
        matmul::<true>(
            [m, n, k],
            &mut self.sum,
            dst_strides,
            true,
            lhs,
            [lhs_row, 1],
            rhs,
            [1, rhs_row],
        );
    }

    /// The sum, row-major [m×n].
    pub fn into_row_major(self) -> Vec<f32> {
        let (m, n) = (self.m, self.n);
        if !self.column_major {
            return self.sum;
        }
        let mut out = vec![0.0f32; m * n];
        // In square tiles, so that both the reads and the writes stay within a few cache
        // lines per tile (a plain loop strides through `out` a row apart per value).
        const TILE: usize = 16;
        for c0 in (0..n).step_by(TILE) {
            for r0 in (0..m).step_by(TILE) {
                for c in c0..(c0 + TILE).min(n) {
                    let col = &self.sum[c * m..(c + 1) * m];
                    for r in r0..(r0 + TILE).min(m) {
                        out[r * n + c] = col[r];
                    }
                }
            }
        }
        out
    }
}

/// The product into initialised `dst`, on rayon's threads when `parallel`.
fn product(
    parallel: bool,
    mnk: [usize; 3],
    (dst, dst_strides): (&mut [f32], [usize; 2]),
    accumulate: bool,
    lhs: Operand,
    rhs: Operand,
) {
    let dst = ((dst.as_mut_ptr(), dst.len()), dst_strides);
    // SAFETY: `dst` is an initialised, exclusively borrowed slice of `dst.len()` values.
    unsafe { product_raw(parallel, mnk, dst, accumulate, lhs, rhs) }
}

/// The product on a raw `dst` of `len` values.
///
/// # Safety
/// `dst` must be valid for writes of `len` values (and for reads when `accumulate`), and
/// must not alias `lhs` or `rhs`.
#[allow(clippy::too_many_arguments)]
unsafe fn product_raw(
    parallel: bool,
    [m, n, k]: [usize; 3],
    ((dst, dst_len), [dst_rs, dst_cs]): ((*mut f32, usize), [usize; 2]),
    accumulate: bool,
    (lhs, [lhs_rs, lhs_cs]): Operand,
    (rhs, [rhs_rs, rhs_cs]): Operand,
) {
    if m == 0 || n == 0 {
        return;
    }
    let last = |rs: usize, cs: usize, r: usize, c: usize| (r - 1) * rs + (c - 1) * cs;
    assert!(
        last(dst_rs, dst_cs, m, n) < dst_len,
        "matmul: dst too short"
    );
    if k == 0 {
        if !accumulate {
            for r in 0..m {
                for c in 0..n {
                    // SAFETY: inside `dst` by the assert above.
                    unsafe { dst.add(r * dst_rs + c * dst_cs).write(0.0) };
                }
            }
        }
        return;
    }
    assert!(
        last(lhs_rs, lhs_cs, m, k) < lhs.len(),
        "matmul: lhs too short"
    );
    assert!(
        last(rhs_rs, rhs_cs, k, n) < rhs.len(),
        "matmul: rhs too short"
    );
    let parallelism = if parallel && m * n * k >= PARALLEL_WORK {
        gemm::Parallelism::Rayon(0)
    } else {
        gemm::Parallelism::None
    };
    // SAFETY: the asserts above keep every element the strides address inside its slice;
    // the caller guarantees `dst` is writable and does not alias `lhs` or `rhs`.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst,
            dst_cs as isize,
            dst_rs as isize,
            accumulate,
            lhs.as_ptr(),
            lhs_cs as isize,
            lhs_rs as isize,
            rhs.as_ptr(),
            rhs_cs as isize,
            rhs_rs as isize,
            1.0,
            1.0,
            false,
            false,
            false,
            parallelism,
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::check::pattern;

    /// The textbook triple loop, for `dst[m×n] = lhs[m×k] · rhs[k×n]` row-major.
    fn naive([m, n, k]: [usize; 3], lhs: &[f32], rhs: &[f32]) -> Vec<f32> {
        let mut out = vec![0.0f32; m * n];
        for r in 0..m {
            for c in 0..n {
                out[r * n + c] = (0..k).map(|i| lhs[r * k + i] * rhs[i * n + c]).sum();
            }
        }
        out
    }

    /// Into a fresh buffer that was never zeroed (filled with NaN first, so a value left
    /// unwritten or read would show), including `k = 0` and a size above
    /// [`PARALLEL_WORK`], on rayon's threads and on the calling thread.
    #[test]
    fn uninit_product_writes_every_value() {
        type Uninit =
            fn([usize; 3], &mut [MaybeUninit<f32>], &[f32], [usize; 2], &[f32], [usize; 2]);
        let products: [(&str, Uninit); 2] = [
            ("matmul_uninit (parallel)", matmul_uninit::<true>),
            ("matmul_uninit (serial)", matmul_uninit::<false>),
        ];
        for (name, product) in products {
            for mnk in [[3, 5, 4], [1, 1, 1], [4, 3, 0], [67, 45, 33]] {
                let [m, n, k] = mnk;
                let lhs: Vec<f32> = pattern(m * k, 7, 13, 4.0);
                let rhs: Vec<f32> = pattern(k * n, 5, 11, 3.0);
                let mut dst: Vec<f32> = Vec::with_capacity(m * n);
                dst.spare_capacity_mut()
                    .iter_mut()
                    .for_each(|v| _ = v.write(f32::NAN));
                product(
                    mnk,
                    &mut dst.spare_capacity_mut()[..m * n],
                    &lhs,
                    [k, 1],
                    &rhs,
                    [n, 1],
                );
                // SAFETY: the product wrote all `m·n` values.
                unsafe { dst.set_len(m * n) };
                let want = naive(mnk, &lhs, &rhs);
                for (a, b) in dst.iter().zip(&want) {
                    assert!(
                        (a - b).abs() <= 1e-4 * b.abs().max(1.0),
                        "{name} {mnk:?}: {a} vs {b}"
                    );
                }
            }
        }
    }

    /// Against the triple loop, summed over three blocks of `k` (with strides wider than
    /// the blocks, as the convolutions' row blocks have), including an empty sum, in both
    /// layouts.
    #[test]
    fn gradient_sum_matches_naive() {
        for [m, n, k] in [
            [3, 5, 12],
            [1, 1, 3],
            [4, 0, 6],
            [0, 4, 6],
            [67, 45, 99],
            [5, 70, 30],
            [67, 80, 40],
        ] {
            let lhs: Vec<f32> = pattern(m * k, 7, 13, 4.0);
            let rhs: Vec<f32> = pattern(n * k, 5, 11, 3.0);
            // Both layouts where n allows: the k_total given picks one.
            for k_total in [k, COLUMN_MAJOR_MIN_K] {
                let mut sum = GradientSum::new(m, n, k_total);
                for (k0, k1) in [(0, k / 3), (k / 3, k / 2), (k / 2, k)] {
                    sum.add(
                        k1 - k0,
                        &lhs[k0.min(lhs.len())..],
                        k,
                        &rhs[k0.min(rhs.len())..],
                        k,
                    );
                }
                // rhs [n×k] read as [k×n] with strides [1, k] is rhsᵀ.
                let rhs_t: Vec<f32> = (0..k * n).map(|i| rhs[(i % n) * k + i / n]).collect();
                let want = naive([m, n, k], &lhs, &rhs_t);
                let got = sum.into_row_major();
                assert_eq!(got.len(), m * n);
                for (a, b) in got.iter().zip(&want) {
                    assert!(
                        (a - b).abs() <= 1e-4 * b.abs().max(1.0),
                        "{m}x{n}x{k} ({k_total}): {a} vs {b}"
                    );
                }
            }
        }
    }
}
