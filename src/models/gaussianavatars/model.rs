//! GaussianAvatars' Gaussians as a burn module: the stored attributes as parameters, placed
//! on the posed mesh with burn tensor ops (differentiated by autodiff, w.r.t. the stored
//! attributes and the vertices).
//!
//! The placement is the lift's tensor-op path ([`crate::lift::reference::lift_rows`]) with
//! per-Gaussian frames `k R` ([`FrameKind::ScaledRotation`], GaussianAvatars'
//! `compute_face_orientation`) and the triangles' centroids as anchors: `mu = k R mu_l + T`
//! and `Sigma = (k R) R(q) diag(exp(s))^2 R(q)^T (k R)^T`, which is GaussianAvatars'
//! covariance of `get_rotation = R * q` and `get_scaling = k exp(s)`. The host twin,
//! [`super::binding::to_world`], is what the tests compare it with.

use burn::module::{Module, Param, ParamId};
use burn::tensor::activation::sigmoid;
use burn::tensor::{Device, Int, Tensor, TensorData};

use super::binding::check_binding;
use crate::error::Result;
use crate::kernels::lift::constants::{
    LOCAL_CHANNELS, LOCAL_LOG_SCALE, LOCAL_MEAN, LOCAL_OPACITY, LOCAL_QUAT, OUT_COV, OUT_MEAN,
    OUT_OPACITY,
};
use crate::lift::reference::{face_frames, lift_rows};
use crate::splat::ply::PlyGaussians;
use crate::splat::{Gaussians, sh};
use crate::texel::FrameKind;

/// Initial opacity (`create_from_pcd`: `inverse_sigmoid(0.1)`), local log scale 0 (the
/// triangle's own scale) and identity rotation, at the triangle's centroid.
pub const INIT_OPACITY: f32 = 0.1;

/// The stored Gaussians of a GaussianAvatars avatar (`GaussianModel`'s `_xyz`,
/// `_features_dc` / `_features_rest`, `_opacity`, `_scaling`, `_rotation`) and `binding`.
#[derive(Module, Debug)]
pub struct GaModel {
    /// `[N, 3]` positions local to the triangle.
    pub xyz: Param<Tensor<2>>,
    /// `[N, 1, 3]` the DC SH coefficient (`_features_dc`).
    pub features_dc: Param<Tensor<3>>,
    /// `[N, K - 1, 3]` the higher bands, `K = (sh_degree + 1)^2` (`_features_rest`; trained
    /// at a twentieth of the DC's rate); `None` at degree 0.
    pub features_rest: Option<Param<Tensor<3>>>,
    /// `[N]` opacity logits.
    pub opacity: Param<Tensor<1>>,
    /// `[N, 3]` log scales (before the triangle's `k`).
    pub scaling: Param<Tensor<2>>,
    /// `[N, 4]` quaternions (w, x, y, z), normalised when used.
    pub rotation: Param<Tensor<2>>,
    /// `[N]` each Gaussian's triangle (a parameter only so that checkpoints keep it; never
    /// trained).
    pub binding: Param<Tensor<1, Int>>,
    /// SH degree (0..=3).
    pub sh_degree: usize,
}

impl GaModel {
    /// The module of stored Gaussians `g` bound by `binding`, on `device`.
    pub fn from_stored(g: &PlyGaussians, binding: &[u32], device: &Device) -> Result<Self> {
        check_binding(binding, g.len(), u32::MAX as usize)?;
        let n = g.len();
        let k = g.sh_coeffs();
        let t = |v: &[f32], w: usize| {
            Tensor::<2>::from_data(TensorData::new(v.to_vec(), [n, w]), device)
        };
        let sh = Tensor::<3>::from_data(TensorData::new(g.sh.clone(), [n, k, 3]), device);
        Ok(Self {
            xyz: Param::from_tensor(t(&g.means, 3)),
            features_dc: Param::from_tensor(sh.clone().narrow(1, 0, 1)),
            features_rest: (k > 1).then(|| Param::from_tensor(sh.narrow(1, 1, k - 1))),
            opacity: Param::from_tensor(Tensor::from_data(
                TensorData::new(g.opacity_logits.clone(), [n]),
                device,
            )),
            scaling: Param::from_tensor(t(&g.log_scales, 3)),
            rotation: Param::from_tensor(t(&g.quats, 4)),
            binding: Param::initialized(
                ParamId::new(),
                Tensor::<1, Int>::from_data(
                    TensorData::new(binding.iter().map(|&f| f as i32).collect::<Vec<_>>(), [n]),
                    device,
                ),
            ),
            sh_degree: g.sh_degree,
        })
    }

    /// GaussianAvatars' initialisation (`create_from_pcd` without a point cloud): one Gaussian
    /// per triangle at its centroid (local position 0), local log scale 0 (the triangle's own
    /// scale), identity rotation, opacity 0.1, the DC colour coefficient uniform in
    /// [0, 1/255) (`np.random.random / 255`, a near-grey start), higher bands 0.
    pub fn init(num_faces: usize, sh_degree: usize, seed: u64, device: &Device) -> Result<Self> {
        let k = (sh_degree + 1) * (sh_degree + 1);
        let mut rng = crate::util::rng::Pcg::new(seed);
        let mut sh = vec![0.0f32; num_faces * k * 3];
        for g in sh.chunks_mut(k * 3) {
            for c in &mut g[..3] {
                *c = rng.uniform() / 255.0;
            }
        }
        let logit = (INIT_OPACITY / (1.0 - INIT_OPACITY)).ln();
        let stored = PlyGaussians {
            means: vec![0.0; 3 * num_faces],
            sh,
            sh_degree,
            opacity_logits: vec![logit; num_faces],
            log_scales: vec![0.0; 3 * num_faces],
            quats: [1.0, 0.0, 0.0, 0.0].repeat(num_faces),
        };
        let binding: Vec<u32> = (0..num_faces as u32).collect();
        Self::from_stored(&stored, &binding, device)
    }

    /// The stored Gaussians and their binding on the host (what `point_cloud.ply` holds).
    pub fn to_stored(&self) -> (PlyGaussians, Vec<u32>) {
        let host = |t: Tensor<2>| -> Vec<f32> { t.into_data().iter::<f32>().collect() };
        let stored = PlyGaussians {
            means: host(self.xyz.val()),
            sh: self.features().into_data().iter::<f32>().collect(),
            sh_degree: self.sh_degree,
            opacity_logits: self.opacity.val().into_data().iter::<f32>().collect(),
            log_scales: host(self.scaling.val()),
            quats: host(self.rotation.val()),
        };
        let binding = self
            .binding
            .val()
            .into_data()
            .iter::<i64>()
            .map(|f| f as u32)
            .collect();
        (stored, binding)
    }

    /// `[N, K, 3]` every SH coefficient, the DC term first.
    pub fn features(&self) -> Tensor<3> {
        match &self.features_rest {
            Some(rest) => Tensor::cat(vec![self.features_dc.val(), rest.val()], 1),
            None => self.features_dc.val(),
        }
    }

    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.binding.val().dims()[0]
    }

    /// True when there are none.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The Gaussians on the posed mesh, colours for a camera at `camera_position`.
    ///
    /// # Shapes
    /// - `faces`: `[F]` (every binding below F, [`check_binding`]); `vertices`: [V, 3]
    pub fn gaussians(
        &self,
        faces: &[[u32; 3]],
        vertices: Tensor<2>,
        camera_position: [f32; 3],
    ) -> Gaussians {
        self.gaussians_at_degree(faces, vertices, camera_position, self.sh_degree)
    }

    /// [`GaModel::gaussians`] with colours from the SH bands up to `degree` only
    /// (GaussianAvatars' `active_sh_degree`, raised during training by `oneupSHdegree`);
    /// at most the stored degree.
    pub fn gaussians_at_degree(
        &self,
        faces: &[[u32; 3]],
        vertices: Tensor<2>,
        camera_position: [f32; 3],
        degree: usize,
    ) -> Gaussians {
        let degree = degree.min(self.sh_degree);
        let n = self.len();
        let device = vertices.device();
        let corner = |c: usize| {
            let idx: Vec<i32> = faces.iter().map(|f| f[c] as i32).collect();
            let f = idx.len();
            vertices
                .clone()
                .select(0, Tensor::from_data(TensorData::new(idx, [f]), &device))
        };
        let centroids = (corner(0) + corner(1) + corner(2)) / 3.0;
        let f = faces.len();
        let frames = face_frames(FrameKind::ScaledRotation, faces, &vertices)
            .reshape([f, 9])
            .select(0, self.binding.val())
            .reshape([n, 3, 3]);
        let anchors = centroids.select(0, self.binding.val());
        // The lift's local layout; its colour channels are unused here (SH below).
        let mut parts: Vec<Tensor<2>> = Vec::with_capacity(5);
        let mut at = 0;
        let mut push = |t: Tensor<2>, offset: usize| {
            assert_eq!(at, offset, "local channel order");
            at += t.dims()[1];
            parts.push(t);
        };
        push(self.xyz.val(), LOCAL_MEAN);
        push(self.rotation.val(), LOCAL_QUAT);
        push(self.scaling.val(), LOCAL_LOG_SCALE);
        push(self.opacity.val().reshape([n, 1]), LOCAL_OPACITY);
        let rest = LOCAL_CHANNELS - at;
        parts.push(Tensor::zeros([n, rest], &device));
        let packed = lift_rows(Tensor::cat(parts, 1), frames, anchors);
        let means = packed.clone().narrow(1, OUT_MEAN, 3);
        let coeffs = (degree + 1) * (degree + 1);
        let colors = sh::colors(
            self.features().narrow(1, 0, coeffs),
            degree,
            means.clone(),
            camera_position,
        );
        Gaussians {
            means,
            cov6: packed.clone().narrow(1, OUT_COV, 6),
            colors,
            opacities: sigmoid(packed.narrow(1, OUT_OPACITY, 1)).reshape([n]),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::models::gaussianavatars::binding::{face_frames as host_frames, to_world};
    use crate::util::rng::Pcg;

    fn host(t: Tensor<2>) -> Vec<f32> {
        t.into_data().iter::<f32>().collect()
    }

    /// Vertices, faces, stored Gaussians and their binding.
    type Scene = (Vec<[f32; 3]>, Vec<[u32; 3]>, PlyGaussians, Vec<u32>);

    /// Two triangles sharing an edge, three Gaussians, SH degree 1.
    fn scene(rng: &mut Pcg) -> Scene {
        let verts = vec![
            [0.0, 0.0, 0.0],
            [0.02, 0.001, 0.0],
            [0.003, 0.025, 0.004],
            [0.022, 0.02, -0.006],
        ];
        let faces = vec![[0, 1, 2], [1, 3, 2]];
        let n = 3;
        let mut r = |k: usize, s: f32| {
            (0..k)
                .map(|_| s * (2.0 * rng.uniform() - 1.0))
                .collect::<Vec<f32>>()
        };
        let g = PlyGaussians {
            means: r(3 * n, 0.5),
            sh: r(3 * 4 * n, 0.4),
            sh_degree: 1,
            opacity_logits: r(n, 2.0),
            log_scales: r(3 * n, 1.0).iter().map(|v| v - 1.0).collect(),
            quats: r(4 * n, 1.0)
                .iter()
                .enumerate()
                .map(|(i, v)| if i % 4 == 0 { v + 1.5 } else { *v })
                .collect(),
        };
        (verts, faces, g, vec![0, 1, 1])
    }

    #[test]
    fn initialisation_puts_one_gaussian_at_each_centroid() {
        let device = Device::flex();
        let mut rng = Pcg::new(9);
        let (verts, faces, _, _) = scene(&mut rng);
        let m = GaModel::init(faces.len(), 3, 1, &device).unwrap();
        assert_eq!(m.len(), 2);
        let v = Tensor::<2>::from_data(TensorData::new(verts.concat(), [verts.len(), 3]), &device);
        let out = m.gaussians(&faces, v, [0.0, 0.0, 1.0]);
        let frames = host_frames(&faces, &verts);
        let means = host(out.means);
        for (i, f) in frames.iter().enumerate() {
            assert!(
                means[3 * i..3 * i + 3]
                    .iter()
                    .zip(&f.center)
                    .all(|(a, b)| (a - b).abs() < 1e-6)
            );
        }
        let op: Vec<f32> = out.opacities.into_data().iter::<f32>().collect();
        assert!(op.iter().all(|o| (o - 0.1).abs() < 1e-6), "{op:?}");
        // Near grey: SH DC below 1/255, so RGB = 0.5 + C0 * dc.
        assert!(
            host(out.colors)
                .iter()
                .all(|c| (c - 0.5).abs() < 0.3 / 255.0)
        );
    }

    #[test]
    fn stored_gaussians_come_back_as_they_went_in() {
        let device = Device::flex();
        let mut rng = Pcg::new(4);
        let (_, _, g, binding) = scene(&mut rng);
        let m = GaModel::from_stored(&g, &binding, &device).unwrap();
        assert_eq!(m.to_stored(), (g, binding));
    }

    #[test]
    fn tensor_ops_match_the_host_binding() {
        let device = Device::flex();
        let mut rng = Pcg::new(3);
        let (verts, faces, g, binding) = scene(&mut rng);
        let m = GaModel::from_stored(&g, &binding, &device).unwrap();
        let v = Tensor::<2>::from_data(TensorData::new(verts.concat(), [verts.len(), 3]), &device);
        let out = m.gaussians(&faces, v, [0.0, 0.0, 1.0]);
        let world = to_world(&g, &binding, &host_frames(&faces, &verts)).unwrap();
        let close = |a: &[f32], b: &[f32], tol: f32| {
            a.iter()
                .zip(b)
                .all(|(x, y)| (x - y).abs() <= tol * (1.0 + y.abs()))
        };
        assert!(close(&host(out.means), &world.means, 1e-5));
        let cov = host(out.cov6);
        let want = world.cov6();
        let scale = want.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        assert!(
            close(
                &cov.iter().map(|v| v / scale).collect::<Vec<_>>(),
                &want.iter().map(|v| v / scale).collect::<Vec<_>>(),
                1e-4
            ),
            "{cov:?} vs {want:?}"
        );
        let op: Vec<f32> = out.opacities.into_data().iter::<f32>().collect();
        assert!(close(&op, &world.opacities(), 1e-6));
    }

    /// Gradients w.r.t. the stored attributes and the vertices against central finite
    /// differences (f64 host loop over the f32 forward, relative tolerance).
    #[test]
    fn gradients_through_the_binding_match_finite_differences() {
        let device = Device::flex().autodiff();
        let mut rng = Pcg::new(5);
        let (verts, faces, g, binding) = scene(&mut rng);
        let n = g.len();
        // loss = sum(w_m * means) + sum(w_c * cov6) / scale + sum(w_rgb * colors) + sum(w_o * opacity)
        let wm: Vec<f32> = (0..3 * n).map(|_| rng.uniform() - 0.5).collect();
        let wc: Vec<f32> = (0..6 * n).map(|_| rng.uniform() - 0.5).collect();
        let wr: Vec<f32> = (0..3 * n).map(|_| rng.uniform() - 0.5).collect();
        let wo: Vec<f32> = (0..n).map(|_| rng.uniform() - 0.5).collect();
        let cov_scale = 1e4f32;
        let loss_of = |g: &PlyGaussians, verts: &[[f32; 3]]| -> (Tensor<1>, GaModel, Tensor<2>) {
            let m = GaModel::from_stored(g, &binding, &device).unwrap();
            let v =
                Tensor::<2>::from_data(TensorData::new(verts.concat(), [verts.len(), 3]), &device)
                    .require_grad();
            let out = m.gaussians(&faces, v.clone(), [0.01, -0.02, 0.3]);
            let t2 = |w: &Vec<f32>, k: usize| {
                Tensor::<2>::from_data(TensorData::new(w.clone(), [n, k]), &device)
            };
            // Means move by about k (centimetres) per unit of xyz: weighted up to matter.
            let loss = (out.means * t2(&wm, 3)).sum() * 100.0
                + (out.cov6 * t2(&wc, 6)).sum() * cov_scale
                + (out.colors * t2(&wr, 3)).sum()
                + (out.opacities
                    * Tensor::<1>::from_data(TensorData::new(wo.clone(), [n]), &device))
                .sum();
            (loss, m, v)
        };
        let value = |g: &PlyGaussians, verts: &[[f32; 3]]| -> f64 {
            loss_of(g, verts)
                .0
                .into_data()
                .iter::<f32>()
                .next()
                .unwrap() as f64
        };
        let (loss, m, v) = loss_of(&g, &verts);
        let grads = loss.backward();
        let grad = |t: &Tensor<2>| -> Vec<f32> {
            t.grad(&grads)
                .map(|g| g.into_data().iter::<f32>().collect())
                .unwrap()
        };
        let analytic = [
            ("xyz", grad(&m.xyz.val())),
            ("scaling", grad(&m.scaling.val())),
            ("rotation", grad(&m.rotation.val())),
            ("vertices", grad(&v)),
        ];
        let check = |name: &str, a: &[f32], perturb: &dyn Fn(usize, f32) -> f64| {
            let eps = 1e-3f32;
            let big = a.iter().fold(0.0f32, |m, v| m.max(v.abs())) as f64;
            for (i, &ai) in a.iter().enumerate() {
                let fd = (perturb(i, eps) - perturb(i, -eps)) / (2.0 * eps as f64);
                // 1% of the group's largest gradient, and of this one.
                let tol = 1e-2 * (big + fd.abs());
                assert!(
                    (ai as f64 - fd).abs() <= tol,
                    "{name}[{i}]: autodiff {ai}, finite differences {fd}"
                );
            }
        };
        for (name, a) in &analytic {
            // Not vacuous: every group has gradients well above the tolerance's floor.
            let big = a.iter().fold(0.0f32, |m, v| m.max(v.abs()));
            assert!(big > 0.1, "{name}: largest gradient {big}");
            match *name {
                "vertices" => check(name, a, &|i, e| {
                    let mut vv = verts.clone();
                    vv[i / 3][i % 3] += e * 1e-2; // vertices are centimetres apart
                    value(&g, &vv) / 1e-2
                }),
                field => check(name, a, &|i, e| {
                    let mut gg = g.clone();
                    let slot = match field {
                        "xyz" => &mut gg.means,
                        "scaling" => &mut gg.log_scales,
                        _ => &mut gg.quats,
                    };
                    slot[i] += e;
                    value(&gg, &verts)
                }),
            }
        }
    }
}
