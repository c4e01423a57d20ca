//! GaussianAvatars (Qian et al., CVPR 2024), the binding baseline: Gaussians stored local to
//! the FLAME triangle each is bound to ([`binding`]), placed every frame by that triangle's
//! posed frame. A sibling of [`crate::models::texavatars`]; both offer [`crate::models::Drivable`].
//!
//! What is here: GaussianAvatars' output folders ([`folder`]: `point_cloud.ply` with
//! `binding_0`, SH degree 0-3, and `flame_param.npz`) loaded, driven, rendered by
//! texavatars' rasterizer and exported as world-space PLY files; [`model`], the stored
//! Gaussians as a burn module placed by differentiable tensor ops (the lift's, with
//! GaussianAvatars' frames). Training it (adaptive density control with binding
//! inheritance, its objective and schedule, FLAME refinement) is
//! [`crate::train::gaussianavatars`].

pub mod binding;
pub mod folder;
pub mod model;

pub use binding::{FaceFrame, face_frames, to_world};
pub use folder::GaAvatar;
pub use model::GaModel;
