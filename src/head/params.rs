//! FLAME parameters as VHAP and GaussianAvatars store them.
//!
//! - One frame (VHAP's export, `flame_param/TTTTT.npz`, also `canonical_flame_param.npz`;
//!   `vhap/export_as_nerf_dataset.py`, `write_flame_param`): `translation` (1,3), `rotation`
//!   (1,3), `neck_pose` (1,3), `jaw_pose` (1,3), `eyes_pose` (1,6), `expr` (1,E), `shape` (S,)
//!   and optionally `static_offset` (1,V,3). [`HeadPose::load_npz`].
//! - T frames (GaussianAvatars' `flame_param.npz` next to a trained `point_cloud.ply`,
//!   `FlameGaussianModel.save_ply`; VHAP's `tracked_flame_params_*.npz`,
//!   `GlobalTracker.save_result`): the same names with (T, ·) per-frame arrays, `shape` (S,)
//!   and `static_offset` (1,V,3) once. [`HeadPose::load_npz_frames`].
//!
//! `dynamic_offset` and every other array (`timestep_id`, `focal_length`, `tex`, `lights`,
//! ...) are ignored.

use std::path::Path;

use crate::error::{Error, Result};
use crate::head::lbs::HeadPose;
use crate::io::npz::{Npz, NpzOut};

/// The `t` rows of `n` values of array `name`: shape (t, n), or (n,) when `t` is 1.
fn rows(z: &mut Npz, what: &str, name: &str, t: usize, n: usize) -> Result<Vec<f32>> {
    let a = z.floats(name)?;
    let ok = match a.shape.as_slice() {
        [rows, cols] => *rows == t && *cols == n,
        [cols] => t == 1 && *cols == n,
        _ => false,
    };
    if !ok {
        return Err(Error::invalid(
            what,
            name,
            format!("shape {:?}, expected ({t}, {n})", a.shape),
        ));
    }
    Ok(a.data)
}

/// Per-vertex static offsets, `[V]`.
pub type StaticOffset = Vec<[f32; 3]>;

/// The subject's arrays of a parameter file, shared by all its frames: `shape` (S,) or
/// (1, S) and the optional `static_offset` (1, V, 3).
pub fn subject(z: &mut Npz, what: &str) -> Result<(Vec<f32>, Option<StaticOffset>)> {
    let static_offset = if z.has("static_offset") {
        let a = z.floats("static_offset")?;
        if a.shape.len() != 3 || a.shape[0] != 1 || a.shape[2] != 3 {
            return Err(Error::invalid(
                what,
                "static_offset",
                format!("shape {:?}, expected (1, V, 3)", a.shape),
            ));
        }
        Some(
            a.data
                .chunks(3)
                .map(|c| [c[0], c[1], c[2]])
                .collect::<Vec<_>>(),
        )
    } else {
        None
    };
    let shape = z.floats("shape")?;
    if shape.shape.len() > 1 && shape.shape[..shape.shape.len() - 1].iter().any(|&d| d != 1) {
        return Err(Error::invalid(
            what,
            "shape",
            format!("shape {:?}, expected (S,) or (1, S)", shape.shape),
        ));
    }
    Ok((shape.data, static_offset))
}

fn fixed<const N: usize>(row: &[f32]) -> [f32; N] {
    std::array::from_fn(|i| row[i])
}

impl HeadPose {
    /// Reads a one-frame VHAP `flame_param` `.npz`; a file of several frames is an error
    /// (read it with [`HeadPose::load_npz_frames`]).
    pub fn load_npz(path: &Path) -> Result<Self> {
        let mut frames = Self::load_npz_frames(path)?;
        if frames.len() != 1 {
            return Err(Error::invalid(
                path.display().to_string(),
                "expr",
                format!(
                    "{} frames; a dataset's flame_param file holds one",
                    frames.len()
                ),
            ));
        }
        Ok(frames.remove(0))
    }

    /// Reads every frame of a FLAME parameter `.npz`: T from `expr` (T, E); every per-frame
    /// array must have T rows; `shape` and `static_offset` are shared by all frames.
    pub fn load_npz_frames(path: &Path) -> Result<Vec<Self>> {
        let what = path.display().to_string();
        let mut z = Npz::open(path)?;
        let (shape, static_offset) = subject(&mut z, &what)?;
        let expr = z.floats("expr")?;
        let (t, e) = match expr.shape.as_slice() {
            [t, e] => (*t, *e),
            [e] => (1, *e),
            _ => {
                return Err(Error::invalid(
                    &what,
                    "expr",
                    format!("shape {:?}, expected (T, E)", expr.shape),
                ));
            }
        };
        if t == 0 {
            return Err(Error::invalid(&what, "expr", "no frames (T = 0)"));
        }
        let rotation = rows(&mut z, &what, "rotation", t, 3)?;
        let neck = rows(&mut z, &what, "neck_pose", t, 3)?;
        let jaw = rows(&mut z, &what, "jaw_pose", t, 3)?;
        let eyes = rows(&mut z, &what, "eyes_pose", t, 6)?;
        let translation = rows(&mut z, &what, "translation", t, 3)?;
        (0..t)
            .map(|i| {
                let pose = HeadPose {
                    shape: shape.clone(),
                    expr: expr.data[i * e..(i + 1) * e].to_vec(),
                    rotation: fixed(&rotation[i * 3..]),
                    neck: fixed(&neck[i * 3..]),
                    jaw: fixed(&jaw[i * 3..]),
                    eyes: fixed(&eyes[i * 6..]),
                    translation: fixed(&translation[i * 3..]),
                    static_offset: static_offset.clone(),
                };
                pose.check_finite(&what)?;
                Ok(pose)
            })
            .collect()
    }

    /// Writes the parameters in VHAP's layout.
    pub fn save_npz(&self, path: &Path) -> Result<()> {
        self.check_finite(&path.display().to_string())?;
        let mut out = NpzOut::default();
        out.floats("translation", &[1, 3], self.translation.to_vec())
            .floats("rotation", &[1, 3], self.rotation.to_vec())
            .floats("neck_pose", &[1, 3], self.neck.to_vec())
            .floats("jaw_pose", &[1, 3], self.jaw.to_vec())
            .floats("eyes_pose", &[1, 6], self.eyes.to_vec())
            .floats("expr", &[1, self.expr.len()], self.expr.clone())
            .floats("shape", &[self.shape.len()], self.shape.clone());
        if let Some(o) = &self.static_offset {
            out.floats("static_offset", &[1, o.len(), 3], o.concat());
        }
        out.write(path)
    }
}
