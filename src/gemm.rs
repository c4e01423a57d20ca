//! Row-major matrix products on the CPU through the `gemm` crate (the one burn-flex itself
//! uses), with explicit strides: the column formulations of the CPU convolutions
//! ([`crate::model::conv_transpose`], [`crate::metrics::vgg_cpu`]) are built on it.

use std::mem::MaybeUninit;

/// Work (multiply-adds) above which a product is split across rayon's threads.
pub const PARALLEL_WORK: usize = 1 << 16;

/// `dst[m×n] (+)= lhs[m×k] · rhs[k×n]` with explicit (row, column) strides, on rayon's
/// threads when the work reaches [`PARALLEL_WORK`].
///
/// # Panics
/// When a stride addresses past the end of its slice.
#[allow(clippy::too_many_arguments)]
pub fn matmul(
    mnk: [usize; 3],
    dst: &mut [f32],
    dst_strides: [usize; 2],
    accumulate: bool,
    lhs: &[f32],
    lhs_strides: [usize; 2],
    rhs: &[f32],
    rhs_strides: [usize; 2],
) {
    product(
        true,
        mnk,
        dst,
        dst_strides,
        accumulate,
        lhs,
        lhs_strides,
        rhs,
        rhs_strides,
    );
}

/// [`matmul`] on the calling thread only: for products that are already one task of a
/// parallel loop.
#[allow(clippy::too_many_arguments)]
pub fn matmul_serial(
    mnk: [usize; 3],
    dst: &mut [f32],
    dst_strides: [usize; 2],
    accumulate: bool,
    lhs: &[f32],
    lhs_strides: [usize; 2],
    rhs: &[f32],
    rhs_strides: [usize; 2],
) {
    product(
        false,
        mnk,
        dst,
        dst_strides,
        accumulate,
        lhs,
        lhs_strides,
        rhs,
        rhs_strides,
    );
}

/// [`matmul`] into a dense row-major `dst` of `m·n` values (strides `[n, 1]`) that need
/// not be initialised: every value is written and none is read. For outputs allocated fresh,
/// where zeroing them first would be one more pass over memory; the caller marks them
/// initialised afterwards (`Vec::set_len`).
///
/// # Panics
/// When `dst` does not have `m·n` values or a stride addresses past the end of its slice.
pub fn matmul_uninit(
    mnk: [usize; 3],
    dst: &mut [MaybeUninit<f32>],
    lhs: &[f32],
    lhs_strides: [usize; 2],
    rhs: &[f32],
    rhs_strides: [usize; 2],
) {
    let [m, n, _] = mnk;
    assert_eq!(dst.len(), m * n, "matmul_uninit: dst is not m x n");
    matmul_into_uninit(mnk, dst, [n, 1], lhs, lhs_strides, rhs, rhs_strides);
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
    // SAFETY: `f32` and `MaybeUninit<f32>` have one layout; `product` writes the `m·n`
    // addressed values (inside `dst`, which it asserts) without reading them when
    // `accumulate` is false.
    let (ptr, len) = (dst.as_mut_ptr().cast::<f32>(), dst.len());
    unsafe {
        product_raw(
            true,
            mnk,
            (ptr, len),
            dst_strides,
            false,
            lhs,
            lhs_strides,
            rhs,
            rhs_strides,
        )
    };
}

#[allow(clippy::too_many_arguments)]
fn product(
    parallel: bool,
    mnk: [usize; 3],
    dst: &mut [f32],
    dst_strides: [usize; 2],
    accumulate: bool,
    lhs: &[f32],
    lhs_strides: [usize; 2],
    rhs: &[f32],
    rhs_strides: [usize; 2],
) {
    // SAFETY: `dst` is an initialised, exclusively borrowed slice of `dst.len()` values.
    unsafe {
        product_raw(
            parallel,
            mnk,
            (dst.as_mut_ptr(), dst.len()),
            dst_strides,
            accumulate,
            lhs,
            lhs_strides,
            rhs,
            rhs_strides,
        )
    }
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
    (dst, dst_len): (*mut f32, usize),
    [dst_rs, dst_cs]: [usize; 2],
    accumulate: bool,
    lhs: &[f32],
    [lhs_rs, lhs_cs]: [usize; 2],
    rhs: &[f32],
    [rhs_rs, rhs_cs]: [usize; 2],
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
    /// [`PARALLEL_WORK`].
    #[test]
    fn uninit_product_writes_every_value() {
        for mnk in [[3, 5, 4], [1, 1, 1], [4, 3, 0], [67, 45, 33]] {
            let [m, n, k] = mnk;
            let lhs: Vec<f32> = (0..m * k)
                .map(|i| ((i * 7 % 13) as f32 - 6.0) / 4.0)
                .collect();
            let rhs: Vec<f32> = (0..k * n)
                .map(|i| ((i * 5 % 11) as f32 - 5.0) / 3.0)
                .collect();
            let mut dst: Vec<f32> = Vec::with_capacity(m * n);
            dst.spare_capacity_mut()
                .iter_mut()
                .for_each(|v| _ = v.write(f32::NAN));
            matmul_uninit(
                mnk,
                &mut dst.spare_capacity_mut()[..m * n],
                &lhs,
                [k, 1],
                &rhs,
                [n, 1],
            );
            // SAFETY: `matmul_uninit` wrote all `m·n` values.
            unsafe { dst.set_len(m * n) };
            let want = naive(mnk, &lhs, &rhs);
            for (a, b) in dst.iter().zip(&want) {
                assert!(
                    (a - b).abs() <= 1e-4 * b.abs().max(1.0),
                    "{mnk:?}: {a} vs {b}"
                );
            }
        }
    }
}
