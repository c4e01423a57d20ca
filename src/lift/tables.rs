//! Flat index tables of a topology for the GPU lifting: per-row frame indices, corners and
//! barycentrics, the bilinear taps, and CSR lists that turn every scatter-add of the
//! backward into a deterministic gather (`kernels/gpu/src/lift/csr_gather.rs`).

use crate::kernels::lift::transform::NO_FRAME;
use crate::lift::Topology;

/// A CSR list: for target `t`, entries `offsets[t]..offsets[t + 1]` of `entries`/`weights`.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Csr {
    pub offsets: Vec<u32>,
    pub entries: Vec<u32>,
    pub weights: Vec<f32>,
}

impl Csr {
    /// Groups `(target, entry, weight)` triples by target, keeping their order within a
    /// target (so sums run in a fixed order).
    pub fn new(targets: usize, triples: impl Iterator<Item = (u32, u32, f32)> + Clone) -> Self {
        let mut counts = vec![0u32; targets + 1];
        for (t, _, _) in triples.clone() {
            counts[t as usize + 1] += 1;
        }
        for t in 0..targets {
            counts[t + 1] += counts[t];
        }
        let total = counts[targets] as usize;
        let mut cursor = counts.clone();
        let mut entries = vec![0u32; total];
        let mut weights = vec![0.0f32; total];
        for (t, e, w) in triples {
            let c = &mut cursor[t as usize];
            entries[*c as usize] = e;
            weights[*c as usize] = w;
            *c += 1;
        }
        Csr {
            offsets: counts,
            entries,
            weights,
        }
    }
}

/// Everything the GPU lifting reads besides the inputs.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct GpuTables {
    /// [F, 3].
    pub faces: Vec<u32>,
    /// Per texel: its face (`NO_FRAME` where uncovered), corners [R*R, 3], barycentrics.
    pub texel_frame: Vec<u32>,
    pub texel_corners: Vec<u32>,
    pub texel_bary: Vec<f32>,
    /// Per sample: taps and weights [N, 4]; face, corners [N, 3], barycentrics [N, 3].
    pub taps: Vec<u32>,
    pub tap_weights: Vec<f32>,
    pub sample_frame: Vec<u32>,
    pub sample_corners: Vec<u32>,
    pub sample_bary: Vec<f32>,
    /// Texel ← (sample, bilinear weight).
    pub texel_from_samples: Csr,
    /// Face ← covered texels; face ← samples (weight 1).
    pub face_from_texels: Csr,
    pub face_from_samples: Csr,
    /// Vertex ← (texel, barycentric weight); vertex ← (sample, barycentric weight).
    pub vertex_from_texels: Csr,
    pub vertex_from_samples: Csr,
    /// Vertex ← face corner `3 f + k` (weight 1).
    pub vertex_from_corners: Csr,
}

impl GpuTables {
    pub fn new(t: &Topology) -> Self {
        let layout = &t.layout;
        let s = &t.samples;
        let rr = layout.res * layout.res;
        let n = s.len();
        let num_faces = t.faces.len();
        let v = t.num_vertices;
        let sample_corners: Vec<[u32; 3]> = s.face.iter().map(|&f| t.faces[f as usize]).collect();
        GpuTables {
            faces: t.faces.concat(),
            texel_frame: layout.face.iter().map(|f| f.unwrap_or(NO_FRAME)).collect(),
            texel_corners: layout.verts.concat(),
            texel_bary: layout.bary.concat(),
            taps: s.taps.concat(),
            tap_weights: s.weights.concat(),
            sample_frame: s.face.clone(),
            sample_corners: sample_corners.concat(),
            sample_bary: s.bary.concat(),
            texel_from_samples: Csr::new(
                rr,
                (0..n).flat_map(|k| {
                    (0..4)
                        .filter(move |&q| s.weights[k][q] != 0.0)
                        .map(move |q| (s.taps[k][q], k as u32, s.weights[k][q]))
                }),
            ),
            face_from_texels: Csr::new(
                num_faces,
                (0..rr).filter_map(|x| layout.face[x].map(|f| (f, x as u32, 1.0))),
            ),
            face_from_samples: Csr::new(
                num_faces,
                s.face.iter().enumerate().map(|(k, &f)| (f, k as u32, 1.0)),
            ),
            vertex_from_texels: Csr::new(
                v,
                (0..rr).filter(|&x| layout.face[x].is_some()).flat_map(|x| {
                    (0..3).map(move |k| (layout.verts[x][k], x as u32, layout.bary[x][k]))
                }),
            ),
            vertex_from_samples: Csr::new(
                v,
                sample_corners
                    .iter()
                    .zip(&s.bary)
                    .enumerate()
                    .flat_map(|(k, (c, b))| (0..3).map(move |q| (c[q], k as u32, b[q]))),
            ),
            vertex_from_corners: Csr::new(
                v,
                t.faces
                    .iter()
                    .enumerate()
                    .flat_map(|(f, c)| (0..3).map(move |k| (c[k], (3 * f + k) as u32, 1.0))),
            ),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn csr_groups_in_order() {
        let c = Csr::new(
            3,
            [(2u32, 7u32, 0.5f32), (0, 1, 1.0), (2, 3, 2.0)].into_iter(),
        );
        assert_eq!(c.offsets, vec![0, 1, 1, 3]);
        assert_eq!(c.entries, vec![1, 7, 3]);
        assert_eq!(c.weights, vec![1.0, 0.5, 2.0]);
    }
}
