//! `texavatars train`: train an avatar on a VHAP export.

use std::path::PathBuf;

use clap::Args;

use crate::device::BackendKind;
use crate::head::HeadAsset;
use crate::train::gaussianavatars::GaTrainConfig;
use crate::train::{self, TrainConfig, TrainOptions};

/// The avatar models `train` can train.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum ModelKind {
    /// TexAvatars: decoders in UV space, the texel lift (configs/train_cpu.json).
    #[default]
    Texavatars,
    /// GaussianAvatars: Gaussians bound to the mesh's triangles, adaptive density control
    /// (configs/train_gaussianavatars.json).
    Gaussianavatars,
}

/// Arguments of `train`.
#[derive(Debug, Args)]
pub struct TrainArgs {
    /// The model to train; its config format follows (see `--config`).
    #[arg(long, value_enum, default_value_t = ModelKind::Texavatars)]
    pub model: ModelKind,
    /// The export's split folder with `transforms_{train,val}.json` (`OUT/union` of
    /// `texavatars synth`).
    #[arg(long)]
    pub data: PathBuf,
    /// Training config (configs/train_cpu.json for TexAvatars,
    /// configs/train_gaussianavatars.json for GaussianAvatars).
    #[arg(long)]
    pub config: PathBuf,
    /// Output folder: checkpoints, metric logs, the trained avatar.
    #[arg(long)]
    pub out: PathBuf,
    /// Continue the run in `--out` from its newest complete checkpoint.
    #[arg(long)]
    pub resume: bool,
    /// Start afresh even when `--out` holds a run or a finished avatar (train's own files
    /// there are removed first).
    #[arg(long, conflicts_with = "resume")]
    pub force: bool,
    /// Where tensors live (overrides the config's `backend`).
    #[arg(long, value_enum)]
    pub backend: Option<BackendKind>,
    /// The head model `.npz` the data was made with (its `.obj` next to it); default:
    /// `DATA/../head/head.npz` when present (a `texavatars synth` output), else the embedded
    /// head.
    #[arg(long)]
    pub head: Option<PathBuf>,
    /// Read dataset files that lie outside the dataset's folder (by default only files in
    /// it, or in a sibling VHAP export it combines, are read).
    #[arg(long)]
    pub allow_outside_paths: bool,
}

/// Runs `train`.
pub fn run(a: TrainArgs) -> anyhow::Result<()> {
    let (config, backend) = match a.model {
        ModelKind::Texavatars => {
            let c = TrainConfig::load(&a.config)?;
            let b = a.backend.unwrap_or(c.backend);
            (Ok(c), b)
        }
        ModelKind::Gaussianavatars => {
            let c = GaTrainConfig::load(&a.config)?;
            let b = a.backend.unwrap_or(c.backend);
            (Err(c), b)
        }
    };
    // burn 0.22 restores a checkpoint's optimiser state on `Device::default()`
    // (`ModuleOptimizer::load_record`), which is wgpu whenever that backend is compiled in: a
    // resumed CPU run would start the Vulkan driver only to move the state off it on the first
    // step. `BURN_DEVICE` points the default at the run's backend (unless the user set it).
    if std::env::var_os("BURN_DEVICE").is_none() {
        let name = match backend {
            BackendKind::Cpu => "ndarray",
            BackendKind::Flex => "flex",
            BackendKind::Wgpu => "wgpu",
            #[cfg(feature = "cuda")]
            BackendKind::Cuda => "cuda",
        };
        // SAFETY: called from `main` right after parsing the command line, before anything
        // has started a thread that could read the environment concurrently.
        unsafe { std::env::set_var("BURN_DEVICE", name) };
    }
    let mut options = TrainOptions::new(&a.data, &a.out);
    options.resume = a.resume;
    options.force = a.force;
    if a.allow_outside_paths {
        options.paths = crate::data::PathPolicy::Anywhere;
    }
    // Ctrl-C / SIGTERM: finish the step, checkpoint, say how to resume, exit 130 / 143.
    options.handle_signals = true;
    options.backend = Some(backend);
    options.head = match &a.head {
        Some(p) => Some(HeadAsset::load(p, None)?),
        None => None,
    };
    let config = match config {
        Ok(c) => c,
        Err(ga) => {
            let r = crate::train::gaussianavatars::train(&ga, &options)?;
            println!(
                "trained GaussianAvatars iterations {}..{} in {:.1} s ({} Gaussians); {}",
                r.start_iteration,
                r.end_iteration,
                r.seconds,
                r.gaussians,
                if r.complete {
                    format!("written to {}", r.output.display())
                } else {
                    "stopped with a checkpoint (no point cloud yet)".into()
                }
            );
            return Ok(());
        }
    };
    let r = train::train(&config, &options)?;
    println!(
        "trained iterations {}..{} in {:.1} s ({} Gaussians); {}",
        r.start_iteration,
        r.end_iteration,
        r.seconds,
        r.gaussians,
        if r.complete {
            format!("avatar written to {}", r.avatar_path.display())
        } else {
            "stopped with a checkpoint (no avatar yet)".into()
        }
    );
    Ok(())
}
