//! GaussianAvatars' binding: Gaussians stored local to a FLAME triangle, placed by the
//! triangle's posed frame.
//!
//! For a Gaussian bound to triangle `f` with stored position `mu_l`, rotation `r_l` and log
//! scale `s_l`, and the posed triangle's centroid `T`, rotation `R = [a0 | a1 | a2]` and scale
//! `k` ([`crate::texel::frames::scaled_rotation`], the frame the lift's "w/o Jacobian"
//! ablation uses too):
//!
//! - position `k R mu_l + T` (GaussianAvatars `scene/gaussian_model.py`, `get_xyz`);
//! - rotation `q(R) * normalize(r_l)`, a quaternion product (`get_rotation`; `q(R)` is
//!   `roma.rotmat_to_unitquat` of the face orientation in `scene/flame_gaussian_model.py`,
//!   `update_mesh_properties`);
//! - scale `k exp(s_l)` (`get_scaling`);
//! - opacity, SH coefficients unchanged: colours are evaluated from the world positions
//!   with the world-space view direction, as GaussianAvatars' renderer does with
//!   `pc.get_features` (the coefficients are not rotated with the triangle).

use glam::{Mat3 as GMat3, Quat, Vec3 as GVec3};

use crate::error::{Error, Result};
use crate::splat::ply::PlyGaussians;
use crate::texel::frames::{Mat3, Vec3, add, col, scale, scaled_rotation};

/// One posed triangle's frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FaceFrame {
    /// The centroid `T` (mean of the three vertices).
    pub center: Vec3,
    /// `R = [a0 | a1 | a2]`, a rotation.
    pub rotation: Mat3,
    /// `k`.
    pub scale: f32,
}

/// The frames of every triangle of the posed mesh.
///
/// # Shapes
/// - `faces`: `[F]`; `vertices`: `[V]`; returns `[F]`
pub fn face_frames(faces: &[[u32; 3]], vertices: &[Vec3]) -> Vec<FaceFrame> {
    faces
        .iter()
        .map(|f| {
            let v = f.map(|i| vertices[i as usize]);
            let (rotation, k) = scaled_rotation(v);
            FaceFrame {
                center: scale(add(add(v[0], v[1]), v[2]), 1.0 / 3.0),
                rotation,
                scale: k,
            }
        })
        .collect()
}

/// `m x`.
fn mul(m: &Mat3, x: Vec3) -> Vec3 {
    let mut y = [0.0; 3];
    for (c, &xc) in x.iter().enumerate() {
        y = add(y, scale(col(m, c), xc));
    }
    y
}

/// `q / |q|`, the identity for a zero or non-finite quaternion (GaussianAvatars normalises
/// with `torch.nn.functional.normalize`, which leaves a zero quaternion zero; a zero
/// rotation is no rotation to the rasterizer either).
pub(crate) fn unit(q: Quat) -> Quat {
    let n = q.length();
    if n > 0.0 && n.is_finite() {
        q / n
    } else {
        Quat::IDENTITY
    }
}

/// The Gaussians of `local` (as stored, bound by `binding` to the triangles of `frames`) in
/// world space: positions, rotations and log scales replaced, everything else kept.
///
/// # Shapes
/// - `local`: N Gaussians; `binding`: `[N]`; `frames`: `[F]`
pub fn to_world(
    local: &PlyGaussians,
    binding: &[u32],
    frames: &[FaceFrame],
) -> Result<PlyGaussians> {
    check_binding(binding, local.len(), frames.len())?;
    let mut world = local.clone();
    for (i, &f) in binding.iter().enumerate() {
        let fr = &frames[f as usize];
        let mu = [
            local.means[3 * i],
            local.means[3 * i + 1],
            local.means[3 * i + 2],
        ];
        let p = add(scale(mul(&fr.rotation, mu), fr.scale), fr.center);
        world.means[3 * i..3 * i + 3].copy_from_slice(&p);
        let r = &fr.rotation;
        let face = Quat::from_mat3(&GMat3::from_cols(
            GVec3::from(col(r, 0)),
            GVec3::from(col(r, 1)),
            GVec3::from(col(r, 2)),
        ));
        let q = &local.quats[4 * i..4 * i + 4];
        // Stored (w, x, y, z); glam is (x, y, z, w).
        let q = unit(face) * unit(Quat::from_xyzw(q[1], q[2], q[3], q[0]));
        world.quats[4 * i..4 * i + 4].copy_from_slice(&[q.w, q.x, q.y, q.z]);
        let ln_k = fr.scale.max(f32::MIN_POSITIVE).ln();
        for s in &mut world.log_scales[3 * i..3 * i + 3] {
            *s += ln_k;
        }
    }
    Ok(world)
}

/// Every Gaussian bound to one of `faces` triangles, one binding per Gaussian.
pub fn check_binding(binding: &[u32], gaussians: usize, faces: usize) -> Result<()> {
    if binding.len() != gaussians {
        return Err(Error::invalid(
            "gaussianavatars",
            "binding_0",
            format!("{} bindings for {gaussians} Gaussians", binding.len()),
        ));
    }
    if let Some((i, f)) = binding
        .iter()
        .enumerate()
        .find(|(_, f)| **f as usize >= faces)
    {
        return Err(Error::invalid(
            "gaussianavatars",
            "binding_0",
            format!(
                "Gaussian {i} is bound to triangle {f}, the head model has {faces} triangles: \
                 use the head model the avatar was trained with (--head; GaussianAvatars \
                 trains FLAME with teeth, `texavatars head add-teeth`)"
            ),
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A right triangle in the xy plane, legs 2 (along x) and 3 (along y), at (1, 1, 1):
    /// a0 = x, a1 = norm(x cross (0, 3, 0)) = z, a2 = -norm(z cross x) = -y;
    /// k = (|e1| + |a2 . e2|) / 2 = (2 + 3) / 2 = 2.5; centroid (1 + 2/3, 2, 1).
    #[test]
    fn a_hand_computed_triangle_places_its_gaussian() {
        let verts = vec![[1.0, 1.0, 1.0], [3.0, 1.0, 1.0], [1.0, 4.0, 1.0]];
        let frames = face_frames(&[[0, 1, 2]], &verts);
        let fr = frames[0];
        let close = |a: &[f32], b: &[f32]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-5);
        assert!(close(&fr.center, &[5.0 / 3.0, 2.0, 1.0]), "{fr:?}");
        assert!((fr.scale - 2.5).abs() < 1e-6);
        assert!(close(&col(&fr.rotation, 0), &[1.0, 0.0, 0.0]));
        assert!(close(&col(&fr.rotation, 1), &[0.0, 0.0, 1.0]));
        assert!(close(&col(&fr.rotation, 2), &[0.0, -1.0, 0.0]));
        // Local (0.1, 0.2, 0.3) -> k R mu + T = 2.5 (0.1, -0.3, 0.2) + T.
        let local = PlyGaussians {
            means: vec![0.1, 0.2, 0.3],
            sh: vec![0.5, -0.25, 0.125],
            sh_degree: 0,
            opacity_logits: vec![0.7],
            log_scales: vec![-1.0, -2.0, -3.0],
            // 90 degrees about local z, not normalised (GaussianAvatars normalises).
            quats: vec![2.0, 0.0, 0.0, 2.0],
        };
        let w = to_world(&local, &[0], &frames).unwrap();
        assert!(close(&w.means, &[5.0 / 3.0 + 0.25, 2.0 - 0.75, 1.0 + 0.5]));
        let ln_k = 2.5f32.ln();
        assert!(close(
            &w.log_scales,
            &[-1.0 + ln_k, -2.0 + ln_k, -3.0 + ln_k]
        ));
        assert_eq!(
            (w.sh.clone(), w.opacity_logits.clone()),
            (local.sh, local.opacity_logits)
        );
        // World rotation R * Rz(90): local x -> R y = z, local y -> R (-x) = -x,
        // local z -> R z = -y.
        let q = Quat::from_xyzw(w.quats[1], w.quats[2], w.quats[3], w.quats[0]);
        let m = GMat3::from_quat(q);
        assert!(close(&m.x_axis.to_array(), &[0.0, 0.0, 1.0]), "{m:?}");
        assert!(close(&m.y_axis.to_array(), &[-1.0, 0.0, 0.0]), "{m:?}");
        assert!(close(&m.z_axis.to_array(), &[0.0, -1.0, 0.0]), "{m:?}");
        assert!((q.length() - 1.0).abs() < 1e-6);
    }

    #[test]
    fn bindings_outside_the_mesh_are_errors() {
        let local = PlyGaussians {
            means: vec![0.0; 6],
            sh: vec![0.0; 6],
            sh_degree: 0,
            opacity_logits: vec![0.0; 2],
            log_scales: vec![0.0; 6],
            quats: vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
        };
        let frames = face_frames(&[[0, 1, 2]], &[[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]);
        let e = to_world(&local, &[0, 1], &frames).unwrap_err().to_string();
        assert!(
            e.contains("Gaussian 1") && e.contains("triangle 1") && e.contains("--head"),
            "{e}"
        );
        let e = to_world(&local, &[0], &frames).unwrap_err().to_string();
        assert!(e.contains("1 bindings for 2"), "{e}");
    }
}
