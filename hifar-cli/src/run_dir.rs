//! Run directories: layout, the exclusive lock, and the manifest.
//!
//! ```text
//! <run>/
//!   .lock                  held (flock) by the `hifar train` using the directory
//!   manifest.json          what ran, with which seeds and versions, and how far it got
//!   curriculum.toml        a copy of the curriculum file
//!   hifar.log              hifar's log, Python's stdout/stderr and tracebacks
//!   metrics.jsonl          one JSON object per training iteration
//!   tensorboard/<stage>/   TensorBoard event files
//!   stages/<stage>/init/   the previous stage's checkpoint expanded to this stage (if any)
//!   stages/<stage>/checkpoints/<env_steps:012>/ and checkpoints/LATEST
//! ```
//! Checkpoint paths in the manifest are relative to the run directory, so a run directory can
//! be moved or copied.

use std::fs::{self, File, OpenOptions};
use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};
use serde_json::Value;

use crate::bad_input;

pub const MANIFEST: &str = "manifest.json";
pub const CURRICULUM_COPY: &str = "curriculum.toml";
pub const LOG: &str = "hifar.log";
pub const METRICS: &str = "metrics.jsonl";
const LOCK: &str = ".lock";

/// Where things are in a run directory (no lock: reading another run's finished stages).
pub struct RunLayout {
    path: PathBuf,
}

/// A run directory held with its exclusive lock (released when dropped); its layout through
/// `Deref`.
pub struct RunDir {
    layout: RunLayout,
    _lock: File,
}

impl std::ops::Deref for RunDir {
    type Target = RunLayout;

    fn deref(&self) -> &RunLayout {
        &self.layout
    }
}

impl RunDir {
    /// Creates a fresh run directory. An existing one is refused unless `force`, which deletes
    /// it first (still refusing if another process holds its lock).
    pub fn create(path: &Path, force: bool) -> Result<RunDir> {
        if path.exists() {
            if !force {
                return Err(bad_input!(
                    "run directory {} already exists; pass --resume to continue it or --force to start over",
                    path.display()
                ));
            }
            if path.join(LOCK).exists() {
                let held = lock(path)?;
                if !path.join(MANIFEST).is_file() {
                    bail!("refusing to delete {}: it has no {MANIFEST}, so it is not a run directory", path.display());
                }
                fs::remove_dir_all(path).with_context(|| format!("cannot delete {}", path.display()))?;
                drop(held);
            } else if fs::read_dir(path)?.next().is_some() && !path.join(MANIFEST).is_file() {
                bail!("refusing to delete {}: it is not empty and not a run directory", path.display());
            } else {
                fs::remove_dir_all(path).with_context(|| format!("cannot delete {}", path.display()))?;
            }
        }
        if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
            fs::create_dir_all(parent).with_context(|| format!("cannot create {}", parent.display()))?;
        }
        match fs::create_dir(path) {
            Ok(()) => {}
            Err(err) if err.kind() == std::io::ErrorKind::AlreadyExists => {
                return Err(bad_input!("run directory {} already exists", path.display()));
            }
            Err(err) => return Err(err).with_context(|| format!("cannot create {}", path.display())),
        }
        let lock = lock(path)?;
        Ok(RunDir { layout: RunLayout::new(path), _lock: lock })
    }

    /// Opens an existing run directory (for `--resume`).
    pub fn open(path: &Path) -> Result<RunDir> {
        if !path.join(MANIFEST).is_file() {
            return Err(bad_input!(
                "{} is not a run directory (no {MANIFEST}); nothing to resume",
                path.display()
            ));
        }
        let lock = lock(path)?;
        Ok(RunDir { layout: RunLayout::new(path), _lock: lock })
    }

    pub fn write_manifest(&self, manifest: &Manifest) -> Result<()> {
        let mut text = serde_json::to_string_pretty(manifest)?;
        text.push('\n');
        let path = self.path.join(MANIFEST);
        crate::atomic::write_file_atomic(&path, text.as_bytes())
            .with_context(|| format!("cannot write {}", path.display()))
    }

    /// Appends a timestamped line to `hifar.log`.
    pub fn log(&self, line: &str) {
        if let Ok(mut file) = OpenOptions::new().create(true).append(true).open(self.log_path()) {
            let _ = writeln!(file, "[{}] {line}", now_rfc3339());
        }
    }
}

impl RunLayout {
    pub fn new(path: &Path) -> RunLayout {
        RunLayout { path: path.to_path_buf() }
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    pub fn log_path(&self) -> PathBuf {
        self.path.join(LOG)
    }

    pub fn metrics_path(&self) -> PathBuf {
        self.path.join(METRICS)
    }

    pub fn tensorboard_dir(&self, stage: &str) -> PathBuf {
        self.path.join("tensorboard").join(stage)
    }

    pub fn stage_dir(&self, stage: &str) -> PathBuf {
        self.path.join("stages").join(stage)
    }

    /// Path relative to the run directory (for the manifest).
    pub fn relative(&self, path: &Path) -> String {
        path.strip_prefix(&self.path).unwrap_or(path).to_string_lossy().into_owned()
    }

    pub fn read_manifest(&self) -> Result<Manifest> {
        Manifest::read(&self.path)
    }
}

fn lock(dir: &Path) -> Result<File> {
    let path = dir.join(LOCK);
    let file = OpenOptions::new()
        .create(true)
        .truncate(false)
        .write(true)
        .open(&path)
        .with_context(|| format!("cannot open lock file {}", path.display()))?;
    match file.try_lock() {
        Ok(()) => Ok(file),
        Err(std::fs::TryLockError::WouldBlock) => bail!(
            "run directory {} is in use by another hifar process (lock {} is held)",
            dir.display(),
            path.display()
        ),
        Err(std::fs::TryLockError::Error(err)) => {
            Err(err).with_context(|| format!("cannot lock {}", path.display()))
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Status {
    Pending,
    Running,
    Completed,
    Interrupted,
    Failed,
    ThresholdMissed,
}

impl Status {
    /// A stage in this state has trained to the end (its budget used, early or not) and has a
    /// final checkpoint; every other state means it still has to be trained.
    pub fn is_finished(self) -> bool {
        matches!(self, Status::Completed | Status::ThresholdMissed)
    }

    pub fn as_str(self) -> &'static str {
        match self {
            Status::Pending => "pending",
            Status::Running => "running",
            Status::Completed => "completed",
            Status::Interrupted => "interrupted",
            Status::Failed => "failed",
            Status::ThresholdMissed => "threshold_missed",
        }
    }
}

impl std::fmt::Display for Status {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// `manifest.json`: everything needed to understand, reproduce and resume a run.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Manifest {
    pub format_version: u32,
    pub name: String,
    pub status: Status,
    /// One line on why the run stopped (failure, missed threshold, interrupt).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub message: Option<String>,
    pub curriculum: CurriculumRecord,
    /// Experiment seed; every stage seed derives from it.
    pub seed: u64,
    pub backend: String,
    pub backend_reason: String,
    /// `--num-envs` override, if any.
    pub num_envs: Option<u32>,
    /// `hifar` and the Python packages (`facade.versions()`).
    pub versions: Value,
    pub git_commit: Option<String>,
    pub host: String,
    pub started_at: String,
    pub ended_at: Option<String>,
    /// One entry per `hifar train` invocation on this directory (the first, then resumes).
    pub sessions: Vec<Session>,
    pub stages: Vec<StageRecord>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CurriculumRecord {
    /// The file given on the command line.
    pub source: String,
    /// Its copy inside the run directory.
    pub copy: String,
    /// The resolved curriculum (defaults filled in, overrides applied).
    pub resolved: Value,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Session {
    pub started_at: String,
    pub ended_at: Option<String>,
    pub resumed: bool,
    pub outcome: Option<Status>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct StageRecord {
    pub name: String,
    pub seed: u64,
    pub status: Status,
    /// Stage whose final checkpoint initialises this one.
    pub init_from: Option<String>,
    pub init_checkpoint: Option<String>,
    pub final_checkpoint: Option<String>,
    pub env_steps: Option<u64>,
    pub best_stand_rate: Option<f64>,
    pub started_at: Option<String>,
    pub ended_at: Option<String>,
    /// The run this stage was copied from (`hifar train --reuse-stages-from`), if any.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reused_from: Option<String>,
}

impl Manifest {
    pub const FORMAT_VERSION: u32 = 1;

    pub fn read(run: &Path) -> Result<Manifest> {
        let path = run.join(MANIFEST);
        let text = fs::read_to_string(&path).with_context(|| format!("cannot read {}", path.display()))?;
        let manifest: Manifest =
            serde_json::from_str(&text).with_context(|| format!("{} is not a hifar manifest", path.display()))?;
        if manifest.format_version != Self::FORMAT_VERSION {
            bail!(
                "{} has format_version {}, this hifar reads {}",
                path.display(),
                manifest.format_version,
                Self::FORMAT_VERSION
            );
        }
        Ok(manifest)
    }

    /// Index of the stage that is (or would be) trained next; `None` when all are done.
    pub fn current_stage(&self) -> Option<usize> {
        self.stages.iter().position(|s| !s.status.is_finished())
    }
}

/// The seed of stage `index`: output `index + 1` of a SplitMix64 stream started at the
/// experiment seed, kept to 63 bits so that every consumer (JAX, NumPy) takes it as an int64.
pub fn stage_seed(experiment_seed: u64, index: usize) -> u64 {
    let mut state = experiment_seed;
    let mut out = 0;
    for _ in 0..=index {
        state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        out = z ^ (z >> 31);
    }
    out >> 1
}

pub fn now_rfc3339() -> String {
    time::OffsetDateTime::now_utc()
        .format(&time::format_description::well_known::Rfc3339)
        .unwrap_or_else(|_| "unknown".into())
}

/// `20250102T030405Z`: the default run-directory suffix.
pub fn compact_utc_now() -> String {
    let format = time::macros::format_description!("[year][month][day]T[hour][minute][second]Z");
    time::OffsetDateTime::now_utc().format(&format).unwrap_or_else(|_| "now".into())
}

pub fn unix_time() -> f64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs_f64())
        .unwrap_or(0.0)
}

pub fn host_name() -> String {
    fs::read_to_string("/proc/sys/kernel/hostname")
        .ok()
        .or_else(|| std::env::var("HOSTNAME").ok())
        .map(|h| h.trim().to_owned())
        .filter(|h| !h.is_empty())
        .unwrap_or_else(|| "unknown".into())
}

/// `git rev-parse HEAD` of the hifar checkout, with `-dirty` when it has local changes.
pub fn git_commit(repo: &Path) -> Option<String> {
    let run = |args: &[&str]| {
        std::process::Command::new("git")
            .arg("-C")
            .arg(repo)
            .args(args)
            .stderr(std::process::Stdio::null())
            .output()
            .ok()
            .filter(|out| out.status.success())
            .map(|out| String::from_utf8_lossy(&out.stdout).trim().to_owned())
    };
    let head = run(&["rev-parse", "HEAD"])?;
    let dirty = run(&["status", "--porcelain", "--untracked-files=no"]).is_some_and(|s| !s.is_empty());
    Some(if dirty { format!("{head}-dirty") } else { head })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stage_seeds_are_deterministic_distinct_and_int64() {
        let seeds: Vec<u64> = (0..4).map(|i| stage_seed(7, i)).collect();
        assert_eq!(seeds, (0..4).map(|i| stage_seed(7, i)).collect::<Vec<_>>());
        for (i, a) in seeds.iter().enumerate() {
            assert!(*a < (1 << 63));
            for b in &seeds[i + 1..] {
                assert_ne!(a, b);
            }
        }
        assert_ne!(stage_seed(7, 0), stage_seed(8, 0));
        // SplitMix64's first output for seed 0 is 0xe220a8397b1dcdaf.
        assert_eq!(stage_seed(0, 0), 0xe220_a839_7b1d_cdaf >> 1);
    }

    #[test]
    fn create_refuses_existing_and_lock_is_exclusive() {
        let tmp = tempfile::tempdir().unwrap();
        let path = tmp.path().join("run");
        let run = RunDir::create(&path, false).unwrap();
        let err = RunDir::create(&path, false).err().unwrap();
        assert!(err.to_string().contains("already exists"), "{err}");
        fs::write(path.join(MANIFEST), "{}").unwrap();
        let err = RunDir::open(&path).err().unwrap();
        assert!(err.to_string().contains("in use by another hifar process"), "{err}");
        let err = RunDir::create(&path, true).err().unwrap();
        assert!(err.to_string().contains("in use"), "{err}");
        drop(run);
        RunDir::open(&path).unwrap();
    }
}
