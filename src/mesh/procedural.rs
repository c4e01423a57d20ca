//! Procedural meshes with UV layouts, for tests, benchmarks and demos.

use crate::mesh::UvMesh;

impl UvMesh {
    /// An `m x m` grid of quads on a cylinder patch (radius 1, 1.2 rad wide, height 1), UVs
    /// on a grid in `[0.05, 0.95]^2`, two triangles per quad with alternating diagonals. At
    /// `m = 70` it has 9800 faces, about FLAME's 9976.
    pub fn cylinder_patch(m: usize) -> UvMesh {
        let m = m.max(1);
        let mut mesh = UvMesh::default();
        for j in 0..=m {
            for i in 0..=m {
                let (s, t) = (i as f32 / m as f32, j as f32 / m as f32);
                let theta = 1.2 * (s - 0.5);
                mesh.positions.push([theta.sin(), t - 0.5, theta.cos()]);
                mesh.uvs.push([0.05 + 0.9 * s, 0.05 + 0.9 * t]);
            }
        }
        let id = |i: usize, j: usize| (j * (m + 1) + i) as u32;
        for j in 0..m {
            for i in 0..m {
                let (a, b, c, d) = (id(i, j), id(i + 1, j), id(i + 1, j + 1), id(i, j + 1));
                let tris = if (i + j) % 2 == 0 {
                    [[a, b, c], [a, c, d]]
                } else {
                    [[a, b, d], [b, c, d]]
                };
                for t in tris {
                    mesh.faces.push(t);
                    mesh.uv_faces.push(t);
                }
            }
        }
        mesh
    }
}
