//! Texel (UV) space: layout maps computed once per topology, the sample grid, and the
//! per-frame geometry (position map, per-face frames).

pub mod frames;
pub mod inspect;
pub mod layout;
pub mod samples;

pub use frames::FrameKind;
pub use layout::UvLayout;
pub use samples::SampleGrid;
