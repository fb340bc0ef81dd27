//! `hifar setup`: the pinned Python environment, created once and reused.
//!
//! The venv is made with the same Python minor version that hifar embeds (its extension modules
//! must load into the embedded interpreter), then `pip install -r requirements.lock` and an
//! editable install of `jax_env`. A stamp file records the hash of `requirements.lock` and
//! `pyproject.toml`; when both are unchanged, setup is a no-op, so every command that needs
//! Python runs it implicitly at almost no cost.

use std::fs;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};

use crate::cli::SetupArgs;
use crate::ui::Status;
use crate::paths;
use crate::python::{self, BaseInfo, Facade};

const STAMP: &str = "hifar-setup.json";
const LOG: &str = "hifar-setup.log";

pub fn run(args: &SetupArgs) -> Result<()> {
    let venv = paths::venv_dir();
    let info = python::base_info().map_err(anyhow::Error::new)?;
    if !args.force && VenvState::of(&venv, &info)? == VenvState::UpToDate {
        eprintln!("Python environment {} is up to date", venv.display());
        return Ok(());
    }
    let _lock = setup_lock(&venv)?;
    match (args.force, VenvState::of(&venv, &info)?) {
        (false, VenvState::UpToDate) => {
            eprintln!("Python environment {} is up to date", venv.display());
            Ok(())
        }
        (force, state) => build(&venv, &info, force || state == VenvState::WrongPython),
    }
}

/// Serialises setups of one venv across processes (parallel tests, two terminals): the lock
/// file sits beside the venv, which may be deleted and recreated under it.
fn setup_lock(venv: &Path) -> Result<fs::File> {
    let parent = venv.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    fs::create_dir_all(parent).with_context(|| format!("cannot create {}", parent.display()))?;
    let name = venv.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "venv".into());
    let path = parent.join(format!(".{name}.hifar-setup.lock"));
    let file = fs::OpenOptions::new()
        .create(true)
        .truncate(false)
        .write(true)
        .open(&path)
        .with_context(|| format!("cannot open {}", path.display()))?;
    file.lock().with_context(|| format!("cannot lock {}", path.display()))?;
    Ok(file)
}

/// Makes sure the venv exists and is current, then activates it and imports the facade.
///
/// A venv that exists without hifar's stamp was made by someone else: it is used as it is.
pub fn ensure_python() -> Result<Facade> {
    let venv = paths::venv_dir();
    let info = python::base_info().map_err(anyhow::Error::new)?;
    if !matches!(VenvState::of(&venv, &info)?, VenvState::UpToDate | VenvState::Unmanaged) {
        let _lock = setup_lock(&venv)?;
        match VenvState::of(&venv, &info)? {
            VenvState::UpToDate | VenvState::Unmanaged => {}
            VenvState::Missing | VenvState::Stale => build(&venv, &info, false)?,
            VenvState::WrongPython => build(&venv, &info, true)?,
        }
    }
    python::activate(&venv, &paths::jax_cache_dir(), &paths::command_log()).map_err(|err| {
        let log = paths::command_log();
        let _ = err.write_traceback(&log);
        if err.summary.contains("No module named 'jax_env'") {
            anyhow::anyhow!(
                "jax_env is not installed in {} ({}); run `hifar setup --force`",
                venv.display(),
                err.summary
            )
        } else {
            anyhow::anyhow!("cannot import jax_env.facade: {} (traceback in {})", err.summary, log.display())
        }
    })
}

#[derive(Debug, Serialize, Deserialize, PartialEq)]
struct Stamp {
    inputs_crc32c: String,
    python: String,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum VenvState {
    Missing,
    /// Created by hifar for other pinned inputs.
    Stale,
    UpToDate,
    /// Created by hifar for another Python minor version than the embedded one.
    WrongPython,
    /// Exists but was not created by `hifar setup`.
    Unmanaged,
}

impl VenvState {
    pub fn of(venv: &Path, info: &BaseInfo) -> Result<VenvState> {
        if !venv.join("pyvenv.cfg").is_file() {
            return Ok(VenvState::Missing);
        }
        let Ok(text) = fs::read_to_string(venv.join(STAMP)) else {
            return Ok(VenvState::Unmanaged);
        };
        let Ok(stamp) = serde_json::from_str::<Stamp>(&text) else {
            return Ok(VenvState::Stale);
        };
        if !stamp.python.starts_with(&format!("{}.", info.major_minor)) {
            return Ok(VenvState::WrongPython);
        }
        Ok(if stamp.inputs_crc32c == inputs_hash()? { VenvState::UpToDate } else { VenvState::Stale })
    }
}

/// Hash of the pinned inputs (requirements.lock, pyproject.toml).
fn inputs_hash() -> Result<String> {
    let root = paths::repo_root();
    let mut parts = Vec::new();
    for name in ["requirements.lock", "pyproject.toml"] {
        let path = root.join(name);
        let bytes = fs::read(&path).with_context(|| {
            format!("cannot read {} (set HIFAR_HOME to the hifar repository)", path.display())
        })?;
        parts.push(format!("{:08x}", crc32c::crc32c(&bytes)));
    }
    Ok(parts.join("-"))
}

fn build(venv: &Path, info: &BaseInfo, recreate: bool) -> Result<()> {
    let root = paths::repo_root();
    let requirements = root.join("requirements.lock");
    let hash = inputs_hash()?;
    if recreate && venv.exists() {
        if !venv.join("pyvenv.cfg").is_file() && fs::read_dir(venv)?.next().is_some() {
            bail!("{} exists and is not a virtual environment; remove it or set HIFAR_VENV", venv.display());
        }
        fs::remove_dir_all(venv).with_context(|| format!("cannot remove {}", venv.display()))?;
    }
    fs::create_dir_all(venv).with_context(|| format!("cannot create {}", venv.display()))?;
    let log = venv.join(LOG);
    let status = Status::start("hifar setup");

    if !venv.join("pyvenv.cfg").is_file() {
        let base = base_python(info)?;
        status.step(&format!("creating virtual environment {} with {}", venv.display(), base.display()));
        let out = run_logged(Command::new(&base).arg("-m").arg("venv").arg(venv), &log)?;
        if !out.success {
            let hint = if out.tail.contains("ensurepip") || out.tail.contains("No module named venv") {
                format!(" (the venv module is missing: on Debian/Ubuntu `apt install python{}-venv`)", info.major_minor)
            } else {
                String::new()
            };
            bail!("`{} -m venv` failed{hint}: {}; see {}", base.display(), out.tail, log.display());
        }
    }
    let python = venv.join("bin").join("python");
    status.step(&format!("installing pinned packages from requirements.lock (log: {})", log.display()));
    let out = run_logged(
        Command::new(&python)
            .args(["-m", "pip", "install", "--disable-pip-version-check", "--no-input", "-r"])
            .arg(&requirements),
        &log,
    )?;
    if !out.success {
        bail!("pip install -r {} failed: {}; see {}", requirements.display(), out.tail, log.display());
    }
    status.step("installing jax_env (editable)");
    let out = run_logged(
        Command::new(&python)
            .args(["-m", "pip", "install", "--disable-pip-version-check", "--no-input", "--no-deps", "-e"])
            .arg(&root),
        &log,
    )?;
    if !out.success {
        bail!("pip install -e {} failed: {}; see {}", root.display(), out.tail, log.display());
    }
    let stamp = Stamp { inputs_crc32c: hash, python: info.version.clone() };
    crate::atomic::write_file_atomic(&venv.join(STAMP), serde_json::to_string_pretty(&stamp)?.as_bytes())
        .with_context(|| format!("cannot write {}", venv.join(STAMP).display()))?;
    status.finish(&format!("Python environment ready: {}", venv.display()));
    Ok(())
}

/// The base interpreter to create the venv with: `HIFAR_PYTHON`, else the embedded
/// installation's `bin/pythonX.Y`, else `pythonX.Y` or `python3` on PATH, whichever reports
/// the embedded minor version.
fn base_python(info: &BaseInfo) -> Result<PathBuf> {
    let versioned = format!("python{}", info.major_minor);
    let mut candidates: Vec<PathBuf> = Vec::new();
    if let Some(explicit) = std::env::var_os("HIFAR_PYTHON").filter(|v| !v.is_empty()) {
        candidates.push(PathBuf::from(explicit));
    }
    candidates.push(info.base_prefix.join("bin").join(&versioned));
    candidates.push(PathBuf::from(&versioned));
    candidates.push(PathBuf::from("python3"));
    for candidate in &candidates {
        let output = Command::new(candidate)
            .args(["-c", "import sys; print('%d.%d' % sys.version_info[:2])"])
            .stderr(Stdio::null())
            .output();
        if let Ok(output) = output {
            if output.status.success() && String::from_utf8_lossy(&output.stdout).trim() == info.major_minor {
                return Ok(candidate.clone());
            }
        }
    }
    bail!(
        "no Python {} interpreter found (hifar embeds Python {} from {}); install python{} or set HIFAR_PYTHON",
        info.major_minor,
        info.version,
        info.base_prefix.display(),
        info.major_minor
    )
}

struct Logged {
    success: bool,
    /// Last non-empty line of the output, for a one-line error.
    tail: String,
}

/// Runs a command with stdout and stderr appended to `log`.
fn run_logged(command: &mut Command, log: &Path) -> Result<Logged> {
    use std::io::Write;
    let mut file = fs::OpenOptions::new().create(true).append(true).open(log)?;
    writeln!(file, "\n$ {command:?}")?;
    let start = file.metadata()?.len();
    let output = command
        .stdin(Stdio::null())
        .stdout(file.try_clone()?)
        .stderr(file.try_clone()?)
        .status()
        .with_context(|| format!("cannot run {:?}", command.get_program()))?;
    let text = fs::read(log)?;
    let new = String::from_utf8_lossy(&text[start.min(text.len() as u64) as usize..]).into_owned();
    let tail = new.lines().rev().find(|l| !l.trim().is_empty()).unwrap_or("").trim().to_owned();
    Ok(Logged { success: output.success(), tail })
}
