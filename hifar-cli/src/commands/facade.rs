//! Calling `jax_env.facade` from a command: Python failures as one-line errors whose traceback
//! goes to a log, and the questions several commands ask Python.

use std::path::Path;

use anyhow::{anyhow, Result};
use serde_json::Value;

use crate::python::{Facade, PythonError};

/// The physics backend `backend = "auto"` means on this machine (`facade.doctor()`).
pub fn default_backend(facade: &Facade, log: &Path) -> Result<String> {
    default_backend_and_reason(facade, log).map(|(backend, _)| backend)
}

/// [`default_backend`], and why `facade.doctor()` chose it.
pub fn default_backend_and_reason(facade: &Facade, log: &Path) -> Result<(String, String)> {
    let report = facade.call("doctor", &[]).map_err(|err| python_failure("facade.doctor() failed", err, log))?;
    let backend = report
        .get("default_backend")
        .and_then(Value::as_str)
        .map(str::to_owned)
        .ok_or_else(|| anyhow!("facade.doctor() returned no default_backend: {report}"))?;
    let reason = report.get("reason").and_then(Value::as_str).unwrap_or("auto").to_owned();
    Ok((backend, reason))
}

/// Turns a Python exception into a one-line error, its traceback appended to `log`.
pub fn python_failure(context: &str, err: PythonError, log: &Path) -> anyhow::Error {
    match err.write_traceback(log) {
        Ok(()) => anyhow!("{context}: {} (traceback in {})", err.summary, log.display()),
        Err(_) => anyhow!("{context}: {}", err.summary),
    }
}
