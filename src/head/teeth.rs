//! Teeth as VHAP adds them to FLAME (`vhap/model/flame.py`, `FlameHead.add_teeth`;
//! GaussianAvatars builds its FLAME with VHAP's `add_teeth=True`): two rows of teeth, each
//! a band of four rings of vertices built from the outer lip rings, appended to a
//! FLAME-style model that has no mouth interior.
//!
//! VHAP's tracked data stores per-vertex arrays (`static_offset`: 5023 FLAME + 120 teeth
//! vertices) in VHAP's vertex order, so the teeth here are vertex for vertex, face for face
//! and UV for UV VHAP's.
//!
//! With rings of `n` vertices (FLAME: 15, from the `lip_outside_ring_upper` and
//! `lip_outside_ring_lower` vertex lists) this adds `8 n` vertices (120) and `12 (n - 1)`
//! triangles (168). With `d` the mean distance between paired upper and lower lip vertices,
//! the midline sits `1.5 d` behind the lips' midpoints at their mean height; the front edges
//! are `0.1 d` above and below it (the lower row `0.4 d` further back), the roots `2 d`
//! further out, and the back rings `d` behind the front (in `-z`).
//!
//! - **Vertices**: eight rings of `n` in lip order, in VHAP's order: upper root, lower root,
//!   upper edge, lower edge, upper root back, upper edge back, lower root back, lower edge
//!   back ([`RING_NAMES`]). The upper teeth are rings 0, 2, 4, 5, the lower 1, 3, 6, 7.
//! - **Faces**: per row three strips between two rings (front, back, and the biting edge
//!   joining them), `n - 1` quads each, each quad two triangles; the quad's diagonal flips at
//!   the middle quad so that each strip is mirror symmetric. Upper row first, then lower.
//!   Corner order inside each triangle is VHAP's (the per-face frames depend on it).
//! - **UVs**: teeth vertex `k` has UV vertex `k` (appended after the mesh's own): `u` runs
//!   from 0.62 to 0.38 along the ring, `v` takes one of seven values from `1 - 0.0083` to
//!   `1 - 0.0425` per ring ([`RING_V`]); a teeth face's UV indices are its vertex indices
//!   counted from the first teeth vertex, plus the mesh's earlier UV count.
//! - **Blendshapes and skinning**: shape blendshapes are the mean of the paired lip
//!   vertices'; expressions, pose correctives and the joint regressor ignore the teeth. Upper
//!   teeth follow the neck joint (1), lower teeth the jaw (2).
//!
//! The ring lists are FLAME vertex ids and are not shipped: a FLAME licensee stores them in
//! the model `.npz` as `lip_outside_ring_upper` and `lip_outside_ring_lower` (`docs/captures.md`).
//! `texavatars head add-teeth` writes a model with teeth and marks it with
//! [`TEETH_MARKER`], so that teeth are never added twice.

use std::path::Path;

use crate::error::{Error, Result};
use crate::head::model::HeadModel;
use crate::io::npz::Npz;
use crate::mesh::obj::UvMesh;

/// The array a model with teeth carries: `[number of teeth vertices]`.
pub const TEETH_MARKER: &str = "teeth_vertices";
/// The eight rings in vertex order (VHAP's `v_teeth_*`).
pub const RING_NAMES: [&str; 8] = [
    "upper_root",
    "lower_root",
    "upper_edge",
    "lower_edge",
    "upper_root_back",
    "upper_edge_back",
    "lower_root_back",
    "lower_edge_back",
];
const UPPER_ROOT: usize = 0;
const LOWER_ROOT: usize = 1;
const UPPER_EDGE: usize = 2;
const LOWER_EDGE: usize = 3;
const UPPER_ROOT_BACK: usize = 4;
const UPPER_EDGE_BACK: usize = 5;
const LOWER_ROOT_BACK: usize = 6;
const LOWER_EDGE_BACK: usize = 7;
/// The rings of the upper teeth (the rest are the lower teeth's).
pub const UPPER_RINGS: [usize; 4] = [UPPER_ROOT, UPPER_EDGE, UPPER_ROOT_BACK, UPPER_EDGE_BACK];
/// The rings of the lower teeth.
pub const LOWER_RINGS: [usize; 4] = [LOWER_ROOT, LOWER_EDGE, LOWER_ROOT_BACK, LOWER_EDGE_BACK];

/// `u` at the first and the last vertex of a ring.
pub const TEETH_U: [f32; 2] = [0.62, 0.38];
/// The range of the seven `v` values, first to last.
pub const TEETH_V: [f32; 2] = [1.0 - 0.0083, 1.0 - 0.0425];
/// Which of the seven `v` values each ring takes.
pub const RING_V: [usize; 8] = [3, 2, 0, 1, 3, 4, 6, 5];

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

/// A quad's two triangles over its corners `[A_i, A_i+1, B_i, B_i+1]` (indices 0..4) of a
/// strip between rings A and B.
type Quad = [[usize; 3]; 2];
/// Diagonal from `A_i` to `B_i+1`.
const DIAG_AB1: Quad = [[0, 3, 2], [0, 1, 3]];
/// Diagonal from `A_i+1` to `B_i`.
const DIAG_A1B: Quad = [[0, 1, 2], [1, 3, 2]];

/// The same triangles wound the other way (last two corners swapped).
const fn flip(q: Quad) -> Quad {
    [[q[0][0], q[0][2], q[0][1]], [q[1][0], q[1][2], q[1][1]]]
}

/// The six strips in face order: rings A and B, the quad for the first half of the strip
/// (quads `i < (n - 1) / 2`) and for the second.
const STRIPS: [(usize, usize, Quad, Quad); 6] = [
    (UPPER_ROOT, UPPER_EDGE, DIAG_AB1, DIAG_A1B),
    (
        UPPER_ROOT_BACK,
        UPPER_EDGE_BACK,
        flip(DIAG_AB1),
        flip(DIAG_A1B),
    ),
    (UPPER_EDGE_BACK, UPPER_EDGE, flip(DIAG_A1B), flip(DIAG_AB1)),
    (LOWER_EDGE, LOWER_ROOT, DIAG_A1B, DIAG_AB1),
    (LOWER_ROOT_BACK, LOWER_EDGE_BACK, DIAG_AB1, DIAG_A1B),
    (LOWER_EDGE_BACK, LOWER_EDGE, DIAG_A1B, DIAG_AB1),
];

/// The teeth triangles for rings of `n`, as indices from the first teeth vertex.
pub fn teeth_faces(n: usize) -> Vec<[u32; 3]> {
    let id = |ring: usize, i: usize| (ring * n + i) as u32;
    let middle = (n - 1) / 2;
    let mut faces = Vec::with_capacity(12 * (n - 1));
    for (a, b, first, second) in STRIPS {
        for i in 0..n - 1 {
            let corners = [id(a, i), id(a, i + 1), id(b, i), id(b, i + 1)];
            let quad = if i < middle { first } else { second };
            faces.extend(quad.map(|t| t.map(|c| corners[c])));
        }
    }
    faces
}

/// The teeth UVs for rings of `n`, one per teeth vertex.
pub fn teeth_uvs(n: usize) -> Vec<[f32; 2]> {
    let lerp = |[a, b]: [f32; 2], t: f64| (a as f64 + (b as f64 - a as f64) * t) as f32;
    let mut uvs = Vec::with_capacity(8 * n);
    for k in RING_V {
        let v = lerp(TEETH_V, k as f64 / 6.0);
        uvs.extend((0..n).map(|i| [lerp(TEETH_U, i as f64 / (n - 1) as f64), v]));
    }
    uvs
}

/// The two outer lip rings, in matching order.
#[derive(Clone, Debug, PartialEq)]
pub struct LipRings {
    pub upper: Vec<u32>,
    pub lower: Vec<u32>,
}

impl LipRings {
    /// Reads `lip_outside_ring_upper` and `lip_outside_ring_lower` from a model `.npz`;
    /// refuses a model that already has teeth ([`TEETH_MARKER`]).
    pub fn load(path: &Path) -> Result<Self> {
        let mut z = Npz::open(path)?;
        let what = path.display().to_string();
        if z.has(TEETH_MARKER) {
            return Err(Error::invalid(
                &what,
                TEETH_MARKER,
                "the model already has teeth (written by `texavatars head add-teeth`)",
            ));
        }
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

/// Returns `model` (and its UV mesh) with the teeth appended (see the module docs).
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
    let j = model.num_joints();
    if j < 3 {
        return Err(Error::invalid(
            what,
            "kintree_table",
            format!(
                "teeth follow the neck (joint 1) and the jaw (joint 2); the model has {j} joints"
            ),
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
    // Offsets from the midline, per ring in vertex order.
    let upper_edge = GAP * up;
    let lower_edge = -GAP * up - LOWER_BACK * back;
    let mut offset = [glam::Vec3::ZERO; 8];
    offset[UPPER_EDGE] = upper_edge;
    offset[UPPER_ROOT] = upper_edge + HEIGHT * up;
    offset[LOWER_EDGE] = lower_edge;
    offset[LOWER_ROOT] = lower_edge - HEIGHT * up;
    for (b, f) in [
        (UPPER_ROOT_BACK, UPPER_ROOT),
        (UPPER_EDGE_BACK, UPPER_EDGE),
        (LOWER_ROOT_BACK, LOWER_ROOT),
        (LOWER_EDGE_BACK, LOWER_EDGE),
    ] {
        offset[b] = offset[f] - THICKNESS * back;
    }

    let added = 8 * n;
    let v1 = v0 + added;
    let k = model.num_shape + model.num_expr;
    let p9 = 9 * (j - 1);
    let mut out = model.clone();
    for o in offset {
        out.v_template
            .extend(middle.iter().map(|&m| (m + o).to_array()));
    }
    // shapedirs: the lip pair's mean for shape components, zero for expressions.
    for _ring in 0..8 {
        for i in 0..n {
            let (a, b) = (rings.upper[i] as usize, rings.lower[i] as usize);
            for c in 0..3 {
                let (sa, sb) = ((a * 3 + c) * k, (b * 3 + c) * k);
                out.shapedirs.extend((0..k).map(|q| {
                    if q < model.num_shape {
                        0.5 * (model.shapedirs[sa + q] + model.shapedirs[sb + q])
                    } else {
                        0.0
                    }
                }));
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
        let joint = if UPPER_RINGS.contains(&r) { 1 } else { 2 };
        for _ in 0..n {
            out.weights
                .extend((0..j).map(|q| if q == joint { 1.0 } else { 0.0 }));
        }
    }
    let local = teeth_faces(n);
    out.faces
        .extend(local.iter().map(|f| f.map(|x| x + v0 as u32)));
    out.validate(what)?;
    let mesh = mesh.map(|m| {
        let mut m = m.clone();
        let t0 = m.uvs.len() as u32;
        m.uvs.extend(teeth_uvs(n));
        m.positions = out.v_template.clone();
        m.faces = out.faces.clone();
        m.uv_faces.extend(local.iter().map(|f| f.map(|x| x + t0)));
        m
    });
    Ok((out, mesh))
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::head::{HeadPose, lbs};

    /// A strip of 15 upper and 15 lower lip vertices (an arc: x = 0.05 t, y = +-0.005,
    /// z = 0.1 - 0.04 t^2 for t from -0.5 to 0.5), triangulated between the two, posed by 5
    /// joints (all at vertex 0, the lips skinned to the neck); its UV mesh has one UV per
    /// vertex and one more. Two shape and one expression components, `shapedirs[x] = x`.
    pub(crate) fn lips_model() -> (HeadModel, UvMesh, LipRings) {
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
        let faces: Vec<[u32; 3]> = (0..n as u32 - 1)
            .flat_map(|i| [[i, i + 1, i + 15], [i + 1, i + 16, i + 15]])
            .collect();
        let mesh = UvMesh {
            positions: v.clone(),
            uvs: v
                .iter()
                .map(|p| [p[0] + 0.5, p[1] + 0.5])
                .chain([[0.0, 0.0]])
                .collect(),
            faces: faces.clone(),
            uv_faces: faces.clone(),
        };
        let model = HeadModel {
            v_template: v,
            shapedirs: (0..nv * 3 * 3).map(|x| x as f32).collect(),
            num_shape: 2,
            num_expr: 1,
            posedirs: vec![0.5; nv * 3 * 36],
            j_regressor,
            weights,
            parents: vec![None, Some(0), Some(1), Some(1), Some(1)],
            faces,
        };
        let rings = LipRings {
            upper: (0..n as u32).collect(),
            lower: (n as u32..2 * n as u32).collect(),
        };
        (model, mesh, rings)
    }

    fn with_teeth() -> (HeadModel, HeadModel, UvMesh) {
        let (model, mesh, rings) = lips_model();
        let (t, m) = add_teeth(&model, Some(&mesh), &rings).expect("teeth");
        (model, t, m.expect("mesh"))
    }

    /// VHAP (`vhap/model/flame.py`, `FlameHead.add_teeth`) concatenates `v_teeth_upper_root,
    /// v_teeth_lower_root, v_teeth_upper_edge, v_teeth_lower_edge, v_teeth_upper_root_back,
    /// v_teeth_upper_edge_back, v_teeth_lower_root_back, v_teeth_lower_edge_back`.
    #[test]
    fn teeth_vertices_are_in_vhaps_ring_order() {
        let (model, t, _) = with_teeth();
        assert_eq!(t.num_vertices(), 30 + 120);
        // d = 0.01 (lips 0.01 apart), midline at y = 0 and 0.015 behind the lips. Per ring:
        // (y, z offset from the lips): edges at y = +-0.001, roots 0.02 further out; the
        // lower row 0.004 further back; the back rings 0.01 further back.
        let want: [(&str, f32, f32); 8] = [
            ("upper_root", 0.021, -0.015),
            ("lower_root", -0.021, -0.019),
            ("upper_edge", 0.001, -0.015),
            ("lower_edge", -0.001, -0.019),
            ("upper_root_back", 0.021, -0.025),
            ("upper_edge_back", 0.001, -0.025),
            ("lower_root_back", -0.021, -0.029),
            ("lower_edge_back", -0.001, -0.029),
        ];
        for (r, (name, y, dz)) in want.iter().enumerate() {
            assert_eq!(RING_NAMES[r], *name);
            for i in 0..15 {
                let lip = model.v_template[i];
                let got = t.v_template[30 + r * 15 + i];
                let expect = [lip[0], *y, lip[2] + dz];
                for c in 0..3 {
                    assert!(
                        (got[c] - expect[c]).abs() < 1e-6,
                        "{name} vertex {i}: {got:?} vs {expect:?}"
                    );
                }
            }
        }
    }

    /// Faces of VHAP's `f_teeth_upper` then `f_teeth_lower` (`vhap/model/flame.py`,
    /// `FlameHead.add_teeth`), copied by hand: quads 0, 6, 7 and 13 of each strip, as
    /// (position in the concatenated list, the `# k` comment next to it in VHAP, triangle).
    const VHAP_FACES: [(usize, usize, [u32; 3]); 48] = [
        // upper root - upper edge
        (0, 0, [0, 31, 30]),
        (1, 1, [0, 1, 31]),
        (12, 12, [6, 37, 36]),
        (13, 13, [6, 7, 37]),
        (14, 14, [7, 8, 37]),
        (15, 15, [8, 38, 37]),
        (26, 26, [13, 14, 43]),
        (27, 27, [14, 44, 43]),
        // upper root back - upper edge back
        (28, 56, [60, 75, 76]),
        (29, 57, [60, 76, 61]),
        (40, 68, [66, 81, 82]),
        (41, 69, [66, 82, 67]),
        (42, 70, [67, 82, 68]),
        (43, 71, [68, 82, 83]),
        (54, 82, [73, 88, 74]),
        (55, 83, [74, 88, 89]),
        // upper edge back - upper edge
        (56, 84, [75, 30, 76]),
        (57, 85, [76, 30, 31]),
        (68, 96, [81, 36, 82]),
        (69, 97, [82, 36, 37]),
        (70, 98, [82, 37, 38]),
        (71, 99, [82, 38, 83]),
        (82, 110, [88, 43, 44]),
        (83, 111, [88, 44, 89]),
        // lower edge - lower root
        (84, 28, [45, 46, 15]),
        (85, 29, [46, 16, 15]),
        (96, 40, [51, 52, 21]),
        (97, 41, [52, 22, 21]),
        (98, 42, [52, 23, 22]),
        (99, 43, [52, 53, 23]),
        (110, 54, [58, 29, 28]),
        (111, 55, [58, 59, 29]),
        // lower root back - lower edge back
        (112, 112, [90, 106, 105]),
        (113, 113, [90, 91, 106]),
        (124, 124, [96, 112, 111]),
        (125, 125, [96, 97, 112]),
        (126, 126, [97, 98, 112]),
        (127, 127, [98, 113, 112]),
        (138, 138, [103, 104, 118]),
        (139, 139, [104, 119, 118]),
        // lower edge back - lower edge
        (140, 140, [105, 106, 45]),
        (141, 141, [106, 46, 45]),
        (152, 152, [111, 112, 51]),
        (153, 153, [112, 52, 51]),
        (154, 154, [112, 53, 52]),
        (155, 155, [112, 113, 53]),
        (166, 166, [118, 59, 58]),
        (167, 167, [118, 119, 59]),
    ];

    #[test]
    fn teeth_faces_are_vhaps_with_its_corner_order() {
        let faces = teeth_faces(15);
        assert_eq!(faces.len(), 168);
        for (pos, comment, want) in VHAP_FACES {
            assert_eq!(faces[pos], want, "VHAP face {pos} (# {comment})");
        }
        // Appended after the model's faces, offset by its vertex count.
        let (model, t, mesh) = with_teeth();
        let f0 = model.faces.len();
        assert_eq!(t.faces.len(), f0 + 168);
        assert_eq!(t.faces[f0 + 99], [30 + 52, 30 + 53, 30 + 23]);
        assert_eq!(mesh.faces, t.faces);
        // Every teeth vertex is used; each strip is mirror symmetric: quad i mirrored
        // (ring index j -> 14 - j) is quad 13 - i.
        let mut used = [false; 120];
        faces
            .iter()
            .flatten()
            .for_each(|&x| used[x as usize] = true);
        assert!(used.iter().all(|&u| u));
        let quad = |s: usize, i: usize, mirror: bool| {
            let mut q: Vec<[u32; 3]> = faces[s * 28 + 2 * i..][..2]
                .iter()
                .map(|f| {
                    let mut f = f.map(|x| if mirror { x / 15 * 15 + 14 - x % 15 } else { x });
                    f.sort_unstable();
                    f
                })
                .collect();
            q.sort_unstable();
            q
        };
        for s in 0..6 {
            for i in 0..14 {
                assert_eq!(
                    quad(s, i, true),
                    quad(s, 13 - i, false),
                    "strip {s} quad {i}"
                );
            }
        }
    }

    /// VHAP (`vhap/model/flame.py`, `FlameHead.add_teeth`): `u = linspace(0.62, 0.38, 15)`,
    /// `v = linspace(1 - 0.0083, 1 - 0.0425, 7)[[3, 2, 0, 1, 3, 4, 6, 5]]`, UV vertex k is
    /// teeth vertex k's, and `textures_idx` gets the teeth faces offset by the UV count.
    #[test]
    fn teeth_uvs_are_vhaps() {
        let (model, t, mesh) = with_teeth();
        let t0 = 31;
        assert_eq!(mesh.uvs.len(), t0 + 120);
        let step = (0.0425 - 0.0083) / 6.0;
        let want = [
            (0, [0.62, 1.0 - 0.0083 - 3.0 * step]),  // upper root 0
            (29, [0.38, 1.0 - 0.0083 - 2.0 * step]), // lower root 14
            (37, [0.5, 1.0 - 0.0083]),               // upper edge 7
            (46, [0.62 - 0.24 / 14.0, 1.0 - 0.0083 - step]), // lower edge 1
            (67, [0.5, 1.0 - 0.0083 - 3.0 * step]),  // upper root back 7
            (89, [0.38, 1.0 - 0.0083 - 4.0 * step]), // upper edge back 14
            (90, [0.62, 1.0 - 0.0425]),              // lower root back 0
            (119, [0.38, 1.0 - 0.0083 - 5.0 * step]), // lower edge back 14
        ];
        for (k, uv) in want {
            let got = mesh.uvs[t0 + k];
            assert!(
                (got[0] - uv[0]).abs() < 1e-6 && (got[1] - uv[1]).abs() < 1e-6,
                "teeth UV {k}: {got:?} vs {uv:?}"
            );
        }
        let f0 = model.faces.len();
        for (f, tf) in t.faces[f0..].iter().zip(&mesh.uv_faces[f0..]) {
            assert_eq!(*tf, f.map(|x| x - 30 + t0 as u32));
        }
        assert_eq!(mesh.uv_faces[..f0], model.faces[..]);
    }

    /// VHAP (`vhap/model/flame.py`, `FlameHead.add_teeth`): shapedirs of every teeth vertex
    /// the mean of its lip pair's shape components, expressions zero; posedirs and
    /// J_regressor zero; `lbs_weights` 1 on the neck (upper) or the jaw (lower).
    #[test]
    fn teeth_blendshapes_and_skinning_are_vhaps() {
        let (model, t, _) = with_teeth();
        let k = 3;
        for r in 0..8 {
            for i in [0, 7, 14] {
                let ti = 30 + r * 15 + i;
                for c in 0..3 {
                    let (a, b) = ((i * 3 + c) * k, ((15 + i) * 3 + c) * k);
                    for q in 0..2 {
                        let want = 0.5 * (model.shapedirs[a + q] + model.shapedirs[b + q]);
                        assert_eq!(t.shapedirs[(ti * 3 + c) * k + q], want, "{ti} {c} {q}");
                    }
                    assert_eq!(t.shapedirs[(ti * 3 + c) * k + 2], 0.0);
                }
            }
        }
        assert_eq!(t.shapedirs[..model.shapedirs.len()], model.shapedirs[..]);
        let pd = model.posedirs.len();
        assert_eq!(t.posedirs[..pd], model.posedirs[..]);
        assert!(t.posedirs[pd..].iter().all(|&x| x == 0.0));
        for a in 0..5 {
            let row = &t.j_regressor[a * 150..(a + 1) * 150];
            assert_eq!(row[..30], model.j_regressor[a * 30..(a + 1) * 30]);
            assert!(row[30..].iter().all(|&x| x == 0.0));
        }
        for r in 0..8 {
            let joint = if [0, 2, 4, 5].contains(&r) { 1 } else { 2 };
            for i in 0..15 {
                let w = &t.weights[(30 + r * 15 + i) * 5..][..5];
                let want: Vec<f32> = (0..5).map(|q| (q == joint) as u8 as f32).collect();
                assert_eq!(w, &want[..], "ring {r} vertex {i}");
            }
        }
        // Lower teeth move with the jaw, upper teeth do not.
        let mut pose = HeadPose::neutral(&t);
        pose.jaw = [0.3, 0.0, 0.0];
        let posed = lbs(&t, &pose).expect("lbs");
        let rest = lbs(&t, &HeadPose::neutral(&t)).expect("lbs");
        for r in 0..8 {
            let v = 30 + r * 15 + 7;
            if LOWER_RINGS.contains(&r) {
                assert_ne!(posed[v], rest[v], "ring {r}");
            } else {
                assert_eq!(posed[v], rest[v], "ring {r}");
            }
        }
    }

    #[test]
    fn bad_rings_are_rejected() {
        let (model, _, mut rings) = lips_model();
        rings.lower.pop();
        let e = add_teeth(&model, None, &rings).unwrap_err().to_string();
        assert!(e.contains("lip rings"), "{e}");
        let (model, _, mut rings) = lips_model();
        rings.upper[0] = 999;
        let e = add_teeth(&model, None, &rings).unwrap_err().to_string();
        assert!(e.contains("999"), "{e}");
    }
}
