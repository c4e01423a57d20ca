//! `texavatars demo`: the main job on the embedded default head.

use std::path::PathBuf;

use clap::Args;

use crate::demo::{DemoOptions, default_train_config, paper_configs, run as run_demo};
use crate::synth::SynthConfig;

/// Arguments of `demo`.
#[derive(Debug, Args)]
pub struct DemoArgs {
    /// Output folder (data/, run/, report/); an interrupted job continues where it stopped
    /// (default: out/demo; with --paper, out/paper).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Training configuration (default: configs/train_cpu.json; with --paper,
    /// configs/train_paper_cpu.json).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// The paper-scale avatar: the benchmark at 550 x 802 (configs/synth_802x550.json) and
    /// the paper networks (configs/train_paper_cpu.json). Hours on 2 cores; stop it at any
    /// time and run the same command again to continue.
    #[arg(long)]
    pub paper: bool,
    /// Score ceil(n / k) of each split's n images, spread evenly over its timesteps and
    /// cameras.
    #[arg(long, default_value_t = 4)]
    pub eval_stride: usize,
    /// Do not install the VGG16 / AlexNet weights when missing (VGG loss and LPIPS need them).
    #[arg(long)]
    pub no_weights_install: bool,
    /// When OUT/data holds a benchmark made with other settings (an earlier version's
    /// defaults), generate it again and train anew (deletes its files and OUT/run).
    #[arg(long)]
    pub force: bool,
}

/// Runs `demo`.
pub fn run(a: DemoArgs) -> anyhow::Result<()> {
    // As in `train`: burn restores a checkpoint's optimiser state on `Device::default()`;
    // keep a resumed CPU run on flex (the demo trains and evaluates on flex).
    if std::env::var_os("BURN_DEVICE").is_none() {
        // SAFETY: called from `main` right after parsing the command line, before anything
        // has started a thread that could read the environment concurrently.
        unsafe { std::env::set_var("BURN_DEVICE", "flex") };
    }
    let (synth_config, train_config, out) = if a.paper {
        let (synth, train) = paper_configs()?;
        (synth, train, "out/paper")
    } else {
        (SynthConfig::default(), default_train_config(), "out/demo")
    };
    let opts = DemoOptions {
        out: a.out.unwrap_or_else(|| PathBuf::from(out)),
        synth_config,
        train_config: a.config.unwrap_or(train_config),
        eval_stride: a.eval_stride,
        install_weights: !a.no_weights_install,
        force: a.force,
    };
    let report = run_demo(&opts, &mut |l| eprintln!("demo: {l}"))?;
    println!("{}", std::fs::read_to_string(report.join("README.md"))?);
    Ok(())
}
