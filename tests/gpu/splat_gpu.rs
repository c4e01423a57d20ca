//! The GPU tile renderer (CubeCL kernels on burn-wgpu; lavapipe without a GPU) through the
//! public, differentiable `render`: against the fixtures, the CPU renderer and the dense
//! reference, central finite differences, hostile inputs. Kernel-level tests (scan, sort,
//! both gradient accumulation paths) are in `gpu_kernels.rs`.

use burn::tensor::{Device, DeviceKind, Tensor, TensorData};
use texavatars::splat::{render, render_reference_tapped, render_tapped};

use crate::common::{self, Scene, assert_close, fixture, fused, ndarray, random_scene, run};

fn wgpu() -> Device {
    Device::wgpu(DeviceKind::DefaultDevice).autodiff()
}

#[test]
fn fixtures_on_wgpu() {
    for name in ["small", "medium", "edge"] {
        let scene = fixture(name);
        let want = scene.expected.as_ref().unwrap().outcome();
        let got = fused(&scene, &wgpu());
        println!(
            "{}",
            assert_close(&format!("{name} gpu/wgpu"), &got, &want, 1e-4, 0.99)
        );
    }
}

#[test]
fn wgpu_matches_cpu_and_reference_on_random_scenes() {
    for (n, w, h, seed) in [(150, 40, 30, 21), (400, 53, 37, 22)] {
        let scene = random_scene(n, w, h, seed);
        let gpu = fused(&scene, &wgpu());
        let cpu = fused(&scene, &ndarray());
        let reference = run(
            &scene,
            &ndarray(),
            |g, s, p| render_reference_tapped(g, s, p).unwrap(),
            None,
        );
        println!(
            "{}",
            assert_close(
                &format!("{} gpu vs cpu", scene.name),
                &gpu,
                &cpu,
                1e-4,
                0.99
            )
        );
        println!(
            "{}",
            assert_close(
                &format!("{} gpu vs reference", scene.name),
                &gpu,
                &reference,
                1e-4,
                0.99
            )
        );
    }
}

#[test]
fn wgpu_transmittance_gradient_matches_cpu() {
    let scene = random_scene(80, 33, 29, 31);
    let (w, h) = scene.size();
    let tw: Vec<f32> = (0..w * h)
        .map(|i| ((i * 31) % 11) as f32 / 5.0 - 1.0)
        .collect();
    let gpu = run(
        &scene,
        &wgpu(),
        |g, s, p| render_tapped(g, s, p).unwrap(),
        Some(&tw),
    );
    let cpu = run(
        &scene,
        &ndarray(),
        |g, s, p| render_tapped(g, s, p).unwrap(),
        Some(&tw),
    );
    println!(
        "{}",
        assert_close("dL/dT gpu vs cpu", &gpu, &cpu, 1e-4, 0.99)
    );
}

fn gpu_loss(s: &Scene, device: &Device) -> f64 {
    let (w, h) = s.size();
    let r = render(&s.gaussians(device), &s.params).unwrap();
    let gw = Tensor::<3>::from_data(TensorData::new(s.grad_weights.clone(), [h, w, 3]), device);
    let loss = (r.image * gw).sum() + r.transmittance.sum() * 0.5;
    loss.into_data().iter::<f32>().next().unwrap() as f64
}

#[test]
fn wgpu_gradients_match_finite_differences() {
    // Large, semi-transparent Gaussians: the loss is smooth in every input (see
    // tests/cpu/splat_cpu.rs).
    let mut s = random_scene(3, 12, 10, 5);
    for i in 0..3 {
        s.means[3 * i..3 * i + 3].copy_from_slice(&[
            0.3 * (i as f32 - 1.0),
            0.1,
            3.0 + 0.5 * i as f32,
        ]);
        s.cov6[6 * i..6 * i + 6].copy_from_slice(&[1.0, 0.1, 0.05, 0.8, -0.1, 1.2]);
        s.opacities[i] = 0.3 + 0.1 * i as f32;
    }
    let (w, h) = s.size();
    let tw = vec![0.5f32; w * h];
    let analytic = run(
        &s,
        &wgpu(),
        |g, s, p| render_tapped(g, s, p).unwrap(),
        Some(&tw),
    );
    let plain = wgpu().inner();
    type Field = fn(&mut Scene) -> &mut Vec<f32>;
    let fields: [(&str, Field, &Vec<f32>, f32); 4] = [
        ("means", |s| &mut s.means, &analytic.grad_means, 1e-2),
        ("cov6", |s| &mut s.cov6, &analytic.grad_cov6, 1e-2),
        ("colors", |s| &mut s.colors, &analytic.grad_colors, 1e-2),
        (
            "opacities",
            |s| &mut s.opacities,
            &analytic.grad_opacities,
            1e-2,
        ),
    ];
    for (name, field, grad, step) in fields {
        for (i, &a) in grad.iter().enumerate() {
            let mut plus = s.clone();
            field(&mut plus)[i] += step;
            let mut minus = s.clone();
            field(&mut minus)[i] -= step;
            let fd = (gpu_loss(&plus, &plain) - gpu_loss(&minus, &plain)) / (2.0 * step as f64);
            let a = a as f64;
            let tol = 3e-2 * fd.abs().max(a.abs()) + 5e-3;
            assert!(
                (fd - a).abs() <= tol,
                "{name}[{i}]: finite difference {fd} vs analytic {a}"
            );
        }
    }
}

#[test]
fn wgpu_hostile_inputs_and_sizes() {
    for (w, h) in [(1, 1), (17, 9), (33, 47)] {
        let mut s = random_scene(20, w, h, 9);
        let nan = f32::NAN;
        s.means[0] = nan;
        s.cov6[6] = f32::INFINITY;
        s.cov6[12..18].copy_from_slice(&[0.0; 6]);
        s.cov6[18..24].copy_from_slice(&[0.01, 0.0, 0.0, -0.02, 0.0, 0.01]);
        s.means[3 * 4 + 2] = -2.0;
        s.means[3 * 5 + 2] = 0.0;
        s.opacities[6] = nan;
        s.cov6[42..48].copy_from_slice(&[1e6, 0.0, 0.0, 1e6, 0.0, 1e6]);
        let o = fused(&s, &wgpu());
        for v in [
            &o.image,
            &o.transmittance,
            &o.grad_means,
            &o.grad_cov6,
            &o.grad_colors,
            &o.grad_opacities,
        ] {
            assert!(
                v.iter().all(|x| x.is_finite()),
                "{w}x{h}: non-finite output or gradient"
            );
        }
        let cpu = fused(&s, &ndarray());
        common::assert_close(&format!("hostile {w}x{h} gpu vs cpu"), &o, &cpu, 1e-4, 0.99);
    }
    let empty = random_scene(0, 20, 7, 1);
    let o = fused(&empty, &wgpu());
    assert!(o.transmittance.iter().all(|&t| t == 1.0));
}
