//! The `texavatars` command line.

use std::process::ExitCode;

use clap::Parser;

/// mimalloc keeps freed pages mapped: the renderer allocates tens of MB per call, which the
/// system allocator maps and faults in afresh every time.
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() -> ExitCode {
    texavatars::alloc::keep_freed_pages();
    let cli = texavatars::cli::Cli::parse();
    match texavatars::cli::run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            match e.downcast_ref::<texavatars::error::Error>() {
                Some(e) => ExitCode::from(e.exit_code()),
                None => ExitCode::FAILURE,
            }
        }
    }
}
