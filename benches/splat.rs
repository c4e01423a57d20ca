//! Rasterizer forward and backward at 802x550 (H x W, NeRSemble's size) for 10k, 100k and
//! 200k Gaussians on the demo head, through the `SplatBackend` extension that `render` uses:
//! the CPU tile renderer on ndarray (rayon; the machine's 2 cores) and the CubeCL kernels on
//! wgpu (lavapipe when there is no GPU).
//!
//! `cargo bench --bench splat`; `TEXAVATARS_BENCH=cpu`, `=flex` or `=wgpu` runs one backend
//! only.
//! Every iteration ends with a read-back, so GPU work is included in the time.

use burn::backend::Dispatch;
use burn::tensor::{Device, DeviceKind, Tensor, TensorData};
use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
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

criterion_group!(benches, bench_cpu_stages, bench);
criterion_main!(benches);
