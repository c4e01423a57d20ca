//! The reference splat: dense, plain burn tensor ops, differentiable by burn's autodiff, on
//! any backend. Every pixel composites every visible Gaussian in depth order, as the
//! fixtures' own reference does. It is the oracle the tile renderers are tested against;
//! memory grows as pixels x Gaussians, so keep it to small scenes.
//!
//! Discrete decisions (culling, the depth order, the skip and early-stop masks) are taken
//! without gradient, exactly as the tile renderers take them; everything continuous goes
//! through tensor ops so autodiff sees the same function.

use burn::tensor::{Bool, Device, Int, Tensor, TensorData};

use crate::splat::backend::SplatParams;
use crate::splat::constants::{ALPHA_MAX, ALPHA_MIN, LOW_PASS, NEAR_PLANE, TRANSMITTANCE_MIN};
use crate::splat::cpu::ProjCamera;

/// Pixels composited per chunk (bounds the size of the dense [pixels, Gaussians] tensors).
const PIXEL_CHUNK: usize = 4096;

/// Screen-space quantities of a set of Gaussians, each [K].
struct Projected {
    u: Tensor<1>,
    v: Tensor<1>,
    a: Tensor<1>,
    b: Tensor<1>,
    c: Tensor<1>,
    z: Tensor<1>,
    det: Tensor<1>,
}

fn col(t: &Tensor<2>, i: usize) -> Tensor<1> {
    t.clone().narrow(1, i, 1).squeeze_dim::<1>(1)
}

fn mat(rows: [[f32; 3]; 3], device: &Device) -> Tensor<2> {
    Tensor::from_data(TensorData::new(rows.concat(), [3, 3]), device)
}

/// Projects [K] Gaussians with tensor ops (the formulas of the fixtures' README).
fn project(means: Tensor<2>, cov6: Tensor<2>, cam: &ProjCamera) -> Projected {
    let device = means.device();
    let k = means.dims()[0];
    let r = mat(cam.r, &device);
    let t0 = Tensor::<2>::from_data(TensorData::new(cam.t.to_vec(), [1, 3]), &device);
    let t = means.matmul(r.clone().transpose()) + t0;
    let (x, y, z) = (col(&t, 0), col(&t, 1), col(&t, 2));
    let tx = (x.clone() / z.clone()).clamp(-cam.lim_x_neg, cam.lim_x_pos) * z.clone();
    let ty = (y.clone() / z.clone()).clamp(-cam.lim_y_neg, cam.lim_y_pos) * z.clone();
    let z2 = z.clone() * z.clone();
    // Sigma as [K, 3, 3].
    let idx = [0, 1, 2, 1, 3, 4, 2, 4, 5];
    let cols: Vec<Tensor<2>> = idx.iter().map(|&i| cov6.clone().narrow(1, i, 1)).collect();
    let sigma = Tensor::cat(cols, 1).reshape([k, 3, 3]);
    let r3 = r.clone().unsqueeze_dim::<3>(0);
    let rt3 = r.transpose().unsqueeze_dim::<3>(0);
    let m = r3.matmul(sigma).matmul(rt3);
    // J as [K, 2, 3].
    let zero = z.zeros_like();
    let j = Tensor::stack::<2>(
        vec![
            z.clone().recip() * cam.fx,
            zero.clone(),
            -(tx * cam.fx) / z2.clone(),
            zero,
            z.clone().recip() * cam.fy,
            -(ty * cam.fy) / z2,
        ],
        1,
    )
    .reshape([k, 2, 3]);
    let s2 = j
        .clone()
        .matmul(m)
        .matmul(j.swap_dims(1, 2))
        .reshape([k, 4]);
    let sxx = col(&s2, 0) + LOW_PASS;
    let sxy = col(&s2, 1);
    let syy = col(&s2, 3) + LOW_PASS;
    let det = sxx.clone() * syy.clone() - sxy.clone() * sxy.clone();
    Projected {
        u: x / z.clone() * cam.fx + cam.cx,
        v: y / z.clone() * cam.fy + cam.cy,
        a: syy / det.clone(),
        b: -sxy / det.clone(),
        c: sxx / det.clone(),
        z,
        det,
    }
}

/// Indices of the visible Gaussians sorted by (depth, index), decided on the host.
fn visible_order(
    means: &Tensor<2>,
    cov6: &Tensor<2>,
    colors: &Tensor<2>,
    opacities: &Tensor<1>,
    cam: &ProjCamera,
) -> Vec<i64> {
    let host = |t: Tensor<2>| t.into_data().iter::<f32>().collect::<Vec<f32>>();
    let m = host(means.clone().detach());
    let cv = host(cov6.clone().detach());
    let cl = host(colors.clone().detach());
    let op: Vec<f32> = opacities
        .clone()
        .detach()
        .into_data()
        .iter::<f32>()
        .collect();
    let n = op.len();
    let finite: Vec<bool> = (0..n)
        .map(|i| {
            m[3 * i..3 * i + 3]
                .iter()
                .chain(&cv[6 * i..6 * i + 6])
                .chain(&cl[3 * i..3 * i + 3])
                .all(|v| v.is_finite())
                && op[i].is_finite()
                && op[i] >= ALPHA_MIN
        })
        .collect();
    // Project only finite ones (non-finite values would poison nothing here, but skip them).
    let keep: Vec<i64> = (0..n as i64).filter(|&i| finite[i as usize]).collect();
    if keep.is_empty() {
        return keep;
    }
    let device = means.device();
    let sel = Tensor::<1, Int>::from_data(TensorData::new(keep.clone(), [keep.len()]), &device);
    let p = project(
        means.clone().detach().select(0, sel.clone()),
        cov6.clone().detach().select(0, sel),
        cam,
    );
    let z: Vec<f32> = p.z.into_data().iter::<f32>().collect();
    let det: Vec<f32> = p.det.into_data().iter::<f32>().collect();
    let mut order: Vec<(f32, i64)> = keep
        .iter()
        .enumerate()
        .filter(|&(j, _)| z[j] > NEAR_PLANE && det[j] > 0.0 && det[j].is_finite())
        .map(|(j, &i)| (z[j], i))
        .collect();
    order.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    order.into_iter().map(|(_, i)| i).collect()
}

/// Renders with dense tensor ops. Returns [H, W, 4]: RGB and final transmittance.
///
/// # Shapes
/// - `means`: [N, 3], `cov6`: [N, 6], `colors`: [N, 3], `opacities`: `[N]`
pub fn render(
    means: Tensor<2>,
    cov6: Tensor<2>,
    colors: Tensor<2>,
    opacities: Tensor<1>,
    params: &SplatParams,
) -> Tensor<3> {
    render_tapped(means, cov6, colors, opacities, None, params)
}

/// [`render`] with the projected centres moved by `screen` (`[N, 2]`, in normalised device
/// coordinates: `u += x W / 2`, `v += y H / 2`, 3DGS's `ndc2Pix`). At `screen = 0` the image
/// is [`render`]'s and the gradient w.r.t. `screen` is the one the fused renderers' tap
/// reports ([`crate::splat::SplatInputs`]): the oracle of that tap.
pub fn render_tapped(
    means: Tensor<2>,
    cov6: Tensor<2>,
    colors: Tensor<2>,
    opacities: Tensor<1>,
    screen: Option<Tensor<2>>,
    params: &SplatParams,
) -> Tensor<3> {
    let device = means.device();
    let cam = ProjCamera::new(&params.camera);
    let (w, h) = (cam.width as usize, cam.height as usize);
    let bg = Tensor::<2>::from_data(TensorData::new(params.background.to_vec(), [1, 3]), &device);
    let order = visible_order(&means, &cov6, &colors, &opacities, &cam);
    if order.is_empty() {
        let rgb = bg.expand([h * w, 3]);
        let t = Tensor::<2>::ones([h * w, 1], &device);
        let out = Tensor::cat(vec![rgb, t], 1);
        if means.dims()[0] == 0 {
            return out.reshape([h, w, 4]);
        }
        // Nothing visible: a constant image. A zero multiple of the (finite-masked) means keeps
        // the output in the autodiff graph, so `backward` works as for any other scene.
        let finite = means.clone().is_finite();
        let zero = (means.mask_fill(finite.bool_not(), 0.0).sum() * 0.0).unsqueeze::<2>();
        return (out + zero).reshape([h, w, 4]);
    }
    let k = order.len();
    let sel = Tensor::<1, Int>::from_data(TensorData::new(order, [k]), &device);
    let p = project(
        means.select(0, sel.clone()),
        cov6.select(0, sel.clone()),
        &cam,
    );
    let (mut pu, mut pv) = (p.u, p.v);
    if let Some(screen) = screen {
        let s = screen.select(0, sel.clone());
        pu = pu + col(&s, 0) * (0.5 * w as f32);
        pv = pv + col(&s, 1) * (0.5 * h as f32);
    }
    let colors = colors.select(0, sel.clone());
    let opac = opacities.select(0, sel).unsqueeze_dim::<2>(0);
    let (u, v) = (pu.unsqueeze_dim::<2>(0), pv.unsqueeze_dim::<2>(0));
    let (a, b, c) = (
        p.a.unsqueeze_dim::<2>(0),
        p.b.unsqueeze_dim::<2>(0),
        p.c.unsqueeze_dim::<2>(0),
    );

    let mut chunks = Vec::new();
    let total = w * h;
    let mut start = 0;
    while start < total {
        let end = (start + PIXEL_CHUNK).min(total);
        let px: Vec<f32> = (start..end).map(|i| (i % w) as f32 + 0.5).collect();
        let py: Vec<f32> = (start..end).map(|i| (i / w) as f32 + 0.5).collect();
        let np = end - start;
        let px = Tensor::<2>::from_data(TensorData::new(px, [np, 1]), &device);
        let py = Tensor::<2>::from_data(TensorData::new(py, [np, 1]), &device);
        let dx = px - u.clone();
        let dy = py - v.clone();
        let sigma = (a.clone() * dx.clone() * dx.clone() + c.clone() * dy.clone() * dy.clone())
            * 0.5
            + b.clone() * dx * dy;
        let raw = opac.clone() * (-sigma.clone()).exp();
        let alpha = raw.clone().clamp_max(ALPHA_MAX);
        // Skip mask: sigma < 0 or alpha < 1/255 (no gradient through the decision).
        let skip: Tensor<2, Bool> = sigma
            .detach()
            .lower_elem(0.0)
            .bool_or(alpha.clone().detach().lower_elem(ALPHA_MIN));
        let alpha = alpha.mask_fill(skip, 0.0);
        // Early stop: a pixel stops at the first Gaussian that would take T below 1e-4;
        // T is non-increasing, so "not stopped" is exactly "T after this one >= 1e-4".
        let log1m = (-alpha.clone().detach()).log1p();
        let t_after = log1m.cumsum(1).exp();
        let stopped = t_after.lower_elem(TRANSMITTANCE_MIN);
        let alpha = alpha.mask_fill(stopped, 0.0);
        let log1m = (-alpha.clone()).log1p();
        let cum = log1m.clone().cumsum(1);
        let t_before = (cum.clone() - log1m).exp();
        let t_final = cum.narrow(1, k - 1, 1).exp();
        let weights = alpha * t_before;
        let rgb = weights.matmul(colors.clone()) + t_final.clone() * bg.clone();
        chunks.push(Tensor::cat(vec![rgb, t_final], 1));
        start = end;
    }
    Tensor::cat(chunks, 0).reshape([h, w, 4])
}
