//! Per-frame FLAME parameters as VHAP exports them (`flame_param/TTTTT.npz`, also
//! `canonical_flame_param.npz`): `translation` (1,3), `rotation` (1,3), `neck_pose` (1,3),
//! `jaw_pose` (1,3), `eyes_pose` (1,6), `expr` (1,E), `shape` (S,) and optionally
//! `static_offset` (1,V,3). `dynamic_offset` is accepted and ignored.

use std::path::Path;

use crate::error::{Error, Result};
use crate::head::lbs::HeadPose;
use crate::io::npz::{Npz, NpzOut};

fn fixed<const N: usize>(z: &mut Npz, what: &str, name: &str) -> Result<[f32; N]> {
    let a = z.floats(name)?;
    let data: [f32; N] = a.data.as_slice().try_into().map_err(|_| {
        Error::invalid(
            what,
            name,
            format!("shape {:?}, expected (1, {N})", a.shape),
        )
    })?;
    Ok(data)
}

impl HeadPose {
    /// Reads a VHAP `flame_param` `.npz`.
    pub fn load_npz(path: &Path) -> Result<Self> {
        let what = path.display().to_string();
        let mut z = Npz::open(path)?;
        let static_offset = if z.has("static_offset") {
            let a = z.floats("static_offset")?;
            if a.shape.len() != 3 || a.shape[0] != 1 || a.shape[2] != 3 {
                return Err(Error::invalid(
                    &what,
                    "static_offset",
                    format!("shape {:?}, expected (1, V, 3)", a.shape),
                ));
            }
            Some(a.data.chunks(3).map(|c| [c[0], c[1], c[2]]).collect())
        } else {
            None
        };
        let pose = HeadPose {
            shape: z.floats("shape")?.data,
            expr: z.floats("expr")?.data,
            rotation: fixed(&mut z, &what, "rotation")?,
            neck: fixed(&mut z, &what, "neck_pose")?,
            jaw: fixed(&mut z, &what, "jaw_pose")?,
            eyes: fixed(&mut z, &what, "eyes_pose")?,
            translation: fixed(&mut z, &what, "translation")?,
            static_offset,
        };
        pose.check_finite(&what)?;
        Ok(pose)
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
