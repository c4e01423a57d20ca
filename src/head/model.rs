//! A FLAME-compatible head model: the arrays of FLAME's model file, in an `.npz`.
//!
//! | array | shape | meaning |
//! |---|---|---|
//! | `v_template` | [V, 3] | template vertices |
//! | `shapedirs` | [V, 3, S + E] | shape then expression blendshapes |
//! | `posedirs` | [V, 3, 9 (J - 1)] or [9 (J - 1), 3 V] | pose-corrective blendshapes |
//! | `J_regressor` | [J, V] | joint regressor (dense) |
//! | `weights` | [V, J] | skinning weights |
//! | `kintree_table` | [2, J] | row 0: parent of each joint (root: -1 or 2^32 - 1) |
//! | `f` | [F, 3] | triangles |
//! | `num_shape` (optional) | `[]` or `[1]` | S; absent: 300 when S + E = 400 (FLAME 2023) |
//!
//! FLAME's joints are root (global), neck, jaw, left eye, right eye: pose vectors are
//! `[global 3, neck 3, jaw 3, eyes 6]` in axis-angle.

use std::path::Path;

use crate::error::{Error, Result};
use crate::io::npz::{Npz, NpzOut};

/// FLAME's number of joints.
pub const JOINTS: usize = 5;
/// Shape coefficients in FLAME 2023's `shapedirs` (then 100 expression coefficients).
pub const FLAME_SHAPE: usize = 300;

/// A FLAME-compatible linear blend skinning model.
///
/// # Shapes
/// - `v_template`: [V, 3]; `shapedirs`: [V, 3, K] with K = `num_shape + num_expr`;
///   `posedirs`: [V, 3, 9 (J - 1)]; `j_regressor`: [J, V]; `weights`: [V, J];
///   `parents`: `[J]` (`None` for the root); `faces`: [F, 3]
#[derive(Clone, Debug, PartialEq)]
pub struct HeadModel {
    pub v_template: Vec<[f32; 3]>,
    pub shapedirs: Vec<f32>,
    pub num_shape: usize,
    pub num_expr: usize,
    pub posedirs: Vec<f32>,
    pub j_regressor: Vec<f32>,
    pub weights: Vec<f32>,
    pub parents: Vec<Option<usize>>,
    pub faces: Vec<[u32; 3]>,
}

impl HeadModel {
    /// Number of vertices.
    pub fn num_vertices(&self) -> usize {
        self.v_template.len()
    }

    /// Number of joints.
    pub fn num_joints(&self) -> usize {
        self.parents.len()
    }

    /// Checks every array's shape and every index; `what` names the source in errors.
    pub fn validate(&self, what: &str) -> Result<()> {
        let v = self.num_vertices();
        let j = self.num_joints();
        let k = self.num_shape + self.num_expr;
        let expect = |field: &str, got: usize, want: usize| {
            if got == want {
                Ok(())
            } else {
                Err(Error::invalid(
                    what,
                    field,
                    format!("{got} values, expected {want}"),
                ))
            }
        };
        if v == 0 {
            return Err(Error::invalid(what, "v_template", "no vertices"));
        }
        expect("shapedirs", self.shapedirs.len(), v * 3 * k)?;
        expect(
            "posedirs",
            self.posedirs.len(),
            v * 3 * 9 * j.saturating_sub(1),
        )?;
        expect("J_regressor", self.j_regressor.len(), j * v)?;
        expect("weights", self.weights.len(), v * j)?;
        let arrays: [(&str, &[f32]); 5] = [
            ("v_template", self.v_template.as_flattened()),
            ("shapedirs", &self.shapedirs),
            ("posedirs", &self.posedirs),
            ("J_regressor", &self.j_regressor),
            ("weights", &self.weights),
        ];
        for (field, values) in arrays {
            if let Some(i) = values.iter().position(|x| !x.is_finite()) {
                return Err(Error::invalid(
                    what,
                    field,
                    format!("value {i} is {}", values[i]),
                ));
            }
        }
        for (i, p) in self.parents.iter().enumerate() {
            match p {
                None if i != 0 => {
                    return Err(Error::invalid(
                        what,
                        "kintree_table",
                        format!("joint {i} has no parent; only joint 0 may be the root"),
                    ));
                }
                Some(_) if i == 0 => {
                    return Err(Error::invalid(
                        what,
                        "kintree_table",
                        "joint 0 must be the root",
                    ));
                }
                Some(q) if *q >= i => {
                    return Err(Error::invalid(
                        what,
                        "kintree_table",
                        format!("joint {i}'s parent {q} does not come before it"),
                    ));
                }
                _ => {}
            }
        }
        if let Some((i, f)) = self
            .faces
            .iter()
            .enumerate()
            .find(|(_, f)| f.iter().any(|&x| x as usize >= v))
        {
            return Err(Error::invalid(
                what,
                "f",
                format!("face {i} {f:?} indexes past {v} vertices"),
            ));
        }
        Ok(())
    }

    /// Loads the model from an `.npz` (see the module documentation).
    pub fn load(path: &Path) -> Result<Self> {
        Self::from_npz(Npz::open(path)?, path)
    }

    /// Reads the model from an `.npz` held in memory; `path` names it in error messages.
    pub fn from_bytes(bytes: Vec<u8>, path: &Path) -> Result<Self> {
        Self::from_npz(Npz::from_bytes(bytes, path)?, path)
    }

    fn from_npz(mut z: Npz, path: &Path) -> Result<Self> {
        let what = path.display().to_string();
        let shape_err = |field: &str, got: &[usize], want: &str| {
            Error::invalid(&what, field, format!("shape {got:?}, expected {want}"))
        };
        let vt = z.floats("v_template")?;
        if vt.shape.len() != 2 || vt.shape[1] != 3 {
            return Err(shape_err("v_template", &vt.shape, "[V, 3]"));
        }
        let v = vt.shape[0];
        let sd = z.floats("shapedirs")?;
        if sd.shape.len() != 3 || sd.shape[0] != v || sd.shape[1] != 3 {
            return Err(shape_err("shapedirs", &sd.shape, &format!("[{v}, 3, K]")));
        }
        let k = sd.shape[2];
        let num_shape = if z.has("num_shape") {
            let n = z.ints("num_shape")?;
            match n.data.as_slice() {
                [s] if *s >= 0 && (*s as usize) <= k => *s as usize,
                _ => {
                    return Err(Error::invalid(
                        &what,
                        "num_shape",
                        format!("{:?} is not a count <= {k}", n.data),
                    ));
                }
            }
        } else if k == FLAME_SHAPE + 100 {
            FLAME_SHAPE
        } else {
            return Err(Error::invalid(
                &what,
                "num_shape",
                format!("missing, and shapedirs has {k} components (not FLAME 2023's 400)"),
            ));
        };
        let kt = z.ints("kintree_table")?;
        if kt.shape.len() != 2 || kt.shape[0] != 2 {
            return Err(shape_err("kintree_table", &kt.shape, "[2, J]"));
        }
        let j = kt.shape[1];
        let parents: Vec<Option<usize>> = kt.data[..j]
            .iter()
            .map(|&p| {
                if p < 0 || p >= j as i64 {
                    None
                } else {
                    Some(p as usize)
                }
            })
            .collect();
        let jr = z.floats("J_regressor")?;
        if jr.shape != [j, v] {
            return Err(shape_err("J_regressor", &jr.shape, &format!("[{j}, {v}]")));
        }
        let w = z.floats("weights")?;
        if w.shape != [v, j] {
            return Err(shape_err("weights", &w.shape, &format!("[{v}, {j}]")));
        }
        let p = 9 * j.saturating_sub(1);
        let pd = z.floats("posedirs")?;
        let posedirs = if pd.shape == [v, 3, p] {
            pd.data
        } else if pd.shape == [p, 3 * v] {
            // The FLAME PyTorch layout: transpose to [V, 3, P].
            let mut out = vec![0.0f32; v * 3 * p];
            for q in 0..p {
                for i in 0..3 * v {
                    out[i * p + q] = pd.data[q * 3 * v + i];
                }
            }
            out
        } else {
            return Err(shape_err(
                "posedirs",
                &pd.shape,
                &format!("[{v}, 3, {p}] or [{p}, {}]", 3 * v),
            ));
        };
        let f = z.ints("f")?;
        if f.shape.len() != 2 || f.shape[1] != 3 {
            return Err(shape_err("f", &f.shape, "[F, 3]"));
        }
        let faces = f
            .data
            .chunks(3)
            .map(|c| {
                c.iter()
                    .map(|&x| u32::try_from(x).unwrap_or(u32::MAX))
                    .collect::<Vec<_>>()
            })
            .map(|c| [c[0], c[1], c[2]])
            .collect();
        let model = HeadModel {
            v_template: vt.data.chunks(3).map(|c| [c[0], c[1], c[2]]).collect(),
            shapedirs: sd.data,
            num_shape,
            num_expr: k - num_shape,
            posedirs,
            j_regressor: jr.data,
            weights: w.data,
            parents,
            faces,
        };
        model.validate(&what)?;
        Ok(model)
    }

    /// Writes the model as an `.npz` in the layout [`load`](Self::load) reads.
    pub fn save(&self, path: &Path) -> Result<()> {
        self.to_npz(&path.display().to_string())?.write(path)
    }

    /// The model's arrays as [`save`](Self::save) writes them, for a caller that adds
    /// arrays of its own before writing; `what` names the model in errors.
    pub fn to_npz(&self, what: &str) -> Result<NpzOut> {
        self.validate(what)?;
        let v = self.num_vertices();
        let j = self.num_joints();
        let k = self.num_shape + self.num_expr;
        let mut parents: Vec<i64> = self
            .parents
            .iter()
            .map(|p| p.map_or(-1, |p| p as i64))
            .collect();
        parents.extend((0..j).map(|i| i as i64));
        let mut out = NpzOut::default();
        out.floats("v_template", &[v, 3], self.v_template.concat())
            .floats("shapedirs", &[v, 3, k], self.shapedirs.clone())
            .floats(
                "posedirs",
                &[v, 3, 9 * j.saturating_sub(1)],
                self.posedirs.clone(),
            )
            .floats("J_regressor", &[j, v], self.j_regressor.clone())
            .floats("weights", &[v, j], self.weights.clone())
            .ints("kintree_table", &[2, j], parents)
            .ints(
                "f",
                &[self.faces.len(), 3],
                self.faces.iter().flatten().map(|&x| x as i64).collect(),
            )
            .ints("num_shape", &[1], vec![self.num_shape as i64]);
        Ok(out)
    }
}
