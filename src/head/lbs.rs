//! Linear blend skinning of a [`HeadModel`], as FLAME does it.
//!
//! 1. `v = v_template + static_offset + shapedirs · [shape, expr]`
//! 2. joints `J = J_regressor · v`
//! 3. rotations `R_i = rodrigues(pose_i)`; pose feature `(R_i - I)` for the non-root joints
//! 4. `v += posedirs · pose_feature`
//! 5. world transforms down the kinematic tree, `A_i = G_i · [I | -J_i]`
//! 6. `v' = (sum_i w_vi A_i) v + translation`
//!
//! Coefficient vectors shorter than the model's are zero-padded (as GaussianAvatars does);
//! longer ones are an error.

use crate::error::{Error, Result};
use crate::head::model::HeadModel;

/// Per-frame FLAME parameters.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct HeadPose {
    pub shape: Vec<f32>,
    pub expr: Vec<f32>,
    /// Global rotation (axis-angle).
    pub rotation: [f32; 3],
    pub neck: [f32; 3],
    pub jaw: [f32; 3],
    /// Left then right eye (axis-angle each).
    pub eyes: [f32; 6],
    pub translation: [f32; 3],
    /// Per-vertex offsets added to the template, `[V]` (optional).
    pub static_offset: Option<Vec<[f32; 3]>>,
}

impl HeadPose {
    /// The rest pose of `model`: zero coefficients of the model's sizes, no rotation.
    pub fn neutral(model: &HeadModel) -> Self {
        HeadPose {
            shape: vec![0.0; model.num_shape],
            expr: vec![0.0; model.num_expr],
            ..Default::default()
        }
    }

    /// Axis-angle per joint: global, neck, jaw, left eye, right eye.
    pub fn joint_rotations(&self) -> [[f32; 3]; 5] {
        [
            self.rotation,
            self.neck,
            self.jaw,
            [self.eyes[0], self.eyes[1], self.eyes[2]],
            [self.eyes[3], self.eyes[4], self.eyes[5]],
        ]
    }

    /// Fails, naming `what` and the field (VHAP's key), when any value is NaN or infinite.
    pub fn check_finite(&self, what: &str) -> Result<()> {
        let fields: [(&str, &[f32]); 7] = [
            ("shape", &self.shape),
            ("expr", &self.expr),
            ("rotation", &self.rotation),
            ("neck_pose", &self.neck),
            ("jaw_pose", &self.jaw),
            ("eyes_pose", &self.eyes),
            ("translation", &self.translation),
        ];
        for (name, values) in fields {
            if let Some(i) = values.iter().position(|x| !x.is_finite()) {
                return Err(Error::invalid(
                    what,
                    name,
                    format!("value {i} is {}", values[i]),
                ));
            }
        }
        if let Some(o) = &self.static_offset
            && let Some(i) = o.iter().position(|p| p.iter().any(|x| !x.is_finite()))
        {
            return Err(Error::invalid(
                what,
                "static_offset",
                format!("vertex {i} is {:?}", o[i]),
            ));
        }
        Ok(())
    }

    /// The 15-value pose vector `[global 3, neck 3, jaw 3, eyes 6]`.
    pub fn pose15(&self) -> [f32; 15] {
        let mut p = [0.0f32; 15];
        p[..3].copy_from_slice(&self.rotation);
        p[3..6].copy_from_slice(&self.neck);
        p[6..9].copy_from_slice(&self.jaw);
        p[9..].copy_from_slice(&self.eyes);
        p
    }

    /// Sets the rotations from a 15-value pose vector (the inverse of [`Self::pose15`]).
    pub fn set_pose15(&mut self, p: &[f32; 15]) {
        self.rotation.copy_from_slice(&p[..3]);
        self.neck.copy_from_slice(&p[3..6]);
        self.jaw.copy_from_slice(&p[6..9]);
        self.eyes.copy_from_slice(&p[9..]);
    }
}

type M3 = [[f64; 3]; 3];

/// Rotation matrix of an axis-angle vector (Rodrigues); exact first order near zero.
pub fn rodrigues(aa: [f32; 3]) -> [[f32; 3]; 3] {
    rodrigues64(aa.map(f64::from)).map(|r| r.map(|v| v as f32))
}

fn rodrigues64(aa: [f64; 3]) -> M3 {
    let theta = (aa[0] * aa[0] + aa[1] * aa[1] + aa[2] * aa[2]).sqrt();
    let k = [
        [0.0, -aa[2], aa[1]],
        [aa[2], 0.0, -aa[0]],
        [-aa[1], aa[0], 0.0],
    ];
    // R = I + a K + b K^2 with a = sin t / t, b = (1 - cos t) / t^2 (series near 0).
    let (a, b) = if theta < 1e-6 {
        (1.0 - theta * theta / 6.0, 0.5 - theta * theta / 24.0)
    } else {
        (theta.sin() / theta, (1.0 - theta.cos()) / (theta * theta))
    };
    let mut r = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            let k2: f64 = (0..3).map(|m| k[i][m] * k[m][j]).sum();
            r[i][j] = f64::from(u8::from(i == j)) + a * k[i][j] + b * k2;
        }
    }
    r
}

fn mul(a: &M3, b: &M3) -> M3 {
    std::array::from_fn(|i| std::array::from_fn(|j| (0..3).map(|k| a[i][k] * b[k][j]).sum()))
}

fn apply(a: &M3, v: [f64; 3]) -> [f64; 3] {
    std::array::from_fn(|i| (0..3).map(|k| a[i][k] * v[k]).sum())
}

/// Template plus static offsets plus shape and expression blendshapes (step 1 of LBS).
/// Coefficients beyond the model's are ignored (`lbs` rejects them).
pub(crate) fn shaped_vertices(model: &HeadModel, pose: &HeadPose) -> Vec<[f64; 3]> {
    let v = model.num_vertices();
    let k = model.num_shape + model.num_expr;
    let mut coef = vec![0.0f64; k];
    for (i, &c) in pose.shape.iter().take(model.num_shape).enumerate() {
        coef[i] = f64::from(c);
    }
    for (i, &c) in pose.expr.iter().take(model.num_expr).enumerate() {
        coef[model.num_shape + i] = f64::from(c);
    }
    let static_offset = pose.static_offset.as_ref().filter(|o| o.len() == v);
    let active: Vec<(usize, f64)> = coef
        .iter()
        .copied()
        .enumerate()
        .filter(|(_, c)| *c != 0.0)
        .collect();
    (0..v)
        .map(|i| {
            let mut p = model.v_template[i].map(f64::from);
            if let Some(o) = static_offset {
                for c in 0..3 {
                    p[c] += f64::from(o[i][c]);
                }
            }
            for (c, pc) in p.iter_mut().enumerate() {
                let row = &model.shapedirs[(i * 3 + c) * k..(i * 3 + c + 1) * k];
                *pc += active
                    .iter()
                    .map(|&(q, w)| f64::from(row[q]) * w)
                    .sum::<f64>();
            }
            p
        })
        .collect()
}

/// Joint locations of shaped vertices (step 2 of LBS).
pub(crate) fn regress_joints(model: &HeadModel, shaped: &[[f64; 3]]) -> Vec<[f64; 3]> {
    let v = model.num_vertices();
    (0..model.num_joints())
        .map(|a| {
            let row = &model.j_regressor[a * v..(a + 1) * v];
            let mut p = [0.0f64; 3];
            for (w, s) in row.iter().zip(shaped) {
                if *w != 0.0 {
                    for c in 0..3 {
                        p[c] += f64::from(*w) * s[c];
                    }
                }
            }
            p
        })
        .collect()
}

/// The rest-pose joint locations for `pose`'s shape, expression and static offsets (before
/// any rotation or translation).
pub fn joints(model: &HeadModel, pose: &HeadPose) -> Vec<[f32; 3]> {
    let shaped = shaped_vertices(model, pose);
    regress_joints(model, &shaped)
        .into_iter()
        .map(|p| p.map(|x| x as f32))
        .collect()
}

/// Poses the model: returns the posed vertices `[V]`.
pub fn lbs(model: &HeadModel, pose: &HeadPose) -> Result<Vec<[f32; 3]>> {
    let what = "head pose";
    pose.check_finite(what)?;
    let v = model.num_vertices();
    let j = model.num_joints();
    if pose.shape.len() > model.num_shape {
        return Err(Error::invalid(
            what,
            "shape",
            format!(
                "{} coefficients, the model has {}",
                pose.shape.len(),
                model.num_shape
            ),
        ));
    }
    if pose.expr.len() > model.num_expr {
        return Err(Error::invalid(
            what,
            "expr",
            format!(
                "{} coefficients, the model has {}",
                pose.expr.len(),
                model.num_expr
            ),
        ));
    }
    if j != 5 {
        return Err(Error::invalid(
            what,
            "joints",
            format!("FLAME poses 5 joints, the model has {j}"),
        ));
    }
    if let Some(o) = &pose.static_offset
        && o.len() != v
    {
        return Err(Error::invalid(
            what,
            "static_offset",
            format!("{} offsets for {v} vertices", o.len()),
        ));
    }
    let mut shaped = shaped_vertices(model, pose);
    let joints = regress_joints(model, &shaped);
    // 3. Rotations and the pose feature.
    let rots: Vec<M3> = pose
        .joint_rotations()
        .iter()
        .map(|aa| rodrigues64(aa.map(f64::from)))
        .collect();
    let p = 9 * (j - 1);
    let mut feature = vec![0.0f64; p];
    for a in 1..j {
        for r in 0..3 {
            for c in 0..3 {
                feature[(a - 1) * 9 + r * 3 + c] = rots[a][r][c] - f64::from(u8::from(r == c));
            }
        }
    }
    // 4. Pose correctives.
    if feature.iter().any(|f| *f != 0.0) {
        for (i, s) in shaped.iter_mut().enumerate() {
            for (c, sc) in s.iter_mut().enumerate() {
                let row = &model.posedirs[(i * 3 + c) * p..(i * 3 + c + 1) * p];
                *sc += row
                    .iter()
                    .zip(&feature)
                    .map(|(d, f)| f64::from(*d) * f)
                    .sum::<f64>();
            }
        }
    }
    // 5. World transforms (rotation, translation) per joint.
    let mut world: Vec<(M3, [f64; 3])> = Vec::with_capacity(j);
    for a in 0..j {
        let local_t = match model.parents[a] {
            None => joints[a],
            Some(q) => std::array::from_fn(|c| joints[a][c] - joints[q][c]),
        };
        let g = match model.parents[a] {
            None => (rots[a], local_t),
            Some(q) => {
                let (pr, pt) = &world[q];
                let t = apply(pr, local_t);
                (mul(pr, &rots[a]), std::array::from_fn(|c| t[c] + pt[c]))
            }
        };
        world.push(g);
    }
    // A_i = G_i [I | -J_i].
    let skin: Vec<(M3, [f64; 3])> = world
        .iter()
        .zip(&joints)
        .map(|((r, t), jp)| {
            let rj = apply(r, *jp);
            (*r, std::array::from_fn(|c| t[c] - rj[c]))
        })
        .collect();
    // 6. Blend.
    let tr = pose.translation.map(f64::from);
    Ok((0..v)
        .map(|i| {
            let w = &model.weights[i * j..(i + 1) * j];
            let mut r = [[0.0f64; 3]; 3];
            let mut t = [0.0f64; 3];
            for (a, &wa) in w.iter().enumerate() {
                if wa == 0.0 {
                    continue;
                }
                let wa = f64::from(wa);
                for (x, (rx, tx)) in r.iter_mut().zip(t.iter_mut()).enumerate() {
                    for (rxy, sxy) in rx.iter_mut().zip(&skin[a].0[x]) {
                        *rxy += wa * sxy;
                    }
                    *tx += wa * skin[a].1[x];
                }
            }
            let q = apply(&r, shaped[i]);
            std::array::from_fn(|c| (q[c] + t[c] + tr[c]) as f32)
        })
        .collect())
}
