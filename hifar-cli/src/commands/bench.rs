//! `hifar bench`: throughput of raw `mujoco.batch`, the native and MJX environments, and the
//! learner, measured by `jax_env.bench`.
//!
//! The benchmark runs each measurement in a child process (so compile time and peak memory
//! are per entry), which needs a real `python` executable: it runs in the venv's interpreter,
//! not in the embedded one. Its output (table or JSON) is passed through unchanged.

use std::process::Command;

use anyhow::{bail, Context, Result};

use crate::cli::BenchArgs;
use crate::commands::setup;
use crate::paths;

pub fn run(args: &BenchArgs) -> Result<()> {
    setup::ensure_python()?;
    let python = paths::venv_dir().join("bin").join("python");
    let mut command = Command::new(&python);
    command.current_dir(paths::repo_root()).args(["-m", "jax_env.bench"]);
    if args.json {
        command.arg("--json");
    }
    if args.quick {
        command.arg("--quick");
    }
    if !args.batches.is_empty() {
        command.arg("--batches").args(args.batches.iter().map(u32::to_string));
    }
    if let Some(max) = args.mjx_max_batch {
        command.args(["--mjx-max-batch", &max.to_string()]);
    }
    let status = command.status().with_context(|| format!("cannot start {}", python.display()))?;
    if !status.success() {
        bail!("the benchmark failed ({status}); its messages are above");
    }
    Ok(())
}
