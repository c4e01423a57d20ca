//! VHAP's NeRSemble export for GaussianAvatars: `transforms_{train,val,test}.json`.
//!
//! Top level: `cx, cy, fl_x, fl_y, h, w` (defaults for every frame), optional
//! `camera_angle_x/y`, `timestep_indices`, `camera_indices`, and `frames`. Per frame:
//! `timestep_index`, `camera_index`, `file_path`, optional `fg_mask_path` and
//! `flame_param_path`, `transform_matrix` (camera-to-world, OpenGL axes: x right, y up,
//! z backward) and optional per-frame `cx, cy, fl_x, fl_y, h, w`. Paths are relative to the
//! JSON's folder; combined multi-sequence sets use `../<seq>/...`, which is kept as is.
//!
//! # The eta side file
//! The paper's image-derived expression embedding (eta, 128 values) is not part of VHAP's
//! format. This project keeps it next to each timestep's FLAME parameters:
//! `flame_param/TTTTT.npz` → `eta/TTTTT.npy`, float32 `[128]`. A missing file means zeros
//! (as for real captures without an encoder); a present file with another shape is an error.

use std::path::{Path, PathBuf};

use serde::Deserialize;

use crate::camera::Camera;
use crate::error::{Error, Result};

#[derive(Debug, Deserialize)]
struct TransformsJson {
    cx: f32,
    cy: f32,
    fl_x: f32,
    fl_y: f32,
    h: u32,
    w: u32,
    frames: Vec<FrameJson>,
}

#[derive(Debug, Deserialize)]
struct FrameJson {
    timestep_index: usize,
    camera_index: usize,
    file_path: String,
    fg_mask_path: Option<String>,
    flame_param_path: Option<String>,
    transform_matrix: [[f32; 4]; 4],
    cx: Option<f32>,
    cy: Option<f32>,
    fl_x: Option<f32>,
    fl_y: Option<f32>,
    h: Option<u32>,
    w: Option<u32>,
}

/// One frame of a VHAP export: which timestep and camera, where its files are, and its
/// camera in this project's convention (OpenCV world-to-camera).
#[derive(Clone, Debug, PartialEq)]
pub struct VhapFrame {
    pub timestep: usize,
    pub camera_index: usize,
    pub image: PathBuf,
    pub mask: Option<PathBuf>,
    pub flame_param: Option<PathBuf>,
    pub camera: Camera,
}

/// Length of the eta conditioning vector.
pub const ETA_DIM: usize = 128;

/// Where the eta side file of a timestep lives, given its `flame_param` path.
pub fn eta_path(flame_param: &Path) -> PathBuf {
    let stem = flame_param.file_stem().unwrap_or_default();
    let dir = flame_param
        .parent()
        .and_then(Path::parent)
        .unwrap_or(Path::new("."));
    dir.join("eta").join(stem).with_extension("npy")
}

/// The eta vector of a timestep: the side file's 128 values, or zeros when it is absent.
pub fn load_eta(flame_param: &Path) -> Result<Vec<f32>> {
    let path = eta_path(flame_param);
    if !path.exists() {
        return Ok(vec![0.0; ETA_DIM]);
    }
    let a = crate::io::npy::read(&path)?;
    if a.data.len() != ETA_DIM {
        return Err(Error::invalid(
            path.display().to_string(),
            "eta",
            format!("shape {:?}, expected [{ETA_DIM}]", a.shape),
        ));
    }
    if a.data.iter().any(|v| !v.is_finite()) {
        return Err(Error::invalid(
            path.display().to_string(),
            "eta",
            "not finite",
        ));
    }
    Ok(a.data)
}

/// OpenGL camera-to-world → OpenCV world-to-camera: flip the camera's y and z axes, then
/// invert the rigid transform.
pub fn opencv_world_to_camera(c2w_gl: &[[f32; 4]; 4]) -> [[f32; 4]; 4] {
    // Columns 1 and 2 of the rotation (the camera's y and z axes) change sign.
    let r: [[f32; 3]; 3] = std::array::from_fn(|i| [c2w_gl[i][0], -c2w_gl[i][1], -c2w_gl[i][2]]);
    let t = [c2w_gl[0][3], c2w_gl[1][3], c2w_gl[2][3]];
    let mut w2c = [[0.0f32; 4]; 4];
    for i in 0..3 {
        for j in 0..3 {
            w2c[i][j] = r[j][i];
        }
        w2c[i][3] = -(0..3).map(|k| r[k][i] * t[k]).sum::<f32>();
    }
    w2c[3][3] = 1.0;
    w2c
}

/// The inverse of [`opencv_world_to_camera`]: camera-to-world in OpenGL axes.
pub fn opengl_camera_to_world(w2c_cv: &[[f32; 4]; 4]) -> [[f32; 4]; 4] {
    // c2w (OpenCV) = [R^T | -R^T t]; then flip the camera's y and z axes.
    let mut out = [[0.0f32; 4]; 4];
    for i in 0..3 {
        for j in 0..3 {
            let r_t = w2c_cv[j][i];
            out[i][j] = if j == 0 { r_t } else { -r_t };
        }
        out[i][3] = -(0..3).map(|k| w2c_cv[k][i] * w2c_cv[k][3]).sum::<f32>();
    }
    out[3][3] = 1.0;
    out
}

/// One frame to write into a `transforms_*.json`: paths relative to the JSON's folder.
#[derive(Clone, Debug)]
pub struct FrameRecord {
    pub timestep: usize,
    pub camera_index: usize,
    pub file_path: String,
    pub fg_mask_path: String,
    pub flame_param_path: String,
    pub camera: Camera,
}

/// Writes a `transforms_*.json` in VHAP's layout (top-level intrinsics from the first
/// frame, every frame with its own too), through a temporary file.
pub fn save_transforms(path: &Path, frames: &[FrameRecord]) -> Result<()> {
    let what = path.display().to_string();
    let Some(first) = frames.first() else {
        return Err(Error::invalid(what, "frames", "no frames to write"));
    };
    let c = &first.camera;
    let angle = |f: f32, size: u32| 2.0 * (0.5 * size as f32 / f).atan();
    let mut timesteps: Vec<usize> = frames.iter().map(|f| f.timestep).collect();
    timesteps.sort_unstable();
    timesteps.dedup();
    let mut cameras: Vec<usize> = frames.iter().map(|f| f.camera_index).collect();
    cameras.sort_unstable();
    cameras.dedup();
    let list: Vec<serde_json::Value> = frames
        .iter()
        .map(|f| {
            let k = &f.camera;
            serde_json::json!({
                "timestep_index": f.timestep,
                "camera_index": f.camera_index,
                "file_path": f.file_path,
                "fg_mask_path": f.fg_mask_path,
                "flame_param_path": f.flame_param_path,
                "transform_matrix": opengl_camera_to_world(&k.world_to_camera),
                "cx": k.cx, "cy": k.cy, "fl_x": k.fx, "fl_y": k.fy, "h": k.height, "w": k.width,
                "camera_angle_x": angle(k.fx, k.width), "camera_angle_y": angle(k.fy, k.height),
            })
        })
        .collect();
    let doc = serde_json::json!({
        "cx": c.cx, "cy": c.cy, "fl_x": c.fx, "fl_y": c.fy, "h": c.height, "w": c.width,
        "camera_angle_x": angle(c.fx, c.width), "camera_angle_y": angle(c.fy, c.height),
        "timestep_indices": timesteps,
        "camera_indices": cameras,
        "frames": list,
    });
    let text = serde_json::to_string_pretty(&doc)
        .map_err(|e| Error::invalid(&what, "json", e.to_string()))?;
    let tmp = path.with_extension("json.partial");
    std::fs::write(&tmp, text).map_err(|e| Error::io(&tmp, e))?;
    std::fs::rename(&tmp, path).map_err(|e| Error::io(path, e))
}

/// Reads a `transforms_*.json`.
pub fn load_transforms(path: &Path) -> Result<Vec<VhapFrame>> {
    let what = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let json: TransformsJson = serde_json::from_str(&text).map_err(|e| {
        // serde names the missing or mistyped key and the line in its message.
        Error::invalid(&what, "json", e.to_string())
    })?;
    let dir = path.parent().unwrap_or(Path::new("."));
    json.frames
        .into_iter()
        .enumerate()
        .map(|(i, f)| {
            let field = |name: &str| format!("frames[{i}].{name}");
            let camera = Camera {
                width: f.w.unwrap_or(json.w),
                height: f.h.unwrap_or(json.h),
                fx: f.fl_x.unwrap_or(json.fl_x),
                fy: f.fl_y.unwrap_or(json.fl_y),
                cx: f.cx.unwrap_or(json.cx),
                cy: f.cy.unwrap_or(json.cy),
                world_to_camera: opencv_world_to_camera(&f.transform_matrix),
            };
            if camera.width == 0 || camera.height == 0 {
                return Err(Error::invalid(
                    &what,
                    field("w/h"),
                    "image size must be positive",
                ));
            }
            for (name, v) in [("fl_x", camera.fx), ("fl_y", camera.fy)] {
                if !(v.is_finite() && v > 0.0) {
                    return Err(Error::invalid(
                        &what,
                        field(name),
                        format!("{v} is not a positive focal length"),
                    ));
                }
            }
            let m = &f.transform_matrix;
            if m.iter().flatten().any(|v| !v.is_finite()) {
                return Err(Error::invalid(
                    &what,
                    field("transform_matrix"),
                    "not finite",
                ));
            }
            if (m[3][0].abs() + m[3][1].abs() + m[3][2].abs() + (m[3][3] - 1.0).abs()) > 1e-4 {
                return Err(Error::invalid(
                    &what,
                    field("transform_matrix"),
                    "last row is not [0, 0, 0, 1]",
                ));
            }
            Ok(VhapFrame {
                timestep: f.timestep_index,
                camera_index: f.camera_index,
                image: dir.join(&f.file_path),
                mask: f.fg_mask_path.map(|p| dir.join(p)),
                flame_param: f.flame_param_path.map(|p| dir.join(p)),
                camera,
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn saved_transforms_read_back_with_the_same_cameras() {
        // A rotated, translated camera: write it as OpenGL c2w, read it as OpenCV w2c.
        let (c, s) = (0.6f32.cos(), 0.6f32.sin());
        let w2c = [
            [c, 0.0, -s, 0.1],
            [0.0, 1.0, 0.0, -0.2],
            [s, 0.0, c, 1.3],
            [0.0, 0.0, 0.0, 1.0],
        ];
        let back = opencv_world_to_camera(&opengl_camera_to_world(&w2c));
        for i in 0..4 {
            for j in 0..4 {
                assert!((back[i][j] - w2c[i][j]).abs() < 1e-6, "{back:?}");
            }
        }
        let camera = Camera {
            width: 20,
            height: 30,
            fx: 40.0,
            fy: 41.0,
            cx: 10.0,
            cy: 15.0,
            world_to_camera: w2c,
        };
        let d = dir("save");
        let p = d.join("transforms_train.json");
        let rec = FrameRecord {
            timestep: 3,
            camera_index: 5,
            file_path: "../seq/images/00003_05.png".into(),
            fg_mask_path: "../seq/fg_masks/00003_05.png".into(),
            flame_param_path: "../seq/flame_param/00003.npz".into(),
            camera,
        };
        save_transforms(&p, &[rec]).expect("save");
        let frames = load_transforms(&p).expect("load");
        assert_eq!(frames.len(), 1);
        let f = &frames[0];
        assert_eq!((f.timestep, f.camera_index), (3, 5));
        assert!(f.image.ends_with("../seq/images/00003_05.png"));
        assert_eq!((f.camera.fx, f.camera.cy, f.camera.width), (40.0, 15.0, 20));
        for (row, expected) in f.camera.world_to_camera.iter().zip(&w2c) {
            for (a, b) in row.iter().zip(expected) {
                assert!((a - b).abs() < 1e-6);
            }
        }
        assert!(
            save_transforms(&p, &[])
                .unwrap_err()
                .to_string()
                .contains("frames")
        );
    }

    fn dir(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("texavatars-vhap-{}-{name}", std::process::id()));
        std::fs::create_dir_all(&d).expect("dir");
        d
    }

    const JSON: &str = r#"{
        "cx": 275.0, "cy": 401.0, "fl_x": 1000.0, "fl_y": 1001.0, "h": 802, "w": 550,
        "camera_angle_x": 0.5, "camera_angle_y": 0.7,
        "timestep_indices": [0, 1], "camera_indices": [8],
        "frames": [
            {"timestep_index": 0, "camera_index": 8, "file_path": "images/00000_08.png",
             "fg_mask_path": "fg_masks/00000_08.png", "flame_param_path": "flame_param/00000.npz",
             "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,2],[0,0,0,1]],
             "cx": 275.0, "cy": 401.0, "fl_x": 1000.0, "fl_y": 1001.0, "h": 802, "w": 550},
            {"timestep_index": 1, "camera_index": 8, "file_path": "../other/images/00001_08.png",
             "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,2],[0,0,0,1]], "fl_x": 900.0}
        ]
    }"#;

    #[test]
    fn reads_frames_and_converts_cameras() {
        let d = dir("ok");
        let p = d.join("transforms_train.json");
        std::fs::write(&p, JSON).expect("write");
        let frames = load_transforms(&p).expect("load");
        assert_eq!(frames.len(), 2);
        assert_eq!(frames[0].image, d.join("images/00000_08.png"));
        assert_eq!(frames[0].flame_param, Some(d.join("flame_param/00000.npz")));
        assert_eq!(frames[1].image, d.join("../other/images/00001_08.png"));
        assert_eq!(frames[1].mask, None);
        assert_eq!(frames[1].camera.fx, 900.0);
        assert_eq!(frames[1].camera.fy, 1001.0);
        // An OpenGL camera at z = +2 looking down -z sees the origin 2 units in front (OpenCV
        // +z), with y flipped.
        let m = frames[0].camera.world_to_camera;
        let apply = |p: [f32; 3]| -> [f32; 3] {
            std::array::from_fn(|i| (0..3).map(|k| m[i][k] * p[k]).sum::<f32>() + m[i][3])
        };
        assert_eq!(apply([0.0, 0.0, 0.0]), [0.0, 0.0, 2.0]);
        assert_eq!(apply([0.0, 1.0, 0.0]), [0.0, -1.0, 2.0]);
        assert_eq!(apply([1.0, 0.0, 0.0]), [1.0, 0.0, 2.0]);
    }

    #[test]
    fn eta_side_file_or_zeros() {
        let d = dir("eta");
        let fp = d.join("flame_param").join("00003.npz");
        assert_eq!(eta_path(&fp), d.join("eta").join("00003.npy"));
        assert_eq!(load_eta(&fp).expect("absent"), vec![0.0; ETA_DIM]);
        std::fs::create_dir_all(d.join("eta")).expect("dir");
        let v: Vec<f32> = (0..ETA_DIM).map(|i| i as f32).collect();
        crate::io::npy::write(&eta_path(&fp), &[ETA_DIM], &v).expect("write");
        assert_eq!(load_eta(&fp).expect("present"), v);
        crate::io::npy::write(&eta_path(&fp), &[2], &[0.0, 1.0]).expect("write");
        let e = load_eta(&fp).expect_err("shape").to_string();
        assert!(e.contains("00003.npy") && e.contains("eta"), "{e}");
    }

    #[test]
    fn bad_files_name_file_and_field() {
        let d = dir("bad");
        let cases = [
            ("missing.json", None, "missing.json"),
            (
                "no_cx.json",
                Some(JSON.replacen("\"cx\": 275.0, \"cy\"", "\"cy\"", 1)),
                "cx",
            ),
            (
                "trunc.json",
                Some(JSON[..JSON.len() / 2].to_string()),
                "trunc.json",
            ),
            (
                "bad_fl.json",
                Some(JSON.replace("\"fl_x\": 900.0", "\"fl_x\": -1.0")),
                "frames[1].fl_x",
            ),
            (
                "bad_row.json",
                Some(JSON.replacen("[0,0,0,1]]", "[0,0,1,1]]", 1)),
                "frames[0].transform_matrix",
            ),
        ];
        for (name, text, want) in cases {
            let p = d.join(name);
            if let Some(t) = text {
                std::fs::write(&p, t).expect("write");
            }
            let e = load_transforms(&p).expect_err(name).to_string();
            assert!(e.contains(name) && e.contains(want), "{name}: {e}");
        }
    }
}
