//! Loading the training module of a checkpoint ([`from_checkpoint`]) with the shapes the
//! densified Gaussians had when it was written.

use std::path::Path;

use burn::tensor::{Device, TensorData};

use super::state::{DensityState, GaSetup};
use super::step::GaTraining;
use crate::error::{Error, Result};
use crate::models::gaussianavatars::model::GaModel;
use crate::train::gaussianavatars::density::Stats;
use crate::train::refine::FlameRefinement;

/// The module of a checkpoint's record (`model-E.bpk`): the Gaussians, binding and
/// statistics it holds, so that burn's own load finds matching shapes (densification
/// changes them).
pub fn from_checkpoint(
    path: &Path,
    setup: GaSetup,
    refine: Option<FlameRefinement>,
    device: &Device,
) -> Result<GaTraining> {
    let what = path.display().to_string();
    let reader = burn_pack::Reader::from_file(path)
        .map_err(|e| Error::invalid(&what, "burnpack", e.to_string()))?;
    let mut floats = std::collections::HashMap::new();
    for t in reader
        .into_tensors()
        .map_err(|e| Error::invalid(&what, "burnpack", e.to_string()))?
    {
        let (name, dtype, shape, _, bytes) = t
            .into_parts()
            .map_err(|e| Error::invalid(&what, "burnpack", e.to_string()))?;
        let data = TensorData::from_bytes(bytes, shape.clone(), dtype);
        let values: Vec<f64> = data.iter::<f64>().collect();
        floats.insert(name, (shape.as_slice().to_vec(), values));
    }
    let get = |name: &str| -> Result<(Vec<usize>, Vec<f64>)> {
        floats
            .get(name)
            .cloned()
            .ok_or_else(|| Error::invalid(&what, name, "missing from the checkpoint"))
    };
    let f32s = |v: Vec<f64>| -> Vec<f32> { v.into_iter().map(|x| x as f32).collect() };
    let (_, xyz) = get("model.xyz")?;
    let (dc_shape, dc) = get("model.features_dc")?;
    let n = dc_shape[0];
    let rest = get("model.features_rest").ok();
    let k = 1 + rest.as_ref().map_or(0, |(s, _)| s[1]);
    let mut sh = Vec::with_capacity(n * k * 3);
    for g in 0..n {
        sh.extend(dc[3 * g..3 * g + 3].iter().map(|&x| x as f32));
        if let Some((_, r)) = &rest {
            let w = (k - 1) * 3;
            sh.extend(r[w * g..w * (g + 1)].iter().map(|&x| x as f32));
        }
    }
    let degree = (k as f64).sqrt() as usize - 1;
    let stored = crate::splat::ply::PlyGaussians {
        means: f32s(xyz),
        sh,
        sh_degree: degree,
        opacity_logits: f32s(get("model.opacity")?.1),
        log_scales: f32s(get("model.scaling")?.1),
        quats: f32s(get("model.rotation")?.1),
    };
    let binding: Vec<u32> = get("model.binding")?.1.iter().map(|&b| b as u32).collect();
    let model = GaModel::from_stored(&stored, &binding, device)?;
    let stats = Stats {
        grad_accum: f32s(get("density.grad_accum")?.1),
        denom: f32s(get("density.denom")?.1),
        max_radii: f32s(get("density.max_radii")?.1),
    };
    let density = DensityState::new(stats, f32s(get("density.face_scale")?.1), device);
    Ok(GaTraining {
        model,
        density,
        refine,
        setup,
    })
}
