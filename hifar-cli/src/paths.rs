//! Where hifar finds its repository, its Python environment and its caches.

use std::path::PathBuf;

/// The repository root (holds `requirements.lock`, `pyproject.toml`, `jax_env/`, `curricula/`):
/// `HIFAR_HOME` if set, else the checkout this binary was built from.
pub fn repo_root() -> PathBuf {
    match std::env::var_os("HIFAR_HOME") {
        Some(home) if !home.is_empty() => PathBuf::from(home),
        _ => {
            let manifest_dir = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
            manifest_dir.parent().map(PathBuf::from).unwrap_or(manifest_dir)
        }
    }
}

/// The Python virtual environment: `HIFAR_VENV` if set, else `<repo>/.venv`.
pub fn venv_dir() -> PathBuf {
    match std::env::var_os("HIFAR_VENV") {
        Some(venv) if !venv.is_empty() => absolute(PathBuf::from(venv)),
        _ => repo_root().join(".venv"),
    }
}

/// hifar's cache directory: `$XDG_CACHE_HOME/hifar`, else `~/.cache/hifar`.
pub fn cache_dir() -> PathBuf {
    if let Some(xdg) = std::env::var_os("XDG_CACHE_HOME").filter(|v| !v.is_empty()) {
        return PathBuf::from(xdg).join("hifar");
    }
    if let Some(home) = std::env::var_os("HOME").filter(|v| !v.is_empty()) {
        return PathBuf::from(home).join(".cache").join("hifar");
    }
    std::env::temp_dir().join("hifar-cache")
}

/// JAX's persistent compilation cache (used unless `JAX_COMPILATION_CACHE_DIR` is set).
pub fn jax_cache_dir() -> PathBuf {
    cache_dir().join("jax")
}

/// Log for Python tracebacks of commands that have no run directory (check, act, doctor).
pub fn command_log() -> PathBuf {
    cache_dir().join("hifar.log")
}

/// Makes a path absolute against the current directory (without resolving symlinks).
pub fn absolute(path: PathBuf) -> PathBuf {
    if path.is_absolute() {
        return path;
    }
    std::env::current_dir().map(|cwd| cwd.join(&path)).unwrap_or(path)
}
