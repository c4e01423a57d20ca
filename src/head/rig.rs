//! Linear blend skinning in burn tensor ops, so that gradients reach the per-frame FLAME
//! parameters (translation, the five joint rotations, expression): the tensor twin of
//! [`lbs()`](super::lbs()) for one subject, used by FLAME refinement
//! ([`crate::train::refine`]).
//!
//! The subject's shape and static offsets are fixed, so their part of step 1 of LBS (and of
//! the joint regression) is done once on the host in f64: [`Rig::new`] keeps the shaped
//! template, its joints, and the expression and pose blendshapes laid out for one matrix
//! product each. Per frame:
//!
//! 1. `v = base + expr · exprdirs`, `J = J_base + expr · J_exprdirs`
//! 2. `R_i = rodrigues(pose_i)` (a form without a `1 - cos` cancellation, see [`rodrigues`])
//! 3. `v += (R_i - I)_{i >= 1} · posedirs`
//! 4. world transforms down the kinematic tree, `A_i = G_i [I | -J_i]`
//! 5. `v' = (sum_i w_vi A_i) v + translation`
//!
//! Parity with the host's f64 [`lbs()`](super::lbs()) and the gradients against finite
//! differences of it are tested below.

use burn::module::Module;
use burn::tensor::{Device, Tensor, TensorData};

use super::lbs::{HeadPose, regress_joints, shaped_vertices};
use super::model::{HeadModel, JOINTS};
use crate::error::{Error, Result};

/// Length of the pose vector `[global 3, neck 3, jaw 3, eyes 6]`.
pub const POSE_LEN: usize = 3 * JOINTS;

/// Added to `|aa|^2` before its square root in [`rodrigues`]: the angle stays above 1e-6,
/// so `sin(t) / t` never divides by zero; at `aa = 0` the derivative of the angle's terms is
/// multiplied by `aa = 0`, and the rotation's derivative is the exact generator `[e_k]x`.
const ANGLE_EPS2: f32 = 1e-12;

/// One subject's head model as device tensors, posing frames differentiably.
///
/// # Shapes
/// - `base`: [V, 3], the template with the subject's static offsets and shape
/// - `exprdirs`: [E, 3 V]; `j_base`: [J, 3]; `j_exprdirs`: [E, 3 J]
/// - `posedirs`: [9 (J - 1), 3 V]; `weights`: [V, J]
///
/// A burn module of constant tensors (no parameters; nothing saved), so that it follows
/// its owner to a device and out of autodiff (`valid`).
#[derive(Module, Debug)]
pub struct Rig {
    base: Tensor<2>,
    exprdirs: Tensor<2>,
    j_base: Tensor<2>,
    j_exprdirs: Tensor<2>,
    posedirs: Tensor<2>,
    weights: Tensor<2>,
    #[module(skip)]
    parents: Vec<Option<usize>>,
    #[module(skip)]
    num_vertices: usize,
    #[module(skip)]
    num_expr: usize,
}

impl Rig {
    /// The rig of `model` for the subject of `identity` (its `shape` and `static_offset`;
    /// every other field is ignored), on `device`.
    pub fn new(model: &HeadModel, identity: &HeadPose, device: &Device) -> Result<Self> {
        let what = "head rig";
        model.validate(what)?;
        if model.num_joints() != JOINTS {
            return Err(Error::invalid(
                what,
                "kintree_table",
                format!("{} joints; FLAME poses {JOINTS}", model.num_joints()),
            ));
        }
        if identity.shape.len() > model.num_shape {
            return Err(Error::invalid(
                what,
                "shape",
                format!(
                    "{} coefficients, the model has {}",
                    identity.shape.len(),
                    model.num_shape
                ),
            ));
        }
        let v = model.num_vertices();
        let (s, e) = (model.num_shape, model.num_expr);
        let k = s + e;
        let subject = HeadPose {
            shape: identity.shape.clone(),
            expr: Vec::new(),
            static_offset: identity.static_offset.clone(),
            ..Default::default()
        };
        subject.check_finite(what)?;
        let base = shaped_vertices(model, &subject);
        let j_base = regress_joints(model, &base);
        // exprdirs [E, 3V]: column q of shapedirs [V, 3, K] for q in S..K.
        let mut exprdirs = vec![0.0f32; e * 3 * v];
        for row in 0..3 * v {
            for q in 0..e {
                exprdirs[q * 3 * v + row] = model.shapedirs[row * k + s + q];
            }
        }
        // J_exprdirs [E, 3J] = J_regressor applied to each expression blendshape.
        let mut j_exprdirs = vec![0.0f32; e * 3 * JOINTS];
        for q in 0..e {
            let dirs = &exprdirs[q * 3 * v..(q + 1) * 3 * v];
            for a in 0..JOINTS {
                let reg = &model.j_regressor[a * v..(a + 1) * v];
                for c in 0..3 {
                    let sum: f64 = reg
                        .iter()
                        .enumerate()
                        .filter(|(_, w)| **w != 0.0)
                        .map(|(i, w)| f64::from(*w) * f64::from(dirs[i * 3 + c]))
                        .sum();
                    j_exprdirs[q * 3 * JOINTS + a * 3 + c] = sum as f32;
                }
            }
        }
        // posedirs [P, 3V] from the model's [V, 3, P].
        let p = 9 * (JOINTS - 1);
        let mut posedirs = vec![0.0f32; p * 3 * v];
        for row in 0..3 * v {
            for q in 0..p {
                posedirs[q * 3 * v + row] = model.posedirs[row * p + q];
            }
        }
        let flat = |pts: &[[f64; 3]]| -> Vec<f32> {
            pts.iter().flat_map(|p| p.map(|x| x as f32)).collect()
        };
        let t = |data: Vec<f32>, shape: [usize; 2]| {
            Tensor::<2>::from_data(TensorData::new(data, shape), device)
        };
        Ok(Rig {
            base: t(flat(&base), [v, 3]),
            exprdirs: t(exprdirs, [e, 3 * v]),
            j_base: t(flat(&j_base), [JOINTS, 3]),
            j_exprdirs: t(j_exprdirs, [e, 3 * JOINTS]),
            posedirs: t(posedirs, [p, 3 * v]),
            weights: t(model.weights.clone(), [v, JOINTS]),
            parents: model.parents.clone(),
            num_vertices: v,
            num_expr: e,
        })
    }

    /// Number of vertices posed.
    pub fn num_vertices(&self) -> usize {
        self.num_vertices
    }

    /// Number of expression coefficients a frame takes (the model's).
    pub fn num_expr(&self) -> usize {
        self.num_expr
    }

    /// Poses frames.
    ///
    /// # Shapes
    /// - `expr`: [N, E] (the model's E); `pose`: [N, 15]; `translation`: [N, 3]
    /// - returns [N, V, 3]
    pub fn pose(&self, expr: Tensor<2>, pose: Tensor<2>, translation: Tensor<2>) -> Tensor<3> {
        let n = expr.dims()[0];
        let frames: Vec<Tensor<3>> = (0..n)
            .map(|i| {
                self.pose_one(
                    expr.clone().narrow(0, i, 1),
                    pose.clone().narrow(0, i, 1),
                    translation.clone().narrow(0, i, 1),
                )
                .unsqueeze_dim::<3>(0)
            })
            .collect();
        Tensor::cat(frames, 0)
    }

    /// One frame: `expr` [1, E], `pose` [1, 15], `translation` [1, 3] → [V, 3].
    fn pose_one(&self, expr: Tensor<2>, pose: Tensor<2>, translation: Tensor<2>) -> Tensor<2> {
        let v = self.num_vertices;
        let device = expr.device();
        // 1. Expression blendshapes and joints.
        let shaped = self.base.clone() + expr.clone().matmul(self.exprdirs.clone()).reshape([v, 3]);
        let joints =
            self.j_base.clone() + expr.matmul(self.j_exprdirs.clone()).reshape([JOINTS, 3]);
        // 2. Rotations [J, 3, 3].
        let rots = rodrigues(pose.reshape([JOINTS, 3]));
        // 3. Pose correctives from (R_i - I), i >= 1.
        let eye = Tensor::<3>::from_data(
            TensorData::new(
                [1.0f32, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0].repeat(JOINTS - 1),
                [JOINTS - 1, 3, 3],
            ),
            &device,
        );
        let feature = (rots.clone().narrow(0, 1, JOINTS - 1) - eye).reshape([1, 9 * (JOINTS - 1)]);
        let posed = shaped + feature.matmul(self.posedirs.clone()).reshape([v, 3]);
        // 4. World transforms down the tree; A_i = [R_w | t_w - R_w J_i], flattened to 12.
        let joint = |a: usize| joints.clone().narrow(0, a, 1).reshape([3, 1]);
        let mut world: Vec<(Tensor<2>, Tensor<2>)> = Vec::with_capacity(JOINTS);
        for a in 0..JOINTS {
            let r = rots.clone().narrow(0, a, 1).reshape([3, 3]);
            let g = match self.parents[a] {
                None => (r, joint(a)),
                Some(q) => {
                    let (pr, pt) = &world[q];
                    let t = pr.clone().matmul(joint(a) - joint(q)) + pt.clone();
                    (pr.clone().matmul(r), t)
                }
            };
            world.push(g);
        }
        let skin: Vec<Tensor<2>> = world
            .iter()
            .enumerate()
            .map(|(a, (r, t))| {
                let t = t.clone() - r.clone().matmul(joint(a));
                Tensor::cat(vec![r.clone().reshape([1, 9]), t.reshape([1, 3])], 1)
            })
            .collect();
        // 5. Blend per vertex and apply.
        let blended = self.weights.clone().matmul(Tensor::cat(skin, 0)); // [V, 12]
        let r = blended.clone().narrow(1, 0, 9).reshape([v, 3, 3]);
        let t = blended.narrow(1, 9, 3);
        let rotated = (r * posed.reshape([v, 1, 3])).sum_dim(2).reshape([v, 3]);
        rotated + t + translation
    }
}

/// Rotation matrices of axis-angle vectors, `R = I + a K + b K^2` with `K = [aa]x`,
/// `a = sin t / t` and `b = (1 - cos t) / t^2` written as `(sin(t/2) / (t/2))^2 / 2`, which
/// has no cancellation for small angles (in f32, `1 - cos t` is 0 below t ≈ 2.4e-4). The angle
/// is `sqrt(|aa|^2 + 1e-12)`.
///
/// # Shapes
/// - `aa`: [M, 3]; returns [M, 3, 3]
pub fn rodrigues(aa: Tensor<2>) -> Tensor<3> {
    let m = aa.dims()[0];
    let device = aa.device();
    let x = aa.clone().narrow(1, 0, 1);
    let y = aa.clone().narrow(1, 1, 1);
    let z = aa.clone().narrow(1, 2, 1);
    let zero = x.clone().zeros_like();
    let k = Tensor::cat(
        vec![
            zero.clone(),
            -z.clone(),
            y.clone(),
            z,
            zero.clone(),
            -x.clone(),
            -y,
            x,
            zero,
        ],
        1,
    )
    .reshape([m, 3, 3]);
    let theta = (aa.clone() * aa).sum_dim(1).add_scalar(ANGLE_EPS2).sqrt(); // [M, 1]
    let a = theta.clone().sin() / theta.clone();
    let half = theta.mul_scalar(0.5);
    let s = half.clone().sin() / half;
    let b = (s.clone() * s).mul_scalar(0.5);
    let eye = Tensor::<3>::from_data(
        TensorData::new(
            [1.0f32, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0].repeat(m),
            [m, 3, 3],
        ),
        &device,
    );
    let k2 = k.clone().matmul(k.clone());
    eye + a.reshape([m, 1, 1]) * k + b.reshape([m, 1, 1]) * k2
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::head::{HeadAsset, lbs};

    /// The embedded head with pose correctives added (its own are zero: MakeHuman has none),
    /// so that step 3 is exercised.
    fn model() -> HeadModel {
        let mut m = HeadAsset::embedded().expect("embedded head").model;
        for (i, d) in m.posedirs.iter_mut().enumerate() {
            *d = 0.02 * ((i as f32) * 0.61).sin();
        }
        m
    }

    /// A subject and a frame with every joint turned, an expression and a translation.
    fn frame(m: &HeadModel, k: f32) -> HeadPose {
        HeadPose {
            shape: (0..m.num_shape.min(10))
                .map(|i| 0.3 * ((i as f32) * 0.7).sin())
                .collect(),
            expr: (0..m.num_expr)
                .map(|i| k * ((i as f32) * 1.3 + 0.4).cos())
                .collect(),
            rotation: [0.1 * k, -0.25 * k, 0.05],
            neck: [0.2 * k, 0.1, -0.1 * k],
            jaw: [0.3 * k, 0.0, 0.02],
            eyes: [0.05, -0.1 * k, 0.0, 0.05, 0.1 * k, 0.0],
            translation: [0.01, -0.02 * k, 0.03],
            static_offset: Some(
                (0..m.num_vertices())
                    .map(|i| [1e-3 * (i as f32 * 0.1).sin(), 0.0, -5e-4])
                    .collect(),
            ),
        }
    }

    fn inputs(p: &HeadPose, device: &Device) -> (Tensor<2>, Tensor<2>, Tensor<2>) {
        let t = |v: Vec<f32>| {
            let n = v.len();
            Tensor::<2>::from_data(TensorData::new(v, [1, n]), device)
        };
        (
            t(p.expr.clone()),
            t(p.pose15().to_vec()),
            t(p.translation.to_vec()),
        )
    }

    fn values(t: Tensor<3>) -> Vec<f32> {
        t.into_data().iter::<f32>().collect()
    }

    #[test]
    fn rig_poses_as_the_host_lbs_does() {
        let m = model();
        let device = Device::flex();
        for k in [0.0, 1.0, -2.0] {
            let p = frame(&m, k);
            let rig = Rig::new(&m, &p, &device).expect("rig");
            let (e, q, t) = inputs(&p, &device);
            let got = values(rig.pose(e, q, t));
            let want: Vec<f32> = lbs(&m, &p).expect("lbs").concat();
            assert_eq!(got.len(), want.len());
            let err = got
                .iter()
                .zip(&want)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0f32, f32::max);
            // Coordinates of about 0.2 m in f32: a few ulps.
            assert!(err < 2e-6, "k = {k}: largest difference {err} m");
        }
    }

    #[test]
    fn rodrigues_matches_the_host_and_is_exact_at_zero() {
        let device = Device::flex();
        let aa = [
            [0.0f32, 0.0, 0.0],
            [1e-5, -2e-5, 0.0],
            [0.3, -0.2, 0.9],
            [2.5, 0.1, -1.0],
        ];
        let t = Tensor::<2>::from_data(TensorData::new(aa.concat(), [4, 3]), &device);
        let got = values(rodrigues(t));
        for (i, a) in aa.iter().enumerate() {
            let want = crate::head::lbs::rodrigues(*a);
            for r in 0..3 {
                for c in 0..3 {
                    let g = got[i * 9 + r * 3 + c];
                    assert!(
                        (g - want[r][c]).abs() < 1e-6,
                        "{a:?} [{r}][{c}]: {g} vs {}",
                        want[r][c]
                    );
                }
            }
        }
    }

    /// The gradient of a weighted sum of the posed vertices with respect to every frame
    /// parameter, against central differences of the host's f64 `lbs` (an independent
    /// implementation of the same formula).
    #[test]
    fn rig_gradients_match_finite_differences_of_the_host_lbs() {
        let m = model();
        let device = Device::flex().autodiff();
        let p = frame(&m, 1.0);
        let rig = Rig::new(&m, &p, &device).expect("rig");
        let v = m.num_vertices();
        let weights: Vec<f32> = (0..v * 3).map(|i| ((i as f32) * 0.37).sin()).collect();
        let w = Tensor::<3>::from_data(TensorData::new(weights.clone(), [1, v, 3]), &device);
        let (e, q, t) = inputs(&p, &device);
        let (e, q, t) = (e.require_grad(), q.require_grad(), t.require_grad());
        let loss = (rig.pose(e.clone(), q.clone(), t.clone()) * w).sum();
        let grads = loss.backward();
        let grad = |x: &Tensor<2>| -> Vec<f32> {
            x.grad(&grads)
                .expect("gradient")
                .into_data()
                .iter::<f32>()
                .collect()
        };
        let (ge, gq, gt) = (grad(&e), grad(&q), grad(&t));
        let objective = |p: &HeadPose| -> f64 {
            lbs(&m, p)
                .expect("lbs")
                .concat()
                .iter()
                .zip(&weights)
                .map(|(a, b)| f64::from(*a) * f64::from(*b))
                .sum()
        };
        let h = 1e-3f32;
        let fd = |set: &dyn Fn(&mut HeadPose, f32)| -> f64 {
            let (mut plus, mut minus) = (p.clone(), p.clone());
            set(&mut plus, h);
            set(&mut minus, -h);
            (objective(&plus) - objective(&minus)) / (2.0 * f64::from(h))
        };
        let check = |name: &str, got: f32, want: f64| {
            let tol = 2e-3 * want.abs().max(1.0);
            assert!(
                (f64::from(got) - want).abs() < tol,
                "{name}: autodiff {got}, finite differences {want}"
            );
        };
        for i in 0..POSE_LEN {
            let want = fd(&|p: &mut HeadPose, d| {
                let mut pose = p.pose15();
                pose[i] += d;
                p.set_pose15(&pose);
            });
            check(&format!("pose[{i}]"), gq[i], want);
        }
        for (c, &g) in gt.iter().enumerate() {
            check(
                &format!("translation[{c}]"),
                g,
                fd(&|p: &mut HeadPose, d| p.translation[c] += d),
            );
        }
        for i in [0, 1, 5, m.num_expr - 1] {
            check(
                &format!("expr[{i}]"),
                ge[i],
                fd(&|p: &mut HeadPose, d| p.expr[i] += d),
            );
        }
    }
}
