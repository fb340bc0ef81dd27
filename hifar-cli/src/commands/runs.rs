//! `hifar runs` and `hifar runs show RUN`: read-only views of run directories.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use serde_json::Value;

use crate::bad_input;
use crate::cli::{RunsArgs, RunsCommand};
use crate::metrics::{monitor_mean_stand_rate, read_jsonl};
use crate::run_dir::{Manifest, METRICS};
use crate::ui::group_digits;

pub fn run(args: &RunsArgs) -> Result<()> {
    match &args.command {
        None => list(&args.root),
        Some(RunsCommand::Show { run }) => show(&resolve(&args.root, run)?),
    }
}

/// Per-stage figures from `metrics.jsonl`: newest env steps, best stand rate of the training
/// episodes (PPO phase), and best mean stand rate of the deterministic monitor (when the
/// curriculum runs one).
#[derive(Debug, Default, Clone, Copy)]
struct StageMetrics {
    env_steps: u64,
    best_stand_rate: Option<f64>,
    best_det_stand_rate: Option<f64>,
    iterations: u64,
}

fn max_option(best: Option<f64>, value: f64) -> Option<f64> {
    Some(best.map_or(value, |best| best.max(value)))
}

fn stage_metrics(run: &Path) -> Result<BTreeMap<String, StageMetrics>> {
    let mut out: BTreeMap<String, StageMetrics> = BTreeMap::new();
    for record in read_jsonl(&run.join(METRICS))? {
        let Some(stage) = record.get("stage").and_then(Value::as_str) else { continue };
        let entry = out.entry(stage.to_owned()).or_default();
        entry.iterations += 1;
        if let Some(steps) = record.get("env_steps").and_then(Value::as_u64) {
            entry.env_steps = entry.env_steps.max(steps);
        }
        let is_ppo = record.get("phase").and_then(Value::as_str).is_none_or(|p| p == "ppo");
        if let (true, Some(rate)) = (is_ppo, record.get("stand_rate").and_then(Value::as_f64)) {
            entry.best_stand_rate = max_option(entry.best_stand_rate, rate);
        }
        // The monitor judges the deterministic policy, whichever phase trains it.
        if let Some(rate) = monitor_mean_stand_rate(&record) {
            entry.best_det_stand_rate = max_option(entry.best_det_stand_rate, rate);
        }
    }
    Ok(out)
}

fn list(root: &Path) -> Result<()> {
    let entries = match std::fs::read_dir(root) {
        Ok(entries) => entries,
        Err(err) if err.kind() == std::io::ErrorKind::NotFound => {
            println!("no runs in {} (it does not exist)", root.display());
            return Ok(());
        }
        Err(err) => return Err(err).with_context(|| format!("cannot read {}", root.display())),
    };
    let mut rows = Vec::new();
    let mut dirs: Vec<PathBuf> = entries.filter_map(|e| e.ok().map(|e| e.path())).filter(|p| p.is_dir()).collect();
    dirs.sort();
    for dir in dirs {
        let name = dir.file_name().unwrap_or_default().to_string_lossy().into_owned();
        let Ok(manifest) = Manifest::read(&dir) else { continue };
        let metrics = stage_metrics(&dir).unwrap_or_default();
        let current = manifest
            .current_stage()
            .map(|i| manifest.stages[i].name.clone())
            .unwrap_or_else(|| "-".into());
        let env_steps: u64 = manifest
            .stages
            .iter()
            .map(|s| s.env_steps.or_else(|| metrics.get(&s.name).map(|m| m.env_steps)).unwrap_or(0))
            .sum();
        let best = metrics.values().filter_map(|m| m.best_stand_rate).fold(None, max_option);
        let best_det = metrics.values().filter_map(|m| m.best_det_stand_rate).fold(None, max_option);
        rows.push([
            name,
            manifest.status.to_string(),
            current,
            group_digits(env_steps),
            rate(best),
            rate(best_det),
            short_time(&manifest.started_at),
        ]);
    }
    if rows.is_empty() {
        println!("no runs in {}", root.display());
        return Ok(());
    }
    print_table(&["RUN", "STATUS", "STAGE", "ENV STEPS", "BEST STAND", "BEST DET", "STARTED"], &rows);
    Ok(())
}

fn resolve(root: &Path, run: &Path) -> Result<PathBuf> {
    if run.join(crate::run_dir::MANIFEST).is_file() {
        return Ok(run.to_path_buf());
    }
    let under_root = root.join(run);
    if under_root.join(crate::run_dir::MANIFEST).is_file() {
        return Ok(under_root);
    }
    Err(bad_input!(
        "no run {} (neither {} nor {} holds a manifest.json); `hifar runs` lists the runs",
        run.display(),
        run.display(),
        under_root.display()
    ))
}

fn show(run: &Path) -> Result<()> {
    let manifest = Manifest::read(run)?;
    let metrics = stage_metrics(run)?;
    println!("run           {}", run.display());
    println!("name          {}", manifest.name);
    println!("status        {}", manifest.status);
    if let Some(message) = &manifest.message {
        println!("message       {message}");
    }
    println!("curriculum    {} (copy: {})", manifest.curriculum.source, run.join(&manifest.curriculum.copy).display());
    println!("seed          {}", manifest.seed);
    println!("backend       {} ({})", manifest.backend, manifest.backend_reason);
    if let Some(n) = manifest.num_envs {
        println!("num_envs      {n} (override)");
    }
    println!("started       {}", manifest.started_at);
    println!("ended         {}", manifest.ended_at.as_deref().unwrap_or("-"));
    println!("sessions      {}", manifest.sessions.len());
    println!("host          {}", manifest.host);
    println!("git           {}", manifest.git_commit.as_deref().unwrap_or("-"));
    if let Value::Object(versions) = &manifest.versions {
        let line: Vec<String> = versions.iter().map(|(k, v)| format!("{k} {}", v.as_str().unwrap_or(&v.to_string()))).collect();
        println!("versions      {}", line.join(", "));
    }
    for stage in &manifest.stages {
        if let Some(source) = &stage.reused_from {
            println!("reused        stage {} from {source}", stage.name);
        }
    }
    println!();
    let rows: Vec<[String; 7]> = manifest
        .stages
        .iter()
        .map(|stage| {
            let m = metrics.get(&stage.name).copied().unwrap_or_default();
            let best = stage.best_stand_rate.or(m.best_stand_rate);
            [
                stage.name.clone(),
                stage.status.to_string(),
                stage.seed.to_string(),
                group_digits(stage.env_steps.unwrap_or(m.env_steps)),
                rate(best),
                rate(m.best_det_stand_rate),
                stage.final_checkpoint.clone().unwrap_or_else(|| "-".into()),
            ]
        })
        .collect();
    print_table(&["STAGE", "STATUS", "SEED", "ENV STEPS", "BEST STAND", "BEST DET", "FINAL CHECKPOINT"], &rows);
    Ok(())
}

fn print_table<const N: usize>(header: &[&str; N], rows: &[[String; N]]) {
    let mut widths = header.map(str::len);
    for row in rows {
        for (w, cell) in widths.iter_mut().zip(row) {
            *w = (*w).max(cell.chars().count());
        }
    }
    let line = |cells: Vec<&str>| {
        let parts: Vec<String> = cells.iter().zip(widths).map(|(c, w)| format!("{c:<w$}")).collect();
        println!("{}", parts.join("  ").trim_end());
    };
    line(header.to_vec());
    for row in rows {
        line(row.iter().map(String::as_str).collect());
    }
}

/// A stand rate with three decimals, "-" when unknown.
fn rate(rate: Option<f64>) -> String {
    rate.map(|r| format!("{r:.3}")).unwrap_or_else(|| "-".into())
}

/// "2025-01-02T03:04:05.123Z" -> "2025-01-02 03:04:05".
fn short_time(rfc3339: &str) -> String {
    rfc3339.get(..19).map(|t| t.replace('T', " ")).unwrap_or_else(|| rfc3339.to_owned())
}
