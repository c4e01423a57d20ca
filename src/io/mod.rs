//! File formats shared by the commands: `.npy` and `.npz` arrays and PNG images.

pub mod image;
pub mod npy;
pub mod npz;
