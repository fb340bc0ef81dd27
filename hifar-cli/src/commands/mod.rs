//! One module per subcommand; `run` dispatches.

use std::io::IsTerminal;
use std::time::Duration;

use anyhow::Result;
use indicatif::{ProgressBar, ProgressStyle};

use crate::cli::{Cli, Command};

pub mod act;
pub mod bench;
pub mod check;
pub mod doctor;
pub mod eval;
pub mod expand;
pub mod export;
pub mod report;
pub mod rollout;
pub mod runs;
pub mod setup;
pub mod target;

pub fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Setup(args) => setup::run(&args),
        Command::Doctor => doctor::run(),
        Command::Check(args) => check::run(&args),
        Command::Train(args) => crate::train::run(&args),
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

/// A spinner on a terminal, plain lines otherwise (CI logs, tests).
pub struct Status {
    bar: Option<ProgressBar>,
    prefix: &'static str,
}

impl Status {
    pub fn start(prefix: &'static str) -> Status {
        let bar = std::io::stderr().is_terminal().then(|| {
            let bar = ProgressBar::new_spinner();
            bar.set_style(ProgressStyle::with_template("{spinner} {prefix}: {msg} [{elapsed}]").expect("valid template"));
            bar.set_prefix(prefix);
            bar.enable_steady_tick(Duration::from_millis(120));
            bar
        });
        Status { bar, prefix }
    }

    pub fn step(&self, message: &str) {
        match &self.bar {
            Some(bar) => bar.set_message(message.to_owned()),
            None => eprintln!("{}: {message}", self.prefix),
        }
    }

    pub fn finish(&self, message: &str) {
        if let Some(bar) = &self.bar {
            bar.finish_and_clear();
        }
        eprintln!("{message}");
    }
}

impl Drop for Status {
    fn drop(&mut self) {
        if let Some(bar) = &self.bar {
            bar.finish_and_clear();
        }
    }
}

/// The physics backend `backend = "auto"` means on this machine (`facade.doctor()`).
pub fn default_backend(facade: &crate::python::Facade, log: &std::path::Path) -> Result<String> {
    let report = facade.call("doctor", &[]).map_err(|err| python_failure("facade.doctor() failed", err, log))?;
    report
        .get("default_backend")
        .and_then(serde_json::Value::as_str)
        .map(str::to_owned)
        .ok_or_else(|| anyhow::anyhow!("facade.doctor() returned no default_backend: {report}"))
}

/// Turns a Python exception into a one-line error, its traceback appended to `log`.
pub fn python_failure(context: &str, err: crate::python::PythonError, log: &std::path::Path) -> anyhow::Error {
    match err.write_traceback(log) {
        Ok(()) => anyhow::anyhow!("{context}: {} (traceback in {})", err.summary, log.display()),
        Err(_) => anyhow::anyhow!("{context}: {}", err.summary),
    }
}
