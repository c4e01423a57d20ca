//! A trained avatar's refined FLAME parameters as files: written by training next to the
//! avatar, read back by evaluation, export and the dataset (which then poses the training
//! timesteps with them).

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::head::HeadPose;
use crate::io::npz::{Npz, NpzOut};

/// File of the refined parameters in a training output folder, in the layout GaussianAvatars
/// writes next to its `point_cloud.ply` and reads back (`scene/flame_gaussian_model.py`,
/// `FlameGaussianModel.save_ply` / `load_ply`, indexed by `select_mesh_by_timestep`): row
/// `t` of every `(T, ·)` array is timestep `t` (T: the largest refined timestep plus one;
/// rows of timesteps that were not refined are zero, as `load_meshes` initialises them),
/// `shape` `(S,)`, `static_offset` `(1, V, 3)`, `dynamic_offset` `(T, V, 3)` (zero), and
/// `timestep_index` `(R,)`: the R timesteps that were refined.
pub const REFINED_NPZ: &str = "refined_flame_param.npz";
/// Its index: which `flame_param` file and timestep each row refines.
pub const REFINED_INDEX: &str = "refined_flame_param.json";

/// Refined FLAME parameters of a trained avatar: one [`HeadPose`] per training timestep.
#[derive(Clone, Debug, PartialEq)]
pub struct RefinedParams {
    /// `flame_param_path` of each row (relative to the transforms file's folder).
    pub keys: Vec<String>,
    /// `timestep_index` of each row.
    pub timesteps: Vec<usize>,
    /// The refined parameters (the subject's shape and static offsets included).
    pub poses: Vec<HeadPose>,
    /// Vertices of the head model (the size of the file's offsets).
    pub num_vertices: usize,
}

/// The JSON index next to [`REFINED_NPZ`].
#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct RefinedIndex {
    flame_param_path: Vec<String>,
    timestep_index: Vec<usize>,
}

impl RefinedParams {
    /// The parameters of `key`'s timestep, when it was refined.
    pub fn get(&self, key: &str) -> Option<&HeadPose> {
        self.keys
            .iter()
            .position(|k| k == key)
            .map(|r| &self.poses[r])
    }

    /// Writes [`REFINED_NPZ`] and [`REFINED_INDEX`] into `dir`.
    pub fn save(&self, dir: &Path) -> Result<()> {
        let npz = dir.join(REFINED_NPZ);
        let what = npz.display().to_string();
        let Some(first) = self.poses.first() else {
            return Err(Error::invalid(&what, "frames", "none"));
        };
        let (e, v) = (first.expr.len(), self.num_vertices);
        // Row t of the file is timestep t (GaussianAvatars indexes `flame_param[k][[t]]`).
        let t_len = self.timesteps.iter().max().map_or(0, |&t| t + 1);
        let mut row_of = vec![None; t_len];
        for (r, (&t, p)) in self.timesteps.iter().zip(&self.poses).enumerate() {
            p.check_finite(&what)?;
            if p.expr.len() != e {
                return Err(Error::invalid(
                    &what,
                    "expr",
                    format!("row {r} has {} coefficients, row 0 {e}", p.expr.len()),
                ));
            }
            if let Some(q) = row_of[t].replace(r) {
                return Err(Error::invalid(
                    &what,
                    "timestep_index",
                    format!(
                        "timestep {t} is refined twice ({} and {})",
                        self.keys[q], self.keys[r]
                    ),
                ));
            }
        }
        let rows = |n: usize, f: &dyn Fn(&HeadPose) -> Vec<f32>| -> Vec<f32> {
            row_of
                .iter()
                .flat_map(|r| match r {
                    Some(r) => f(&self.poses[*r]),
                    None => vec![0.0; n],
                })
                .collect()
        };
        let static_offset = match &first.static_offset {
            Some(o) if o.len() == v => o.concat(),
            Some(o) => {
                return Err(Error::invalid(
                    &what,
                    "static_offset",
                    format!("{} vertices, the head model has {v}", o.len()),
                ));
            }
            None => vec![0.0; v * 3],
        };
        let mut out = NpzOut::default();
        out.floats(
            "translation",
            &[t_len, 3],
            rows(3, &|p| p.translation.to_vec()),
        )
        .floats("rotation", &[t_len, 3], rows(3, &|p| p.rotation.to_vec()))
        .floats("neck_pose", &[t_len, 3], rows(3, &|p| p.neck.to_vec()))
        .floats("jaw_pose", &[t_len, 3], rows(3, &|p| p.jaw.to_vec()))
        .floats("eyes_pose", &[t_len, 6], rows(6, &|p| p.eyes.to_vec()))
        .floats("expr", &[t_len, e], rows(e, &|p| p.expr.clone()))
        .floats("shape", &[first.shape.len()], first.shape.clone())
        .floats("static_offset", &[1, v, 3], static_offset)
        .floats("dynamic_offset", &[t_len, v, 3], vec![0.0; t_len * v * 3])
        .ints(
            "timestep_index",
            &[self.timesteps.len()],
            self.timesteps.iter().map(|&x| x as i64).collect(),
        );
        out.write(&npz)?;
        let index = RefinedIndex {
            flame_param_path: self.keys.clone(),
            timestep_index: self.timesteps.clone(),
        };
        let path = dir.join(REFINED_INDEX);
        std::fs::write(
            &path,
            serde_json::to_string_pretty(&index).expect("serialises") + "\n",
        )
        .map_err(|e| Error::io(&path, e))
    }

    /// Reads what [`RefinedParams::save`] wrote into `dir`; `None` when `dir` has no
    /// [`REFINED_NPZ`] (a run without refinement).
    pub fn load(dir: &Path) -> Result<Option<Self>> {
        let npz = dir.join(REFINED_NPZ);
        if !npz.is_file() {
            return Ok(None);
        }
        let path = dir.join(REFINED_INDEX);
        let what = path.display().to_string();
        let text = std::fs::read_to_string(&path).map_err(|e| Error::io(&path, e))?;
        let index: RefinedIndex = serde_json::from_str(&text).map_err(|e| {
            Error::invalid(
                &what,
                format!("line {} column {}", e.line(), e.column()),
                e.to_string(),
            )
        })?;
        let frames = HeadPose::load_npz_frames(&npz)?;
        let mut z = Npz::open(&npz)?;
        let stored = z.ints("timestep_index")?.data;
        // Files written by earlier versions hold one row per refined timestep, in the index's
        // order, without `dynamic_offset`; read them as they were written.
        let by_row = !z.has("dynamic_offset");
        let num_vertices = if by_row {
            if frames.len() != index.timestep_index.len() {
                return Err(Error::invalid(
                    &what,
                    "timestep_index",
                    format!(
                        "{} timesteps for the {} rows of {} (no dynamic_offset: one row per timestep)",
                        index.timestep_index.len(),
                        frames.len(),
                        npz.display()
                    ),
                ));
            }
            frames[0].static_offset.as_ref().map_or(0, Vec::len)
        } else {
            let offsets = z.floats("dynamic_offset")?.shape;
            match offsets.as_slice() {
                [t, v, 3] if *t == frames.len() => *v,
                _ => {
                    return Err(Error::invalid(
                        npz.display().to_string(),
                        "dynamic_offset",
                        format!("shape {offsets:?}, expected ({}, V, 3)", frames.len()),
                    ));
                }
            }
        };
        if index.flame_param_path.len() != index.timestep_index.len() {
            return Err(Error::invalid(
                &what,
                "flame_param_path",
                format!(
                    "{} paths for {} timesteps",
                    index.flame_param_path.len(),
                    index.timestep_index.len()
                ),
            ));
        }
        if stored
            .iter()
            .map(|&x| x as usize)
            .ne(index.timestep_index.iter().copied())
        {
            return Err(Error::invalid(
                &what,
                "timestep_index",
                format!("differs from {}'s timestep_index", npz.display()),
            ));
        }
        let poses = index
            .timestep_index
            .iter()
            .enumerate()
            .map(|(r, &t)| {
                frames
                    .get(if by_row { r } else { t })
                    .cloned()
                    .ok_or_else(|| {
                        Error::invalid(
                            &what,
                            "timestep_index",
                            format!(
                                "timestep {t}, but {} has {} rows",
                                npz.display(),
                                frames.len()
                            ),
                        )
                    })
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Some(RefinedParams {
            keys: index.flame_param_path,
            timesteps: index.timestep_index,
            poses,
            num_vertices,
        }))
    }

    /// Writes one VHAP `flame_param` file per row into `dir/flame_param/TTTTT.npz`
    /// (`TTTTT`: the row's `timestep_index`), in the layout of VHAP's
    /// `NeRFDatasetWriter.write_flame_param` (`vhap/export_as_nerf_dataset.py`). Returns
    /// the files written.
    pub fn export_vhap(&self, dir: &Path) -> Result<Vec<std::path::PathBuf>> {
        let folder = dir.join("flame_param");
        std::fs::create_dir_all(&folder).map_err(|e| Error::io(&folder, e))?;
        self.timesteps
            .iter()
            .zip(&self.poses)
            .map(|(t, p)| {
                let path = folder.join(format!("{t:05}.npz"));
                p.save_npz(&path)?;
                Ok(path)
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pose(k: f32) -> HeadPose {
        HeadPose {
            shape: vec![0.5, -0.25, 0.125, 1.0],
            expr: (0..5).map(|i| k + i as f32 * 0.01).collect(),
            rotation: [k, 0.1, 0.2],
            neck: [0.0, k, 0.0],
            jaw: [k * 0.5, 0.0, 0.0],
            eyes: [k, 0.0, 0.0, 0.0, k, 0.0],
            translation: [0.0, 0.0, k],
            static_offset: None,
        }
    }

    fn params() -> RefinedParams {
        RefinedParams {
            keys: vec![
                "flame_param/00003.npz".into(),
                "flame_param/00001.npz".into(),
            ],
            timesteps: vec![3, 1],
            poses: vec![pose(1.0), pose(2.0)],
            num_vertices: 6,
        }
    }

    fn temp(name: &str) -> std::path::PathBuf {
        let d = std::env::temp_dir().join(format!("texavatars-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).expect("temp dir");
        d
    }

    /// The file reads as GaussianAvatars reads its own `flame_param.npz`
    /// (`scene/flame_gaussian_model.py`): `load_ply` takes every array as is,
    /// `select_mesh_by_timestep(t)` takes `shape[None]`, row `[t]` of `expr`, `rotation`,
    /// `neck_pose`, `jaw_pose`, `eyes_pose`, `translation` and `dynamic_offset`, and
    /// `static_offset` whole; `load_meshes` zero-fills the rows of timesteps without a mesh.
    #[test]
    fn saved_file_has_gaussianavatars_flame_param_layout() {
        let dir = temp("refined-ga");
        let p = params();
        p.save(&dir).expect("save");
        let mut z = Npz::open(&dir.join(REFINED_NPZ)).expect("open");
        let (t_len, v) = (4, 6);
        for (name, width) in [
            ("expr", 5),
            ("rotation", 3),
            ("neck_pose", 3),
            ("jaw_pose", 3),
            ("eyes_pose", 6),
            ("translation", 3),
        ] {
            let a = z.floats(name).expect(name);
            assert_eq!(a.shape, vec![t_len, width], "{name}");
            let row = |t: usize| a.data[t * width..(t + 1) * width].to_vec();
            for (&t, q) in p.timesteps.iter().zip(&p.poses) {
                let want = match name {
                    "expr" => q.expr.clone(),
                    "rotation" => q.rotation.to_vec(),
                    "neck_pose" => q.neck.to_vec(),
                    "jaw_pose" => q.jaw.to_vec(),
                    "eyes_pose" => q.eyes.to_vec(),
                    _ => q.translation.to_vec(),
                };
                assert_eq!(row(t), want, "{name} row {t}");
            }
            for t in [0, 2] {
                assert!(row(t).iter().all(|&x| x == 0.0), "{name} row {t}");
            }
        }
        assert_eq!(z.floats("shape").expect("shape").shape, vec![4]);
        let so = z.floats("static_offset").expect("static_offset");
        assert_eq!(so.shape, vec![1, v, 3]);
        let dyn_off = z.floats("dynamic_offset").expect("dynamic_offset");
        assert_eq!(dyn_off.shape, vec![t_len, v, 3]);
        assert!(dyn_off.data.iter().all(|&x| x == 0.0));
        assert_eq!(z.ints("timestep_index").expect("index").data, vec![3, 1]);

        // Our reader gives the rows back (the subject's missing static offset as zeros).
        let back = RefinedParams::load(&dir).expect("load").expect("present");
        let mut want = p.clone();
        for q in &mut want.poses {
            q.static_offset = Some(vec![[0.0; 3]; v]);
        }
        assert_eq!(back, want);
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn a_timestep_refined_twice_is_refused() {
        let dir = temp("refined-twice");
        let mut p = params();
        p.timesteps[1] = 3;
        let e = p.save(&dir).expect_err("duplicate").to_string();
        assert!(e.contains("timestep 3 is refined twice"), "{e}");
        assert!(!dir.join(REFINED_NPZ).exists());
        std::fs::remove_dir_all(&dir).ok();
    }

    /// Runs before the GaussianAvatars layout wrote one row per refined timestep, in the
    /// index's order, without `dynamic_offset`; they still load.
    #[test]
    fn files_with_one_row_per_timestep_still_load() {
        let dir = temp("refined-rows");
        let p = params();
        let rows = |f: &dyn Fn(&HeadPose) -> Vec<f32>| -> Vec<f32> {
            p.poses.iter().flat_map(f).collect()
        };
        let mut out = NpzOut::default();
        out.floats("translation", &[2, 3], rows(&|q| q.translation.to_vec()))
            .floats("rotation", &[2, 3], rows(&|q| q.rotation.to_vec()))
            .floats("neck_pose", &[2, 3], rows(&|q| q.neck.to_vec()))
            .floats("jaw_pose", &[2, 3], rows(&|q| q.jaw.to_vec()))
            .floats("eyes_pose", &[2, 6], rows(&|q| q.eyes.to_vec()))
            .floats("expr", &[2, 5], rows(&|q| q.expr.clone()))
            .floats("shape", &[4], p.poses[0].shape.clone())
            .ints("timestep_index", &[2], vec![3, 1]);
        out.write(&dir.join(REFINED_NPZ)).expect("write");
        let index = RefinedIndex {
            flame_param_path: p.keys.clone(),
            timestep_index: p.timesteps.clone(),
        };
        std::fs::write(
            dir.join(REFINED_INDEX),
            serde_json::to_string(&index).expect("json"),
        )
        .expect("write");
        let back = RefinedParams::load(&dir).expect("load").expect("present");
        assert_eq!(back.poses, p.poses);
        assert_eq!(back.timesteps, p.timesteps);
        std::fs::remove_dir_all(&dir).ok();
    }
}
