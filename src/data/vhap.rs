//! VHAP's NeRSemble export for GaussianAvatars: `transforms_{train,val,test}.json`, read as
//! VHAP writes them and GaussianAvatars reads them.
//!
//! Top level: `cx, cy, fl_x, fl_y, h, w` (defaults for every frame), optional
//! `camera_angle_x/y`, `timestep_indices`, `camera_indices`, and `frames`. Per frame:
//! `timestep_index`, `camera_index`, `file_path`, optional `fg_mask_path` and
//! `flame_param_path`, `transform_matrix` (camera-to-world, OpenGL axes: x right, y up,
//! z backward), optional per-frame `cx, cy, fl_x, fl_y, h, w, camera_angle_x` (they override
//! the top level) and VHAP's `camera_id`, `timestep_id` (written, ignored on read). Paths are
//! relative to the JSON's folder; combined multi-sequence sets use `../<seq>/...`, which is
//! kept as is.
//!
//! # Conventions (checked against the peers' code, see the tests)
//! - **Principal point.** VHAP exports with `camera_convention_conversion = "opencv->opengl"`
//!   (`vhap/config/base.py`, `DataConfig`), whose `convert_camera_convention`
//!   (`vhap/util/camera.py`) flips the camera's y and z axes *and* stores
//!   `cy = h - cy_opencv`. The reader turns it back (`cy_opencv = h - cy`) and the writer
//!   stores `h - cy`; `cx` is unchanged. Image coordinates are continuous with pixel `(i, j)`
//!   centred at `(i + 0.5, j + 0.5)`, as VHAP's `projection_from_intrinsics` maps them.
//! - **Intrinsics without `fl_x`.** GaussianAvatars' `readCamerasFromTransforms`
//!   (`scene/dataset_readers.py`) needs only `camera_angle_x` (per frame, else top level) and
//!   takes the same focal length for y and the principal point at the image centre; so does
//!   this reader when `fl_x` is absent. Without `w`/`h` the image's own size is used.
//! - **`file_path`** may omit `.png`: as GaussianAvatars does, `.png` is appended when the
//!   path does not contain it.
//! - Images with alpha are composited on white and masks are optional (see
//!   [`crate::data::dataset`]).
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

/// Intrinsics as VHAP writes them: at the top level (defaults for every frame) and per
/// frame (overriding the top level).
#[derive(Clone, Copy, Debug, Default, Deserialize)]
struct Intrinsics {
    cx: Option<f32>,
    cy: Option<f32>,
    fl_x: Option<f32>,
    fl_y: Option<f32>,
    h: Option<u32>,
    w: Option<u32>,
    camera_angle_x: Option<f32>,
}

impl Intrinsics {
    /// Each value of `self`, else `top`'s.
    fn or(self, top: Intrinsics) -> Intrinsics {
        Intrinsics {
            cx: self.cx.or(top.cx),
            cy: self.cy.or(top.cy),
            fl_x: self.fl_x.or(top.fl_x),
            fl_y: self.fl_y.or(top.fl_y),
            h: self.h.or(top.h),
            w: self.w.or(top.w),
            camera_angle_x: self.camera_angle_x.or(top.camera_angle_x),
        }
    }
}

#[derive(Debug, Deserialize)]
struct TransformsJson {
    #[serde(flatten)]
    intrinsics: Intrinsics,
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
    #[serde(flatten)]
    intrinsics: Intrinsics,
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
/// frame, every frame with its own too; `cy` in VHAP's flipped convention, see the module
/// docs; `camera_id` and `timestep_id` as strings), through a temporary file.
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
                "camera_id": format!("{:02}", f.camera_index),
                "timestep_id": format!("frame_{:05}", f.timestep),
                "transform_matrix": opengl_camera_to_world(&k.world_to_camera),
                "cx": k.cx, "cy": vhap_cy(k), "fl_x": k.fx, "fl_y": k.fy, "h": k.height, "w": k.width,
                "camera_angle_x": angle(k.fx, k.width), "camera_angle_y": angle(k.fy, k.height),
            })
        })
        .collect();
    let doc = serde_json::json!({
        "cx": c.cx, "cy": vhap_cy(c), "fl_x": c.fx, "fl_y": c.fy, "h": c.height, "w": c.width,
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

/// VHAP's stored `cy` of a camera: `h - cy` (`convert_camera_convention`, "opencv->opengl").
fn vhap_cy(c: &Camera) -> f32 {
    c.height as f32 - c.cy
}

/// The image a frame's `file_path` names: relative to `dir`, with `.png` appended when the
/// path does not contain it (GaussianAvatars' `readCamerasFromTransforms`).
fn image_path(dir: &Path, file_path: &str) -> PathBuf {
    if file_path.contains(".png") {
        dir.join(file_path)
    } else {
        dir.join(format!("{file_path}.png"))
    }
}

/// Reads a `transforms_*.json` (see the module docs for the conventions).
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
            let image = image_path(dir, &f.file_path);
            let k = f.intrinsics.or(json.intrinsics);
            let (width, height) = match (k.w, k.h) {
                (Some(w), Some(h)) => (w, h),
                // GaussianAvatars reads the size from the image when the JSON has none.
                _ => image::image_dimensions(&image).map_err(|e| {
                    Error::invalid(
                        &what,
                        field("w/h"),
                        format!(
                            "no image size in the JSON and {} gives none: {e}",
                            image.display()
                        ),
                    )
                })?,
            };
            if width == 0 || height == 0 {
                return Err(Error::invalid(
                    &what,
                    field("w/h"),
                    "image size must be positive",
                ));
            }
            let fx = match (k.fl_x, k.camera_angle_x) {
                (Some(fx), _) => fx,
                (None, Some(angle)) => {
                    if !(angle.is_finite() && angle > 0.0 && angle < std::f32::consts::PI) {
                        return Err(Error::invalid(
                            &what,
                            field("camera_angle_x"),
                            format!("{angle} is not a field of view in (0, pi)"),
                        ));
                    }
                    0.5 * width as f32 / (0.5 * angle).tan()
                }
                (None, None) => {
                    return Err(Error::invalid(
                        &what,
                        field("fl_x"),
                        "missing, and no camera_angle_x to derive it from",
                    ));
                }
            };
            let fy = k.fl_y.unwrap_or(fx);
            let cx = k.cx.unwrap_or(0.5 * width as f32);
            let cy = match k.cy {
                Some(stored) => height as f32 - stored,
                None => 0.5 * height as f32,
            };
            for (name, v) in [("cx", cx), ("cy", cy)] {
                if !v.is_finite() {
                    return Err(Error::invalid(&what, field(name), "not finite"));
                }
            }
            let camera = Camera {
                width,
                height,
                fx,
                fy,
                cx,
                cy,
                world_to_camera: opencv_world_to_camera(&f.transform_matrix),
            };
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
            if let Some(why) = crate::camera::rotation_problem(m) {
                return Err(Error::invalid(&what, field("transform_matrix"), why));
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
                image,
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
            cy: 12.0,
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
        // On disk in VHAP's convention (`vhap/util/camera.py`, `convert_camera_convention`,
        // "opencv->opengl"): cy = h - cy_opencv = 30 - 12; cx unchanged; camera_id and
        // timestep_id as VHAP's export writes them (strings).
        let raw: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&p).expect("read")).expect("json");
        assert_eq!(raw["cy"], serde_json::json!(18.0));
        assert_eq!(raw["frames"][0]["cy"], serde_json::json!(18.0));
        assert_eq!(raw["frames"][0]["cx"], serde_json::json!(10.0));
        assert!(raw["frames"][0]["camera_id"].is_string());
        assert_eq!(raw["frames"][0]["timestep_id"], "frame_00003");
        let frames = load_transforms(&p).expect("load");
        assert_eq!(frames.len(), 1);
        let f = &frames[0];
        assert_eq!((f.timestep, f.camera_index), (3, 5));
        assert!(f.image.ends_with("../seq/images/00003_05.png"));
        assert_eq!((f.camera.fx, f.camera.cy, f.camera.width), (40.0, 12.0, 20));
        for (row, want) in f.camera.world_to_camera.iter().zip(&w2c) {
            for (a, b) in row.iter().zip(want) {
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
                "no_focal.json",
                Some(
                    r#"{"w": 10, "h": 10, "frames": [{"timestep_index": 0, "camera_index": 0,
                        "file_path": "a.png",
                        "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,2],[0,0,0,1]]}]}"#
                        .to_string(),
                ),
                "frames[0].fl_x",
            ),
            (
                "no_size.json",
                Some(
                    r#"{"camera_angle_x": 0.5, "frames": [{"timestep_index": 0,
                        "camera_index": 0, "file_path": "absent",
                        "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,2],[0,0,0,1]]}]}"#
                        .to_string(),
                ),
                "frames[0].w/h",
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
