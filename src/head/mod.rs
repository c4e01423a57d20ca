//! FLAME-compatible head models: the model file, per-frame parameters and linear blend
//! skinning.

pub mod lbs;
pub mod model;
pub mod params;

pub use lbs::{HeadPose, lbs};
pub use model::HeadModel;
