//! Datasets: the VHAP / GaussianAvatars export format.

pub mod vhap;
