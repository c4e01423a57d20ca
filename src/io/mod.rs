//! File formats shared by the commands: `.npy` arrays and PNG images.

pub mod image;
pub mod npy;
