//! The reference lifting in plain burn tensor ops: any backend, differentiated by burn's
//! autodiff. It is the oracle the fused implementations are tested against.

use burn::tensor::activation::sigmoid;
use burn::tensor::{Device, Int, Tensor, TensorData};

use crate::kernels::lift::constants::*;
use crate::lift::{LiftMode, LiftParams};
use crate::texel::FrameKind;

fn ints(v: Vec<i32>, device: &Device) -> Tensor<1, Int> {
    let n = v.len();
    Tensor::from_data(TensorData::new(v, [n]), device)
}

fn floats<const D: usize>(v: Vec<f32>, shape: [usize; D], device: &Device) -> Tensor<D> {
    Tensor::from_data(TensorData::new(v, shape), device)
}

fn col(t: &Tensor<2>, i: usize) -> Tensor<2> {
    t.clone().narrow(1, i, 1)
}

/// `sqrt(sum x^2 + eps^2)` over dim 1, kept as [K, 1].
fn safe_norm(x: &Tensor<2>) -> Tensor<2> {
    (x.clone().powi_scalar(2).sum_dim(1) + NORM_EPS * NORM_EPS).sqrt()
}

fn cross(a: &Tensor<2>, b: &Tensor<2>) -> Tensor<2> {
    let (a0, a1, a2) = (col(a, 0), col(a, 1), col(a, 2));
    let (b0, b1, b2) = (col(b, 0), col(b, 1), col(b, 2));
    Tensor::cat(
        vec![
            a1.clone() * b2.clone() - a2.clone() * b1.clone(),
            a2 * b0.clone() - a0.clone() * b2,
            a0 * b1 - a1 * b0,
        ],
        1,
    )
}

/// Rows `idx` of `t`.
fn rows(t: &Tensor<2>, idx: &[u32], device: &Device) -> Tensor<2> {
    t.clone()
        .select(0, ints(idx.iter().map(|&i| i as i32).collect(), device))
}

/// Matrices [K, 3, 3] with the given columns (each [K, 3]).
fn from_cols(c0: Tensor<2>, c1: Tensor<2>, c2: Tensor<2>) -> Tensor<3> {
    Tensor::stack(vec![c0, c1, c2], 2)
}

/// Per-face frames [F, 3, 3] of the posed vertices [V, 3].
pub fn face_frames(kind: FrameKind, faces: &[[u32; 3]], vertices: &Tensor<2>) -> Tensor<3> {
    let device = vertices.device();
    let corner = |k: usize| {
        let idx: Vec<u32> = faces.iter().map(|f| f[k]).collect();
        rows(vertices, &idx, &device)
    };
    let (v0, v1, v2) = (corner(0), corner(1), corner(2));
    let e1 = v1 - v0.clone();
    let e2 = v2 - v0;
    match kind {
        FrameKind::Jacobian => {
            let n = cross(&e1, &e2);
            let m = safe_norm(&n);
            from_cols(e1, e2, n / m.sqrt())
        }
        FrameKind::ScaledRotation => {
            let a0 = e1.clone() / safe_norm(&e1);
            let c = cross(&a0, &e2);
            let a1 = c.clone() / safe_norm(&c);
            let d = cross(&a1, &a0);
            let a2 = -(d.clone() / safe_norm(&d));
            let k = (safe_norm(&e1) + (a2.clone() * e2).sum_dim(1).abs()) * 0.5;
            from_cols(a0 * k.clone(), a1 * k.clone(), a2 * k)
        }
    }
}

/// Lifts local attributes [K, 14] with frames [K, 3, 3] and anchors [K, 3]: returns the
/// packed [K, 13] with the opacity channel still a logit. With the frames `k R` of
/// [`FrameKind::ScaledRotation`] and the triangles' centroids as anchors this is
/// GaussianAvatars' binding ([`crate::models::gaussianavatars::model`] uses it so).
pub fn lift_rows(local: Tensor<2>, frames: Tensor<3>, anchors: Tensor<2>) -> Tensor<2> {
    let k = local.dims()[0];
    let mean_l = local.clone().narrow(1, LOCAL_MEAN, 3);
    let q = local.clone().narrow(1, LOCAL_QUAT, 4);
    let log_s = local.clone().narrow(1, LOCAL_LOG_SCALE, 3);
    let opacity = local.clone().narrow(1, LOCAL_OPACITY, 1);
    let rgb = local.narrow(1, LOCAL_RGB, 3);

    let q = q.clone() / safe_norm(&q);
    let (w, x, y, z) = (col(&q, 0), col(&q, 1), col(&q, 2), col(&q, 3));
    let one = w.ones_like();
    let two = |a: Tensor<2>| a * 2.0;
    let r = Tensor::cat(
        vec![
            one.clone() - two(y.clone() * y.clone() + z.clone() * z.clone()),
            two(x.clone() * y.clone() - w.clone() * z.clone()),
            two(x.clone() * z.clone() + w.clone() * y.clone()),
            two(x.clone() * y.clone() + w.clone() * z.clone()),
            one.clone() - two(x.clone() * x.clone() + z.clone() * z.clone()),
            two(y.clone() * z.clone() - w.clone() * x.clone()),
            two(x.clone() * z.clone() - w.clone() * y.clone()),
            two(y.clone() * z.clone() + w * x.clone()),
            one - two(x.clone() * x + y.clone() * y),
        ],
        1,
    )
    .reshape([k, 3, 3]);
    // A = J R diag(exp(s)); Sigma = A A^T.
    let a = frames.clone().matmul(r) * log_s.exp().unsqueeze_dim::<3>(1);
    let sigma = a.clone().matmul(a.swap_dims(1, 2)).reshape([k, 9]);
    let cov6 = Tensor::cat(
        [0, 1, 2, 4, 5, 8].iter().map(|&i| col(&sigma, i)).collect(),
        1,
    );
    let mean = frames.matmul(mean_l.unsqueeze_dim::<3>(2)).reshape([k, 3]) + anchors;
    Tensor::cat(vec![mean, cov6, rgb, opacity], 1)
}

/// The lift in tensor ops: local maps [14, R, R], vertices [V, 3] → packed [N, 13].
pub fn lift(local: Tensor<3>, vertices: Tensor<2>, params: &LiftParams) -> Tensor<2> {
    let device = vertices.device();
    let topo = &params.topology;
    let r = topo.res();
    let rr = r * r;
    let s = &topo.samples;
    let n = s.len();
    let frames = face_frames(params.frame, &topo.faces, &vertices);
    // [R*R, 14], texel-major.
    let local_t = local.reshape([LOCAL_CHANNELS, rr]).transpose();
    let taps: Vec<u32> = s.taps.iter().flatten().copied().collect();
    let weights = floats(s.weights.concat(), [n, 4, 1], &device);
    let blend = |t: Tensor<2>| -> Tensor<2> {
        let c = t.dims()[1];
        (rows(&t, &taps, &device).reshape([n, 4, c]) * weights.clone())
            .sum_dim(1)
            .reshape([n, c])
    };
    // Barycentric interpolation of vertices: sum_k b_k v[idx_k].
    let anchors = |idx: &[[u32; 3]], bary: &[[f32; 3]]| -> Tensor<2> {
        let m = idx.len();
        let b = floats(bary.concat(), [m, 3], &device);
        (0..3)
            .map(|k| {
                let i: Vec<u32> = idx.iter().map(|v| v[k]).collect();
                rows(&vertices, &i, &device) * col(&b, k)
            })
            .reduce(|a, b| a + b)
            .unwrap_or_else(|| Tensor::zeros([m, 3], &device))
    };
    let packed = match params.mode {
        LiftMode::Global => {
            let layout = &topo.layout;
            let face_of: Vec<u32> = layout.face.iter().map(|f| f.unwrap_or(0)).collect();
            let valid = floats(layout.validity(), [rr, 1, 1], &device);
            let identity = floats(
                vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                [1, 3, 3],
                &device,
            );
            let tex_frames = frames
                .reshape([topo.faces.len(), 9])
                .select(
                    0,
                    ints(face_of.iter().map(|&f| f as i32).collect(), &device),
                )
                .reshape([rr, 3, 3]);
            let tex_frames = tex_frames * valid.clone() + identity * (valid.ones_like() - valid);
            // Invalid texels have zero barycentrics, so their anchor is the origin.
            let tex_anchor = anchors(&layout.verts, &layout.bary);
            let payload = lift_rows(local_t, tex_frames, tex_anchor);
            blend(payload)
        }
        LiftMode::Local => {
            let sampled = blend(local_t);
            let idx: Vec<[u32; 3]> = s.face.iter().map(|&f| topo.faces[f as usize]).collect();
            let sample_frames = frames
                .reshape([topo.faces.len(), 9])
                .select(0, ints(s.face.iter().map(|&f| f as i32).collect(), &device))
                .reshape([n, 3, 3]);
            lift_rows(sampled, sample_frames, anchors(&idx, &s.bary))
        }
    };
    let rest = packed.clone().narrow(1, 0, OUT_OPACITY);
    let opacity = sigmoid(packed.narrow(1, OUT_OPACITY, 1));
    Tensor::cat(vec![rest, opacity], 1)
}
