//! Rasterizer forward and backward at 802x550 (H x W, NeRSemble's size) for 10k, 100k and
//! 200k Gaussians on the demo head, through the `SplatBackend` extension that `render` uses:
//! the CPU tile renderer on ndarray (rayon; the machine's 2 cores) and the CubeCL kernels on
//! wgpu (lavapipe when there is no GPU).
//!
//! `cargo bench --bench splat`; `TEXAVATARS_BENCH=cpu`, `=flex` or `=wgpu` runs one backend
//! only; `=wgpu` also times the backward's three accumulation paths (float atomics, subgroup
//! sums then atomics, per-intersection slots) against each other.
//! Every iteration ends with a read-back, so GPU work is included in the time.

use burn::backend::Dispatch;
use burn::tensor::{Device, DeviceKind, Tensor, TensorData};
use criterion::{BenchmarkId, Criterion, criterion_group};
use std::time::Duration;
use texavatars::splat::{SplatBackend, SplatInputs, SplatParams, demo, sh};

/// The allocator the `texavatars` binary uses (see `src/main.rs`).
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn inputs(n: usize, device: &Device) -> SplatInputs<Dispatch> {
    let ply = demo::scene(n, 7);
    let colors: Vec<f32> = ply.sh.iter().map(|c| (c * sh::C0 + 0.5).max(0.0)).collect();
    let t2 = |v: Vec<f32>, w: usize| {
        Tensor::<2>::from_data(TensorData::new(v, [n, w]), device).into_dispatch()
    };
    SplatInputs {
        means: t2(ply.means.clone(), 3),
        cov6: t2(ply.cov6(), 6),
        colors: t2(colors, 3),
        opacities: Tensor::<1>::from_data(TensorData::new(ply.opacities(), [n]), device)
            .into_dispatch(),
        screen: t2(vec![0.0; 2 * n], 2),
    }
}

fn sync(t: burn::backend::DispatchTensor) {
    let t = Tensor::<1>::from_dispatch(t);
    let _ = t.sum().into_data();
}

#[allow(deprecated)]
fn devices() -> Vec<(&'static str, Device)> {
    let which = std::env::var("TEXAVATARS_BENCH").unwrap_or_default();
    let mut d = Vec::new();
    if which.is_empty() || which == "cpu" {
        d.push(("cpu_ndarray", Device::ndarray()));
    }
    if which.is_empty() || which == "flex" {
        d.push(("cpu_flex", Device::flex()));
    }
    if which.is_empty() || which == "wgpu" {
        d.push(("wgpu", Device::wgpu(DeviceKind::DefaultDevice)));
    }
    d
}

fn bench(c: &mut Criterion) {
    let cam = demo::camera();
    let params = SplatParams {
        camera: cam.camera,
        background: cam.background,
    };
    let (w, h) = (cam.camera.width as usize, cam.camera.height as usize);
    for (name, device) in devices() {
        let mut group = c.benchmark_group(format!("splat_{name}_802x550"));
        group.sample_size(10);
        group.warm_up_time(Duration::from_secs(2));
        group.measurement_time(Duration::from_secs(8));
        for n in [10_000usize, 100_000, 200_000] {
            let inp = inputs(n, &device);
            group.bench_with_input(BenchmarkId::new("forward", n), &n, |b, _| {
                b.iter(|| {
                    let s = <Dispatch as SplatBackend>::splat_forward(inp.clone(), params);
                    sync(s.out)
                })
            });
            let state = <Dispatch as SplatBackend>::splat_forward(inp.clone(), params);
            let g: Vec<f32> = (0..h * w * 4)
                .map(|i| ((i % 7) as f32 - 3.0) * 0.1)
                .collect();
            let grad =
                Tensor::<3>::from_data(TensorData::new(g, [h, w, 4]), &device).into_dispatch();
            group.bench_with_input(BenchmarkId::new("backward", n), &n, |b, _| {
                b.iter(|| {
                    let g = <Dispatch as SplatBackend>::splat_backward(
                        inp.clone(),
                        state.clone(),
                        grad.clone(),
                        params,
                    );
                    // Wait for every output, not just one of them.
                    let sum = [g.means, g.cov6, g.colors]
                        .into_iter()
                        .map(|t| Tensor::<2>::from_dispatch(t).sum())
                        .fold(Tensor::<1>::from_dispatch(g.opacities).sum(), |a, b| a + b);
                    let _ = sum.into_data();
                })
            });
        }
        group.finish();
    }
}

/// The CPU forward's stages on host memory (where the time goes), 200k Gaussians.
fn bench_cpu_stages(c: &mut Criterion) {
    if std::env::var("TEXAVATARS_BENCH").is_ok_and(|v| v != "cpu") {
        return;
    }
    use texavatars::splat::cpu;
    let cam = demo::camera();
    let ply = demo::scene(200_000, 7);
    let colors: Vec<f32> = ply.sh.iter().map(|c| (c * sh::C0 + 0.5).max(0.0)).collect();
    let (cov6, opacities) = (ply.cov6(), ply.opacities());
    let scene = cpu::Scene {
        means: &ply.means,
        cov6: &cov6,
        colors: &colors,
        opacities: &opacities,
    };
    let pc = cpu::ProjCamera::new(&cam.camera);
    let mut group = c.benchmark_group("splat_cpu_stages_200000_802x550");
    group.sample_size(10);
    group.warm_up_time(Duration::from_secs(1));
    group.measurement_time(Duration::from_secs(4));
    group.bench_function("project", |b| b.iter(|| cpu::project_all(&scene, &pc)));
    let projections = cpu::project_all(&scene, &pc);
    group.bench_function("bin", |b| b.iter(|| cpu::bin(&projections, &pc)));
    let bins = cpu::bin(&projections, &pc);
    group.bench_function("rasterize", |b| {
        b.iter(|| cpu::rasterize(&pc, &projections, &bins, cam.background))
    });
    group.finish();
}

/// The GPU backward's three ways of accumulating per-Gaussian gradients on the same scene
/// (`TEXAVATARS_BENCH=wgpu` only): one float atomic add per contributing pixel
/// (`atomics`), a subgroup sum first where cubecl reports subgroups for the adapter
/// (`plane_atomics`), and per-intersection slots with a deterministic sum (`slots`, the path
/// of adapters without float atomics).
fn bench_gpu_accumulation(c: &mut Criterion) {
    use burn::tensor::{DType, Shape};
    use burn_cubecl::CubeDevice;
    use burn_cubecl::cubecl::device::WgpuDeviceKind;
    use burn_cubecl::cubecl::prelude::*;
    use burn_cubecl::tensor::CubeTensor;
    use texavatars::splat::gpu::{self, GpuOptions, PlaneReduction};

    if std::env::var("TEXAVATARS_BENCH").as_deref() != Ok("wgpu") {
        return;
    }
    let Ok(dev) = CubeDevice::wgpu(WgpuDeviceKind::DefaultDevice) else {
        eprintln!("no wgpu device: the accumulation benchmark is skipped");
        return;
    };
    let client = dev.client();
    let upload = |data: &[f32], shape: &[usize]| {
        let handle = client.create_from_slice(f32::as_bytes(data));
        CubeTensor::new_contiguous(
            client.clone(),
            dev.clone(),
            Shape::from(shape.to_vec()),
            handle,
            DType::F32,
        )
    };
    let cam = demo::camera();
    let (w, h) = (cam.camera.width as usize, cam.camera.height as usize);
    let mut variants = vec![
        (
            "atomics",
            GpuOptions {
                allow_float_atomics: true,
                plane_reduction: PlaneReduction::Off,
            },
        ),
        (
            "slots",
            GpuOptions {
                allow_float_atomics: false,
                plane_reduction: PlaneReduction::Off,
            },
        ),
    ];
    if gpu::plane_ops_supported(&client) {
        variants.push((
            "plane_atomics",
            GpuOptions {
                allow_float_atomics: true,
                plane_reduction: PlaneReduction::Auto,
            },
        ));
    }
    let mut group = c.benchmark_group("splat_wgpu_backward_accumulation_802x550");
    group.sample_size(10);
    group.warm_up_time(Duration::from_secs(1));
    group.measurement_time(Duration::from_secs(4));
    let g: Vec<f32> = (0..h * w * 4)
        .map(|i| ((i % 7) as f32 - 3.0) * 0.1)
        .collect();
    for n in [100_000usize, 200_000] {
        let ply = demo::scene(n, 7);
        let colors: Vec<f32> = ply.sh.iter().map(|c| (c * sh::C0 + 0.5).max(0.0)).collect();
        let (cov6, opacities) = (ply.cov6(), ply.opacities());
        // Uploaded once; an iteration clones the handles, as the backend's backward does.
        let inputs = [
            upload(&ply.means, &[n, 3]),
            upload(&cov6, &[n, 6]),
            upload(&colors, &[n, 3]),
            upload(&opacities, &[n]),
        ];
        let [m, cv, col, o] = inputs.clone();
        let fwd = gpu::forward(m, cv, col, o, &cam.camera, cam.background);
        let grad = upload(&g, &[h, w, 4]);
        for (name, options) in &variants {
            eprintln!(
                "{name} at {n} Gaussians: {:?}",
                options.accumulation(&client)
            );
            group.bench_with_input(BenchmarkId::new(*name, n), &n, |b, _| {
                b.iter(|| {
                    let [m, cv, col, o] = inputs.clone();
                    let [.., go, _] = gpu::backward_with_options(
                        m,
                        cv,
                        col,
                        o,
                        &cam.camera,
                        cam.background,
                        &fwd,
                        grad.clone(),
                        *options,
                    );
                    // The last gradient written: waits for the whole backward.
                    let _ = burn_cubecl::ops::into_data_sync(go);
                })
            });
        }
    }
    group.finish();
}

criterion_group!(benches, bench_cpu_stages, bench, bench_gpu_accumulation);
#[path = "common/mod.rs"]
mod common;

fn main() {
    common::main_on_pool(benches);
}
