//! Datasets: the VHAP / GaussianAvatars export format, as a burn dataset and batcher.

pub mod batch;
pub mod dataset;
pub mod identity;
pub mod split;
pub mod validate;
pub mod vhap;

pub use batch::{HeadBatch, HeadBatcher};
pub use dataset::{Conditioning, HeadDataset, HeadItem};
pub use identity::Identity;
pub use split::Split;
pub use validate::PathPolicy;
