//! Clap commands: thin wrappers that parse, call the library and report.

pub mod bench;
pub mod demo;
pub mod eta;
pub mod eval;
pub mod export;
pub mod head;
pub mod metrics;
pub mod render;
pub mod splat;
pub mod study;
pub mod synth;
pub mod train;
pub mod uv;
pub mod view;
pub mod weights;

use clap::{Parser, Subcommand};

/// TexAvatars: hybrid texel-3D Gaussian head avatars.
#[derive(Debug, Parser)]
#[command(name = "texavatars", version, about)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
    /// Memory budget of this run: bytes with an optional K, M, G or T suffix (powers of
    /// 1024), e.g. 16G. Commands refuse inputs whose estimated memory is above it, before
    /// any work. Default: the TEXAVATARS_MAX_MEMORY environment variable, else 3/4 of the
    /// machine's memory (see `texavatars::limits`).
    #[arg(long, global = true, value_name = "SIZE", value_parser = crate::limits::parse_bytes)]
    pub max_memory: Option<u64>,
}

/// Top-level commands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Benchmarks of a driven avatar (frames per second).
    #[command(subcommand)]
    Bench(bench::BenchCommand),
    /// The main job: synthetic benchmark, CPU training, evaluation, report (out/demo).
    Demo(demo::DemoArgs),
    /// Compute eta (the 128-value image expression code) for every timestep of an export
    /// from its own images: face crops, VGG16 features, a projection fitted on the
    /// training split; written as the eta/TTTTT.npy side files.
    Eta(eta::EtaArgs),
    /// Render a trained avatar on the evaluation splits (novel view, novel expression,
    /// FREE) and score it: metrics.json, the paper's table, comparison images.
    Eval(eval::EvalArgs),
    /// Export a driven avatar (per-frame 3DGS PLY files).
    #[command(subcommand)]
    Export(export::ExportCommand),
    /// Head models: import the default head, print a summary, add VHAP's teeth.
    #[command(subcommand)]
    Head(head::HeadCommand),
    /// PSNR, SSIM and LPIPS (alex, vgg, GaussianAvatars' unscaled variant) between two
    /// images, printed as one JSON object.
    Metrics(metrics::MetricsArgs),
    /// Drive a trained avatar with a motion (dataset split, another subject's FLAME
    /// parameters, or curves) and write frames, a contact sheet, a GIF and an MP4.
    Render(render::RenderArgs),
    /// The Gaussian rasterizer on its own.
    #[command(subcommand)]
    Splat(splat::SplatCommand),
    /// The paper's comparison: train and evaluate the full method, its ablations and
    /// GaussianAvatars on several subjects and write Table 1 and Table 2 (resumable;
    /// --plan / --run K / --collect to spread the runs over machines).
    Study(study::StudyArgs),
    /// Render the synthetic multi-view head benchmark (VHAP / GaussianAvatars format).
    Synth(synth::SynthArgs),
    /// Train an avatar on a VHAP export (e.g. the synthetic benchmark's `union` folder).
    Train(train::TrainArgs),
    /// UV layouts of meshes.
    #[command(subcommand)]
    Uv(uv::UvCommand),
    /// Drive a trained avatar live in a web browser: a local server with orbit camera,
    /// expression and pose sliders, motion playback and ground truth.
    View(view::ViewArgs),
    /// Pretrained VGG16 / AlexNet weights for the perceptual loss and LPIPS.
    #[command(subcommand)]
    Weights(weights::WeightsCommand),
}

/// Runs a parsed command line.
///
/// `--max-memory` is applied first ([`crate::limits::set_max_memory`]: for the rest of the
/// process), and a malformed `TEXAVATARS_MAX_MEMORY` is an error before any work.
pub fn run(cli: Cli) -> anyhow::Result<()> {
    crate::limits::set_max_memory(cli.max_memory);
    crate::limits::budget()?;
    let command = match cli.command {
        // The viewer keeps this thread waiting for its server for the whole session; on a
        // pool thread that would take a worker from its render thread's parallel loops (and
        // with one worker, stall them), so it stays off the pool.
        Command::View(a) => return view::run(a),
        c => c,
    };
    // Every other command runs on a pool thread, where each parallel loop starts without a
    // sleep and wake-up of the calling thread (kernels/cpu/src/threads.rs).
    texavatars_cpu::threads::on_pool(|| match command {
        Command::Bench(c) => bench::run(c),
        Command::Demo(a) => demo::run(a),
        Command::Eta(a) => eta::run(a),
        Command::Eval(a) => eval::run(a),
        Command::Export(c) => export::run(c),
        Command::Head(c) => head::run(c),
        Command::Metrics(a) => metrics::run(a),
        Command::Render(a) => render::run(a),
        Command::Splat(c) => splat::run(c),
        Command::Study(a) => study::run(a),
        Command::Synth(a) => synth::run(a),
        Command::Train(a) => train::run(a),
        Command::Uv(c) => uv::run(c),
        Command::View(a) => view::run(a),
        Command::Weights(c) => weights::run(c),
    })
}
