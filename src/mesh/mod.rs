//! Triangle meshes with UV layouts.

pub mod obj;
pub mod procedural;

pub use obj::UvMesh;
