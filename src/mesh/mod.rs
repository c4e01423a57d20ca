//! Triangle meshes with UV layouts.

pub mod obj;

pub use obj::UvMesh;
