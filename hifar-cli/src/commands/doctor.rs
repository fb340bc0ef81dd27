//! `hifar doctor`: what hifar found, what is missing, and how to fix it.
//!
//! Never creates anything: with no environment it says to run `hifar setup`. Exit 0 when
//! nothing is missing, 1 otherwise.

use anyhow::{bail, Result};
use serde_json::Value;

use crate::commands::setup::VenvState;
use crate::{paths, python};

pub fn run() -> Result<()> {
    let mut problems: Vec<String> = Vec::new();
    println!("hifar         {}", env!("CARGO_PKG_VERSION"));
    println!("repository    {}", paths::repo_root().display());
    let info = python::base_info().map_err(anyhow::Error::new)?;
    println!("python        {} (embedded; base installation {})", info.version, info.base_prefix.display());

    let venv = paths::venv_dir();
    let state = VenvState::of(&venv, &info)?;
    let state_text = match state {
        VenvState::Missing => "missing",
        VenvState::Stale => "out of date with requirements.lock/pyproject.toml",
        VenvState::UpToDate => "up to date",
        VenvState::WrongPython => "made for another Python version",
        VenvState::Unmanaged => "not created by `hifar setup` (used as is)",
    };
    println!("venv          {} ({state_text})", venv.display());
    match state {
        VenvState::Missing => {
            println!("\nproblems:\n  - no Python environment at {}: run `hifar setup`", venv.display());
            bail!("Python environment missing; run `hifar setup`");
        }
        VenvState::Stale | VenvState::WrongPython => {
            problems.push(format!("the environment is {state_text}: run `hifar setup`"));
        }
        VenvState::UpToDate | VenvState::Unmanaged => {}
    }

    let log = paths::command_log();
    let facade = match python::activate(&venv, &paths::jax_cache_dir(), &paths::command_log()) {
        Ok(facade) => facade,
        Err(err) => {
            let _ = err.write_traceback(&log);
            println!("jax_env       cannot be imported: {}", err.summary);
            println!("\nproblems:\n  - jax_env.facade does not import ({}): run `hifar setup --force` (traceback in {})", err.summary, log.display());
            bail!("jax_env is not usable");
        }
    };
    match facade.call("versions", &[]) {
        Ok(Value::Object(versions)) => {
            let line: Vec<String> = versions
                .iter()
                .map(|(name, version)| format!("{name} {}", version.as_str().map(str::to_owned).unwrap_or_else(|| version.to_string())))
                .collect();
            println!("packages      {}", line.join(", "));
            for required in ["jax", "jaxlib", "mujoco", "mujoco_mjx", "brax"] {
                if versions.get(required).is_none_or(Value::is_null) {
                    problems.push(format!("{required} is not installed: run `hifar setup --force`"));
                }
            }
        }
        Ok(other) => problems.push(format!("facade.versions() returned {other}, expected a dict")),
        Err(err) => problems.push(format!("facade.versions() failed: {}", err.summary)),
    }
    match facade.call("doctor", &[]) {
        Ok(report) => {
            let devices = match report.get("devices") {
                Some(Value::Array(devices)) => devices.iter().map(show).collect::<Vec<_>>().join(", "),
                _ => "unknown".into(),
            };
            println!("jax devices   {devices}");
            println!(
                "backend       {} ({})",
                report.get("default_backend").map(show).unwrap_or_else(|| "unknown".into()),
                report.get("reason").map(show).unwrap_or_default()
            );
            if let Some(Value::Array(list)) = report.get("problems") {
                problems.extend(list.iter().map(show));
            }
        }
        Err(err) => {
            let _ = err.write_traceback(&log);
            problems.push(format!("facade.doctor() failed: {} (traceback in {})", err.summary, log.display()));
        }
    }
    if problems.is_empty() {
        println!("\nno problems found");
        Ok(())
    } else {
        println!("\nproblems:");
        for problem in &problems {
            println!("  - {problem}");
        }
        bail!("{} problem(s) found", problems.len())
    }
}

fn show(value: &Value) -> String {
    match value {
        Value::String(s) => s.clone(),
        other => other.to_string(),
    }
}
