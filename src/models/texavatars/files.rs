//! The files of a `texavatars train` run's output folder that the trained avatar is read
//! from (training writes them, [`crate::models::load()`] reads them).

/// The resolved training config of the run (read back by `--resume`).
pub const CONFIG: &str = "train_config.json";
/// The avatar's config (networks and ablations), for loading the trained avatar.
pub const AVATAR_CONFIG: &str = "avatar.json";
/// The trained avatar's parameters (burnpack), written when the run ends.
pub const AVATAR: &str = "avatar.bpk";
/// burn's checkpoint folder.
pub const CHECKPOINTS: &str = "checkpoint";
/// The subject's shape and static offsets the avatar was trained with (VHAP's canonical
/// parameter file).
pub const IDENTITY: &str = crate::data::identity::CANONICAL;
