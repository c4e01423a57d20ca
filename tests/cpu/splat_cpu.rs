//! The CPU tile renderer (ndarray and flex backends) and the dense reference against the
//! fixtures of an independent reference, against each other on random scenes, against
//! central finite differences, and under hostile inputs.

use burn::tensor::Device;
use burn::tensor::{Tensor, TensorData};
use texavatars::splat::cpu;
use texavatars::splat::{
    render, render_packed, render_reference, render_reference_tapped, render_tapped,
};

use crate::common::{
    Outcome, Scene, assert_close, fixture, fused, ndarray, random_scene, reference, run,
};

#[test]
fn fixtures_cpu_and_reference() {
    for name in ["small", "medium", "edge"] {
        let scene = fixture(name);
        let want = scene.expected.as_ref().unwrap().outcome();
        let got = fused(&scene, &ndarray());
        println!(
            "{}",
            assert_close(&format!("{name} cpu/ndarray"), &got, &want, 1e-4, 0.99)
        );
        let got = fused(&scene, &Device::flex().autodiff());
        println!(
            "{}",
            assert_close(&format!("{name} cpu/flex"), &got, &want, 1e-4, 0.99)
        );
        // The dense reference holds pixels x Gaussians values (about 2 GB for `medium`).
        let got = reference(&scene, &ndarray());
        println!(
            "{}",
            assert_close(&format!("{name} reference"), &got, &want, 1e-4, 0.99)
        );
    }
}

#[test]
fn cpu_matches_reference_on_random_scenes() {
    for (n, w, h, seed) in [(50, 40, 30, 1), (200, 37, 53, 2), (120, 64, 64, 3)] {
        let scene = random_scene(n, w, h, seed);
        let want = reference(&scene, &ndarray());
        let got = fused(&scene, &ndarray());
        println!("{}", assert_close(&scene.name, &got, &want, 1e-4, 0.99));
    }
}

#[test]
fn transmittance_gradient_matches_reference() {
    let scene = random_scene(80, 33, 29, 11);
    let (w, h) = scene.size();
    let tw: Vec<f32> = (0..w * h)
        .map(|i| ((i * 7919) % 13) as f32 / 6.0 - 1.0)
        .collect();
    let device = ndarray();
    let want = run(
        &scene,
        &device,
        |g, s, p| render_reference_tapped(g, s, p).unwrap(),
        Some(&tw),
    );
    let got = run(
        &scene,
        &device,
        |g, s, p| render_tapped(g, s, p).unwrap(),
        Some(&tw),
    );
    println!("{}", assert_close("with dL/dT", &got, &want, 1e-4, 0.99));
}

/// A smooth scene for finite differences: large Gaussians whose 1/255 cut-off lies outside
/// the image, opacities below the 0.99 clamp, so the loss is smooth in every input.
fn smooth_scene() -> Scene {
    let mut s = random_scene(4, 12, 10, 5);
    s.params.background = [0.3, 0.6, 0.1];
    for i in 0..4 {
        s.means[3 * i] = 0.3 * (i as f32 - 1.5);
        s.means[3 * i + 1] = 0.2 * ((i % 2) as f32 - 0.5);
        s.means[3 * i + 2] = 3.0 + 0.5 * i as f32;
        s.cov6[6 * i..6 * i + 6].copy_from_slice(&[1.0, 0.1, 0.05, 0.8, -0.1, 1.2]);
        s.opacities[i] = 0.3 + 0.1 * i as f32;
    }
    s
}

fn cpu_loss(s: &Scene) -> f64 {
    let scene = cpu::Scene {
        means: &s.means,
        cov6: &s.cov6,
        colors: &s.colors,
        opacities: &s.opacities,
    };
    let fwd = cpu::forward(&scene, &s.params.camera, s.params.background);
    let (w, h) = s.size();
    (0..w * h)
        .map(|p| {
            (0..3)
                .map(|c| fwd.out[4 * p + c] as f64 * s.grad_weights[3 * p + c] as f64)
                .sum::<f64>()
                + 0.5 * fwd.out[4 * p + 3] as f64
        })
        .sum()
}

#[test]
fn cpu_gradients_match_finite_differences() {
    let s = smooth_scene();
    let (w, h) = s.size();
    let scene = cpu::Scene {
        means: &s.means,
        cov6: &s.cov6,
        colors: &s.colors,
        opacities: &s.opacities,
    };
    let fwd = cpu::forward(&scene, &s.params.camera, s.params.background);
    let mut grad_out = vec![0.0f32; w * h * 4];
    for p in 0..w * h {
        grad_out[4 * p..4 * p + 3].copy_from_slice(&s.grad_weights[3 * p..3 * p + 3]);
        grad_out[4 * p + 3] = 0.5;
    }
    let g = cpu::backward(
        &scene,
        &s.params.camera,
        s.params.background,
        &fwd,
        &grad_out,
    );
    type Field = fn(&mut Scene) -> &mut Vec<f32>;
    let fields: [(&str, Field, &Vec<f32>, f32); 4] = [
        ("means", |s| &mut s.means, &g.means, 1e-3),
        ("cov6", |s| &mut s.cov6, &g.cov6, 1e-3),
        ("colors", |s| &mut s.colors, &g.colors, 1e-2),
        ("opacities", |s| &mut s.opacities, &g.opacities, 1e-3),
    ];
    for (name, field, analytic, h) in fields {
        for (i, &a) in analytic.iter().enumerate() {
            let mut plus = s.clone();
            field(&mut plus)[i] += h;
            let mut minus = s.clone();
            field(&mut minus)[i] -= h;
            let fd = (cpu_loss(&plus) - cpu_loss(&minus)) / (2.0 * h as f64);
            let a = a as f64;
            let tol = 2e-2 * fd.abs().max(a.abs()) + 2e-3;
            assert!(
                (fd - a).abs() <= tol,
                "{name}[{i}]: finite difference {fd} vs analytic {a}"
            );
        }
    }
}

/// The screen-space tap (3DGS's `viewspace_point_tensor.grad`, which GaussianAvatars
/// densifies by): the fused CPU renderer's tap gradient equals central finite differences
/// of the loss when the dense reference's projected centres move by the tap's value in NDC
/// (`reference::render_tapped`; 3DGS's units: diff-gaussian-rasterization,
/// `cuda_rasterizer/backward.cu`, `renderCUDA`, `dL_dmean2D = dL/dpixel * 0.5 W`).
#[test]
fn screen_tap_gradient_matches_finite_differences() {
    let s = smooth_scene();
    let (w, h) = s.size();
    let n = s.len();
    let weights: Vec<f32> = s.grad_weights.clone();
    let device = Device::flex();
    let loss = |screen: Vec<f32>| -> f64 {
        let g = s.gaussians(&device);
        let screen = Tensor::<2>::from_data(TensorData::new(screen, [n, 2]), &device);
        let r = render_reference_tapped(&g, screen, &s.params).unwrap();
        let gw = Tensor::<3>::from_data(TensorData::new(weights.clone(), [h, w, 3]), &device);
        let l = (r.image * gw).sum() + r.transmittance.sum() * 0.5;
        l.into_scalar::<f32>() as f64
    };
    let got = run(
        &s,
        &Device::flex().autodiff(),
        |g, t, p| render_tapped(g, t, p).unwrap(),
        Some(&vec![0.5; w * h]),
    );
    assert_eq!(got.grad_screen.len(), 2 * n);
    let eps = 1e-3f32;
    for (i, &a) in got.grad_screen.iter().enumerate() {
        let mut plus = vec![0.0; 2 * n];
        plus[i] = eps;
        let mut minus = vec![0.0; 2 * n];
        minus[i] = -eps;
        let fd = (loss(plus) - loss(minus)) / (2.0 * eps as f64);
        let a = a as f64;
        assert!(
            a.abs() > 1e-3,
            "screen[{i}]: the scene should move the loss"
        );
        assert!(
            (fd - a).abs() <= 2e-2 * fd.abs().max(a.abs()) + 1e-3,
            "screen[{i}]: finite difference {fd} vs tap {a}"
        );
    }
}

fn assert_finite(label: &str, o: &Outcome) {
    for (name, v) in [
        ("image", &o.image),
        ("transmittance", &o.transmittance),
        ("grad means", &o.grad_means),
        ("grad cov6", &o.grad_cov6),
        ("grad colors", &o.grad_colors),
        ("grad opacities", &o.grad_opacities),
    ] {
        assert!(
            v.iter().all(|x| x.is_finite()),
            "{label}: non-finite {name}"
        );
    }
}

/// A scene of hostile Gaussians: NaN/Inf values, zero and indefinite covariances, behind the
/// camera, at the near plane, needle-thin, huge, transparent, opaque.
pub fn hostile_scene(w: u32, h: u32) -> Scene {
    let mut s = random_scene(24, w, h, 9);
    let nan = f32::NAN;
    let inf = f32::INFINITY;
    let cases: [([f32; 3], [f32; 6], f32); 14] = [
        ([nan, 0.0, 3.0], [0.01, 0.0, 0.0, 0.01, 0.0, 0.01], 0.5),
        ([0.0, 0.0, 3.0], [nan, 0.0, 0.0, 0.01, 0.0, 0.01], 0.5),
        ([0.0, 0.0, 3.0], [0.01, 0.0, 0.0, 0.01, 0.0, 0.01], nan),
        ([inf, 0.0, 3.0], [0.01, 0.0, 0.0, 0.01, 0.0, 0.01], 0.5),
        ([0.0, 0.0, 3.0], [inf, 0.0, 0.0, 0.01, 0.0, 0.01], 0.5),
        ([0.0, 0.1, 3.0], [0.0; 6], 0.5),
        ([0.1, 0.0, 3.0], [0.01, 0.0, 0.0, -0.02, 0.0, 0.01], 0.5),
        ([0.0, 0.0, -2.0], [0.01, 0.0, 0.0, 0.01, 0.0, 0.01], 0.9),
        ([0.0, 0.0, 0.0], [0.01, 0.0, 0.0, 0.01, 0.0, 0.01], 0.9),
        ([0.0, 0.0, 0.01], [0.01, 0.0, 0.0, 0.01, 0.0, 0.01], 0.9),
        (
            [0.0, 0.0, 0.0100001],
            [1e-8, 0.0, 0.0, 1e-8, 0.0, 1e-8],
            0.9,
        ),
        ([0.2, -0.1, 3.0], [1e-12, 0.0, 0.0, 1.0, 0.0, 1e-12], 0.999),
        ([0.0, 0.0, 4.0], [1e6, 0.0, 0.0, 1e6, 0.0, 1e6], 1.0),
        ([0.0, 0.0, 2.0], [0.05, 0.0, 0.0, 0.05, 0.0, 0.05], 1e-6),
    ];
    for (i, (m, c, o)) in cases.iter().enumerate() {
        s.means[3 * i..3 * i + 3].copy_from_slice(m);
        s.cov6[6 * i..6 * i + 6].copy_from_slice(c);
        s.opacities[i] = *o;
    }
    s
}

#[test]
fn hostile_inputs_give_finite_outputs_and_gradients() {
    for (w, h) in [(1, 1), (17, 9), (16, 16), (33, 47)] {
        let s = hostile_scene(w, h);
        assert_finite(&format!("cpu {w}x{h}"), &fused(&s, &ndarray()));
        assert_finite(&format!("reference {w}x{h}"), &reference(&s, &ndarray()));
    }
}

#[test]
fn empty_scene_renders_background() {
    let mut s = random_scene(0, 20, 7, 1);
    s.params.background = [0.25, 0.5, 0.75];
    let o = fused(&s, &ndarray());
    assert!(o.image.chunks(3).all(|p| p == [0.25, 0.5, 0.75]));
    assert!(o.transmittance.iter().all(|&t| t == 1.0));
    // The reference of an empty scene is a constant (no graph): forward only.
    let g = s.gaussians(&ndarray().inner());
    let r = render_reference(&g, &s.params).unwrap();
    let image: Vec<f32> = r.image.into_data().iter::<f32>().collect();
    assert!(image.chunks(3).all(|p| p == [0.25, 0.5, 0.75]));
    // All culled (behind the camera) but N > 0: backward works and gives zeros.
    let mut s = random_scene(5, 20, 7, 1);
    for i in 0..5 {
        s.means[3 * i + 2] = -1.0;
    }
    for o in [fused(&s, &ndarray()), reference(&s, &ndarray())] {
        assert!(o.transmittance.iter().all(|&t| t == 1.0));
        assert!(o.grad_means.iter().all(|&g| g == 0.0));
    }
}

#[test]
fn hundred_thousand_gaussians() {
    let s = random_scene(100_000, 64, 48, 4);
    let o = fused(&s, &ndarray());
    assert_finite("100k", &o);
    // Something was drawn: most of the view is covered.
    let covered = o.transmittance.iter().filter(|&&t| t < 0.5).count();
    assert!(covered > o.transmittance.len() / 2, "covered {covered}");
}

#[test]
fn bad_shapes_are_reported() {
    let s = random_scene(3, 8, 8, 1);
    let mut g = s.gaussians(&ndarray().inner());
    g.cov6 = g.cov6.narrow(1, 0, 5);
    let e = render(&g, &s.params).unwrap_err().to_string();
    assert!(e.contains("cov6"), "{e}");
}

/// `render_packed` (the training path: the lifting operator's `[N, 13]` output straight into
/// the renderer) gives the image, the transmittance and, column by column, the gradients of
/// `render` on the four separate tensors, on both CPU backends with autodiff and without.
#[test]
fn packed_inputs_render_and_differentiate_as_separate_ones() {
    use texavatars::lift::constants::{OUT_CHANNELS, OUT_COV, OUT_MEAN, OUT_OPACITY, OUT_RGB};
    let scene = random_scene(90, 35, 27, 21);
    let (w, h) = scene.size();
    let n = scene.len();
    let tw: Vec<f32> = (0..w * h)
        .map(|i| ((i * 31) % 7) as f32 / 3.0 - 1.0)
        .collect();
    let mut rows = vec![0.0f32; n * OUT_CHANNELS];
    for (i, row) in rows.chunks_mut(OUT_CHANNELS).enumerate() {
        row[OUT_MEAN..OUT_MEAN + 3].copy_from_slice(&scene.means[3 * i..3 * i + 3]);
        row[OUT_COV..OUT_COV + 6].copy_from_slice(&scene.cov6[6 * i..6 * i + 6]);
        row[OUT_RGB..OUT_RGB + 3].copy_from_slice(&scene.colors[3 * i..3 * i + 3]);
        row[OUT_OPACITY] = scene.opacities[i];
    }
    for device in [ndarray(), Device::flex().autodiff()] {
        let want = run(
            &scene,
            &device,
            |g, s, p| render_tapped(g, s, p).expect("valid inputs"),
            Some(&tw),
        );
        let packed =
            Tensor::<2>::from_data(TensorData::new(rows.clone(), [n, OUT_CHANNELS]), &device)
                .require_grad();
        let r = render_packed(packed.clone(), &scene.params).expect("valid inputs");
        let gw = Tensor::<3>::from_data(
            TensorData::new(scene.grad_weights.clone(), [h, w, 3]),
            &device,
        );
        let t = Tensor::<2>::from_data(TensorData::new(tw.clone(), [h, w]), &device);
        let loss = (r.image.clone() * gw).sum() + (r.transmittance.clone() * t).sum();
        let grads = loss.backward();
        let host = |d: TensorData| d.iter::<f32>().collect::<Vec<f32>>();
        assert_eq!(host(r.image.into_data()), want.image);
        assert_eq!(host(r.transmittance.into_data()), want.transmittance);
        let g = host(packed.grad(&grads).expect("packed is tracked").into_data());
        let column = |from: usize, k: usize| -> Vec<f32> {
            g.chunks(OUT_CHANNELS)
                .flat_map(|row| row[from..from + k].to_vec())
                .collect()
        };
        assert!(want.grad_means.iter().any(|&v| v != 0.0));
        assert_eq!(column(OUT_MEAN, 3), want.grad_means);
        assert_eq!(column(OUT_COV, 6), want.grad_cov6);
        assert_eq!(column(OUT_RGB, 3), want.grad_colors);
        assert_eq!(column(OUT_OPACITY, 1), want.grad_opacities);

        // Without autodiff: the same image.
        let inner = device.clone().inner();
        let packed =
            Tensor::<2>::from_data(TensorData::new(rows.clone(), [n, OUT_CHANNELS]), &inner);
        let r = render_packed(packed, &scene.params).expect("valid inputs");
        assert_eq!(host(r.image.into_data()), want.image);
    }
    let bad = Tensor::<2>::zeros([n, OUT_CHANNELS - 1], &ndarray());
    let e = render_packed(bad, &scene.params).unwrap_err().to_string();
    assert!(e.contains("packed") && e.contains("[N, 13]"), "{e}");
}

/// A training crop ([`texavatars::data::crop`]) renders exactly its window of the whole
/// frame: same pixels (the tile grid moves with the window, the values must not). The scene
/// keeps the Gaussians whose centres project inside the window: for a centre far outside
/// it, the EWA Jacobian is clamped at the window's field of view instead of the frame's
/// (3DGS's `FOV_MARGIN`, kernels/gpu/src/splat/constants.rs), a difference the crop option
/// accepts (docs/training.md).
#[test]
fn a_crop_camera_renders_the_window_of_the_frame() {
    use texavatars::data::crop::Window;
    let mut s = random_scene(600, 70, 50, 21);
    let win = Window {
        x0: 13,
        y0: 9,
        width: 37,
        height: 29,
    };
    let cam = s.params.camera;
    let inside = |i: usize| {
        let m = &cam.world_to_camera;
        let p = &s.means[3 * i..3 * i + 3];
        let q: [f32; 3] =
            std::array::from_fn(|r| m[r][0] * p[0] + m[r][1] * p[1] + m[r][2] * p[2] + m[r][3]);
        let (u, v) = (cam.fx * q[0] / q[2] + cam.cx, cam.fy * q[1] / q[2] + cam.cy);
        (13.0..50.0).contains(&u) && (9.0..38.0).contains(&v)
    };
    let keep: Vec<usize> = (0..s.opacities.len()).filter(|&i| inside(i)).collect();
    let pick = |v: &[f32], k: usize| -> Vec<f32> {
        keep.iter()
            .flat_map(|&i| v[k * i..k * i + k].to_vec())
            .collect()
    };
    (s.means, s.cov6, s.colors, s.opacities) = (
        pick(&s.means, 3),
        pick(&s.cov6, 6),
        pick(&s.colors, 3),
        pick(&s.opacities, 1),
    );
    assert!(keep.len() > 50, "{} Gaussians in the window", keep.len());
    let scene = cpu::Scene {
        means: &s.means,
        cov6: &s.cov6,
        colors: &s.colors,
        opacities: &s.opacities,
    };
    let full = cpu::forward(&scene, &cam, s.params.background);
    let part = cpu::forward(&scene, &win.camera(&cam), s.params.background);
    let mut worst = 0f32;
    for y in 0..win.height as usize {
        for x in 0..win.width as usize {
            let fp = ((y + 9) * 70 + x + 13) * 4;
            let wp = (y * win.width as usize + x) * 4;
            for c in 0..4 {
                worst = worst.max((full.out[fp + c] - part.out[wp + c]).abs());
            }
        }
    }
    let covered = part.out.chunks(4).filter(|p| p[3] < 0.99).count();
    assert!(
        covered > 100,
        "the window shows Gaussians ({covered} pixels)"
    );
    assert!(worst < 1e-5, "largest difference {worst}");
}
