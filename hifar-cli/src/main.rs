use std::process::ExitCode;

use clap::Parser;
use hifar_cli::{cli::Cli, commands, error};

fn main() -> ExitCode {
    // End quietly, like other Unix filters, when whoever reads stdout goes away
    // (`hifar check FILE | head -1`): Rust ignores SIGPIPE, which turns that into a panic on
    // the next `println!`. The embedded Python is initialised without its signal handlers, so
    // this default stands.
    #[cfg(unix)]
    // SAFETY: called first thing in main, before any other thread exists.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
    let cli = Cli::parse();
    match commands::run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => error::report(&err),
    }
}
