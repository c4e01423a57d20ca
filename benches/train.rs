//! One training iteration (render, objective, backward, Adam step) of the whole avatar
//! (default on the CPU, flex), batch 1, without the VGG term (on only for the last part of a run; see
//! docs/training.md for its cost).
//!
//! `cargo bench --bench train`; `TEXAVATARS_BENCH_CONFIG=cpu|paper` picks
//! `configs/train_<name>.json` (default `cpu`); `TEXAVATARS_BENCH_BACKEND=flex|cpu|wgpu|cuda`
//! where it runs (default `flex`; `benches/gpu.sh` uses `wgpu`). The images: the synthetic benchmark at 138 x 200
//! for `cpu` and at NeRSemble's 550 x 802 for `paper` (two cameras, generated once into a
//! temporary folder before timing).

use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use burn::train::TrainStep;
use criterion::{Criterion, criterion_group};
use texavatars::data::{HeadBatcher, HeadDataset, Split};
use texavatars::device::BackendKind;
use texavatars::head::HeadAsset;
use texavatars::synth::{self, SynthConfig};
use texavatars::train::{
    AvatarTraining, LossWeights, Objective, TrainBatch, TrainConfig, optimizer,
};

/// The allocator the `texavatars` binary uses (see `src/main.rs`).
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn bench(c: &mut Criterion) {
    let name = std::env::var("TEXAVATARS_BENCH_CONFIG").unwrap_or_else(|_| "cpu".into());
    // The source tree it was built from; where the executable runs elsewhere (`benches/gpu.sh`
    // with GPU_SH_BIN on a machine without Rust), the configs of the working directory.
    let built_in = Path::new(env!("CARGO_MANIFEST_DIR"));
    let root = if built_in.join("configs").is_dir() {
        built_in
    } else {
        Path::new(".")
    };
    let path = root.join(format!("configs/train_{name}.json"));
    let config = TrainConfig::load(&path).expect("config");
    let head = HeadAsset::embedded().expect("head");
    let (w, h) = if name == "paper" {
        (550, 802)
    } else {
        (138, 200)
    };
    let data = std::env::temp_dir().join(format!(
        "texavatars-bench-train-{name}-{}",
        std::process::id()
    ));
    let synth_cfg = SynthConfig {
        width: w,
        height: h,
        supersample: 1,
        cameras: 2,
        val_camera: 1,
        frames_per_sequence: 2,
        free_frames: 2,
        texture_res: 256,
        ..SynthConfig::default()
    };
    synth::generate(&synth_cfg, &head, &data, &mut |_| {}).expect("synth");
    let backend_name = std::env::var("TEXAVATARS_BENCH_BACKEND").unwrap_or_else(|_| "flex".into());
    let backend = <BackendKind as clap::ValueEnum>::from_str(&backend_name, true)
        .unwrap_or_else(|e| panic!("TEXAVATARS_BENCH_BACKEND={backend_name}: {e}"));
    let device = backend.autodiff_device();
    let mut avatar_cfg = config.avatar().expect("avatar config");
    avatar_cfg.net.condition.expression = head.model.num_expr;
    let avatar = avatar_cfg.init(&head.mesh, &device).expect("avatar");
    let ds = HeadDataset::open(
        &data.join("union"),
        Split::Train,
        Arc::new(head.model.clone()),
    )
    .expect("dataset");
    let item = ds.load_item(0).expect("item");
    let batch = TrainBatch {
        batch: HeadBatcher.try_batch(vec![item], &device).expect("batch"),
        iteration: 0,
    };
    let mut model = Some(AvatarTraining {
        avatar,
        refine: None,
        objective: Objective {
            weights: LossWeights::default(),
            vgg: None,
            vgg_from: usize::MAX,
            guard: None,
        },
    });
    let mut optim = optimizer(&config);
    let mut step = |model: &mut Option<AvatarTraining>| {
        let m = model.take().expect("model");
        let out = m.step(batch.clone());
        *model = Some(optim.step(config.lr_decoders, m, out.grads));
    };
    if matches!(backend_name.as_str(), "wgpu" | "cuda") {
        // Kernel launches and the splat's blocking reads per step, after two warm-up steps
        // (autotuning and the fusion optimiser's first passes launch extra kernels).
        const STEPS: u64 = 3;
        for _ in 0..2 {
            step(&mut model);
        }
        device.sync().expect("device sync");
        let reads = texavatars::splat::gpu::host_reads();
        let count = texavatars::device::LaunchCount::start();
        for _ in 0..STEPS {
            step(&mut model);
        }
        // Everything queued (fusion defers launches) is issued before the count is read.
        device.sync().expect("device sync");
        let by_kernel = count.by_kernel();
        println!(
            "launches per training step ({backend_name}, {name}, mean of {STEPS}): {:.1}; \
             blocking reads by the splat per step: {:.1}",
            count.total() as f64 / STEPS as f64,
            (texavatars::splat::gpu::host_reads() - reads) as f64 / STEPS as f64
        );
        for (kernel, n) in by_kernel.iter().take(25) {
            println!("  {:>8.1}  {kernel}", *n as f64 / STEPS as f64);
        }
    }
    let mut group = c.benchmark_group(format!("train_iteration_{name}"));
    group.sample_size(10);
    group.warm_up_time(Duration::from_secs(3));
    group.measurement_time(Duration::from_secs(if name == "paper" { 60 } else { 10 }));
    let gaussians = model.as_ref().map_or(0, |m| m.avatar.num_gaussians());
    group.bench_function(
        format!("{backend_name}_{w}x{h}_{gaussians}_gaussians"),
        |b| b.iter(|| step(&mut model)),
    );
    group.finish();
    let _ = std::fs::remove_dir_all(&data);
}

criterion_group!(benches, bench);
#[path = "common/mod.rs"]
mod common;

fn main() {
    common::main_on_pool(benches);
}
