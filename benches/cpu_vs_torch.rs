//! CPU training against PyTorch, in one run (issue "CPU training faster than PyTorch"):
//! medians of the same work in burn (flex, this crate) and in PyTorch (the scripts beside
//! this file), printed as one Markdown table with the ratio.
//!
//! - decoders forward + backward (`configs/cpu.json`, `configs/paper.json`), batch 1:
//!   `benches/decoders_torch.py`;
//! - the VGG16 perceptual loss (reference pass, render pass, backward to the render) at the
//!   demo's 138 x 200 and at NeRSemble's 550 x 802, with this crate's CPU extension and with
//!   burn's generic ops (the path before it): `benches/perceptual_torch.py`;
//! - one whole training step of the `cpu` configuration at 138 x 200, without and with the
//!   perceptual loss (burn only: there is no CPU PyTorch implementation of the whole step;
//!   the reference TexAvatars and GaussianAvatars rasterize with CUDA).
//!
//! The step is timed twice: from the untrained model and after it has fitted the batch
//! ([`FITTED_FROM`]); the renderer's share differs between the two.
//!
//! `cargo bench --bench cpu_vs_torch`. `TEXAVATARS_BENCH_RUNS` sets the timed runs per row
//! (default 10, after 2 warm-up runs); `TEXAVATARS_BENCH_TRACE=1` also prints every run's
//! time in order (stderr); `TEXAVATARS_BENCH_SKIP_PAPER=1` leaves out the
//! `paper` decoders and the 550 x 802 loss. Without `python3 -c "import torch"` the PyTorch
//! column says so and the burn side still runs. `TEXAVATARS_BENCH_ROWS` (a comma-separated
//! subset of `decoders`, `perceptual`, `perceptual_before`, `step`, `step_vgg`) runs only
//! those groups, e.g. under `perf`; `perceptual_before` (burn's generic ops) runs only with
//! `perceptual`.

#![allow(deprecated)]

use std::path::Path;
use std::process::Command;
use std::sync::Arc;
use std::time::Instant;

use burn::tensor::{Device, Distribution, Tensor, TensorData};
use burn::train::TrainStep;
use texavatars::camera::Camera;
use texavatars::data::{HeadBatcher, HeadDataset, Split};
use texavatars::head::HeadAsset;
use texavatars::io::npy::Array;
use texavatars::metrics::weights::HostWeights;
use texavatars::metrics::{Net, VggPerceptual};
use texavatars::models::texavatars::NetConfig;
use texavatars::synth::{self, SynthConfig};
use texavatars::train::{
    AvatarTraining, LossWeights, Objective, TrainBatch, TrainConfig, optimizer,
};

/// The allocator the `texavatars` binary uses, with its settings (`src/main.rs`,
/// `src/alloc.rs`).
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

const WARM_UP: usize = 2;

/// One row of the printed table: what, burn's median, PyTorch's median or why there is none.
type Row = (String, f64, Result<f64, String>);

fn runs() -> usize {
    std::env::var("TEXAVATARS_BENCH_RUNS")
        .ok()
        .and_then(|v| v.parse().ok())
        .filter(|&n| n > 0)
        .unwrap_or(10)
}

/// Median wall time of `f` in milliseconds over [`runs`] calls after [`WARM_UP`].
fn median_ms(mut f: impl FnMut()) -> f64 {
    for _ in 0..WARM_UP {
        f();
    }
    let mut t: Vec<f64> = (0..runs())
        .map(|_| {
            let s = Instant::now();
            f();
            s.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    if std::env::var_os("TEXAVATARS_BENCH_TRACE").is_some() {
        let each: Vec<String> = t.iter().map(|ms| format!("{ms:.1}")).collect();
        eprintln!("  runs (ms, in order): {}", each.join(" "));
    }
    t.sort_by(f64::total_cmp);
    t[t.len() / 2]
}

/// The PyTorch script's median in milliseconds, or why there is none.
fn torch_ms(script: &str, args: &[&str]) -> Result<f64, String> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("benches")
        .join(script);
    let runs = runs().to_string();
    let out = Command::new("python3")
        .arg(&path)
        .args(args)
        .args(["--runs", &runs, "--json"])
        .output()
        .map_err(|e| format!("python3 not runnable: {e}"))?;
    if !out.status.success() {
        let err = String::from_utf8_lossy(&out.stderr);
        return Err(if err.contains("No module named 'torch'") {
            "torch not installed (pip install torch)".into()
        } else {
            format!("{script} failed: {}", err.lines().last().unwrap_or(""))
        });
    }
    let text = String::from_utf8_lossy(&out.stdout);
    let line = text.lines().last().unwrap_or("");
    let v: serde_json::Value =
        serde_json::from_str(line).map_err(|e| format!("{script}: {e}: {line}"))?;
    v["median_ms"]
        .as_f64()
        .ok_or_else(|| format!("{script}: no median_ms in {line}"))
}

/// NeRSemble's image size with a frontal camera (as `benches/decoders.rs`).
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

fn decoders_ms(config: &str) -> f64 {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("configs")
        .join(format!("{config}.json"));
    let cfg = NetConfig::load(&path).expect("config");
    let device = Device::flex().autodiff();
    device.seed(0);
    let net = cfg.init(&device).expect("valid config");
    let pluecker = net.view_input(&[camera()], &device).expect("camera");
    let dim = cfg.condition.dim();
    let cond: Vec<f32> = (0..dim).map(|k| (k as f32 * 0.37).sin()).collect();
    let condition = Tensor::<2>::from_data(TensorData::new(cond, [1, dim]), &device);
    let r = cfg.uv_res;
    let w = Tensor::<4>::random([1, 14, r, r], Distribution::Uniform(-1.0, 1.0), &device);
    median_ms(|| {
        let maps = net
            .forward(condition.clone(), pluecker.clone())
            .expect("valid inputs");
        let grads = (maps.packed() * w.clone()).sum().backward();
        let g = net.exp2code.linear.v.val().grad(&grads).expect("gradient");
        let _ = g.sum().into_data();
    })
}

/// VGG16 weights with He-scaled random values (the time does not depend on the values).
fn random_vgg() -> HostWeights {
    let mut state = 0x2545_f491_4f6c_dd1du64;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 40) as f32 / (1u64 << 24) as f32 - 0.5
    };
    let convs = Net::Vgg16
        .convs()
        .iter()
        .map(|c| {
            let n = c.out_channels * c.in_channels * 9;
            let s = (24.0 / (c.in_channels * 9) as f32).sqrt();
            (
                Array {
                    shape: vec![c.out_channels, c.in_channels, 3, 3],
                    data: (0..n).map(|_| next() * s).collect(),
                },
                Array {
                    shape: vec![c.out_channels],
                    data: (0..c.out_channels).map(|_| next() * 0.02).collect(),
                },
            )
        })
        .collect();
    HostWeights {
        net: Net::Vgg16,
        convs,
        lins: Vec::new(),
    }
}

/// The perceptual loss with gradients to the render: (this crate's CPU op, burn's ops).
fn perceptual_ms(vgg: &VggPerceptual, [h, w]: [usize; 2], burn_ops: bool) -> f64 {
    let device = Device::flex().autodiff();
    device.seed(1);
    let a0 = Tensor::<4>::random([1, 3, h, w], Distribution::Uniform(0.0, 1.0), &device);
    let b = Tensor::<4>::random([1, 3, h, w], Distribution::Uniform(0.0, 1.0), &device);
    median_ms(|| {
        let a = a0.clone().require_grad();
        let loss = if burn_ops {
            vgg.forward_burn(a.clone(), b.clone())
        } else {
            vgg.forward(a.clone(), b.clone())
        };
        let grads = loss.backward();
        let _ = a.grad(&grads).expect("gradient").sum().into_data();
    })
}

/// Iterations after which [`train_step_ms`] times its second phase.
///
/// The renderer's work depends on the Gaussians: the untrained model's are large, so every
/// tile has many, and as they shrink to fit the image the step gets cheaper. A trace of 100
/// runs (`TEXAVATARS_BENCH_TRACE=1`) shows the step without the perceptual loss falling over
/// the first dozen iterations and levelling off from about iteration 20, most of the drop in
/// the renderer; by iteration 100 the model has settled on the batch.
const FITTED_FROM: usize = 100;

/// Medians of one training step in milliseconds, each with the first timed iteration
/// (counted from 0): from the untrained model (the first [`runs`] iterations after
/// [`WARM_UP`]) and from iteration [`FITTED_FROM`] on (later if the first phase ran past
/// it), when the model has fitted the batch (a single frame, stepped on over and over).
fn train_step_ms(vgg: Option<Arc<VggPerceptual>>) -> [(usize, f64); 2] {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/train_cpu.json");
    let config = TrainConfig::load(&path).expect("config");
    let head = HeadAsset::embedded().expect("head");
    let data = std::env::temp_dir().join(format!("texavatars-bench-cvt-{}", std::process::id()));
    let synth_cfg = SynthConfig {
        width: 138,
        height: 200,
        supersample: 1,
        cameras: 2,
        val_camera: 1,
        frames_per_sequence: 2,
        free_frames: 2,
        texture_res: 256,
        ..SynthConfig::default()
    };
    synth::generate(&synth_cfg, &head, &data, &mut |_| {}).expect("synth");
    let device = Device::flex().autodiff();
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
            vgg,
            vgg_from: 0,
            guard: None,
        },
    });
    let mut optim = optimizer(&config);
    let done = std::cell::Cell::new(0);
    let mut step = || {
        let m = model.take().expect("model");
        let out = m.step(batch.clone());
        model = Some(optim.step(config.lr_decoders, m, out.grads));
        done.set(done.get() + 1);
    };
    let untrained = median_ms(&mut step);
    while done.get() + WARM_UP < FITTED_FROM {
        step();
    }
    let fitted_from = done.get() + WARM_UP;
    let fitted = median_ms(&mut step);
    let _ = std::fs::remove_dir_all(&data);
    [(WARM_UP, untrained), (fitted_from, fitted)]
}

/// The two rows of one [`train_step_ms`] measurement.
fn step_rows(rows: &mut Vec<Row>, vgg: &str, [(a, untrained), (b, fitted)]: [(usize, f64); 2]) {
    let n = runs();
    for (when, ms) in [
        (
            format!("iterations {a}-{}, untrained", a + n - 1),
            untrained,
        ),
        (format!("iterations {b}-{}, fitted", b + n - 1), fitted),
    ] {
        rows.push((
            format!("training step `cpu`, 138x200, {vgg} ({when})"),
            ms,
            Err("no CPU PyTorch implementation of the whole step".to_string()),
        ));
    }
}

/// Whether the row group `name` is asked for (`TEXAVATARS_BENCH_ROWS`; all when unset).
fn wanted(name: &str) -> bool {
    std::env::var("TEXAVATARS_BENCH_ROWS")
        .map(|v| v.split(',').any(|r| r.trim() == name))
        .unwrap_or(true)
}

fn main() {
    texavatars::alloc::keep_freed_pages();
    // As the `texavatars` binary does (`cli::run`, kernels/cpu/src/threads.rs).
    texavatars::cpu::threads::on_pool(run);
}

fn run() {
    let skip_paper = std::env::var("TEXAVATARS_BENCH_SKIP_PAPER").is_ok_and(|v| v == "1");
    let threads = rayon::current_num_threads();
    println!(
        "burn-flex vs PyTorch on the CPU, {threads} threads, median of {} runs after {WARM_UP} \
         warm-up runs",
        runs()
    );
    let mut rows: Vec<Row> = Vec::new();
    let mut configs = vec!["cpu"];
    if !wanted("decoders") {
        configs.clear();
    } else if !skip_paper {
        configs.push("paper");
    }
    for c in configs {
        eprintln!("decoders {c} ...");
        let ours = decoders_ms(c);
        let torch = torch_ms("decoders_torch.py", &["--config", c]);
        rows.push((format!("decoders fwd+bwd, `{c}`"), ours, torch));
    }
    let vgg = Arc::new(VggPerceptual::from_host(
        &random_vgg(),
        &Device::flex().autodiff(),
    ));
    let mut sizes = vec![[200usize, 138usize]];
    if !wanted("perceptual") {
        sizes.clear();
    } else if !skip_paper {
        sizes.push([802, 550]);
    }
    for [h, w] in sizes {
        eprintln!("perceptual loss {w}x{h} ...");
        let size = format!("{h}x{w}");
        let torch = torch_ms("perceptual_torch.py", &["--size", &size]);
        let ours = perceptual_ms(&vgg, [h, w], false);
        rows.push((format!("VGG perceptual loss {w}x{h}"), ours, torch.clone()));
        if wanted("perceptual_before") {
            let before = perceptual_ms(&vgg, [h, w], true);
            rows.push((
                format!("VGG perceptual loss {w}x{h}, burn ops (before)"),
                before,
                torch,
            ));
        }
    }
    if wanted("step") {
        eprintln!("training steps ...");
        step_rows(&mut rows, "no VGG", train_step_ms(None));
    }
    if wanted("step_vgg") {
        eprintln!("training step with the perceptual loss ...");
        step_rows(&mut rows, "with VGG", train_step_ms(Some(vgg.clone())));
    }
    println!();
    println!("| what | burn-flex | PyTorch | ratio |");
    println!("|---|---|---|---|");
    for (what, ours, torch) in rows {
        match torch {
            Ok(t) => println!("| {what} | {ours:.1} ms | {t:.1} ms | {:.2}x |", ours / t),
            Err(why) => println!("| {what} | {ours:.1} ms | ({why}) | |"),
        }
    }
}
