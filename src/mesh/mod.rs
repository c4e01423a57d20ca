//! Triangle meshes with UV layouts, and a CPU rasterizer for them.

pub mod obj;
pub mod procedural;
pub mod raster;

pub use obj::UvMesh;
