//! The plain 2D convolution's passes on host memory (no bias, one group, dilation 1), in the
//! column formulation: the view encoder's and the appearance decoder's 3x3 convolutions
//! ([`crate::conv`] is the op).
//!
//! - forward, per batch item: `col = im2col(X)` ([C_in·k_h·k_w, H_out·W_out]), then
//!   `Y = W · col` ([C_out, H_out·W_out]);
//! - backward: `dW += dY · colᵀ` (the column matrix gathered again rather than kept), and
//!   `dcol = Wᵀ · dY`, scatter-added back to the input planes (`col2im`).
//!
//! This is [`crate::conv_transpose`]'s index map read the other way: a convolution is the
//! adjoint of the transposed convolution with the same kernel, stride and padding, so the
//! gather and scatter are that module's `im2col` and `col2im_plane`, with the convolution's
//! output on the map's input side and its input on the map's output side. The input's size is
//! given rather than derived, so an input row or column that no output reads (when
//! `H + 2·padding - k_h` is not a multiple of the stride) gets a zero gradient.
//!
//! Thread mapping: the products run on rayon through `gemm`; `im2col` is parallel over
//! the rows of `col`; `col2im` over input channels (one task per input plane, so no two tasks
//! write one pixel).

use rayon::prelude::*;

use crate::constants::planes_per_task;
use crate::conv::ConvParams;
use crate::conv_transpose::{Dims, IndexMap, col2im_plane, im2col, with_columns};
use crate::gemm::{GradientSum, matmul, matmul_uninit};

/// The shared index map's sizes for a convolution of `x` by `weight`: the convolution's
/// output takes the map's input side (`ci` = C_out, `h x w` = H_out x W_out), its input the
/// map's output side (`co` = C_in, `ho x wo` = H x W).
pub(crate) fn dims(x: &[usize], weight: &[usize], p: &ConvParams) -> Dims {
    let [n, ci, h, w] = [x[0], x[1], x[2], x[3]];
    let [co, kh, kw] = [weight[0], weight[2], weight[3]];
    let [ho, wo] = p.output_size([h, w], [kh, kw]).unwrap_or([0, 0]);
    Dims {
        n,
        ci: co,
        co: ci,
        h: ho,
        w: wo,
        kh,
        kw,
        ho: h,
        wo: w,
    }
}

/// Forward on host memory: `x` [N, C_in, H, W], `weight` [C_out, C_in·k_h·k_w] → [N, C_out,
/// H_out, W_out] (in the map's names: C_out = `d.ci`, C_in = `d.co`, the output plane
/// `d.p()`, the input plane `d.ho · d.wo`), then `epilogue(c, plane)` on every output plane of channel `c` of a
/// batch item right after that item's product wrote it (parallel over the planes), while
/// the item's output is still warm in cache.
///
/// The epilogue is an `Option`, unlike `conv_transpose::host_forward_then`'s closure: here
/// it is a parallel pass of its own after the product, which `None` skips, while the
/// transposed convolution runs its epilogue inside the task that builds each plane, where an
/// empty closure costs nothing.
pub(crate) fn host_forward_then(
    x: &[f32],
    weight: &[f32],
    d: Dims,
    p: &IndexMap,
    epilogue: Option<impl Fn(usize, &mut [f32]) + Sync>,
) -> Vec<f32> {
    let (pp, q, plane) = (d.p(), d.q(), d.ho * d.wo);
    let mut out = Vec::with_capacity(d.n * d.ci * pp);
    with_columns(q * pp, |col| {
        for b in 0..d.n {
            im2col(&x[b * d.co * plane..(b + 1) * d.co * plane], col, d, p);
            // Y [C_out, P] = W [C_out, q] · col [q, P]
            let ob = &mut out.spare_capacity_mut()[b * d.ci * pp..(b + 1) * d.ci * pp];
            matmul_uninit::<true>([d.ci, pp, q], ob, weight, [q, 1], col, [pp, 1]);
            if let (Some(f), true) = (&epilogue, pp > 0) {
                // SAFETY: `matmul_uninit` just wrote all `C_out·P` values of `ob`, and
                // `MaybeUninit<f32>` has `f32`'s layout.
                let ob = unsafe { &mut *(ob as *mut [std::mem::MaybeUninit<f32>] as *mut [f32]) };
                ob.par_chunks_mut(pp)
                    .enumerate()
                    .with_min_len(planes_per_task(pp))
                    .for_each(|(c, o)| f(c, o));
            }
        }
    });
    // SAFETY: `matmul_uninit` wrote the `C_out·P` values of every batch item.
    unsafe { out.set_len(d.n * d.ci * pp) };
    out
}

/// Backward on host memory → (dx [N, C_in, H, W], dweight [C_out, C_in, k_h, k_w]).
pub(crate) fn host_backward(
    x: &[f32],
    weight: &[f32],
    g: &[f32],
    d: Dims,
    p: &IndexMap,
) -> (Vec<f32>, Vec<f32>) {
    let (pp, q, plane) = (d.p(), d.q(), d.ho * d.wo);
    let mut dx = vec![0.0f32; d.n * d.co * plane];
    let mut dw = GradientSum::new(d.ci, q, d.n * d.p());
    with_columns(q * pp, |col| {
        for b in 0..d.n {
            let gb = &g[b * d.ci * pp..(b + 1) * d.ci * pp];
            im2col(&x[b * d.co * plane..(b + 1) * d.co * plane], col, d, p);
            // dW [C_out, q] += dY [C_out, P] · colᵀ [P, q]
            dw.add(pp, gb, pp, col, pp);
            // dcol [q, P] = Wᵀ [q, C_out] · dY [C_out, P], into the column buffer (read
            // above).
            matmul::<true>(
                [q, pp, d.ci],
                col,
                [pp, 1],
                false,
                weight,
                [1, q],
                gb,
                [pp, 1],
            );
            dx[b * d.co * plane..(b + 1) * d.co * plane]
                .par_chunks_mut(plane)
                .enumerate()
                .with_min_len(planes_per_task(plane))
                .for_each(|(c, o)| col2im_plane(col, o, c, d, p));
        }
    });
    (dx, dw.into_row_major())
}
