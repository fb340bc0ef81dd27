use std::process::ExitCode;

use clap::Parser;
use hifar_cli::{cli::Cli, commands, error};

fn main() -> ExitCode {
    let cli = Cli::parse();
    match commands::run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => error::report(&err),
    }
}
