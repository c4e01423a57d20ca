//! The command-line tests, one test binary (each integration test binary links all of
//! burn): the `splat` and `uv` commands, driving a tiny trained avatar (`render`, `export
//! ply`, `bench fps`, `view`, and a GaussianAvatars folder) and `eval`. Most run the built
//! `texavatars` executable.

#[path = "../common/cli.rs"]
mod cli;
#[path = "../common/mod.rs"]
mod common;
#[path = "../tiny/mod.rs"]
mod tiny;

mod drive;
mod eval;
mod splat_cli;
mod uv_cli;
