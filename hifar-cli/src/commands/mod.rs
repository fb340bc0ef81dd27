//! One module per subcommand; `run` dispatches.

use anyhow::Result;

use crate::cli::{Cli, Command};

pub mod act;
pub mod bench;
pub mod check;
pub mod doctor;
pub mod eval;
pub mod expand;
pub mod export;
pub mod facade;
pub mod report;
pub mod rollout;
pub mod runs;
pub mod setup;
pub mod target;
pub mod train;

pub fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Setup(args) => setup::run(&args),
        Command::Doctor => doctor::run(),
        Command::Check(args) => check::run(&args),
        Command::Train(args) => train::run(&args),
        Command::ExpandCheckpoint(args) => expand::run(&args),
        Command::Act(args) => act::run(&args),
        Command::Bench(args) => bench::run(&args),
        Command::Eval(args) => eval::run(&args),
        Command::Rollout(args) => rollout::run(&args),
        Command::Report(args) => report::run(&args),
        Command::Export(args) => export::run(&args),
        Command::Runs(args) => runs::run(&args),
    }
}
