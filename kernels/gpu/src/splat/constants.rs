//! Every magic number of the Gaussian rasterizer, with the reason for it.
//!
//! The reference (dense burn ops), the CPU tile renderer and the GPU kernels all read these,
//! so the three implementations cannot drift apart. The values are the conventions of
//! gsplat's classic pinhole mode, which the fixtures in `tests/fixtures/splat` follow.

/// Side of a square screen tile in pixels. 16x16 = 256 threads per workgroup on the GPU.
pub const TILE_SIZE: u32 = 16;

/// Pixels per tile.
pub const TILE_PIXELS: u32 = TILE_SIZE * TILE_SIZE;

/// Gaussians whose camera-space depth is at or below this are culled (near plane).
pub const NEAR_PLANE: f32 = 0.01;

/// Isotropic screen-space low-pass filter added to every projected covariance, in pixels^2.
/// It makes every splat at least about one pixel wide (anti-aliasing, as in 3DGS).
pub const LOW_PASS: f32 = 0.3;

/// The EWA Jacobian is evaluated at the mean's tangent clamped to the image's field of view
/// widened by this fraction of the half-width (`lim = (W - cx)/fx + FOV_MARGIN * 0.5 W / fx`),
/// so Gaussians far outside the view do not get huge screen footprints.
pub const FOV_MARGIN: f32 = 0.3;

/// Upper clamp of a Gaussian's alpha at a pixel: keeps 1 - alpha away from zero so the
/// backward pass can divide by it.
pub const ALPHA_MAX: f32 = 0.99;

/// A Gaussian contributes to a pixel only where its alpha reaches this (8-bit visibility).
pub const ALPHA_MIN: f32 = 1.0 / 255.0;

/// A pixel stops compositing once its transmittance would fall below this.
pub const TRANSMITTANCE_MIN: f32 = 1e-4;

/// Determinants of the projected covariance at or below this are treated as degenerate
/// (not positive definite): the Gaussian is culled.
pub const MIN_DET: f32 = 0.0;

/// Relative safety margin on the opacity-aware screen extent of a Gaussian when choosing the
/// tiles it touches. The extent is exact in real arithmetic; the margin absorbs float32
/// rounding in the conic and in `exp`, so no pixel whose alpha reaches [`ALPHA_MIN`] can fall
/// outside the tiles a Gaussian is listed in. Extra tiles cost time, never correctness.
pub const BOUNDS_REL_MARGIN: f32 = 1e-3;

/// Absolute safety margin (pixels) added to the screen extent, for the same reason as
/// [`BOUNDS_REL_MARGIN`] when the extent itself is close to zero.
pub const BOUNDS_ABS_MARGIN: f32 = 1e-2;

/// Per-Gaussian floats in the projection buffer the GPU forward pass keeps for the backward:
/// `u, v, conic a, conic b, conic c, depth z, opacity, tiles touched` (see `project.rs`).
pub const PROJECTED_STRIDE: u32 = 8;

/// Per-Gaussian floats of the screen-space gradient the backward rasterizer accumulates:
/// `d/du, d/dv, d/dconic a, d/dconic b, d/dconic c, d/dr, d/dg, d/db, d/dopacity`.
pub const GRAD2D_STRIDE: u32 = 9;
