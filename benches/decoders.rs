//! The networks of method §3 (Exp2Code, view encoder, both decoders), batch 1: forward alone
//! and forward + backward of `sum(maps * w)` through burn's autodiff. The Pluecker map is
//! computed once outside the timed loop (a training loop caches it per camera).
//!
//! `cargo bench --bench decoders`; `TEXAVATARS_BENCH_CONFIG=cpu|tiny|paper` picks
//! `configs/<name>.json` (default `cpu`), `TEXAVATARS_BENCH=ndarray|flex` one backend (default
//! both). `benches/decoders_torch.py` runs the same networks in PyTorch for comparison.

#![allow(deprecated)]

use std::path::Path;
use std::time::Duration;

use burn::tensor::{Device, Distribution, Tensor, TensorData};
use criterion::{Criterion, criterion_group};
use texavatars::camera::Camera;
use texavatars::models::texavatars::NetConfig;

/// The allocator the `texavatars` binary uses (see `src/main.rs`).
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// NeRSemble's image size with a plausible frontal camera.
fn camera() -> Camera {
    Camera {
        width: 550,
        height: 802,
        fx: 2000.0,
        fy: 2000.0,
        cx: 275.0,
        cy: 401.0,
        world_to_camera: [
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 1.0],
            [0.0, 0.0, 0.0, 1.0],
        ],
    }
}

fn bench(c: &mut Criterion) {
    let name = std::env::var("TEXAVATARS_BENCH_CONFIG").unwrap_or_else(|_| "cpu".into());
    let which = std::env::var("TEXAVATARS_BENCH").unwrap_or_default();
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("configs")
        .join(format!("{name}.json"));
    let cfg = NetConfig::load(&path).expect("config");
    let mut cases: Vec<(&str, Device)> = Vec::new();
    if which.is_empty() || which == "ndarray" {
        cases.push(("ndarray", Device::ndarray()));
    }
    if which.is_empty() || which == "flex" {
        cases.push(("flex", Device::flex()));
    }
    let mut group = c.benchmark_group(format!("decoders_{name}_R{}", cfg.uv_res));
    group.sample_size(10);
    group.warm_up_time(Duration::from_secs(2));
    group.measurement_time(Duration::from_secs(8));
    let dim = cfg.condition.dim();
    let r = cfg.uv_res;
    let cond: Vec<f32> = (0..dim).map(|k| (k as f32 * 0.37).sin()).collect();
    for (backend, plain) in cases {
        for autodiff in [false, true] {
            let device = if autodiff {
                plain.clone().autodiff()
            } else {
                plain.clone()
            };
            device.seed(0);
            let net = cfg.init(&device).expect("valid config");
            let pluecker = net.view_input(&[camera()], &device).expect("camera");
            let condition =
                Tensor::<2>::from_data(TensorData::new(cond.clone(), [1, dim]), &device);
            let w = Tensor::<4>::random([1, 14, r, r], Distribution::Uniform(-1.0, 1.0), &device);
            let label = if autodiff {
                "forward_backward"
            } else {
                "forward"
            };
            group.bench_function(format!("{label}/{backend}"), |b| {
                b.iter(|| {
                    let maps = net
                        .forward(condition.clone(), pluecker.clone())
                        .expect("valid inputs");
                    if autodiff {
                        let grads = (maps.packed() * w.clone()).sum().backward();
                        let g = net.exp2code.linear.v.val().grad(&grads).expect("gradient");
                        let _ = g.sum().into_data();
                    } else {
                        let _ = maps.packed().sum().into_data();
                    }
                })
            });
        }
    }
    group.finish();
}

criterion_group!(benches, bench);
#[path = "common/mod.rs"]
mod common;

fn main() {
    common::main_on_pool(benches);
}
