//! Datasets: the VHAP / GaussianAvatars export format, as a burn dataset and batcher.

pub mod batch;
pub mod crop;
pub mod dataset;
pub mod eta;
pub mod identity;
pub mod refined;
pub mod split;
pub mod validate;
pub mod vhap;

pub use batch::{HeadBatch, HeadBatcher};

/// The background the ground truth is composited on and every model renders on (method
/// §1, §5: white; GaussianAvatars' `--white_background` for NeRSemble).
pub const BACKGROUND: [f32; 3] = [1.0, 1.0, 1.0];
pub use dataset::{Conditioning, HeadDataset, HeadItem};
pub use identity::Identity;
pub use split::Split;
pub use validate::PathPolicy;

/// The head a dataset was made with: `data/../head/head.npz` when present (a
/// `texavatars synth` output), else the embedded default.
pub fn head_for(data: &std::path::Path) -> crate::error::Result<crate::head::HeadAsset> {
    let npz = data.join("../head/head.npz");
    if npz.exists() {
        crate::head::HeadAsset::load(&npz, None)
    } else {
        crate::head::HeadAsset::embedded()
    }
}
