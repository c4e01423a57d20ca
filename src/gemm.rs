//! Row-major matrix products on the CPU through the `gemm` crate (the one burn-flex itself
//! uses), with explicit strides: the column formulations of the CPU convolutions
//! ([`crate::model::conv_transpose`], [`crate::metrics::vgg_cpu`]) are built on it.

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

#[allow(clippy::too_many_arguments)]
fn product(
    parallel: bool,
    [m, n, k]: [usize; 3],
    dst: &mut [f32],
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
    if k == 0 {
        if !accumulate {
            dst.fill(0.0);
        }
        return;
    }
    let last = |rs: usize, cs: usize, r: usize, c: usize| (r - 1) * rs + (c - 1) * cs;
    assert!(
        last(dst_rs, dst_cs, m, n) < dst.len(),
        "matmul: dst too short"
    );
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
    // `dst` is borrowed mutably and does not alias `lhs` or `rhs`.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.as_mut_ptr(),
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
