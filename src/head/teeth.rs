//! GaussianAvatars' teeth: two rows of teeth, each a band of four rings of vertices built
//! from the outer lip rings, added to a FLAME-style model that has no mouth interior.
//!
//! With rings of `n` vertices (FLAME: 15, from GaussianAvatars' `lip_outside_ring_upper`
//! and `lip_outside_ring_lower` vertex lists) this adds `8 n` vertices (120) and
//! `12 (n - 1)` triangles (168). Geometry follows GaussianAvatars: with `d` the mean
//! distance between paired upper and lower lip vertices, the midline of the lips sits
//! `1.5 d` behind the lips at their mean height; the front edges are `0.1 d` above and
//! below it (the lower row `0.4 d` further back), the roots `2 d` further out, and the back
//! rings `d` behind the front. Upper teeth follow the neck joint, lower teeth the jaw;
//! their shape blendshapes are the mean of the paired lip vertices', and expressions,
//! pose correctives and the joint regressor ignore them.
//!
//! Vertex order per row: root, edge, back edge, back root (each ring in lip order); upper
//! row first. UVs: one rectangle per ring in [`TEETH_UV_RECT`] (GaussianAvatars' spot in
//! FLAME's layout), rings in vertex order from top to bottom. GaussianAvatars repeats one
//! ring's `v`; here each ring has its own.
//!
//! The ring lists are FLAME vertex ids and are not shipped: a FLAME licensee stores them in
//! the model `.npz` as `lip_outside_ring_upper` and `lip_outside_ring_lower` (README).

use std::path::Path;

use crate::error::{Error, Result};
use crate::head::model::HeadModel;
use crate::io::npz::Npz;
use crate::mesh::obj::UvMesh;

/// Teeth UV rectangle `[u0, v0, u1, v1]` (GaussianAvatars: u from 0.62 to 0.38,
/// v from 1 - 0.0425 to 1 - 0.0083).
pub const TEETH_UV_RECT: [f32; 4] = [0.38, 1.0 - 0.0425, 0.62, 1.0 - 0.0083];
/// Teeth sit this many lip distances behind the lips.
const DEPTH: f32 = 1.5;
/// Half the gap between the upper and lower front edges, in lip distances.
const GAP: f32 = 0.1;
/// The lower row is this much further back.
const LOWER_BACK: f32 = 0.4;
/// Tooth height (edge to root).
const HEIGHT: f32 = 2.0;
/// Tooth thickness (front to back).
const THICKNESS: f32 = 1.0;

/// The two outer lip rings, in matching order.
#[derive(Clone, Debug, PartialEq)]
pub struct LipRings {
    pub upper: Vec<u32>,
    pub lower: Vec<u32>,
}

impl LipRings {
    /// Reads `lip_outside_ring_upper` and `lip_outside_ring_lower` from a model `.npz`.
    pub fn load(path: &Path) -> Result<Self> {
        let mut z = Npz::open(path)?;
        let what = path.display().to_string();
        let mut ring = |name: &str| -> Result<Vec<u32>> {
            z.ints(name)?
                .data
                .iter()
                .map(|&i| {
                    u32::try_from(i)
                        .map_err(|_| Error::invalid(&what, name, format!("negative index {i}")))
                })
                .collect()
        };
        Ok(LipRings {
            upper: ring("lip_outside_ring_upper")?,
            lower: ring("lip_outside_ring_lower")?,
        })
    }
}

/// Returns `model` (and its UV mesh) with the teeth appended.
pub fn add_teeth(
    model: &HeadModel,
    mesh: Option<&UvMesh>,
    rings: &LipRings,
) -> Result<(HeadModel, Option<UvMesh>)> {
    let what = "teeth";
    let n = rings.upper.len();
    let v0 = model.num_vertices();
    if n < 2 || rings.lower.len() != n {
        return Err(Error::invalid(
            what,
            "lip rings",
            format!(
                "{} upper and {} lower vertices; need two equal rings of at least 2",
                n,
                rings.lower.len()
            ),
        ));
    }
    if let Some(&i) = rings
        .upper
        .iter()
        .chain(&rings.lower)
        .find(|&&i| i as usize >= v0)
    {
        return Err(Error::invalid(
            what,
            "lip rings",
            format!("vertex {i} is not in the model ({v0} vertices)"),
        ));
    }
    let p = |i: u32| glam::Vec3::from(model.v_template[i as usize]);
    let d = rings
        .upper
        .iter()
        .zip(&rings.lower)
        .map(|(&a, &b)| (p(a) - p(b)).length())
        .sum::<f32>()
        / n as f32;
    let mut middle: Vec<glam::Vec3> = rings
        .upper
        .iter()
        .zip(&rings.lower)
        .map(|(&a, &b)| 0.5 * (p(a) + p(b)))
        .collect();
    let mean_y = middle.iter().map(|m| m.y).sum::<f32>() / n as f32;
    for m in &mut middle {
        m.y = mean_y;
        m.z -= DEPTH * d;
    }
    let up = glam::Vec3::Y * d;
    let back = glam::Vec3::Z * d;
    let upper_edge: Vec<_> = middle.iter().map(|&m| m + GAP * up).collect();
    let lower_edge: Vec<_> = middle
        .iter()
        .map(|&m| m - GAP * up - LOWER_BACK * back)
        .collect();
    let ring_sets: [Vec<glam::Vec3>; 8] = [
        upper_edge.iter().map(|&e| e + HEIGHT * up).collect(),
        upper_edge.clone(),
        upper_edge.iter().map(|&e| e - THICKNESS * back).collect(),
        upper_edge
            .iter()
            .map(|&e| e + HEIGHT * up - THICKNESS * back)
            .collect(),
        lower_edge.iter().map(|&e| e - HEIGHT * up).collect(),
        lower_edge.clone(),
        lower_edge.iter().map(|&e| e - THICKNESS * back).collect(),
        lower_edge
            .iter()
            .map(|&e| e - HEIGHT * up - THICKNESS * back)
            .collect(),
    ];
    let added = 8 * n;
    let v1 = v0 + added;
    let k = model.num_shape + model.num_expr;
    let j = model.num_joints();
    let p9 = 9 * j.saturating_sub(1);
    let mut out = model.clone();
    out.v_template
        .extend(ring_sets.iter().flatten().map(|q| q.to_array()));
    // shapedirs: lip mean for shape components, zero for expressions.
    for _ring in 0..8 {
        for i in 0..n {
            let (a, b) = (rings.upper[i] as usize, rings.lower[i] as usize);
            for c in 0..3 {
                for q in 0..k {
                    let val = if q < model.num_shape {
                        0.5 * (model.shapedirs[(a * 3 + c) * k + q]
                            + model.shapedirs[(b * 3 + c) * k + q])
                    } else {
                        0.0
                    };
                    out.shapedirs.push(val);
                }
            }
        }
    }
    out.posedirs
        .extend(std::iter::repeat_n(0.0, added * 3 * p9));
    let mut jr = Vec::with_capacity(j * v1);
    for a in 0..j {
        jr.extend_from_slice(&model.j_regressor[a * v0..(a + 1) * v0]);
        jr.extend(std::iter::repeat_n(0.0, added));
    }
    out.j_regressor = jr;
    for r in 0..8 {
        for _ in 0..n {
            let mut w = vec![0.0f32; j];
            w[if r < 4 { 1 } else { 2 }.min(j - 1)] = 1.0;
            out.weights.extend(w);
        }
    }
    // Faces: three strips per row (root-edge, edge-back edge, back edge-back root).
    let id = |ring: usize, i: usize| (v0 + ring * n + i) as u32;
    let mut new_faces = Vec::with_capacity(12 * (n - 1));
    for row in 0..2 {
        for s in 0..3 {
            let (ra, rb) = (row * 4 + s, row * 4 + s + 1);
            for i in 0..n - 1 {
                let (a, b, c, e) = (id(ra, i), id(ra, i + 1), id(rb, i + 1), id(rb, i));
                if row == 0 {
                    new_faces.push([a, e, c]);
                    new_faces.push([a, c, b]);
                } else {
                    new_faces.push([a, c, e]);
                    new_faces.push([a, b, c]);
                }
            }
        }
    }
    out.faces.extend(&new_faces);
    out.validate(what)?;
    let mesh = mesh.map(|m| {
        let mut m = m.clone();
        let t0 = m.uvs.len() as u32;
        let [u0, va, u1, vb] = TEETH_UV_RECT;
        for r in 0..8 {
            let v = vb - (vb - va) * r as f32 / 7.0;
            for i in 0..n {
                let u = u1 - (u1 - u0) * i as f32 / (n - 1) as f32;
                m.uvs.push([u, v]);
            }
        }
        m.positions = out.v_template.clone();
        m.faces = out.faces.clone();
        m.uv_faces
            .extend(new_faces.iter().map(|f| f.map(|x| x - v0 as u32 + t0)));
        m
    });
    Ok((out, mesh))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::head::{HeadPose, lbs};

    /// A strip of 15 upper and 15 lower lip vertices (an arc), posed by 5 joints.
    fn lips_model() -> (HeadModel, LipRings) {
        let n = 15;
        let mut v = Vec::new();
        for row in 0..2 {
            for i in 0..n {
                let t = i as f32 / (n - 1) as f32 - 0.5;
                v.push([
                    t * 0.05,
                    if row == 0 { 0.005 } else { -0.005 },
                    0.1 - t * t * 0.04,
                ]);
            }
        }
        let nv = v.len();
        let mut weights = vec![0.0; nv * 5];
        for i in 0..nv {
            weights[i * 5 + 1] = 1.0;
        }
        let mut j_regressor = vec![0.0; 5 * nv];
        for a in 0..5 {
            j_regressor[a * nv] = 1.0;
        }
        let model = HeadModel {
            v_template: v,
            shapedirs: (0..nv * 3 * 2).map(|x| x as f32).collect(),
            num_shape: 1,
            num_expr: 1,
            posedirs: vec![0.0; nv * 3 * 36],
            j_regressor,
            weights,
            parents: vec![None, Some(0), Some(1), Some(1), Some(1)],
            faces: vec![[0, 1, 15]],
        };
        let rings = LipRings {
            upper: (0..n as u32).collect(),
            lower: (n as u32..2 * n as u32).collect(),
        };
        (model, rings)
    }

    #[test]
    fn teeth_have_gaussian_avatars_counts_and_layout() {
        let (model, rings) = lips_model();
        let mesh = UvMesh {
            positions: model.v_template.clone(),
            uvs: vec![[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]],
            faces: model.faces.clone(),
            uv_faces: vec![[0, 1, 2]],
        };
        let (t, m) = add_teeth(&model, Some(&mesh), &rings).expect("teeth");
        assert_eq!(t.num_vertices() - model.num_vertices(), 120);
        assert_eq!(t.faces.len() - model.faces.len(), 168);
        let m = m.expect("mesh");
        assert_eq!(m.uvs.len(), 3 + 120);
        assert_eq!(m.uv_faces.len(), m.faces.len());
        // d = 0.01: upper front edge 0.001 above the lips' mean height (0), 0.015 behind.
        let upper_edge_mid = t.v_template[30 + 15 + 7];
        assert!(
            (upper_edge_mid[1] - 0.001).abs() < 1e-6,
            "{upper_edge_mid:?}"
        );
        assert!((upper_edge_mid[2] - (0.1 - 0.015)).abs() < 1e-6);
        // Lower root: 0.02 below the lower edge, which is 0.004 further back.
        let lower_root_mid = t.v_template[30 + 60 + 7];
        assert!((lower_root_mid[1] - (-0.001 - 0.02)).abs() < 1e-6);
        assert!((lower_root_mid[2] - (0.1 - 0.015 - 0.004)).abs() < 1e-6);
        // Shape blendshape = mean of the lip pair's, expression blendshape zero.
        let k = 2;
        let (a, b, ti) = (7usize, 22usize, 30 + 7);
        let want = 0.5 * (model.shapedirs[a * 3 * k] + model.shapedirs[b * 3 * k]);
        assert_eq!(t.shapedirs[ti * 3 * k], want);
        assert_eq!(t.shapedirs[ti * 3 * k + 1], 0.0);
        // Lower teeth follow the jaw, upper the neck.
        let mut pose = HeadPose::neutral(&t);
        pose.jaw = [0.3, 0.0, 0.0];
        let posed = lbs(&t, &pose).expect("lbs");
        let rest = lbs(&t, &HeadPose::neutral(&t)).expect("lbs");
        assert_eq!(posed[30 + 7], rest[30 + 7]);
        assert_ne!(posed[30 + 60 + 7], rest[30 + 60 + 7]);
    }

    #[test]
    fn bad_rings_are_rejected() {
        let (model, mut rings) = lips_model();
        rings.lower.pop();
        let e = add_teeth(&model, None, &rings).unwrap_err().to_string();
        assert!(e.contains("lip rings"), "{e}");
        let (model, mut rings) = lips_model();
        rings.upper[0] = 999;
        let e = add_teeth(&model, None, &rings).unwrap_err().to_string();
        assert!(e.contains("999"), "{e}");
    }
}
