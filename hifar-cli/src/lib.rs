//! hifar: experiments for Booster T1 fall-recovery policies.
//!
//! The library holds everything; `main.rs` only parses arguments and maps errors to exit codes.
//! Python is reached only through [`python`], which owns the embedded interpreter.

pub mod atomic;
pub mod checkpoint;
pub mod cli;
pub mod commands;
pub mod curriculum;
pub mod error;
pub mod metrics;
pub mod names;
pub mod paths;
pub mod python;
pub mod recording;
pub mod run_dir;
pub mod terminal;
pub mod ui;
