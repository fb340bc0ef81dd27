//! The policy a command acts on: a checkpoint directory, or a run directory standing for the
//! final checkpoint of its last completed stage. Either way the checkpoint must be deployable
//! ([`checkpoint::check_deployable`]: no RMA adaptation module that never trained), unless the
//! command acts without the adaptation module (`hifar eval --actor privileged`).

use std::path::{Path, PathBuf};

use anyhow::Result;
use serde_json::Value;

use crate::checkpoint::{self, CheckpointMeta};
use crate::run_dir::{Manifest, MANIFEST};
use crate::{bad_input, paths};

/// A resolved `CKPT|RUN` argument.
#[derive(Debug, Clone)]
pub struct PolicyTarget {
    /// The checkpoint directory (absolute).
    pub checkpoint: PathBuf,
    pub meta: CheckpointMeta,
    /// The run directory when the argument named one (absolute).
    pub run: Option<PathBuf>,
    /// For a run, the checkpoint's stage table from the run's resolved curriculum; for a bare
    /// checkpoint None (Python then reads the checkpoint's own `stage_config`).
    pub stage: Option<Value>,
    /// For a run whose later stage has not completed: why this is not the run's final policy.
    pub notice: Option<String>,
}

impl PolicyTarget {
    /// The stage table the environment will be rebuilt from, if any is known.
    pub fn known_stage(&self) -> Option<&Value> {
        self.stage.as_ref().or_else(|| self.meta.extra.get(checkpoint::STAGE_CONFIG_KEY))
    }
}

/// A deployable policy target.
pub fn resolve(target: &Path) -> Result<PolicyTarget> {
    let resolved = find(target)?;
    checkpoint::check_deployable(&resolved.checkpoint, &resolved.meta)?;
    Ok(announced(resolved))
}

/// A policy target, deployable or not (a checkpoint of a stage's PPO phase included).
pub fn resolve_any(target: &Path) -> Result<PolicyTarget> {
    Ok(announced(find(target)?))
}

/// The target, once accepted, with its notice (if any) on stderr: a refusal stays one line.
fn announced(target: PolicyTarget) -> PolicyTarget {
    if let Some(notice) = &target.notice {
        eprintln!("note: {notice}");
    }
    target
}

fn find(target: &Path) -> Result<PolicyTarget> {
    let shown = target.display();
    if target.join(MANIFEST).is_file() {
        let run = paths::absolute(target.to_path_buf());
        let manifest = Manifest::read(&run)?;
        let Some(relative) = last_final_checkpoint(&manifest) else {
            return Err(bad_input!("{shown}: the run has no finished stage yet (no final checkpoint in {MANIFEST})"));
        };
        let checkpoint = run.join(relative);
        let meta = checkpoint::read_meta(&checkpoint)?;
        let stage = Some(stage_table(&manifest, &run, &meta.stage)?);
        let notice = unfinished_after(&manifest, &meta.stage).map(|why| format!("{shown}: {why}"));
        return Ok(PolicyTarget { checkpoint, meta, run: Some(run), stage, notice });
    }
    if target.join("checkpoint.json").is_file() {
        let meta = checkpoint::read_meta(target)?;
        return Ok(PolicyTarget { checkpoint: paths::absolute(target.to_path_buf()), meta, run: None, stage: None, notice: None });
    }
    if !target.exists() {
        return Err(bad_input!("{shown}: no such checkpoint or run directory"));
    }
    Err(bad_input!("{shown}: neither a run directory ({MANIFEST}) nor a checkpoint directory (checkpoint.json)"))
}

/// The final checkpoint (relative to the run) of the last stage that completed (`completed`,
/// or `threshold_missed`: it used its budget). A stage that is running, interrupted or failed
/// has no final checkpoint of its own, whatever an older session left in the manifest.
fn last_final_checkpoint(manifest: &Manifest) -> Option<String> {
    manifest
        .stages
        .iter()
        .rev()
        .filter(|s| s.status.is_finished())
        .find_map(|s| s.final_checkpoint.clone())
}

/// Why a run's policy is not its last stage's, when a later stage has not completed: a run
/// that is still training (or was stopped) stands for an earlier stage's policy.
fn unfinished_after(manifest: &Manifest, picked: &str) -> Option<String> {
    let index = manifest.stages.iter().position(|s| s.name == picked)?;
    let later = manifest.stages[index + 1..]
        .iter()
        .find(|s| !s.status.is_finished())?;
    Some(format!(
        "stage {:?} is {}; this is stage {picked:?}'s final checkpoint, not the run's final policy",
        later.name, later.status
    ))
}

/// The stage table named `stage` in a run's resolved curriculum.
fn stage_table(manifest: &Manifest, run: &Path, stage: &str) -> Result<Value> {
    let stages = manifest.curriculum.resolved.get("stage").and_then(Value::as_array);
    let named = |s: &&Value| s.get("name").and_then(Value::as_str) == Some(stage);
    stages.into_iter().flatten().find(named).cloned().ok_or_else(|| {
        let names: Vec<&str> =
            stages.into_iter().flatten().filter_map(|s| s.get("name").and_then(Value::as_str)).collect();
        bad_input!(
            "{}: the checkpoint's stage {stage:?} is not in the run's curriculum (stages: {})",
            run.display(),
            names.join(", ")
        )
    })
}
