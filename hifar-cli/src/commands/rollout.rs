//! `hifar rollout`: one episode of a policy recorded as an MCAP file for Foxglove, optionally
//! an MP4 video and a PNG filmstrip.
//!
//! Every argument is checked into a [`Plan`] before Python starts (names against the fixed
//! lists, numbers against their ranges, output files against `--force`), so a typo costs no
//! JAX start-up. `facade.rollout` simulates the episode under the nominal evaluation conditions
//! and renders the pictures; this side writes the MCAP (`crate::recording`).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use serde_json::Value;

use crate::cli::RolloutArgs;
use crate::commands::target::{self, PolicyTarget};
use crate::commands::facade::{default_backend, python_failure, Request, RolloutRequest};
use crate::commands::setup;
use crate::ui::Status;
use crate::recording::{self, Recording};
use crate::names::names;
use crate::{bad_input, paths};

/// A checked `hifar rollout` invocation.
#[derive(Debug)]
struct Plan {
    target: PolicyTarget,
    /// The stage table to rebuild the environment from (None: the checkpoint's own).
    stage: Option<Value>,
    stage_name: String,
    scenario: String,
    terrain: String,
    push_force: Option<f64>,
    push_direction: Option<String>,
    seed: u64,
    duration: Option<f64>,
    out: PathBuf,
    video: Option<PathBuf>,
    filmstrip: Option<PathBuf>,
}

fn one_of(what: &str, value: &str, valid: &[&str]) -> Result<()> {
    if valid.contains(&value) {
        Ok(())
    } else {
        Err(bad_input!("unknown {what} {value:?}; valid: {}", valid.join(", ")))
    }
}

/// An output file: absolute, its directory existing, not a directory itself, and new unless
/// `force`.
fn output(flag: &str, path: &Path, force: bool) -> Result<PathBuf> {
    let shown = path.display();
    let path = paths::absolute(path.to_path_buf());
    let parent = path.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    if path.file_name().is_none() {
        return Err(bad_input!("{flag} {shown}: not a file name"));
    }
    if !parent.is_dir() {
        return Err(bad_input!("{flag} {shown}: directory {} does not exist", parent.display()));
    }
    if path.is_dir() {
        return Err(bad_input!("{flag} {shown} is a directory"));
    }
    if path.exists() && !force {
        return Err(bad_input!("{flag} {shown} already exists (pass --force to replace it)"));
    }
    Ok(path)
}

fn number(stage: &Value, table: &str, key: &str) -> Option<f64> {
    stage.get(table)?.get(key)?.as_f64()
}

impl Plan {
    fn new(args: &RolloutArgs) -> Result<Plan> {
        one_of("scenario", &args.scenario, &names().scenarios)?;
        one_of("terrain", &args.terrain, &names().terrains)?;
        if let Some(direction) = &args.push_direction {
            one_of("push direction", direction, &names().push_directions)?;
        }
        if let Some(force) = args.push_force {
            if !(force.is_finite() && force >= 0.0) {
                return Err(bad_input!("--push-force {force}: must be a number of newtons >= 0"));
            }
        }
        if let Some(duration) = args.duration {
            if !(duration.is_finite() && duration > 0.0) {
                return Err(bad_input!("--duration {duration}: must be a number of seconds > 0"));
            }
        }
        let out = output("--out", &args.out, args.force)?;
        let video = args.video.as_deref().map(|p| output("--video", p, args.force)).transpose()?;
        let filmstrip = args.filmstrip.as_deref().map(|p| output("--filmstrip", p, args.force)).transpose()?;
        let mut seen = vec![&out];
        for path in video.iter().chain(filmstrip.iter()) {
            if seen.contains(&path) {
                return Err(bad_input!("{} is given as two outputs; --out, --video and --filmstrip must differ", path.display()));
            }
            seen.push(path);
        }

        let target = target::resolve(&args.target)?;
        // The stage the episode runs in: the run's, else the checkpoint's own copy (written by
        // the learner and by expand-checkpoint); the duration is checked against it here.
        let Some(known) = target.known_stage() else {
            return Err(bad_input!(
                "{}: checkpoint.json has no stage_config; pass the run directory instead (its curriculum names the stage)",
                target.checkpoint.display()
            ));
        };
        if let Some(duration) = args.duration {
            if let Some(ctrl_dt) = number(known, "sim", "ctrl_dt") {
                if duration < 2.0 * ctrl_dt - 1e-9 {
                    return Err(bad_input!(
                        "--duration {duration}: shorter than two control steps of stage {} (ctrl_dt {ctrl_dt} s)",
                        target.meta.stage
                    ));
                }
            }
            if let Some(settle) = number(known, "scenario_params", "settle_s") {
                if duration <= settle {
                    return Err(bad_input!(
                        "--duration {duration}: must be longer than stage {}'s settle_s ({settle} s, while a dropped robot settles)",
                        target.meta.stage
                    ));
                }
            }
        }
        Ok(Plan {
            stage: target.stage.clone(),
            stage_name: target.meta.stage.clone(),
            target,
            scenario: args.scenario.clone(),
            terrain: args.terrain.clone(),
            push_force: args.push_force,
            push_direction: args.push_direction.clone(),
            seed: args.seed,
            duration: args.duration,
            out,
            video,
            filmstrip,
        })
    }

    fn request(&self, backend: &str) -> RolloutRequest {
        RolloutRequest {
            checkpoint: self.target.checkpoint.clone(),
            stage: self.stage.clone(),
            scenario: self.scenario.clone(),
            terrain: self.terrain.clone(),
            push_force: self.push_force,
            push_direction: self.push_direction.clone(),
            seed: self.seed,
            backend: backend.to_owned(),
            duration_s: self.duration,
            video: self.video.clone(),
            filmstrip: self.filmstrip.clone(),
        }
    }
}

/// What is recorded; `direction` is the push's (None before Python has chosen its default).
fn describe(plan: &Plan, backend: &str, direction: Option<&str>) -> String {
    let mut text = format!("{} on {} terrain, {backend} backend", plan.scenario, plan.terrain);
    if let Some(force) = plan.push_force.filter(|f| *f > 0.0) {
        match direction {
            Some(direction) => text.push_str(&format!(", {force} N {direction} push")),
            None => text.push_str(&format!(", {force} N push")),
        }
    }
    text
}

fn shown(path: &Path) -> String {
    std::env::current_dir()
        .ok()
        .and_then(|cwd| path.strip_prefix(cwd).ok().map(Path::to_path_buf))
        .unwrap_or_else(|| path.to_path_buf())
        .display()
        .to_string()
}

pub fn run(args: &RolloutArgs) -> Result<()> {
    let plan = Plan::new(args)?;
    let facade = setup::ensure_python()?;
    let backend = match &args.backend {
        Some(backend) => backend.clone(),
        None => default_backend(&facade, &paths::command_log())?,
    };
    let status = Status::start("hifar rollout");
    status.step(&format!("recording {} (stage {})", describe(&plan, &backend, plan.push_direction.as_deref()), plan.stage_name));
    let (result, arrays) = facade
        .call_with_arrays(RolloutRequest::FUNCTION, &[plan.request(&backend).to_json()])
        .map_err(|err| python_failure("facade.rollout failed", err, &paths::command_log()))?;
    let rec = Recording::from_result(result, arrays).context("facade.rollout returned an unexpected result")?;
    let what = describe(&plan, &backend, Some(&rec.push_direction));

    let mut metadata = BTreeMap::new();
    let mut put = |key: &str, value: String| {
        metadata.insert(key.to_owned(), value);
    };
    put("hifar_version", env!("CARGO_PKG_VERSION").to_owned());
    put("checkpoint", plan.target.checkpoint.display().to_string());
    put("stage", plan.stage_name.clone());
    put("scenario", plan.scenario.clone());
    put("terrain", plan.terrain.clone());
    put("backend", backend.clone());
    put("seed", plan.seed.to_string());
    put("push_force_n", plan.push_force.unwrap_or(0.0).to_string());
    if let Some(direction) = &plan.push_direction {
        put("push_direction", direction.clone());
    }
    put("dt_s", rec.dt.to_string());
    put("success", rec.success.to_string());
    put("recovery_time_s", rec.recovery_time.map(|t| t.to_string()).unwrap_or_else(|| "none".into()));
    let written = recording::write_mcap(&plan.out, &rec, &metadata)?;

    let mut files = vec![plan.out.clone()];
    files.extend(rec.video.iter().cloned());
    files.extend(rec.filmstrip.iter().cloned());
    let outcome = match (rec.success, rec.recovery_time) {
        (true, Some(t)) => format!("stood up, recovery time {t:.2} s"),
        (true, None) => "stood up".to_owned(),
        (false, _) => "did not stand up".to_owned(),
    };
    let messages: u64 = written.messages.values().sum();
    status.finish(&format!(
        "{} steps ({:.2} s) of {what}: {outcome}; wrote {} ({messages} messages on {} channels){}",
        rec.steps(),
        rec.duration_s(),
        shown(&plan.out),
        written.messages.len(),
        files[1..].iter().map(|f| format!(", {}", shown(f))).collect::<String>()
    ));
    for file in &files {
        println!("{}", file.display());
    }
    Ok(())
}
