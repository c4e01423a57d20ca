//! A small procedural scene for `texavatars splat demo`: a head-like ellipsoid of
//! Gaussians (skin, two eyes, brows, lips) seen by a NeRSemble-like frontal camera.
//! Deterministic: the same seed gives the same file.

use crate::camera::{Camera, CameraFile};
use crate::splat::ply::PlyGaussians;
use crate::splat::sh::C0;
use crate::util::rng::Pcg;

/// The demo camera: 550 x 802 (W x H, NeRSemble's size), 1.2 units in front of the head.
pub fn camera() -> CameraFile {
    CameraFile {
        camera: Camera {
            width: 550,
            height: 802,
            fx: 1400.0,
            fy: 1400.0,
            cx: 275.0,
            cy: 401.0,
            world_to_camera: [
                [1.0, 0.0, 0.0, 0.0],
                [0.0, -1.0, 0.0, 0.0],
                [0.0, 0.0, -1.0, 1.2],
                [0.0, 0.0, 0.0, 1.0],
            ],
        },
        background: [1.0, 1.0, 1.0],
    }
}

fn colour_at(p: [f32; 3]) -> [f32; 3] {
    let [x, y, z] = p;
    let skin = [0.87, 0.68, 0.58];
    if z > 0.0 {
        for ex in [-0.055f32, 0.055] {
            let d2 = (x - ex).powi(2) + (y - 0.03).powi(2);
            if d2 < 0.018f32.powi(2) {
                return [0.15, 0.25, 0.45];
            }
            if d2 < 0.028f32.powi(2) {
                return [0.95, 0.95, 0.95];
            }
            if (x - ex).abs() < 0.035 && (y - 0.075).abs() < 0.008 {
                return [0.3, 0.2, 0.15];
            }
        }
        if x.abs() < 0.045 && (y + 0.075).abs() < 0.012 {
            return [0.75, 0.3, 0.32];
        }
    }
    if y > 0.11 {
        return [0.35, 0.22, 0.12];
    }
    skin
}

/// `n` Gaussians on a head-sized ellipsoid (semi-axes 0.09 x 0.12 x 0.1 units).
pub fn scene(n: usize, seed: u64) -> PlyGaussians {
    let mut rng = Pcg::new(seed);
    let mut g = PlyGaussians::default();
    let axes = [0.09f32, 0.12, 0.1];
    for _ in 0..n {
        let d = [rng.normal(), rng.normal(), rng.normal()];
        let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-6);
        let shell = 1.0 - 0.04 * rng.uniform();
        let p = [
            axes[0] * d[0] / len * shell,
            axes[1] * d[1] / len * shell,
            axes[2] * d[2] / len * shell,
        ];
        g.means.extend(p);
        let c = colour_at(p);
        g.sh.extend(c.map(|v| (v + 0.03 * rng.normal() - 0.5) / C0));
        g.opacity_logits.push(2.0 + rng.normal());
        let s = (0.004f32 + 0.003 * rng.uniform()).ln();
        g.log_scales.extend([s, s + 0.3 * rng.normal(), s - 1.0]);
        g.quats
            .extend([rng.normal(), rng.normal(), rng.normal(), rng.normal()]);
    }
    g
}
