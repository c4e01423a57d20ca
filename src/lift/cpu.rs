//! The fused CPU lifting: forward and handwritten backward on host memory (rayon).
//!
//! Global mode: per face frames → per texel lift into the 13-channel payload (parallel over
//! texels) → per sample bilinear blend (parallel over samples). Backward mirrors it: per
//! sample gradients scattered onto the taps' texels, per texel backward of the lift, then the
//! frames' and anchors' gradients gathered per face and vertex. Local mode samples the 14
//! local channels first and lifts per sample.
//!
//! Texels that no sample reads ([`Topology::tapped`]) are skipped both ways.
//!
//! Scatters onto texels and vertices run serially in a fixed order, so results are
//! deterministic.

use rayon::prelude::*;

use crate::kernels::lift::constants::*;
use crate::lift::transform::{LiftGrads, LocalGeom, lift, lift_backward};
use crate::lift::{LiftMode, Topology};
use crate::texel::FrameKind;
use crate::texel::frames::{IDENTITY, Mat3, Vec3, face_frame, face_frame_backward, interpolate};

fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// The 14 local channels of texel `t` from channel-major maps `[14, R*R]`.
fn texel_local(local: &[f32], rr: usize, t: usize) -> [f32; LOCAL_CHANNELS] {
    std::array::from_fn(|c| local[c * rr + t])
}

fn geom(l: &[f32; LOCAL_CHANNELS]) -> LocalGeom {
    LocalGeom {
        mean: [l[LOCAL_MEAN], l[LOCAL_MEAN + 1], l[LOCAL_MEAN + 2]],
        quat: [
            l[LOCAL_QUAT],
            l[LOCAL_QUAT + 1],
            l[LOCAL_QUAT + 2],
            l[LOCAL_QUAT + 3],
        ],
        log_scale: [
            l[LOCAL_LOG_SCALE],
            l[LOCAL_LOG_SCALE + 1],
            l[LOCAL_LOG_SCALE + 2],
        ],
    }
}

fn vertices3(vertices: &[f32]) -> Vec<Vec3> {
    vertices
        .chunks_exact(3)
        .map(|v| [v[0], v[1], v[2]])
        .collect()
}

fn frames(topo: &Topology, kind: FrameKind, verts: &[Vec3]) -> Vec<Mat3> {
    topo.faces
        .par_iter()
        .map(|f| face_frame(kind, f.map(|i| verts[i as usize])))
        .collect()
}

/// Frame and anchor of texel `t` (identity and origin where no face covers it).
fn texel_frame(topo: &Topology, frames: &[Mat3], verts: &[Vec3], t: usize) -> (Mat3, Vec3) {
    let l = &topo.layout;
    match l.face[t] {
        Some(f) => (
            frames[f as usize],
            interpolate(&l.verts[t], &l.bary[t], verts),
        ),
        None => (IDENTITY, [0.0; 3]),
    }
}

/// Frame and anchor of kept sample `n` (local mode).
fn sample_frame(topo: &Topology, frames: &[Mat3], verts: &[Vec3], n: usize) -> (Mat3, Vec3) {
    let s = &topo.samples;
    let f = s.face[n] as usize;
    (frames[f], interpolate(&topo.faces[f], &s.bary[n], verts))
}

/// Bilinear blend of the 14 local channels at sample `n`.
fn sampled_local(topo: &Topology, local: &[f32], n: usize) -> [f32; LOCAL_CHANNELS] {
    let rr = topo.res() * topo.res();
    let s = &topo.samples;
    let mut l = [0.0f32; LOCAL_CHANNELS];
    for q in 0..4 {
        let w = s.weights[n][q];
        if w == 0.0 {
            continue;
        }
        let t = s.taps[n][q] as usize;
        for (c, v) in l.iter_mut().enumerate() {
            *v += w * local[c * rr + t];
        }
    }
    l
}

/// Packs a lifted Gaussian: mean, cov, rgb, and the opacity channel as given.
fn pack(mean: Vec3, cov: [f32; 6], l: &[f32; LOCAL_CHANNELS], opacity: f32) -> [f32; OUT_CHANNELS] {
    let mut o = [0.0f32; OUT_CHANNELS];
    o[OUT_MEAN..OUT_MEAN + 3].copy_from_slice(&mean);
    o[OUT_COV..OUT_COV + 6].copy_from_slice(&cov);
    o[OUT_RGB..OUT_RGB + 3].copy_from_slice(&l[LOCAL_RGB..LOCAL_RGB + 3]);
    o[OUT_OPACITY] = opacity;
    o
}

/// Per-texel payload of global mode (opacity channel still a logit); zero at texels no
/// sample reads ([`Topology::tapped`]).
fn payload(
    topo: &Topology,
    local: &[f32],
    frames: &[Mat3],
    verts: &[Vec3],
) -> Vec<[f32; OUT_CHANNELS]> {
    let rr = topo.res() * topo.res();
    let tapped = topo.tapped();
    (0..rr)
        .into_par_iter()
        .with_min_len(256)
        .map(|t| {
            if !tapped[t] {
                return [0.0; OUT_CHANNELS];
            }
            let l = texel_local(local, rr, t);
            let (j, p) = texel_frame(topo, frames, verts, t);
            let (mean, cov) = lift(&j, p, &geom(&l));
            pack(mean, cov, &l, l[LOCAL_OPACITY])
        })
        .collect()
}

/// Forward: local maps `[14, R, R]` (channel-major), vertices `[V, 3]` → packed `[N, 13]`.
pub fn forward(
    topo: &Topology,
    mode: LiftMode,
    kind: FrameKind,
    local: &[f32],
    vertices: &[f32],
) -> Vec<f32> {
    let verts = vertices3(vertices);
    let frames = frames(topo, kind, &verts);
    let s = &topo.samples;
    let n = s.len();
    let mut out = vec![0.0f32; n * OUT_CHANNELS];
    match mode {
        LiftMode::Global => {
            let pay = payload(topo, local, &frames, &verts);
            out.par_chunks_mut(OUT_CHANNELS)
                .enumerate()
                .with_min_len(256)
                .for_each(|(k, o)| {
                    for q in 0..4 {
                        let w = s.weights[k][q];
                        if w == 0.0 {
                            continue;
                        }
                        for (o, p) in o.iter_mut().zip(&pay[s.taps[k][q] as usize]) {
                            *o += w * p;
                        }
                    }
                    o[OUT_OPACITY] = sigmoid(o[OUT_OPACITY]);
                });
        }
        LiftMode::Local => {
            out.par_chunks_mut(OUT_CHANNELS)
                .enumerate()
                .with_min_len(256)
                .for_each(|(k, o)| {
                    let l = sampled_local(topo, local, k);
                    let (j, p) = sample_frame(topo, &frames, &verts, k);
                    let (mean, cov) = lift(&j, p, &geom(&l));
                    o.copy_from_slice(&pack(mean, cov, &l, sigmoid(l[LOCAL_OPACITY])));
                });
        }
    }
    out
}

/// Gradients of the 14 local channels from a lift's gradients and the payload gradient.
fn local_grads(
    g: &LiftGrads,
    d: &[f32; OUT_CHANNELS],
    d_opacity_logit: f32,
) -> [f32; LOCAL_CHANNELS] {
    let mut l = [0.0f32; LOCAL_CHANNELS];
    l[LOCAL_MEAN..LOCAL_MEAN + 3].copy_from_slice(&g.local.mean);
    l[LOCAL_QUAT..LOCAL_QUAT + 4].copy_from_slice(&g.local.quat);
    l[LOCAL_LOG_SCALE..LOCAL_LOG_SCALE + 3].copy_from_slice(&g.local.log_scale);
    l[LOCAL_OPACITY] = d_opacity_logit;
    l[LOCAL_RGB..LOCAL_RGB + 3].copy_from_slice(&d[OUT_RGB..OUT_RGB + 3]);
    l
}

fn split_out_grad(d: &[f32; OUT_CHANNELS]) -> (Vec3, [f32; 6]) {
    (
        [d[OUT_MEAN], d[OUT_MEAN + 1], d[OUT_MEAN + 2]],
        std::array::from_fn(|k| d[OUT_COV + k]),
    )
}

/// Backward: `dout` `[N, 13]` → (dL/d local `[14, R, R]`, dL/d vertices `[V, 3]`).
pub fn backward(
    topo: &Topology,
    mode: LiftMode,
    kind: FrameKind,
    local: &[f32],
    vertices: &[f32],
    dout: &[f32],
) -> (Vec<f32>, Vec<f32>) {
    let verts = vertices3(vertices);
    let frames = frames(topo, kind, &verts);
    let rr = topo.res() * topo.res();
    let s = &topo.samples;
    let n = s.len();
    let mut dlocal = vec![0.0f32; LOCAL_CHANNELS * rr];
    let mut dframes = vec![[[0.0f32; 3]; 3]; topo.faces.len()];
    let mut dverts = vec![[0.0f32; 3]; verts.len()];
    let dout_at =
        |k: usize| -> [f32; OUT_CHANNELS] { std::array::from_fn(|c| dout[k * OUT_CHANNELS + c]) };
    let add_anchor = |dverts: &mut [Vec3], vs: &[u32; 3], b: &[f32; 3], d: Vec3| {
        for k in 0..3 {
            let v = &mut dverts[vs[k] as usize];
            for c in 0..3 {
                v[c] += b[k] * d[c];
            }
        }
    };
    let add_frame = |m: &mut Mat3, d: &Mat3| {
        for r in 0..3 {
            for c in 0..3 {
                m[r][c] += d[r][c];
            }
        }
    };
    match mode {
        LiftMode::Global => {
            // Sampled opacity logits, for the sigmoid's derivative.
            let pay = payload(topo, local, &frames, &verts);
            let mut dpay = vec![[0.0f32; OUT_CHANNELS]; rr];
            for k in 0..n {
                let mut d = dout_at(k);
                let logit: f32 = (0..4)
                    .map(|q| s.weights[k][q] * pay[s.taps[k][q] as usize][OUT_OPACITY])
                    .sum();
                let o = sigmoid(logit);
                d[OUT_OPACITY] *= o * (1.0 - o);
                for q in 0..4 {
                    let w = s.weights[k][q];
                    if w == 0.0 {
                        continue;
                    }
                    for (p, d) in dpay[s.taps[k][q] as usize].iter_mut().zip(&d) {
                        *p += w * d;
                    }
                }
            }
            let tapped = topo.tapped();
            let per_texel: Vec<(LiftGrads, [f32; LOCAL_CHANNELS])> = (0..rr)
                .into_par_iter()
                .with_min_len(256)
                .map(|t| {
                    // No sample reads the texel: its payload gradient is zero.
                    if !tapped[t] {
                        return Default::default();
                    }
                    let d = &dpay[t];
                    let l = texel_local(local, rr, t);
                    let (j, _) = texel_frame(topo, &frames, &verts, t);
                    let (dmean, dcov) = split_out_grad(d);
                    let g = lift_backward(&j, &geom(&l), dmean, &dcov);
                    let gl = local_grads(&g, d, d[OUT_OPACITY]);
                    (g, gl)
                })
                .collect();
            let layout = &topo.layout;
            for (t, (g, gl)) in per_texel.iter().enumerate() {
                for (c, v) in gl.iter().enumerate() {
                    dlocal[c * rr + t] = *v;
                }
                if let Some(f) = layout.face[t] {
                    add_frame(&mut dframes[f as usize], &g.frame);
                    add_anchor(&mut dverts, &layout.verts[t], &layout.bary[t], g.anchor);
                }
            }
        }
        LiftMode::Local => {
            let per_sample: Vec<(LiftGrads, [f32; LOCAL_CHANNELS])> = (0..n)
                .into_par_iter()
                .with_min_len(256)
                .map(|k| {
                    let d = dout_at(k);
                    let l = sampled_local(topo, local, k);
                    let (j, _) = sample_frame(topo, &frames, &verts, k);
                    let o = sigmoid(l[LOCAL_OPACITY]);
                    let (dmean, dcov) = split_out_grad(&d);
                    let g = lift_backward(&j, &geom(&l), dmean, &dcov);
                    (g, local_grads(&g, &d, d[OUT_OPACITY] * o * (1.0 - o)))
                })
                .collect();
            for (k, (g, gl)) in per_sample.iter().enumerate() {
                for q in 0..4 {
                    let w = s.weights[k][q];
                    if w == 0.0 {
                        continue;
                    }
                    let t = s.taps[k][q] as usize;
                    for (c, v) in gl.iter().enumerate() {
                        dlocal[c * rr + t] += w * v;
                    }
                }
                let f = s.face[k] as usize;
                add_frame(&mut dframes[f], &g.frame);
                add_anchor(&mut dverts, &topo.faces[f], &s.bary[k], g.anchor);
            }
        }
    }
    let face_grads: Vec<[Vec3; 3]> = topo
        .faces
        .par_iter()
        .zip(&dframes)
        .map(|(f, dm)| face_frame_backward(kind, f.map(|i| verts[i as usize]), dm))
        .collect();
    for (f, g) in topo.faces.iter().zip(&face_grads) {
        for k in 0..3 {
            let v = &mut dverts[f[k] as usize];
            for c in 0..3 {
                v[c] += g[k][c];
            }
        }
    }
    (dlocal, dverts.concat())
}
