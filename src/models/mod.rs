//! The avatar models, side by side: [`texavatars`] (the method: decoders in UV space and the
//! texel lift) and [`gaussianavatars`] (the baseline: Gaussians bound to mesh triangles).
//! Neither knows the other; both offer [`Drivable`] ([`drivable`]), and [`load()`] reads
//! whichever one an output folder holds. Training them is [`crate::train`]'s.

pub mod drivable;
pub mod gaussianavatars;
pub mod load;
pub mod texavatars;

pub use drivable::{Drivable, StageMark, ViewCache};
pub use load::{Loaded, load, load_avatar};
