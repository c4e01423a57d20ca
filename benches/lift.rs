//! Lifting forward + backward at R = S = 512 on a FLAME-sized procedural mesh (9800 faces):
//! the fused CPU operator (ndarray, flex), the same operator on wgpu (lavapipe), and the
//! tensor-op reference on ndarray, all through burn's autodiff (`lift` then `backward`).
//!
//! `cargo bench --bench lift`; `TEXAVATARS_BENCH=cpu|flex|wgpu|reference` runs one.

#![allow(deprecated)]

use std::sync::Arc;
use std::time::Duration;

use burn::tensor::{Device, DeviceKind, Tensor, TensorData};
use criterion::{Criterion, criterion_group};
use texavatars::lift::{self, LiftMode, LiftParams, Topology};
use texavatars::mesh::UvMesh;
use texavatars::texel::FrameKind;
use texavatars::util::rng::Pcg;

/// The allocator the `texavatars` binary uses (see `src/main.rs`).
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

const RES: usize = 512;

fn bench(c: &mut Criterion) {
    let which = std::env::var("TEXAVATARS_BENCH").unwrap_or_default();
    let mesh = UvMesh::cylinder_patch(70);
    let topology = Arc::new(Topology::new(&mesh, RES, RES).expect("topology"));
    let mut rng = Pcg::new(3);
    let local: Vec<f32> = (0..14 * RES * RES)
        .map(|_| 0.5 * (2.0 * rng.uniform() - 1.0))
        .collect();
    let verts: Vec<f32> = mesh.positions.iter().flatten().copied().collect();
    let n = topology.len();
    let weights: Vec<f32> = (0..n * 13).map(|_| 2.0 * rng.uniform() - 1.0).collect();
    let mut group = c.benchmark_group(format!("lift_fwd_bwd_R{RES}_S{RES}_N{n}"));
    group.sample_size(10);
    group.warm_up_time(Duration::from_secs(2));
    group.measurement_time(Duration::from_secs(10));
    let mut cases: Vec<(&str, Device, bool)> = Vec::new();
    if which.is_empty() || which == "cpu" {
        cases.push(("fused_cpu_ndarray", Device::ndarray().autodiff(), false));
    }
    if which.is_empty() || which == "flex" {
        cases.push(("fused_cpu_flex", Device::flex().autodiff(), false));
    }
    if which.is_empty() || which == "wgpu" {
        cases.push((
            "fused_wgpu",
            Device::wgpu(DeviceKind::DefaultDevice).autodiff(),
            false,
        ));
    }
    if which.is_empty() || which == "reference" {
        cases.push(("reference_ndarray", Device::ndarray().autodiff(), true));
    }
    for mode in [LiftMode::Global, LiftMode::Local] {
        let params = LiftParams {
            topology: topology.clone(),
            mode,
            frame: FrameKind::Jacobian,
        };
        for (name, device, reference) in &cases {
            let lt = Tensor::<3>::from_data(TensorData::new(local.clone(), [14, RES, RES]), device);
            let vt = Tensor::<2>::from_data(
                TensorData::new(verts.clone(), [verts.len() / 3, 3]),
                device,
            );
            let wt = Tensor::<2>::from_data(TensorData::new(weights.clone(), [n, 13]), device);
            group.bench_function(format!("{mode:?}/{name}"), |b| {
                b.iter(|| {
                    let (l, v) = (lt.clone().require_grad(), vt.clone().require_grad());
                    let out = if *reference {
                        lift::lift_reference(l.clone(), v.clone(), &params)
                    } else {
                        lift::lift(l.clone(), v.clone(), &params)
                    }
                    .expect("valid inputs");
                    let packed = Tensor::cat(
                        vec![
                            out.means,
                            out.cov6,
                            out.colors,
                            out.opacities.unsqueeze_dim::<2>(1),
                        ],
                        1,
                    );
                    let grads = (packed * wt.clone()).sum().backward();
                    let gl = l.grad(&grads).expect("grad local").sum();
                    let gv = v.grad(&grads).expect("grad vertices").sum();
                    let _ = (gl + gv).into_data();
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
