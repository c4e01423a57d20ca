//! `texavatars view`: drive a trained avatar live in a web browser, on the CPU.
//!
//! A local web server ([`server`], axum on tokio) serves one page (static files embedded in
//! the binary: no CDN, no network at run time) and a WebSocket. The page sends the user's
//! camera, expression sliders, jaw / neck / eye rotations, eta switch and motion frame as
//! one JSON request per change ([`protocol`]); the render thread ([`scene`]) runs the
//! avatar's own networks, lift and rasterizer and answers with a JPEG and the time of each
//! stage. Latest request wins: while a frame renders, newer requests replace the waiting
//! one, so the page never lags behind the user's hand. A dataset motion adds its cameras as
//! presets and its images as ground truth, with the PSNR. The page also saves the current
//! frame as PNG and the current Gaussians as a world-space PLY. Every size and rate is
//! bounded ([`limits`]).
//!
//! In the data flow it is a sibling of [`crate::drive`] (which it uses): a tool on top of a
//! trained avatar of either model ([`crate::models::Drivable`]).

pub mod limits;
pub mod protocol;
pub mod scene;
pub mod server;

pub use scene::{Info, Scene, SceneOptions};
pub use server::{ViewOptions, Viewer};
