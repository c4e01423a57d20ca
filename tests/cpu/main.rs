//! The fast CPU checks, one test binary (each integration test binary links all of burn, so
//! the checks are grouped): the dataset, the head model and its embedded default, the
//! lifting operator, image metrics, the networks, the CPU splat, the synthetic benchmark,
//! parser fuzzing, the source layering and the documentation. The resource limits are a
//! binary of their own (`tests/limits.rs`): they set the process-wide memory budget.

#[path = "../common/cli.rs"]
mod cli;
#[path = "../common/mod.rs"]
mod common;
#[path = "../tiny/mod.rs"]
mod tiny;

mod data;
mod docs;
mod eta;
mod fuzz;
mod head;
mod head_default;
mod layers;
mod lift;
mod metrics;
mod model;
mod splat_cpu;
mod synth;
