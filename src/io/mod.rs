//! File formats shared by the commands: `.npy` and `.npz` arrays, PNG images and (read-only,
//! never executed) Python pickles of numpy arrays.

pub mod image;
pub mod npy;
pub mod npz;
pub mod pickle;
