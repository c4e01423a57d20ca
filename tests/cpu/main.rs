//! The fast CPU checks, one test binary (each integration test binary links all of burn, so
//! the checks are grouped): the dataset, the head model and its embedded default, the
//! lifting operator, resource limits, image metrics, the networks, the CPU splat, the
//! synthetic benchmark, parser fuzzing, the source layering and the documentation.
//!
//! One process: `limits` runs the command line in-process with `--max-memory 1G`, which then
//! holds for every in-process budget check of this binary (the other modules' in-process
//! work, a 24 x 32 synthetic set at most, fits in it by far).

#[path = "../common/cli.rs"]
mod cli;
#[path = "../common/mod.rs"]
mod common;

mod data;
mod docs;
mod fuzz;
mod head;
mod head_default;
mod layers;
mod lift;
mod limits;
mod metrics;
mod model;
mod splat_cpu;
mod synth;
