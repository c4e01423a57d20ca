//! Evaluation with the paper's protocol (method.md §7), independent of how the renders were
//! made: per-image scores ([`Scorer`]), their means per split ([`Tally`]), the table in the
//! paper's layout ([`paper_table`]), side-by-side panels ([`panel`]) and training curves
//! ([`plot`]).

pub mod plot;
pub mod run;
pub mod score;

pub use plot::{Series, line_plot};
pub use score::{Means, Scorer, Scores, Tally, panel, paper_table};
