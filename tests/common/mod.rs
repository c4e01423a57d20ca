//! Shared test support: fixture scenes, random scenes, gradient comparisons.
#![allow(dead_code)]

pub mod head;

use std::path::{Path, PathBuf};

use burn::tensor::{Device, Tensor, TensorData};
use texavatars::camera::{Camera, CameraFile};
use texavatars::io::npy;
use texavatars::splat::{Gaussians, Rendered, SplatParams};
use texavatars::util::rng::Pcg;

/// A scene in host memory with its optional expected outputs.
#[derive(Clone, Debug)]
pub struct Scene {
    pub name: String,
    pub means: Vec<f32>,
    pub cov6: Vec<f32>,
    pub colors: Vec<f32>,
    pub opacities: Vec<f32>,
    pub params: SplatParams,
    /// [H, W, 3] loss weights: loss = sum(image * grad_weights).
    pub grad_weights: Vec<f32>,
    pub expected: Option<Expected>,
}

/// Expected outputs of a fixture.
#[derive(Clone, Debug)]
pub struct Expected {
    pub image: Vec<f32>,
    pub transmittance: Vec<f32>,
    pub grad_means: Vec<f32>,
    pub grad_cov6: Vec<f32>,
    pub grad_colors: Vec<f32>,
    pub grad_opacities: Vec<f32>,
}

/// The committed fixture folder `tests/fixtures/<rel>` (see `tests/fixtures/README.md`).
/// Panics naming the path when it is missing: the fixtures are part of the repository, so a
/// missing one is a broken checkout, never a reason to skip.
pub fn fixture_path(rel: &str) -> PathBuf {
    let d = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(rel);
    assert!(
        d.exists(),
        "fixture missing: {} (committed under tests/fixtures; see tests/fixtures/README.md)",
        d.display()
    );
    d
}

/// The splat fixture folder `tests/fixtures/splat` (scenes `small`, `medium`, `edge`).
pub fn fixtures_dir() -> PathBuf {
    fixture_path("splat")
}

fn load(dir: &Path, name: &str) -> Vec<f32> {
    npy::read(&dir.join(format!("{name}.npy")))
        .unwrap_or_else(|e| panic!("{e}"))
        .data
}

/// Loads fixture scene `name` (small, medium, edge) from `tests/fixtures/splat/<name>`;
/// panics naming the path of a missing folder or file.
pub fn fixture(name: &str) -> Scene {
    let dir = fixture_path(&format!("splat/{name}"));
    let cam = CameraFile::load(&dir.join("camera.json")).unwrap_or_else(|e| panic!("{e}"));
    Scene {
        name: name.to_string(),
        means: load(&dir, "means"),
        cov6: load(&dir, "cov6"),
        colors: load(&dir, "colors"),
        opacities: load(&dir, "opacities"),
        params: SplatParams {
            camera: cam.camera,
            background: cam.background,
        },
        grad_weights: load(&dir, "grad_weights"),
        expected: Some(Expected {
            image: load(&dir, "image"),
            transmittance: load(&dir, "transmittance"),
            grad_means: load(&dir, "grad_means"),
            grad_cov6: load(&dir, "grad_cov6"),
            grad_colors: load(&dir, "grad_colors"),
            grad_opacities: load(&dir, "grad_opacities"),
        }),
    }
}

/// A camera looking down +z from the origin (OpenCV axes).
pub fn camera(width: u32, height: u32) -> Camera {
    let f = 0.9 * width.max(height) as f32;
    Camera {
        width,
        height,
        fx: f,
        fy: f * 1.05,
        cx: width as f32 * 0.47,
        cy: height as f32 * 0.53,
        world_to_camera: [
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ],
    }
}

/// A random scene of `n` Gaussians in front of [`camera`], some partly outside the view.
pub fn random_scene(n: usize, width: u32, height: u32, seed: u64) -> Scene {
    let mut rng = Pcg::new(seed);
    let mut s = Scene {
        name: format!("random-{n}-{width}x{height}-{seed}"),
        means: Vec::new(),
        cov6: Vec::new(),
        colors: Vec::new(),
        opacities: Vec::new(),
        params: SplatParams {
            camera: camera(width, height),
            background: [0.2, 0.5, 0.9],
        },
        grad_weights: (0..width * height * 3).map(|_| rng.normal()).collect(),
        expected: None,
    };
    for _ in 0..n {
        let z = 2.0 + 3.0 * rng.uniform();
        s.means.extend([
            (rng.uniform() - 0.5) * 1.4 * z,
            (rng.uniform() - 0.5) * 1.4 * z,
            z,
        ]);
        // L L^T with a random lower-triangular L: symmetric positive definite.
        let l = [
            0.02 + 0.1 * rng.uniform(),
            0.05 * rng.normal(),
            0.02 + 0.1 * rng.uniform(),
            0.05 * rng.normal(),
            0.05 * rng.normal(),
            0.02 + 0.1 * rng.uniform(),
        ];
        let (l00, l10, l11, l20, l21, l22) = (l[0], l[1], l[2], l[3], l[4], l[5]);
        s.cov6.extend([
            l00 * l00,
            l00 * l10,
            l00 * l20,
            l10 * l10 + l11 * l11,
            l10 * l20 + l11 * l21,
            l20 * l20 + l21 * l21 + l22 * l22,
        ]);
        s.colors
            .extend([rng.uniform(), rng.uniform(), rng.uniform()]);
        s.opacities.push(0.05 + 0.9 * rng.uniform());
    }
    s
}

impl Scene {
    pub fn len(&self) -> usize {
        self.opacities.len()
    }

    pub fn size(&self) -> (usize, usize) {
        (
            self.params.camera.width as usize,
            self.params.camera.height as usize,
        )
    }

    /// The scene's tensors on `device` (require grad when the device is autodiff).
    pub fn gaussians(&self, device: &Device) -> Gaussians {
        let n = self.len();
        let t2 = |v: &Vec<f32>, w: usize| {
            Tensor::<2>::from_data(TensorData::new(v.clone(), [n, w]), device)
        };
        let mut g = Gaussians {
            means: t2(&self.means, 3),
            cov6: t2(&self.cov6, 6),
            colors: t2(&self.colors, 3),
            opacities: Tensor::from_data(TensorData::new(self.opacities.clone(), [n]), device),
        };
        if device.is_autodiff() {
            g.means = g.means.require_grad();
            g.cov6 = g.cov6.require_grad();
            g.colors = g.colors.require_grad();
            g.opacities = g.opacities.require_grad();
        }
        g
    }
}

/// Outputs and gradients of one implementation on one scene.
#[derive(Clone, Debug)]
pub struct Outcome {
    pub image: Vec<f32>,
    pub transmittance: Vec<f32>,
    pub grad_means: Vec<f32>,
    pub grad_cov6: Vec<f32>,
    pub grad_colors: Vec<f32>,
    pub grad_opacities: Vec<f32>,
    /// The tap's gradient (`[N, 2]`, NDC); empty when the source has none (fixtures).
    pub grad_screen: Vec<f32>,
}

fn host<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().iter::<f32>().collect()
}

/// Renders `scene` on the autodiff `device` with `render` and back-propagates
/// loss = sum(image * grad_weights) (+ sum(T * t_weights) when given).
pub fn run(
    scene: &Scene,
    device: &Device,
    render: impl Fn(&Gaussians, Tensor<2>, &SplatParams) -> Rendered,
    t_weights: Option<&[f32]>,
) -> Outcome {
    let (w, h) = scene.size();
    let g = scene.gaussians(device);
    let mut screen = Tensor::<2>::zeros([scene.len(), 2], device);
    if device.is_autodiff() {
        screen = screen.require_grad();
    }
    let r = render(&g, screen.clone(), &scene.params);
    let gw = Tensor::<3>::from_data(
        TensorData::new(scene.grad_weights.clone(), [h, w, 3]),
        device,
    );
    let mut loss = (r.image.clone() * gw).sum();
    if let Some(tw) = t_weights {
        let tw = Tensor::<2>::from_data(TensorData::new(tw.to_vec(), [h, w]), device);
        loss = loss + (r.transmittance.clone() * tw).sum();
    }
    let grads = loss.backward();
    let grad =
        |t: &Tensor<2>, len: usize| t.grad(&grads).map(host).unwrap_or_else(|| vec![0.0; len]);
    let n = scene.len();
    Outcome {
        image: host(r.image),
        transmittance: host(r.transmittance),
        grad_means: grad(&g.means, 3 * n),
        grad_cov6: grad(&g.cov6, 6 * n),
        grad_colors: grad(&g.colors, 3 * n),
        grad_opacities: g
            .opacities
            .grad(&grads)
            .map(host)
            .unwrap_or_else(|| vec![0.0; n]),
        grad_screen: grad(&screen, 2 * n),
    }
}

/// The ndarray device with autodiff.
#[allow(deprecated)]
pub fn ndarray() -> Device {
    Device::ndarray().autodiff()
}

/// Renders with the fused operator of `device` and back-propagates (see [`run`]).
pub fn fused(scene: &Scene, device: &Device) -> Outcome {
    run(
        scene,
        device,
        |g, s, p| texavatars::splat::render_tapped(g, s, p).expect("valid inputs"),
        None,
    )
}

/// Renders with the dense reference on `device` and back-propagates (see [`run`]).
pub fn reference(scene: &Scene, device: &Device) -> Outcome {
    run(
        scene,
        device,
        |g, s, p| texavatars::splat::render_reference_tapped(g, s, p).expect("valid inputs"),
        None,
    )
}

/// Largest absolute difference.
pub fn max_abs(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

/// Fraction of entries with |a - b| <= rtol |b| + atol, where atol = 1e-4 rtol-scaled by the
/// largest |b| (entries that are zero up to float noise relative to the array's scale pass).
pub fn frac_close(a: &[f32], b: &[f32], rtol: f32) -> f32 {
    assert_eq!(a.len(), b.len());
    if a.is_empty() {
        return 1.0;
    }
    let scale = b.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    let atol = 1e-2 * rtol * scale;
    let ok = a
        .iter()
        .zip(b)
        .filter(|(x, y)| (*x - *y).abs() <= rtol * y.abs() + atol)
        .count();
    ok as f32 / a.len() as f32
}

/// Asserts two outcomes agree: image and T to `img_tol`, gradients to rtol 1e-3 on at least
/// `min_frac` of the entries. Returns a summary line.
pub fn assert_close(
    label: &str,
    got: &Outcome,
    want: &Outcome,
    img_tol: f32,
    min_frac: f32,
) -> String {
    let ie = max_abs(&got.image, &want.image);
    let te = max_abs(&got.transmittance, &want.transmittance);
    assert!(
        got.image.iter().all(|v| v.is_finite()),
        "{label}: non-finite image"
    );
    assert!(
        ie <= img_tol,
        "{label}: image max abs error {ie} > {img_tol}"
    );
    assert!(
        te <= img_tol,
        "{label}: transmittance max abs error {te} > {img_tol}"
    );
    let mut line = format!("{label}: image {ie:.2e} T {te:.2e}");
    for (name, g, w) in [
        ("means", &got.grad_means, &want.grad_means),
        ("cov6", &got.grad_cov6, &want.grad_cov6),
        ("colors", &got.grad_colors, &want.grad_colors),
        ("opacities", &got.grad_opacities, &want.grad_opacities),
        ("screen", &got.grad_screen, &want.grad_screen),
    ] {
        if name == "screen" && w.is_empty() {
            continue;
        }
        assert!(
            g.iter().all(|v| v.is_finite()),
            "{label}: non-finite grad {name}"
        );
        let f = frac_close(g, w, 1e-3);
        assert!(
            f >= min_frac,
            "{label}: grad {name}: only {:.4} of entries within rtol 1e-3",
            f
        );
        line.push_str(&format!(" | {name} {:.4}", f));
    }
    line
}

impl Expected {
    pub fn outcome(&self) -> Outcome {
        Outcome {
            image: self.image.clone(),
            transmittance: self.transmittance.clone(),
            grad_means: self.grad_means.clone(),
            grad_cov6: self.grad_cov6.clone(),
            grad_colors: self.grad_colors.clone(),
            grad_opacities: self.grad_opacities.clone(),
            grad_screen: Vec::new(),
        }
    }
}
