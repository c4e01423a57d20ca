//! The capture rig: cameras on a NeRSemble-like frontal arc around the head.
//!
//! Camera `i` of `n` sits at azimuth `arc (i / (n - 1) - 1/2)`, so with 16 cameras the
//! front lies between cameras 7 and 8; camera `val_camera` is turned to exactly 0 degrees
//! (NeRSemble's held-out front camera) and the others keep their even spread. Elevations
//! alternate between a higher and a lower row (+12 and -4 degrees), the front camera at +4.
//! All look at the head centre; OpenCV axes, world y up, the face looks along +z.

use glam::Vec3;

use crate::camera::Camera;
use crate::synth::config::SynthConfig;

/// Elevation of the upper and lower rows and of the front camera, degrees.
const ROWS_DEGREES: [f32; 3] = [12.0, -4.0, 4.0];

/// World-to-camera (OpenCV) of a camera at `eye` looking at `target`, world up +y.
pub fn look_at(eye: Vec3, target: Vec3) -> [[f32; 4]; 4] {
    let z = (target - eye).normalize();
    let x = z.cross(Vec3::Y).normalize(); // camera x: right in the image
    let y = z.cross(x); // camera y: down in the image
    let t = [-x.dot(eye), -y.dot(eye), -z.dot(eye)];
    [
        [x.x, x.y, x.z, t[0]],
        [y.x, y.y, y.z, t[1]],
        [z.x, z.y, z.z, t[2]],
        [0.0, 0.0, 0.0, 1.0],
    ]
}

/// The rig's cameras looking at `target`.
pub fn rig(config: &SynthConfig, target: Vec3) -> Vec<Camera> {
    let n = config.cameras;
    (0..n)
        .map(|i| {
            let (az, el) = if i == config.val_camera {
                (0.0, ROWS_DEGREES[2])
            } else {
                let t = i as f32 / (n - 1) as f32 - 0.5;
                (config.arc_degrees * t, ROWS_DEGREES[i % 2])
            };
            let (az, el) = (az.to_radians(), el.to_radians());
            let dir = Vec3::new(az.sin() * el.cos(), el.sin(), az.cos() * el.cos());
            Camera::from_fov(
                config.width,
                config.height,
                config.fov_y_degrees,
                look_at(target + config.distance * dir, target),
            )
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cameras_look_at_the_target_and_the_front_one_is_frontal() {
        let c = SynthConfig::default();
        let target = Vec3::new(0.0, -0.03, 0.0);
        let cams = rig(&c, target);
        assert_eq!(cams.len(), 16);
        for cam in &cams {
            let m = cam.world_to_camera;
            let p: [f32; 3] =
                std::array::from_fn(|i| (0..3).map(|k| m[i][k] * target[k]).sum::<f32>() + m[i][3]);
            // The target projects to the image centre at the rig distance.
            assert!(p[0].abs() < 1e-5 && p[1].abs() < 1e-5, "{p:?}");
            assert!((p[2] - c.distance).abs() < 1e-5);
            assert!(cam.validate("rig").is_ok());
        }
        let front = cams[c.val_camera].position();
        assert!(front[0].abs() < 1e-5 && front[2] > 0.9);
        // A point above the target appears above the centre (smaller row).
        let m = cams[3].world_to_camera;
        let up = target + Vec3::Y * 0.1;
        let y: f32 = (0..3).map(|k| m[1][k] * up[k]).sum::<f32>() + m[1][3];
        assert!(y < 0.0);
    }
}
