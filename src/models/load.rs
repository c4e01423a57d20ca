//! Loading whichever model an output folder holds: the one place that names the models
//! ([`super::texavatars`], [`super::gaussianavatars`]); everything above holds a
//! [`Drivable`].

use std::path::{Path, PathBuf};

use burn::module::Module;
use burn::tensor::Device;

use super::drivable::Drivable;
use super::gaussianavatars::GaAvatar;
use super::texavatars::files;
use super::texavatars::{Avatar, AvatarConfig};
use crate::error::{Error, Result};
use crate::head::HeadAsset;

/// An avatar loaded from an output folder, with the subject file it was trained on.
pub struct Loaded {
    pub avatar: Box<dyn Drivable>,
    /// The FLAME parameter file that holds the avatar's subject (shape, static offsets),
    /// when the folder has one: a `train` run's `canonical_flame_param.npz`, a
    /// GaussianAvatars folder's `flame_param.npz`.
    pub identity: Option<PathBuf>,
}

/// Loads whichever model `checkpoint` holds, for `head`: a GaussianAvatars output folder
/// ([`GaAvatar::find`]), else a `texavatars train` run.
pub fn load(checkpoint: &Path, head: &HeadAsset, device: &Device) -> Result<Loaded> {
    if GaAvatar::find(checkpoint).is_some() {
        let ga = GaAvatar::load(checkpoint, &head.model.faces, head.model.num_vertices())?;
        let identity = ga.flame_param();
        return Ok(Loaded {
            avatar: Box::new(ga),
            identity,
        });
    }
    let avatar = load_avatar(checkpoint, head, device)?;
    let identity = checkpoint.join(files::IDENTITY);
    Ok(Loaded {
        avatar: Box::new(avatar),
        identity: identity.is_file().then_some(identity),
    })
}

/// Loads a trained avatar from a training run's folder, for inference (weight norms folded:
/// [`Avatar::for_inference`]).
pub fn load_avatar(run: &Path, head: &HeadAsset, device: &Device) -> Result<Avatar> {
    let cfg_path = run.join(files::AVATAR_CONFIG);
    let text = std::fs::read_to_string(&cfg_path).map_err(|e| Error::io(&cfg_path, e))?;
    let cfg: AvatarConfig = serde_json::from_str(&text).map_err(|e| {
        Error::invalid(
            cfg_path.display().to_string(),
            format!("line {}", e.line()),
            e.to_string(),
        )
    })?;
    let weights = run.join(files::AVATAR);
    if !weights.exists() {
        return Err(Error::invalid(
            weights.display().to_string(),
            "avatar",
            "missing: the run has not finished (train it, or resume it with `texavatars train --resume`)",
        ));
    }
    let avatar = cfg
        .init(&head.mesh, device)?
        .try_load_file(&weights)
        .map_err(|e| Error::invalid(weights.display().to_string(), "record", e.to_string()))?;
    // A diverged run's NaN weights would render white frames without a word.
    avatar.check_finite(&weights.display().to_string())?;
    Ok(Avatar::for_inference(avatar))
}
