//! Typed failures that decide the process exit code (docs/contracts.md, "Exit codes").
//!
//! Commands return `anyhow::Result`; `main` walks the error chain and maps the first typed
//! failure it finds. Anything untyped is a runtime failure (exit 1).

use std::process::ExitCode;

/// Bad usage or a bad input file (exit 2). The message names the file (and line where known).
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct BadInput(pub String);

/// The run stopped on SIGINT/SIGTERM after writing a checkpoint (exit 130).
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct Interrupted(pub String);

/// Builds a [`BadInput`] error with `format!` syntax.
#[macro_export]
macro_rules! bad_input {
    ($($arg:tt)*) => { anyhow::Error::new($crate::error::BadInput(format!($($arg)*))) };
}

pub const EXIT_RUNTIME: u8 = 1;
pub const EXIT_BAD_INPUT: u8 = 2;
pub const EXIT_INTERRUPTED: u8 = 130;

/// The exit code for an error: the first typed failure in its chain decides.
pub fn exit_code(err: &anyhow::Error) -> u8 {
    for cause in err.chain() {
        if cause.is::<BadInput>() || cause.is::<crate::curriculum::CurriculumError>() {
            return EXIT_BAD_INPUT;
        }
        if cause.is::<Interrupted>() {
            return EXIT_INTERRUPTED;
        }
    }
    EXIT_RUNTIME
}

/// Prints an error as one line (the chain joined by ": ") and returns its exit code.
pub fn report(err: &anyhow::Error) -> ExitCode {
    let code = exit_code(err);
    if code == EXIT_INTERRUPTED {
        eprintln!("{err:#}");
    } else {
        eprintln!("error: {err:#}");
    }
    ExitCode::from(code)
}
