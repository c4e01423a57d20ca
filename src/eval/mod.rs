//! Evaluation with the paper's protocol (method.md §7), independent of how the renders were
//! made: which images of a split to score ([`sample`]), per-image scores ([`Scorer`]), their
//! means and standard deviations per split ([`Tally`]) and over subjects
//! ([`combine_subjects`]), the table in the paper's layout ([`paper_table`]), side-by-side
//! panels ([`panel`]), training curves ([`plot`]) and errors per face region ([`regions`]).

pub mod plot;
pub mod regions;
pub mod run;
pub mod sample;
pub mod score;

pub use plot::{Series, line_plot};
pub use score::{Means, Scorer, Scores, Tally, combine_subjects, panel, paper_table};
