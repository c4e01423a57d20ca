//! Rasterizer forward and backward at 550x802 (NeRSemble's size) for 10k, 100k and 200k
//! Gaussians on the demo head, on the CPU tile renderer (2 threads) and on wgpu.
//!
//! `cargo bench --bench splat` (set `TEXAVATARS_BENCH_WGPU=0` to skip wgpu).

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use texavatars::splat::{cpu, demo};

struct HostScene {
    means: Vec<f32>,
    cov6: Vec<f32>,
    colors: Vec<f32>,
    opacities: Vec<f32>,
}

fn host_scene(n: usize) -> HostScene {
    let ply = demo::scene(n, 7);
    let colors = ply
        .sh
        .iter()
        .map(|c| (c * texavatars::splat::sh::C0 + 0.5).max(0.0))
        .collect();
    HostScene {
        means: ply.means.clone(),
        cov6: ply.cov6(),
        colors,
        opacities: ply.opacities(),
    }
}

fn bench_cpu(c: &mut Criterion) {
    let threads = std::env::var("TEXAVATARS_BENCH_THREADS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(2);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("thread pool");
    let cam = demo::camera();
    let mut group = c.benchmark_group(format!("splat_cpu_{threads}threads_550x802"));
    group.sample_size(10);
    for n in [10_000usize, 100_000, 200_000] {
        let s = host_scene(n);
        let scene = cpu::Scene {
            means: &s.means,
            cov6: &s.cov6,
            colors: &s.colors,
            opacities: &s.opacities,
        };
        group.bench_with_input(BenchmarkId::new("forward", n), &n, |b, _| {
            b.iter(|| pool.install(|| cpu::forward(&scene, &cam.camera, cam.background)))
        });
        let fwd = pool.install(|| cpu::forward(&scene, &cam.camera, cam.background));
        let grad_out: Vec<f32> = (0..fwd.out.len())
            .map(|i| ((i % 7) as f32 - 3.0) * 0.1)
            .collect();
        group.bench_with_input(BenchmarkId::new("backward", n), &n, |b, _| {
            b.iter(|| {
                pool.install(|| cpu::backward(&scene, &cam.camera, cam.background, &fwd, &grad_out))
            })
        });
    }
    group.finish();
}

criterion_group!(benches, bench_cpu);
criterion_main!(benches);
