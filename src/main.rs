//! The `texavatars` command line.

use std::process::ExitCode;

use clap::Parser;

fn main() -> ExitCode {
    let cli = texavatars::cli::Cli::parse();
    match texavatars::cli::run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
