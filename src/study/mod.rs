//! `texavatars study`: the paper's comparison in one command. From a study config
//! ([`config`]: subjects, the training configs, seeds, variants), train the full method
//! (once per seed), each paper ablation, w/o FLAME refinement and the GaussianAvatars
//! baseline on every subject, evaluate them all, and write the paper's Table 1 and Table 2
//! with charts, training curves and side-by-side panels ([`report`]).
//!
//! Every (subject, variant, seed) is an independent run ([`run`]): resumable (a finished
//! run is skipped, an interrupted one continues from its checkpoint), runnable one at a
//! time by index (`--run K`) so that a cluster's array job or `xargs -P` can spread them
//! over machines sharing the output folder (`--plan` writes the command lines and a Slurm
//! array script), and collected from whatever has finished (`--collect`). [`paired`]
//! compares each run's images with its subject's full method (`--paired`), and
//! [`ladder`] reads several studies as the rungs of a resolution ladder (`--ladder`).

pub mod config;
pub mod ladder;
pub mod paired;
pub mod report;
pub mod run;

pub use config::{RunSpec, Study, StudyConfig, Variant};
