//! Small helpers below every other module: [`rng`] (seeded random numbers) and [`files`]
//! (clearing a command's own files from an output folder).

pub mod files;
pub mod rng;
