//! Head models: FLAME-compatible model files, per-frame parameters, linear blend
//! skinning, the meta side file, and the embedded CC0 default head with its importer.

pub mod asset;
pub mod lbs;
pub mod meta;
pub mod model;
pub mod mpfb;
pub mod params;
pub mod rig;
pub mod teeth;

pub use asset::HeadAsset;
pub use lbs::{HeadPose, lbs};
pub use meta::HeadMeta;
pub use model::HeadModel;
pub use rig::Rig;
