//! Crash-safe writes: a reader sees the old content or the new one, never a torn file.
//!
//! Files are written to a temporary sibling, fsynced, renamed over the target, and the parent
//! directory is fsynced so that the rename itself survives a power cut. Directories (a
//! checkpoint) are filled under a temporary sibling name and renamed into place the same way.

use std::fs::{self, File, OpenOptions};
use std::io::{self, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

static COUNTER: AtomicU64 = AtomicU64::new(0);

/// A sibling path of `path` that no other writer (thread or process) uses.
fn temp_sibling(path: &Path, tag: &str) -> io::Result<PathBuf> {
    let name = path
        .file_name()
        .ok_or_else(|| io::Error::new(io::ErrorKind::InvalidInput, format!("{} has no file name", path.display())))?;
    let unique = COUNTER.fetch_add(1, Ordering::Relaxed);
    let temp = format!(".{}.{tag}-{}-{unique}", name.to_string_lossy(), std::process::id());
    Ok(path.with_file_name(temp))
}

fn parent_of(path: &Path) -> &Path {
    match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    }
}

/// fsync a directory (makes renames and creations inside it durable).
pub fn sync_dir(dir: &Path) -> io::Result<()> {
    File::open(dir)?.sync_all()
}

/// Writes `bytes` to `path` atomically: temp file in the same directory, write, fsync,
/// rename over `path`, fsync the directory.
pub fn write_file_atomic(path: &Path, bytes: &[u8]) -> io::Result<()> {
    let temp = temp_sibling(path, "tmp")?;
    let result = (|| {
        let mut file = OpenOptions::new().write(true).create_new(true).open(&temp)?;
        file.write_all(bytes)?;
        file.sync_all()?;
        drop(file);
        fs::rename(&temp, path)?;
        sync_dir(parent_of(path))
    })();
    if result.is_err() {
        let _ = fs::remove_file(&temp);
    }
    result
}

/// What [`write_dir_atomic`] does when the final directory already exists.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum IfExists {
    /// Fail with `ErrorKind::AlreadyExists` before calling `fill`.
    Refuse,
    /// Build the new directory, then swap it in and delete the old one.
    Replace,
}

/// Builds a directory atomically: `fill` writes into a temporary sibling directory, every
/// file in it is fsynced, and the directory is renamed to `final_dir`. On any error the
/// temporary directory is removed and `final_dir` is left as it was.
pub fn write_dir_atomic<T, E>(
    final_dir: &Path,
    if_exists: IfExists,
    fill: impl FnOnce(&Path) -> Result<T, E>,
) -> Result<T, E>
where
    E: From<io::Error>,
{
    if if_exists == IfExists::Refuse && final_dir.exists() {
        return Err(io::Error::new(io::ErrorKind::AlreadyExists, format!("{} already exists", final_dir.display())).into());
    }
    let parent = parent_of(final_dir);
    fs::create_dir_all(parent)?;
    let temp = temp_sibling(final_dir, "partial")?;
    fs::create_dir(&temp)?;
    let result = fill(&temp).and_then(|value| {
        sync_tree(&temp)?;
        if final_dir.exists() {
            if if_exists == IfExists::Refuse {
                return Err(io::Error::new(io::ErrorKind::AlreadyExists, format!("{} already exists", final_dir.display())).into());
            }
            let old = temp_sibling(final_dir, "old")?;
            fs::rename(final_dir, &old)?;
            fs::rename(&temp, final_dir)?;
            sync_dir(parent)?;
            fs::remove_dir_all(&old)?;
        } else {
            fs::rename(&temp, final_dir)?;
            sync_dir(parent)?;
        }
        Ok(value)
    });
    if result.is_err() {
        let _ = fs::remove_dir_all(&temp);
    }
    result
}

/// fsync every file and directory under `dir` (directories after their contents).
fn sync_tree(dir: &Path) -> io::Result<()> {
    for entry in fs::read_dir(dir)? {
        let entry = entry?;
        let kind = entry.file_type()?;
        if kind.is_dir() {
            sync_tree(&entry.path())?;
        } else if kind.is_file() {
            File::open(entry.path())?.sync_all()?;
        }
    }
    sync_dir(dir)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn leftovers(dir: &Path) -> Vec<String> {
        fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.starts_with('.'))
            .collect()
    }

    #[test]
    fn file_is_replaced_whole() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("LATEST");
        write_file_atomic(&path, b"one").unwrap();
        write_file_atomic(&path, b"two, longer").unwrap();
        assert_eq!(fs::read(&path).unwrap(), b"two, longer");
        assert!(leftovers(dir.path()).is_empty());
    }

    #[test]
    fn file_in_missing_dir_fails_cleanly() {
        let dir = tempfile::tempdir().unwrap();
        let err = write_file_atomic(&dir.path().join("nope/file"), b"x").unwrap_err();
        assert_eq!(err.kind(), io::ErrorKind::NotFound);
    }

    #[test]
    fn dir_is_renamed_into_place() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("ckpt");
        let n = write_dir_atomic(&out, IfExists::Refuse, |tmp| -> io::Result<usize> {
            assert!(!out.exists(), "the final directory appears only when complete");
            fs::write(tmp.join("a"), b"1")?;
            fs::create_dir(tmp.join("sub"))?;
            fs::write(tmp.join("sub/b"), b"2")?;
            Ok(7)
        })
        .unwrap();
        assert_eq!(n, 7);
        assert_eq!(fs::read(out.join("sub/b")).unwrap(), b"2");
        assert!(leftovers(dir.path()).is_empty());
    }

    #[test]
    fn dir_refuses_existing_and_cleans_up_on_error() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("ckpt");
        fs::create_dir(&out).unwrap();
        fs::write(out.join("keep"), b"old").unwrap();
        let err = write_dir_atomic(&out, IfExists::Refuse, |_| -> io::Result<()> { panic!("not called") }).unwrap_err();
        assert_eq!(err.kind(), io::ErrorKind::AlreadyExists);

        let err = write_dir_atomic(&dir.path().join("other"), IfExists::Refuse, |tmp| -> io::Result<()> {
            fs::write(tmp.join("half"), b"x")?;
            Err(io::Error::other("boom"))
        })
        .unwrap_err();
        assert_eq!(err.to_string(), "boom");
        assert!(!dir.path().join("other").exists());
        assert!(leftovers(dir.path()).is_empty());

        write_dir_atomic(&out, IfExists::Replace, |tmp| -> io::Result<()> { fs::write(tmp.join("new"), b"n") }).unwrap();
        assert!(out.join("new").exists() && !out.join("keep").exists());
        assert!(leftovers(dir.path()).is_empty());
    }
}
