//! Renders one view of a posed head: the CPU z-buffer rasterizer at `supersample^2`
//! samples per pixel, perspective-correct UVs into the baked maps, Lambert + Blinn-Phong
//! specular + ambient under two lights fixed in the world, white background; the image and
//! the foreground mask are the box-filtered samples.

use glam::Vec3;

use crate::camera::Camera;
use crate::mesh::UvMesh;
use crate::mesh::raster::rasterize;
use crate::synth::appearance::{Appearance, WRINKLES};

/// Ambient light.
const AMBIENT: f32 = 0.32;
/// Key and fill lights: direction towards the light (world), intensity.
const LIGHTS: [([f32; 3], f32); 2] = [([0.45, 0.55, 1.0], 0.72), ([-0.7, 0.1, 0.7], 0.28)];
/// Blinn-Phong exponent.
const SHININESS: f32 = 40.0;

/// One rendered view: RGB [H, W, 3] and mask [H, W], both in [0, 1].
pub struct View {
    pub rgb: Vec<f32>,
    pub mask: Vec<f32>,
}

/// Per-vertex normals (area-weighted face normals).
pub fn vertex_normals(vertices: &[[f32; 3]], faces: &[[u32; 3]]) -> Vec<Vec3> {
    let mut n = vec![Vec3::ZERO; vertices.len()];
    for f in faces {
        let p = f.map(|i| Vec3::from(vertices[i as usize]));
        let fnrm = (p[1] - p[0]).cross(p[2] - p[0]);
        for &i in f {
            n[i as usize] += fnrm;
        }
    }
    n.into_iter().map(Vec3::normalize_or_zero).collect()
}

/// Renders `vertices` (posed, world space) with `mesh`'s faces and UVs (its positions are
/// not used) into `camera`'s image.
pub fn render(
    camera: &Camera,
    supersample: u32,
    vertices: &[[f32; 3]],
    mesh: &UvMesh,
    appearance: &Appearance,
    act: &[f32; WRINKLES],
    strength: f32,
) -> View {
    let s = supersample.max(1);
    let (faces, uvs, uv_faces) = (&mesh.faces, &mesh.uvs, &mesh.uv_faces);
    let mut big = *camera;
    big.width *= s;
    big.height *= s;
    big.fx *= s as f32;
    big.fy *= s as f32;
    big.cx *= s as f32;
    big.cy *= s as f32;
    let frags = rasterize(&big, vertices, faces);
    let normals = vertex_normals(vertices, faces);
    let eye = Vec3::from(camera.position());
    let lights: Vec<(Vec3, f32)> = LIGHTS
        .iter()
        .map(|(d, i)| (Vec3::from(*d).normalize(), *i))
        .collect();
    let (w, h) = (camera.width as usize, camera.height as usize);
    let (bw, bh) = (w * s as usize, h * s as usize);
    let mut rgb = vec![0.0f32; w * h * 3];
    let mut mask = vec![0.0f32; w * h];
    let norm = 1.0 / (s * s) as f32;
    for by in 0..bh {
        for bx in 0..bw {
            let k = by * bw + bx;
            let o = (by / s as usize) * w + bx / s as usize;
            let Some(f) = frags.face[k] else {
                for c in 0..3 {
                    rgb[o * 3 + c] += norm;
                }
                continue;
            };
            let b = frags.bary[k];
            let fv = faces[f as usize];
            let ft = uv_faces[f as usize];
            let p: Vec3 = (0..3)
                .map(|c| b[c] * Vec3::from(vertices[fv[c] as usize]))
                .sum();
            let mut nrm: Vec3 = (0..3)
                .map(|c| b[c] * normals[fv[c] as usize])
                .sum::<Vec3>()
                .normalize_or_zero();
            let view = (eye - p).normalize_or_zero();
            if nrm.dot(view) < 0.0 {
                nrm = -nrm; // two-sided: the inside of the mouth, thin parts
            }
            let uv: [f32; 2] =
                std::array::from_fn(|a| (0..3).map(|c| b[c] * uvs[ft[c] as usize][a]).sum());
            let (alb, spec, wr) = appearance.sample(uv, act);
            let dark = 1.0 - strength * wr;
            let mut diffuse = AMBIENT;
            let mut specular = 0.0;
            for &(l, i) in &lights {
                let nl = nrm.dot(l).max(0.0);
                diffuse += i * nl;
                if nl > 0.0 {
                    let hv = (l + view).normalize_or_zero();
                    specular += i * nrm.dot(hv).max(0.0).powf(SHININESS);
                }
            }
            let spec = spec * (1.0 - 0.8 * wr);
            for c in 0..3 {
                let v = alb[c] * dark * diffuse + spec * specular;
                rgb[o * 3 + c] += norm * v.min(1.0);
            }
            mask[o] += norm;
        }
    }
    View { rgb, mask }
}
