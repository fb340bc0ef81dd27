//! Helpers shared by the integration tests.
#![allow(dead_code)]

use std::path::{Path, PathBuf};

/// The `hifar` binary under test.
pub const HIFAR: &str = env!("CARGO_BIN_EXE_hifar");

/// The repository root (holds `tests/data`, `curricula`, `requirements.lock`).
pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().expect("crate lives in the repository").to_path_buf()
}

/// A file under `tests/data`.
pub fn data(name: &str) -> PathBuf {
    repo_root().join("tests").join("data").join(name)
}

/// A fresh temporary directory for one test.
pub fn tempdir() -> tempfile::TempDir {
    tempfile::Builder::new().prefix("hifar-test-").tempdir().expect("temp dir")
}

/// `hifar` run in `dir` with the test environment: the repository as HIFAR_HOME, a private
/// cache directory (command logs), JAX on CPU with the suite's compilation cache.
pub fn hifar(dir: &Path) -> assert_cmd::Command {
    let mut cmd = assert_cmd::Command::new(HIFAR);
    cmd.current_dir(dir);
    for (key, value) in test_env(dir) {
        cmd.env(key, value);
    }
    cmd
}

/// The same environment for a `std::process::Command` (tests that send signals).
pub fn hifar_std(dir: &Path) -> std::process::Command {
    let mut cmd = std::process::Command::new(HIFAR);
    cmd.current_dir(dir);
    for (key, value) in test_env(dir) {
        cmd.env(key, value);
    }
    cmd
}

fn test_env(dir: &Path) -> Vec<(String, PathBuf)> {
    let root = repo_root();
    let mut env = vec![
        ("HIFAR_HOME".to_string(), root.clone()),
        ("XDG_CACHE_HOME".to_string(), dir.join(".cache")),
        ("HIFAR_VENV".to_string(), venv()),
    ];
    if std::env::var_os("JAX_COMPILATION_CACHE_DIR").is_none() {
        env.push(("JAX_COMPILATION_CACHE_DIR".into(), root.join("tests").join(".cache").join("jax")));
    }
    if std::env::var_os("JAX_PLATFORMS").is_none() {
        env.push(("JAX_PLATFORMS".into(), PathBuf::from("cpu")));
    }
    env
}

/// The Python environment the tests use: HIFAR_VENV, else `<repo>/.venv` (made by
/// `bash tests/run.sh`, which runs `hifar setup` before `cargo test`).
pub fn venv() -> PathBuf {
    match std::env::var_os("HIFAR_VENV") {
        Some(venv) if !venv.is_empty() => PathBuf::from(venv),
        _ => repo_root().join(".venv"),
    }
}

/// Panics with instructions when the Python environment is missing (tests that need Python
/// must not trigger an implicit `hifar setup` from many threads at once).
pub fn require_venv() -> PathBuf {
    let venv = venv();
    assert!(
        venv.join("pyvenv.cfg").is_file(),
        "no Python environment at {}: run `bash tests/run.sh` (or `hifar setup`) before `cargo test`",
        venv.display()
    );
    venv
}

/// Text of a command's stderr.
pub fn stderr(output: &std::process::Output) -> String {
    String::from_utf8_lossy(&output.stderr).into_owned()
}

pub fn stdout(output: &std::process::Output) -> String {
    String::from_utf8_lossy(&output.stdout).into_owned()
}

pub fn read_json(path: &Path) -> serde_json::Value {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("cannot read {}: {e}", path.display()));
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{} is not JSON: {e}", path.display()))
}
