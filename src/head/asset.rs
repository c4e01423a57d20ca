//! A head as the rest of the project uses it: model, UV mesh of the same topology, meta.
//! The embedded default is the CC0 MakeHuman head made by `texavatars head import-mpfb`
//! (see `src/head/default/ATTRIBUTION.md`).

use std::path::{Path, PathBuf};

use crate::error::{Error, Result};
use crate::head::meta::HeadMeta;
use crate::head::model::HeadModel;
use crate::head::teeth::{LOWER_RINGS, LipRings, UPPER_RINGS, add_teeth};
use crate::mesh::obj::UvMesh;

const DEFAULT_NPZ: &[u8] = include_bytes!("default/head.npz");
const DEFAULT_OBJ: &str = include_str!("default/head.obj");
const DEFAULT_META: &str = include_str!("default/head.json");

/// Model, UV mesh and meta of one head.
#[derive(Clone, Debug)]
pub struct HeadAsset {
    pub model: HeadModel,
    pub mesh: UvMesh,
    pub meta: HeadMeta,
}

impl HeadAsset {
    /// The embedded default head (no file or network access).
    pub fn embedded() -> Result<Self> {
        let name = Path::new("<embedded>/head");
        let model = HeadModel::from_bytes(DEFAULT_NPZ.to_vec(), &name.with_extension("npz"))?;
        let mesh = UvMesh::parse(DEFAULT_OBJ, "<embedded>/head.obj")?;
        let meta = HeadMeta::parse(DEFAULT_META, &name.with_extension("json"))?;
        Self::new(model, mesh, meta, "<embedded>/head")
    }

    /// Loads `model` (`.npz`), its UV mesh (`obj`, default: the same name with `.obj`)
    /// and the meta `head.json`-style side file (same name with `.json`; absent: none).
    pub fn load(model: &Path, obj: Option<&Path>) -> Result<Self> {
        let obj: PathBuf = obj.map_or_else(|| model.with_extension("obj"), Path::to_path_buf);
        let meta_path = model.with_extension("json");
        let meta = if meta_path.exists() {
            HeadMeta::load(&meta_path)?
        } else {
            HeadMeta::default()
        };
        Self::new(
            HeadModel::load(model)?,
            UvMesh::load(&obj)?,
            meta,
            &model.display().to_string(),
        )
    }

    /// Adds VHAP's teeth (see [`crate::head::teeth`]); the new vertices join the meta's
    /// `teeth_upper` (rings 0, 2, 4, 5) and `teeth_lower` (rings 1, 3, 6, 7) sets.
    pub fn with_teeth(&self, rings: &LipRings) -> Result<Self> {
        let v0 = self.model.num_vertices() as u32;
        let n = rings.upper.len() as u32;
        let (model, mesh) = add_teeth(&self.model, Some(&self.mesh), rings)?;
        let mut meta = self.meta.clone();
        for (name, set) in [("teeth_upper", UPPER_RINGS), ("teeth_lower", LOWER_RINGS)] {
            let ranges = meta.vertex_sets.entry(name.to_string()).or_default();
            for r in set.map(|r| r as u32) {
                // Adjacent rings make one range.
                match ranges.last_mut() {
                    Some(last) if last[1] == v0 + r * n => last[1] += n,
                    _ => ranges.push([v0 + r * n, v0 + (r + 1) * n]),
                }
            }
        }
        let mesh = mesh.ok_or_else(|| Error::invalid("teeth", "mesh", "no UV mesh produced"))?;
        Self::new(model, mesh, meta, "teeth")
    }

    fn new(model: HeadModel, mesh: UvMesh, meta: HeadMeta, what: &str) -> Result<Self> {
        if mesh.positions.len() != model.num_vertices() || mesh.faces != model.faces {
            return Err(Error::invalid(
                what,
                "obj",
                format!(
                    "the UV mesh ({} vertices, {} faces) is not the model's topology ({} vertices, {} faces)",
                    mesh.positions.len(),
                    mesh.faces.len(),
                    model.num_vertices(),
                    model.faces.len()
                ),
            ));
        }
        meta.validate(what, model.num_vertices(), model.num_shape, model.num_expr)?;
        Ok(HeadAsset { model, mesh, meta })
    }
}
