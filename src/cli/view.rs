//! `texavatars view`: the live browser viewer ([`crate::view`]).

use std::net::IpAddr;
use std::path::PathBuf;

use clap::Args;

use crate::device::BackendKind;
use crate::view::{SceneOptions, ViewOptions, Viewer};

/// Arguments of `view`.
#[derive(Debug, Args)]
pub struct ViewArgs {
    /// The trained avatar: a `texavatars train` output folder or a GaussianAvatars output
    /// folder (as for `render`). Without it, an untrained TexAvatars avatar of `--net`
    /// (random weights: for timing the networks only).
    #[arg(long)]
    pub checkpoint: Option<PathBuf>,
    /// Networks of the untrained avatar shown without --checkpoint.
    #[arg(long, default_value = "configs/paper.json")]
    pub net: PathBuf,
    /// A motion to play and scrub (as `render --motion`): a dataset split
    /// (`DATA/transforms_test.json`: its cameras become presets and its images are shown
    /// beside the render with the PSNR), FLAME parameter files, or a curves JSON.
    #[arg(long)]
    pub motion: Option<PathBuf>,
    /// Port to listen on (0: any free port).
    #[arg(long, default_value_t = 8080)]
    pub port: u16,
    /// Address to listen on. The default serves this machine only; `0.0.0.0` serves the
    /// network (the viewer has no authentication).
    #[arg(long, default_value = "127.0.0.1")]
    pub host: IpAddr,
    /// The head model the avatar was trained with (as for `render`).
    #[arg(long)]
    pub head: Option<PathBuf>,
    /// The avatar's subject (a `flame_param` `.npz`; as for `render`).
    #[arg(long)]
    pub identity: Option<PathBuf>,
    /// Where tensors live.
    #[arg(long, value_enum, default_value_t = BackendKind::Flex)]
    pub backend: BackendKind,
}

/// Runs `view` until Ctrl-C.
pub fn run(a: ViewArgs) -> anyhow::Result<()> {
    let viewer = Viewer::start(ViewOptions {
        scene: SceneOptions {
            checkpoint: a.checkpoint,
            net: a.net,
            motion: a.motion,
            head: a.head,
            identity: a.identity,
            backend: a.backend,
        },
        host: a.host,
        port: a.port,
        stop_on_ctrl_c: true,
    })?;
    let info = viewer.info();
    let motion = info.motion.as_ref().map_or(String::new(), |m| {
        format!(", motion {} ({} frames)", m.source, m.frames)
    });
    println!(
        "view: {} ({}, {} Gaussians, {:?}){motion}",
        info.model, info.source, info.gaussians, info.backend
    );
    println!("view: open {} in a browser (Ctrl-C stops)", viewer.url());
    viewer.wait()?;
    Ok(())
}
