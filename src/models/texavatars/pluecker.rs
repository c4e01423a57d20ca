//! Per-pixel Pluecker rays of a camera: the input of the view encoder (method §3).
//!
//! The ray through the centre of pixel `(i, j)` (column `i`, row `j`, see [`crate::camera`])
//! has the world-space direction `d = R^T normalize(((i + 0.5 - cx) / fx, (j + 0.5 - cy) / fy,
//! 1))` and passes through the camera centre `o = -R^T t`; its Pluecker coordinates are
//! `[o x d, d]` (moment first, as in the authors' code). The map of the full image is resized
//! to [`PLUECKER_SQUARE_RES`]^2 (ignoring the aspect ratio), then halved with bilinear
//! resampling until it reaches the encoder's input side (512 -> 256 -> 128 in the paper).
//! Resampling is PyTorch's `interpolate(mode = "bilinear", align_corners = False)` without
//! antialiasing, so a halving is an exact 2 x 2 average.
//!
//! [`PLUECKER_SQUARE_RES`]: super::constants::PLUECKER_SQUARE_RES

use burn::tensor::{Device, Tensor, TensorData};

use super::constants::PLUECKER_CHANNELS;
use crate::camera::Camera;
use crate::error::{Error, Result};

/// A 6-channel Pluecker map, channel-major.
///
/// # Shapes
/// - `data`: [6, height, width]: moment `o x d` (3), then direction `d` (3), row `j` at
///   index `j * width + i` within a channel (image rows, top first)
#[derive(Clone, Debug, PartialEq)]
pub struct PlueckerMap {
    /// Rows.
    pub height: usize,
    /// Columns.
    pub width: usize,
    /// Values, [6, height, width].
    pub data: Vec<f32>,
}

impl PlueckerMap {
    /// The rays of every pixel of the camera's image (`camera.height x camera.width`).
    pub fn of_camera(camera: &Camera) -> Self {
        let (h, w) = (camera.height as usize, camera.width as usize);
        let r = camera.rotation().map(|row| row.map(f64::from));
        let o = camera.position().map(f64::from);
        let (fx, fy) = (f64::from(camera.fx), f64::from(camera.fy));
        let (cx, cy) = (f64::from(camera.cx), f64::from(camera.cy));
        let plane = h * w;
        let mut data = vec![0.0f32; PLUECKER_CHANNELS * plane];
        for j in 0..h {
            for i in 0..w {
                let dc = [(i as f64 + 0.5 - cx) / fx, (j as f64 + 0.5 - cy) / fy, 1.0];
                let n = (dc[0] * dc[0] + dc[1] * dc[1] + dc[2] * dc[2]).sqrt();
                // World direction R^T dc / |dc|.
                let mut d = [0.0f64; 3];
                for (k, dk) in d.iter_mut().enumerate() {
                    *dk = (r[0][k] * dc[0] + r[1][k] * dc[1] + r[2][k] * dc[2]) / n;
                }
                let m = [
                    o[1] * d[2] - o[2] * d[1],
                    o[2] * d[0] - o[0] * d[2],
                    o[0] * d[1] - o[1] * d[0],
                ];
                let p = j * w + i;
                for k in 0..3 {
                    data[k * plane + p] = m[k] as f32;
                    data[(3 + k) * plane + p] = d[k] as f32;
                }
            }
        }
        PlueckerMap {
            height: h,
            width: w,
            data,
        }
    }

    /// The value of channel `c` at row `y`, column `x`.
    pub fn at(&self, c: usize, y: usize, x: usize) -> f32 {
        self.data[(c * self.height + y) * self.width + x]
    }

    /// Bilinear resampling to `height x width`, as PyTorch's `interpolate(mode = "bilinear",
    /// align_corners = False)` (no antialiasing).
    pub fn resize_bilinear(&self, height: usize, width: usize) -> Self {
        let ys = taps(self.height, height);
        let xs = taps(self.width, width);
        let (src_plane, dst_plane) = (self.height * self.width, height * width);
        let mut data = vec![0.0f32; PLUECKER_CHANNELS * dst_plane];
        for c in 0..PLUECKER_CHANNELS {
            let src = &self.data[c * src_plane..(c + 1) * src_plane];
            let dst = &mut data[c * dst_plane..(c + 1) * dst_plane];
            for (y, &(y0, y1, ly)) in ys.iter().enumerate() {
                let (r0, r1) = (&src[y0 * self.width..], &src[y1 * self.width..]);
                for (x, &(x0, x1, lx)) in xs.iter().enumerate() {
                    let top = (1.0 - lx) * r0[x0] + lx * r0[x1];
                    let bottom = (1.0 - lx) * r1[x0] + lx * r1[x1];
                    dst[y * width + x] = (1.0 - ly) * top + ly * bottom;
                }
            }
        }
        PlueckerMap {
            height,
            width,
            data,
        }
    }
}

/// Source taps `(i0, i1, weight of i1)` of each output index of a 1-D bilinear resampling
/// from `n_in` to `n_out` samples with `align_corners = False` (PyTorch's rule: source
/// `(o + 0.5) n_in / n_out - 0.5`, clamped at 0 below; the upper neighbour clamped to the
/// last sample).
fn taps(n_in: usize, n_out: usize) -> Vec<(usize, usize, f32)> {
    let scale = n_in as f64 / n_out as f64;
    (0..n_out)
        .map(|o| {
            let src = ((o as f64 + 0.5) * scale - 0.5).max(0.0);
            let i0 = (src.floor() as usize).min(n_in - 1);
            let i1 = (i0 + 1).min(n_in - 1);
            (i0, i1, (src - i0 as f64) as f32)
        })
        .collect()
}

/// The view encoder's input for one camera: the image's Pluecker map resized to
/// `square_res^2`, then halved until its side is `res`.
///
/// `square_res` must be `res * 2^m` (m >= 0); [`super::NetConfig`] checks this.
pub fn view_input(camera: &Camera, square_res: usize, res: usize) -> Result<PlueckerMap> {
    camera.validate("view input camera")?;
    if res == 0
        || square_res < res
        || !square_res.is_multiple_of(res)
        || !(square_res / res).is_power_of_two()
    {
        return Err(Error::invalid(
            "view input",
            "square_res",
            format!("{square_res} is not the input side {res} times a power of two"),
        ));
    }
    let key = CacheKey::new(camera, square_res, res);
    if let Some(map) = cache_get(&key) {
        return Ok(map);
    }
    let map = build_view_input(camera, square_res, res);
    cache_put(key, &map);
    Ok(map)
}

/// [`view_input`] without the cache, the sides already checked.
fn build_view_input(camera: &Camera, square_res: usize, res: usize) -> PlueckerMap {
    let mut map = PlueckerMap::of_camera(camera).resize_bilinear(square_res, square_res);
    while map.height > res {
        map = map.resize_bilinear(map.height / 2, map.width / 2);
    }
    map
}

/// Maps kept by [`view_input`]: a training run asks for the same few cameras every step,
/// and building one map (every pixel's ray at image size, then 2-3 resamplings) is a
/// noticeable share of a small (`cpu`-config) training step, so it is done once per camera.
/// 32 maps of 6 x 128^2 floats are 12 MB.
const CACHED_MAPS: usize = 32;

/// A camera's bits and the two sides: equal keys give bit-identical maps.
#[derive(Clone, PartialEq, Eq, Hash)]
struct CacheKey {
    bits: [u32; 22],
    square_res: usize,
    res: usize,
}

impl CacheKey {
    fn new(camera: &Camera, square_res: usize, res: usize) -> Self {
        let mut bits = [0u32; 22];
        bits[0] = camera.width;
        bits[1] = camera.height;
        let floats = [camera.fx, camera.fy, camera.cx, camera.cy];
        for (b, f) in bits[2..6].iter_mut().zip(floats) {
            *b = f.to_bits();
        }
        for (b, f) in bits[6..]
            .iter_mut()
            .zip(camera.world_to_camera.iter().flatten())
        {
            *b = f.to_bits();
        }
        CacheKey {
            bits,
            square_res,
            res,
        }
    }
}

type MapCache = std::collections::HashMap<CacheKey, std::sync::Arc<PlueckerMap>>;

fn cache() -> &'static std::sync::Mutex<MapCache> {
    static CACHE: std::sync::OnceLock<std::sync::Mutex<MapCache>> = std::sync::OnceLock::new();
    CACHE.get_or_init(Default::default)
}

fn cache_get(key: &CacheKey) -> Option<PlueckerMap> {
    // A poisoned lock only means another thread panicked mid-insert; the map is still valid.
    let guard = cache().lock().unwrap_or_else(|e| e.into_inner());
    guard.get(key).map(|m| PlueckerMap::clone(m))
}

fn cache_put(key: CacheKey, map: &PlueckerMap) {
    let mut guard = cache().lock().unwrap_or_else(|e| e.into_inner());
    if guard.len() >= CACHED_MAPS {
        // A viewer orbiting the head asks for a new camera every frame: start over rather
        // than keep an eviction order (rebuilding one map is cheap next to a frame).
        guard.clear();
    }
    guard.insert(key, std::sync::Arc::new(map.clone()));
}

/// The view encoder's input for a batch of cameras, on `device`.
///
/// # Shapes
/// - returns [N, 6, res, res] for N = `cameras.len()`
pub fn view_input_batch(
    cameras: &[Camera],
    square_res: usize,
    res: usize,
    device: &Device,
) -> Result<Tensor<4>> {
    let mut data = Vec::with_capacity(cameras.len() * PLUECKER_CHANNELS * res * res);
    for camera in cameras {
        data.extend_from_slice(&view_input(camera, square_res, res)?.data);
    }
    Ok(Tensor::from_data(
        TensorData::new(data, [cameras.len(), PLUECKER_CHANNELS, res, res]),
        device,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn map(h: usize, w: usize) -> PlueckerMap {
        let data = (0..PLUECKER_CHANNELS * h * w)
            .map(|k| ((k * 37 % 101) as f32) * 0.1 - 3.0)
            .collect();
        PlueckerMap {
            height: h,
            width: w,
            data,
        }
    }

    #[test]
    fn halving_is_a_two_by_two_average() {
        let m = map(6, 8);
        let h = m.resize_bilinear(3, 4);
        for c in 0..PLUECKER_CHANNELS {
            for y in 0..3 {
                for x in 0..4 {
                    let avg = 0.25
                        * (m.at(c, 2 * y, 2 * x)
                            + m.at(c, 2 * y, 2 * x + 1)
                            + m.at(c, 2 * y + 1, 2 * x)
                            + m.at(c, 2 * y + 1, 2 * x + 1));
                    assert!((h.at(c, y, x) - avg).abs() < 1e-5);
                }
            }
        }
    }

    #[test]
    fn resize_to_same_size_is_identity_and_upsampling_clamps() {
        let m = map(5, 7);
        assert_eq!(m.resize_bilinear(5, 7), m);
        // Upsampling 2 -> 4 (PyTorch): sources -0.25 (clamped to 0), 0.25, 0.75, 1.25 (upper
        // neighbour clamped): weights of the second sample 0, 0.25, 0.75, 1.
        let m = PlueckerMap {
            height: 1,
            width: 2,
            data: (0..PLUECKER_CHANNELS).flat_map(|_| [0.0, 1.0]).collect(),
        };
        let u = m.resize_bilinear(1, 4);
        let row: Vec<f32> = (0..4).map(|x| u.at(0, 0, x)).collect();
        assert_eq!(row, vec![0.0, 0.25, 0.75, 1.0]);
    }

    #[test]
    fn cached_view_inputs_match_fresh_ones_per_camera() {
        let cam = |tx: f32, cx: f32| Camera {
            width: 40,
            height: 24,
            fx: 30.0,
            fy: 31.0,
            cx,
            cy: 12.5,
            world_to_camera: [
                [1.0, 0.0, 0.0, tx],
                [0.0, 1.0, 0.0, 0.0],
                [0.0, 0.0, 1.0, 2.0],
                [0.0, 0.0, 0.0, 1.0],
            ],
        };
        let cams = [cam(0.1, 20.0), cam(0.1, 20.5), cam(-0.3, 20.0)];
        for _ in 0..2 {
            for c in &cams {
                for (square, res) in [(32, 8), (16, 8)] {
                    let got = view_input(c, square, res).expect("valid sides");
                    assert_eq!(got, build_view_input(c, square, res));
                }
            }
        }
        // Cameras differing in one value only get maps of their own.
        let a = view_input(&cams[0], 32, 8).expect("valid sides");
        let b = view_input(&cams[1], 32, 8).expect("valid sides");
        assert_ne!(a, b);
    }

    #[test]
    fn view_input_rejects_incompatible_sides() {
        let cam = Camera {
            width: 4,
            height: 4,
            fx: 4.0,
            fy: 4.0,
            cx: 2.0,
            cy: 2.0,
            world_to_camera: [
                [1.0, 0.0, 0.0, 0.0],
                [0.0, 1.0, 0.0, 0.0],
                [0.0, 0.0, 1.0, 1.0],
                [0.0, 0.0, 0.0, 1.0],
            ],
        };
        assert!(view_input(&cam, 512, 128).is_ok());
        assert!(view_input(&cam, 512, 96).is_err());
        assert!(view_input(&cam, 64, 128).is_err());
        assert_eq!(view_input(&cam, 16, 16).unwrap().height, 16);
    }
}
