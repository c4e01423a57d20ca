//! Constants of the lifting operator, shared by the reference, the CPU and the GPU code.

/// Lengths used as divisors are "safe norms" `sqrt(x . x + NORM_EPS^2)`, so that zero-area
/// triangles, zero-length edges and zero quaternions give finite values and gradients. It
/// is far below the geometry of a head in metres (an edge of 1 mm has length 1e-3, a face
/// normal |e1 x e2| ~ 1e-6), so it changes nothing measurable on real meshes.
pub const NORM_EPS: f32 = 1e-8;

/// Local maps' channels: position offset 3, quaternion 4 (w, x, y, z), log-scale 3,
/// opacity logit 1, RGB 3.
pub const LOCAL_CHANNELS: usize = 14;

/// Channel offsets into the local maps.
pub const LOCAL_MEAN: usize = 0;
pub const LOCAL_QUAT: usize = 3;
pub const LOCAL_LOG_SCALE: usize = 7;
pub const LOCAL_OPACITY: usize = 10;
pub const LOCAL_RGB: usize = 11;

/// Packed output per Gaussian: mean 3, covariance 6 (xx, xy, xz, yy, yz, zz), RGB 3,
/// opacity 1 (after the sigmoid).
pub const OUT_CHANNELS: usize = 13;
pub const OUT_MEAN: usize = 0;
pub const OUT_COV: usize = 3;
pub const OUT_RGB: usize = 9;
pub const OUT_OPACITY: usize = 12;
