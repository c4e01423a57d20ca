//! Projection of 3D Gaussians to screen space (forward and backward), one Gaussian at a time.
//!
//! Conventions: `tests/fixtures/splat/README.md` and [`crate::splat::constants`].

// Small fixed-size matrix algebra reads best with explicit indices.
#![allow(clippy::needless_range_loop)]

use crate::camera::Camera;
use crate::splat::constants::{ALPHA_MIN, FOV_MARGIN, LOW_PASS, MIN_DET, NEAR_PLANE, TILE_SIZE};

/// The camera quantities projection needs, precomputed once per render.
#[derive(Clone, Copy, Debug)]
pub struct ProjCamera {
    /// Rotation (row-major).
    pub r: [[f32; 3]; 3],
    /// Translation.
    pub t: [f32; 3],
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    /// Image size.
    pub width: u32,
    pub height: u32,
    /// Tangent limits of the EWA Jacobian clamp.
    pub lim_x_pos: f32,
    pub lim_x_neg: f32,
    pub lim_y_pos: f32,
    pub lim_y_neg: f32,
}

impl ProjCamera {
    /// Precomputes the clamp limits of `camera`.
    pub fn new(camera: &Camera) -> Self {
        let (w, h) = (camera.width as f32, camera.height as f32);
        let tan_fovx = 0.5 * w / camera.fx;
        let tan_fovy = 0.5 * h / camera.fy;
        Self {
            r: camera.rotation(),
            t: camera.translation(),
            fx: camera.fx,
            fy: camera.fy,
            cx: camera.cx,
            cy: camera.cy,
            width: camera.width,
            height: camera.height,
            lim_x_pos: (w - camera.cx) / camera.fx + FOV_MARGIN * tan_fovx,
            lim_x_neg: camera.cx / camera.fx + FOV_MARGIN * tan_fovx,
            lim_y_pos: (h - camera.cy) / camera.fy + FOV_MARGIN * tan_fovy,
            lim_y_neg: camera.cy / camera.fy + FOV_MARGIN * tan_fovy,
        }
    }

    /// Tiles along x and y.
    pub fn tiles(&self) -> (u32, u32) {
        (
            self.width.div_ceil(TILE_SIZE),
            self.height.div_ceil(TILE_SIZE),
        )
    }
}

/// A Gaussian after projection: what compositing needs, packed for cache locality.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Splat2d {
    /// Screen-space mean (pixels).
    pub u: f32,
    pub v: f32,
    /// Conic (inverse 2D covariance) `[[a, b], [b, c]]`.
    pub a: f32,
    pub b: f32,
    pub c: f32,
    /// Opacity (after the sigmoid).
    pub opacity: f32,
    /// Colour.
    pub rgb: [f32; 3],
    /// `ln(255 * opacity)`: alpha reaches 1/255 exactly where `sigma` equals this.
    pub sigma_cut: f32,
}

/// Screen footprint of a projected Gaussian: an inclusive pixel box, clipped to the image.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct PixelBox {
    pub x0: u32,
    pub y0: u32,
    pub x1: u32,
    pub y1: u32,
}

impl PixelBox {
    /// Inclusive tile box covering this pixel box.
    pub fn tiles(&self) -> (u32, u32, u32, u32) {
        (
            self.x0 / TILE_SIZE,
            self.y0 / TILE_SIZE,
            self.x1 / TILE_SIZE,
            self.y1 / TILE_SIZE,
        )
    }

    /// Number of tiles the box touches.
    pub fn tile_count(&self) -> u32 {
        let (tx0, ty0, tx1, ty1) = self.tiles();
        (tx1 - tx0 + 1) * (ty1 - ty0 + 1)
    }
}

/// Result of projecting one Gaussian.
#[derive(Clone, Copy, Debug)]
pub struct Projection {
    pub splat: Splat2d,
    pub depth: f32,
    pub pixels: PixelBox,
}

/// Symmetric 3x3 matrix from the 6 unique values `[xx, xy, xz, yy, yz, zz]`.
pub fn sym3(c: &[f32]) -> [[f32; 3]; 3] {
    [[c[0], c[1], c[2]], [c[1], c[3], c[4]], [c[2], c[4], c[5]]]
}

fn mat3_mul(a: &[[f32; 3]; 3], b: &[[f32; 3]; 3]) -> [[f32; 3]; 3] {
    let mut o = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            o[i][j] = a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j];
        }
    }
    o
}

fn transpose3(a: &[[f32; 3]; 3]) -> [[f32; 3]; 3] {
    let mut o = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            o[i][j] = a[j][i];
        }
    }
    o
}

/// The camera-space point and EWA Jacobian of a Gaussian.
struct Ewa {
    /// Camera-space mean.
    t: [f32; 3],
    /// Jacobian rows: `[[fx/z, 0, j02], [0, fy/z, j12]]`, stored as the two non-trivial entries.
    j02: f32,
    j12: f32,
    /// Clamped tangent numerators `tx = z * clamp(x/z)`.
    tx: f32,
    ty: f32,
    x_clamped: bool,
    y_clamped: bool,
    /// `W Sigma W^T` (camera-space 3D covariance).
    m: [[f32; 3]; 3],
}

fn ewa(cam: &ProjCamera, mean: &[f32], cov6: &[f32]) -> Ewa {
    let r = &cam.r;
    let mut t = [0.0f32; 3];
    for (k, tk) in t.iter_mut().enumerate() {
        *tk = r[k][0] * mean[0] + r[k][1] * mean[1] + r[k][2] * mean[2] + cam.t[k];
    }
    let z = t[2];
    let (xr, yr) = (t[0] / z, t[1] / z);
    let x_clamped = !(xr <= cam.lim_x_pos && xr >= -cam.lim_x_neg);
    let y_clamped = !(yr <= cam.lim_y_pos && yr >= -cam.lim_y_neg);
    let tx = z * xr.clamp(-cam.lim_x_neg, cam.lim_x_pos);
    let ty = z * yr.clamp(-cam.lim_y_neg, cam.lim_y_pos);
    let m = mat3_mul(&mat3_mul(r, &sym3(cov6)), &transpose3(r));
    Ewa {
        t,
        j02: -cam.fx * tx / (z * z),
        j12: -cam.fy * ty / (z * z),
        tx,
        ty,
        x_clamped,
        y_clamped,
        m,
    }
}

/// `J M J^T + LOW_PASS I` as `(xx, xy, yy)`.
fn cov2d(cam: &ProjCamera, e: &Ewa) -> (f32, f32, f32) {
    let z = e.t[2];
    let j = [[cam.fx / z, 0.0, e.j02], [0.0, cam.fy / z, e.j12]];
    let mut jm = [[0.0f32; 3]; 2];
    for i in 0..2 {
        for k in 0..3 {
            jm[i][k] = j[i][0] * e.m[0][k] + j[i][1] * e.m[1][k] + j[i][2] * e.m[2][k];
        }
    }
    let dot = |a: &[f32; 3], b: &[f32; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    (
        dot(&jm[0], &j[0]) + LOW_PASS,
        dot(&jm[0], &j[1]),
        dot(&jm[1], &j[1]) + LOW_PASS,
    )
}

/// Projects one Gaussian. `None` when it is culled: non-finite input, depth at or below the
/// near plane, a projected covariance that is not positive definite, an opacity that can never
/// reach `ALPHA_MIN`, or a footprint outside the image.
pub fn project(
    cam: &ProjCamera,
    mean: &[f32],
    cov6: &[f32],
    rgb: &[f32],
    opacity: f32,
) -> Option<Projection> {
    let finite = mean.iter().chain(cov6).chain(rgb).all(|v| v.is_finite());
    // Written so that NaN fails every test.
    if !finite || !opacity.is_finite() || opacity < ALPHA_MIN {
        return None;
    }
    let e = ewa(cam, mean, cov6);
    let z = e.t[2];
    if z.is_nan() || z <= NEAR_PLANE {
        return None;
    }
    let (sxx, sxy, syy) = cov2d(cam, &e);
    let det = sxx * syy - sxy * sxy;
    if !det.is_finite() || det <= MIN_DET {
        return None;
    }
    let inv = 1.0 / det;
    let (a, b, c) = (syy * inv, -sxy * inv, sxx * inv);
    if !(a.is_finite() && b.is_finite() && c.is_finite()) {
        return None;
    }
    let u = cam.fx * e.t[0] / z + cam.cx;
    let v = cam.fy * e.t[1] / z + cam.cy;
    // alpha >= 1/255  <=>  sigma <= ln(255 o). A 1% margin keeps pixels whose alpha rounds to
    // exactly the threshold inside the box; the per-pixel test still decides.
    let sigma_cut = (255.0 * opacity).ln();
    let reach = 2.0 * (sigma_cut * 1.01 + 1e-3);
    let rx = (reach * sxx).sqrt();
    let ry = (reach * syy).sqrt();
    let pixels = pixel_box(cam, u, v, rx, ry)?;
    Some(Projection {
        splat: Splat2d {
            u,
            v,
            a,
            b,
            c,
            opacity,
            rgb: [rgb[0], rgb[1], rgb[2]],
            sigma_cut,
        },
        depth: z,
        pixels,
    })
}

/// Pixels whose centres `(i + 0.5, j + 0.5)` fall inside `[u - rx, u + rx] x [v - ry, v + ry]`,
/// clipped to the image; `None` when empty or not finite.
fn pixel_box(cam: &ProjCamera, u: f32, v: f32, rx: f32, ry: f32) -> Option<PixelBox> {
    let range = |c: f32, r: f32, n: u32| -> Option<(u32, u32)> {
        let lo = (c - r - 0.5).ceil();
        let hi = (c + r - 0.5).floor();
        if lo.is_nan() || hi.is_nan() || hi < 0.0 || lo > (n - 1) as f32 || lo > hi {
            return None;
        }
        let lo = lo.max(0.0) as u32;
        let hi = hi.min((n - 1) as f32) as u32;
        Some((lo, hi))
    };
    let (x0, x1) = range(u, rx, cam.width)?;
    let (y0, y1) = range(v, ry, cam.height)?;
    Some(PixelBox { x0, y0, x1, y1 })
}

/// Gradients flowing into one projected Gaussian from compositing.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Splat2dGrad {
    pub u: f32,
    pub v: f32,
    pub a: f32,
    pub b: f32,
    pub c: f32,
    pub opacity: f32,
    pub rgb: [f32; 3],
}

impl Splat2dGrad {
    /// Adds `o` into `self`.
    pub fn add(&mut self, o: &Splat2dGrad) {
        self.u += o.u;
        self.v += o.v;
        self.a += o.a;
        self.b += o.b;
        self.c += o.c;
        self.opacity += o.opacity;
        for k in 0..3 {
            self.rgb[k] += o.rgb[k];
        }
    }
}

/// Backward of [`project`] for a Gaussian that was not culled: gradients of the mean and of
/// the 6 covariance values (off-diagonals as independent inputs, i.e. summed over both
/// matrix entries). The fov clamp contributes zero derivative w.r.t. `x` (`y`) where active,
/// while `tx = z * lim` still depends on `z`.
pub fn project_backward(
    cam: &ProjCamera,
    mean: &[f32],
    cov6: &[f32],
    g: &Splat2dGrad,
) -> ([f32; 3], [f32; 6]) {
    let e = ewa(cam, mean, cov6);
    let z = e.t[2];
    let (sxx, sxy, syy) = cov2d(cam, &e);
    let det = sxx * syy - sxy * sxy;
    let inv = 1.0 / det;
    let conic = [[syy * inv, -sxy * inv], [-sxy * inv, sxx * inv]];
    // sigma = 0.5 d^T C d: the parameter b is both off-diagonal entries.
    let gc = [[g.a, 0.5 * g.b], [0.5 * g.b, g.c]];
    // dL/dSigma2 = -C G C.
    let mut cg = [[0.0f32; 2]; 2];
    for i in 0..2 {
        for j in 0..2 {
            cg[i][j] = conic[i][0] * gc[0][j] + conic[i][1] * gc[1][j];
        }
    }
    let mut gs = [[0.0f32; 2]; 2];
    for i in 0..2 {
        for j in 0..2 {
            gs[i][j] = -(cg[i][0] * conic[0][j] + cg[i][1] * conic[1][j]);
        }
    }
    let j = [[cam.fx / z, 0.0, e.j02], [0.0, cam.fy / z, e.j12]];
    // G_M = J^T G_S J (3x3).
    let mut gsj = [[0.0f32; 3]; 2];
    for i in 0..2 {
        for k in 0..3 {
            gsj[i][k] = gs[i][0] * j[0][k] + gs[i][1] * j[1][k];
        }
    }
    let mut gm = [[0.0f32; 3]; 3];
    for a in 0..3 {
        for b in 0..3 {
            gm[a][b] = j[0][a] * gsj[0][b] + j[1][a] * gsj[1][b];
        }
    }
    // G_Sigma = W^T G_M W.
    let r = &cam.r;
    let gsig = mat3_mul(&mat3_mul(&transpose3(r), &gm), r);
    let gcov = [
        gsig[0][0],
        gsig[0][1] + gsig[1][0],
        gsig[0][2] + gsig[2][0],
        gsig[1][1],
        gsig[1][2] + gsig[2][1],
        gsig[2][2],
    ];
    // G_J = 2 G_S J M (both symmetric).
    let mut gj = [[0.0f32; 3]; 2];
    for (gj_i, gsj_i) in gj.iter_mut().zip(&gsj) {
        for (k, v) in gj_i.iter_mut().enumerate() {
            *v = 2.0 * (gsj_i[0] * e.m[0][k] + gsj_i[1] * e.m[1][k] + gsj_i[2] * e.m[2][k]);
        }
    }
    let (x, y) = (e.t[0], e.t[1]);
    let rz = 1.0 / z;
    let rz2 = rz * rz;
    let rz3 = rz2 * rz;
    // Mean: u = fx x/z + cx, v = fy y/z + cy (unclamped).
    let mut gt = [
        cam.fx * rz * g.u,
        cam.fy * rz * g.v,
        -(cam.fx * x * g.u + cam.fy * y * g.v) * rz2,
    ];
    // J00 = fx/z, J11 = fy/z.
    gt[2] += -cam.fx * rz2 * gj[0][0] - cam.fy * rz2 * gj[1][1];
    // J02 = -fx tx / z^2.
    if e.x_clamped {
        gt[2] += cam.fx * e.tx * rz3 * gj[0][2];
    } else {
        gt[0] += -cam.fx * rz2 * gj[0][2];
        gt[2] += 2.0 * cam.fx * e.tx * rz3 * gj[0][2];
    }
    if e.y_clamped {
        gt[2] += cam.fy * e.ty * rz3 * gj[1][2];
    } else {
        gt[1] += -cam.fy * rz2 * gj[1][2];
        gt[2] += 2.0 * cam.fy * e.ty * rz3 * gj[1][2];
    }
    // t = W m + t0  =>  dL/dm = W^T dL/dt.
    let mut gmean = [0.0f32; 3];
    for (k, gk) in gmean.iter_mut().enumerate() {
        *gk = r[0][k] * gt[0] + r[1][k] * gt[1] + r[2][k] * gt[2];
    }
    (gmean, gcov)
}
