//! `hifar train`: validate, lay out the run directory, then train the stages in order.
//!
//! Everything that can be checked is checked before the disk is touched: the curriculum's
//! schema (Rust), its names (Python's `check_stage`), the overrides, and whether the run
//! directory may be used. Each stage is then trained by `facade.train_stage`, which calls back
//! after every iteration; the callback records metrics, draws progress, applies the stage's
//! advance threshold and relays SIGINT/SIGTERM as "interrupt" (Python checkpoints and returns).

use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context, Result};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use serde_json::{json, Map, Value};

use crate::checkpoint;
use crate::cli::TrainArgs;
use crate::commands::facade::{default_backend_and_reason, python_failure, Request, TrainRequest};
use crate::commands::{check, setup};
use crate::curriculum::{self, Curriculum};
use crate::error::{BadInput, Interrupted};
use crate::metrics::{self, EventWriter, MetricsLog};
use crate::names::AUTO_BACKEND;
use crate::python::Facade;
use crate::terminal::{Capture, Console};
use crate::run_dir::{
    self, host_name, now_rfc3339, stage_seed, unix_time, CurriculumRecord, Manifest, RunDir, RunLayout, Session,
    StageRecord, Status, CURRICULUM_COPY,
};
use crate::ui::group_digits;
use crate::{bad_input, paths};

/// What one stage will be trained with, resolved before anything is written.
struct StagePlan {
    index: usize,
    name: String,
    /// The stage table as JSON, overrides applied (what Python receives).
    json: Value,
    seed: u64,
    /// Index of the stage whose final checkpoint initialises this one.
    init_from: Option<usize>,
    budget: u64,
    threshold: Option<Threshold>,
}

#[derive(Debug, Clone, Copy)]
struct Threshold {
    min_stand_rate: f64,
    window: usize,
    on_miss_continue: bool,
}

struct Plan {
    curriculum_path: PathBuf,
    curriculum: Curriculum,
    seed: u64,
    backend: String,
    backend_reason: String,
    num_envs: Option<u32>,
    stages: Vec<StagePlan>,
}

pub fn run(args: &TrainArgs) -> Result<()> {
    // 1. The curriculum, Rust side (exit 2 with FILE:LINE:COL), before Python starts.
    let curriculum_path = paths::absolute(args.curriculum.clone());
    let mut curriculum = curriculum::load(&args.curriculum)?;

    // 2. Resume, or reuse another run's stages: that run's manifest supplies the settings the
    //    flags do not.
    let resume_manifest = if args.resume {
        let dir = args.run_dir.as_ref().expect("clap requires --run-dir with --resume");
        Some(read_run_manifest(dir, "nothing to resume")?)
    } else {
        None
    };
    let reuse_source = match &args.reuse_stages_from {
        Some(dir) => Some((paths::absolute(dir.clone()), read_run_manifest(dir, "no stages to reuse")?)),
        None => None,
    };
    let inherited = resume_manifest.as_ref().or(reuse_source.as_ref().map(|(_, m)| m));
    let seed = args.seed.or(inherited.map(|m| m.seed));
    let num_envs = args.num_envs.or(inherited.and_then(|m| m.num_envs));
    let backend_flag = args.backend.clone().or(inherited.map(|m| m.backend.clone()));
    curriculum
        .apply_overrides(seed, backend_flag.as_deref(), num_envs)
        .map_err(|err| anyhow::Error::new(BadInput(err.to_string())))?;

    // 3. Python: names and feature layouts, and the backend "auto" resolves to.
    let facade = setup::ensure_python()?;
    check::check_with_python(&facade, &curriculum, None)?;
    let (backend, backend_reason) = resolve_backend(&facade, &curriculum, args, inherited)?;
    let plan = make_plan(curriculum_path, curriculum, backend, backend_reason, num_envs)?;
    let reuse = match &reuse_source {
        Some((dir, source)) => Some(reusable_stages(dir, source, &plan)?),
        None => None,
    };

    // 4. The run directory.
    let run_path = paths::absolute(match &args.run_dir {
        Some(dir) => dir.clone(),
        None => PathBuf::from("runs").join(format!("{}-{}", plan.curriculum.name(), run_dir::compact_utc_now())),
    });
    let (run, mut manifest) = match resume_manifest {
        Some(previous) => {
            let run = RunDir::open(&run_path)?;
            let manifest = resume_manifest_checked(&run, previous, &plan)?;
            (run, manifest)
        }
        None => {
            let run = RunDir::create(&run_path, args.force)?;
            let manifest = new_manifest(&run, &plan, &facade)?;
            (run, manifest)
        }
    };
    if manifest.current_stage().is_none() {
        eprintln!("run {} has already finished every stage ({})", run.path().display(), manifest.status);
        return Ok(());
    }
    manifest.status = Status::Running;
    manifest.message = None;
    manifest.ended_at = None;
    manifest.sessions.push(Session {
        started_at: now_rfc3339(),
        ended_at: None,
        resumed: args.resume,
        outcome: None,
    });
    run.write_manifest(&manifest)?;
    run.log(&format!(
        "hifar train {} ({}; seed {}, backend {}: {})",
        plan.curriculum_path.display(),
        if args.resume { "resumed" } else { "new run" },
        plan.seed,
        plan.backend,
        plan.backend_reason
    ));
    if let Some(reuse) = &reuse {
        copy_reused_stages(&run, &mut manifest, reuse)?;
    }
    eprintln!(
        "run {}  (seed {}, backend {}: {}; log {})",
        run.path().display(),
        plan.seed,
        plan.backend,
        plan.backend_reason,
        run.log_path().display()
    );

    // 5. Train.
    crate::python::redirect_output(&run.log_path())
        .map_err(|err| python_failure("cannot redirect Python output", err, &run.log_path()))?;
    crate::python::release_signals()
        .map_err(|err| python_failure("cannot reset Python's signal handlers", err, &run.log_path()))?;
    let interrupt = crate::terminal::interrupt_flag()?;
    let capture = Capture::start(&run.log_path())
        .with_context(|| format!("cannot send output to {}", run.log_path().display()))?;
    let outcome = train_stages(&facade, &plan, &run, &mut manifest, &interrupt, &capture.console());
    drop(capture);
    let status = match &outcome {
        Ok(()) => Status::Completed,
        Err(StageFailure::Interrupted(_)) => Status::Interrupted,
        Err(StageFailure::ThresholdMissed(_)) => Status::ThresholdMissed,
        Err(StageFailure::Failed(_)) => Status::Failed,
    };
    manifest.status = status;
    manifest.ended_at = Some(now_rfc3339());
    if let Some(session) = manifest.sessions.last_mut() {
        session.ended_at = manifest.ended_at.clone();
        session.outcome = Some(status);
    }
    let resume_hint = format!(
        "resume with `hifar train {} --run-dir {} --resume`",
        args.curriculum.display(),
        run.path().display()
    );
    let result = match outcome {
        Ok(()) => {
            manifest.message = None;
            Ok(())
        }
        Err(StageFailure::Interrupted(message)) => {
            manifest.message = Some(message.clone());
            Err(anyhow::Error::new(Interrupted(format!("{message}; {resume_hint}"))))
        }
        Err(StageFailure::ThresholdMissed(message)) => {
            manifest.message = Some(message.clone());
            Err(anyhow!(message))
        }
        Err(StageFailure::Failed(err)) => {
            manifest.message = Some(format!("{err:#}"));
            Err(err.context(format!("run {} failed ({resume_hint} after fixing the cause)", run.path().display())))
        }
    };
    run.write_manifest(&manifest)?;
    run.log(&format!("run ended: {status}"));
    if result.is_ok() {
        let last = manifest.stages.last().and_then(|s| s.final_checkpoint.clone()).unwrap_or_default();
        eprintln!("run completed: {}  (final checkpoint {})", run.path().display(), run.path().join(last).display());
    }
    result
}

fn make_plan(
    curriculum_path: PathBuf,
    curriculum: Curriculum,
    backend: String,
    backend_reason: String,
    num_envs: Option<u32>,
) -> Result<Plan> {
    let seed = curriculum.seed();
    let mut stages = Vec::new();
    for (index, stage) in curriculum.stages().iter().enumerate() {
        let advance = stage.advance();
        let threshold = advance.min_stand_rate.map(|min_stand_rate| Threshold {
            min_stand_rate,
            window: advance.window.max(1) as usize,
            on_miss_continue: advance.on_miss_continue(),
        });
        stages.push(StagePlan {
            index,
            name: stage.name().to_owned(),
            json: stage.to_json(),
            seed: stage_seed(seed, index),
            init_from: curriculum.init_source(index),
            budget: advance.env_steps,
            threshold,
        });
    }
    Ok(Plan { curriculum_path, curriculum, seed, backend, backend_reason, num_envs, stages })
}

fn resolve_backend(
    facade: &Facade,
    curriculum: &Curriculum,
    args: &TrainArgs,
    inherited: Option<&Manifest>,
) -> Result<(String, String)> {
    if let Some(flag) = &args.backend {
        return Ok((flag.clone(), "--backend".into()));
    }
    if let Some(manifest) = inherited {
        let when = if args.resume { "as when the run started" } else { "as in the run whose stages are reused" };
        return Ok((manifest.backend.clone(), format!("{when} ({})", manifest.backend_reason)));
    }
    let configured = curriculum.backend();
    if configured != AUTO_BACKEND {
        return Ok((configured.to_owned(), format!("curriculum backend = \"{configured}\"")));
    }
    let (backend, reason) = default_backend_and_reason(facade, &paths::command_log())?;
    Ok((backend, format!("auto: {reason}")))
}

fn new_manifest(run: &RunDir, plan: &Plan, facade: &Facade) -> Result<Manifest> {
    std::fs::copy(&plan.curriculum_path, run.path().join(CURRICULUM_COPY))
        .with_context(|| format!("cannot copy {} into {}", plan.curriculum_path.display(), run.path().display()))?;
    let python_versions = facade
        .call("versions", &[])
        .map_err(|err| python_failure("facade.versions() failed", err, &run.log_path()))?;
    let mut versions = Map::new();
    versions.insert("hifar".into(), json!(env!("CARGO_PKG_VERSION")));
    if let Value::Object(map) = python_versions {
        versions.extend(map);
    }
    let manifest = Manifest {
        format_version: Manifest::FORMAT_VERSION,
        name: plan.curriculum.name().to_owned(),
        status: Status::Pending,
        message: None,
        curriculum: CurriculumRecord {
            source: plan.curriculum_path.to_string_lossy().into_owned(),
            copy: CURRICULUM_COPY.into(),
            resolved: plan.curriculum.resolved_json(),
        },
        seed: plan.seed,
        backend: plan.backend.clone(),
        backend_reason: plan.backend_reason.clone(),
        num_envs: plan.num_envs,
        versions: Value::Object(versions),
        git_commit: run_dir::git_commit(&paths::repo_root()),
        host: host_name(),
        started_at: now_rfc3339(),
        ended_at: None,
        sessions: Vec::new(),
        stages: plan
            .stages
            .iter()
            .map(|stage| StageRecord {
                name: stage.name.clone(),
                seed: stage.seed,
                status: Status::Pending,
                init_from: stage.init_from.map(|i| plan.stages[i].name.clone()),
                init_checkpoint: None,
                final_checkpoint: None,
                env_steps: None,
                best_stand_rate: None,
                started_at: None,
                ended_at: None,
                reused_from: None,
            })
            .collect(),
    };
    run.write_manifest(&manifest)?;
    Ok(manifest)
}

/// The manifest of an existing run directory; `purpose` ends the error for a directory without one.
fn read_run_manifest(dir: &Path, purpose: &str) -> Result<Manifest> {
    Manifest::read(dir).map_err(|err| {
        if dir.join(run_dir::MANIFEST).exists() {
            err
        } else {
            bad_input!("{} is not a run directory (no manifest.json); {purpose}", dir.display())
        }
    })
}

/// The leading stages a new run takes from another run (`--reuse-stages-from`).
struct Reuse {
    source: PathBuf,
    records: Vec<StageRecord>,
}

/// The longest prefix of `source`'s stages that this plan would train identically: completed,
/// with the same resolved stage table, seed, backend and num_envs. None is an error: the user
/// asked to reuse, and training everything anew would be a silent surprise.
fn reusable_stages(dir: &Path, source: &Manifest, plan: &Plan) -> Result<Reuse> {
    let nothing = |why: String| bad_input!("no stage of {} can be reused: {why}", dir.display());
    if source.seed != plan.seed || source.backend != plan.backend || source.num_envs != plan.num_envs {
        return Err(nothing(format!(
            "it was trained with seed {}, backend {}, {}; this run would use seed {}, backend {}, {}",
            source.seed,
            source.backend,
            num_envs_text(source.num_envs),
            plan.seed,
            plan.backend,
            num_envs_text(plan.num_envs)
        )));
    }
    let mut records = Vec::new();
    let mut stop = None;
    for (index, stage) in plan.stages.iter().enumerate() {
        let Some(record) = source.stages.get(index) else {
            stop = Some(format!("it has no stage {}", index + 1));
            break;
        };
        let done = record.status.is_finished() && record.final_checkpoint.is_some();
        if record.name != stage.name || source.curriculum.resolved["stage"][index] != stage.json {
            stop = Some(format!("its stage {} ({}) has other settings than this curriculum's {}", index + 1, record.name, stage.name));
            break;
        }
        if !done {
            stop = Some(format!("its stage {} ({}) is {}", index + 1, record.name, record.status));
            break;
        }
        records.push(record.clone());
    }
    if records.is_empty() {
        return Err(nothing(stop.unwrap_or_default()));
    }
    if records.len() == plan.stages.len() {
        return Err(bad_input!(
            "every stage of {} has this curriculum's settings: nothing would be trained (copy the run directory instead)",
            dir.display()
        ));
    }
    Ok(Reuse { source: dir.to_owned(), records })
}

fn num_envs_text(num_envs: Option<u32>) -> String {
    num_envs.map(|n| format!("--num-envs {n}")).unwrap_or_else(|| "the curriculum's num_envs".into())
}

/// Copies the reused stages into a new run: each stage directory and its TensorBoard events
/// (atomically, directory by directory), their metrics lines, then their manifest records.
fn copy_reused_stages(run: &RunDir, manifest: &mut Manifest, reuse: &Reuse) -> Result<()> {
    let source = RunLayout::new(&reuse.source);
    for record in &reuse.records {
        for (from, to) in [
            (source.stage_dir(&record.name), run.stage_dir(&record.name)),
            (source.tensorboard_dir(&record.name), run.tensorboard_dir(&record.name)),
        ] {
            if from.is_dir() {
                crate::atomic::write_dir_atomic(&to, crate::atomic::IfExists::Replace, |temp| copy_tree(&from, temp))
                    .with_context(|| format!("cannot copy {} to {}", from.display(), to.display()))?;
            }
        }
    }
    let names: Vec<&str> = reuse.records.iter().map(|r| r.name.as_str()).collect();
    let lines = metrics::read_jsonl(&source.metrics_path())
        .with_context(|| format!("cannot read {}", source.metrics_path().display()))?;
    let mut text = String::new();
    for line in lines.iter().filter(|l| l.get("stage").and_then(Value::as_str).is_some_and(|s| names.contains(&s))) {
        text.push_str(&serde_json::to_string(line)?);
        text.push('\n');
    }
    crate::atomic::write_file_atomic(&run.metrics_path(), text.as_bytes())
        .with_context(|| format!("cannot write {}", run.metrics_path().display()))?;
    for (index, record) in reuse.records.iter().enumerate() {
        manifest.stages[index] = StageRecord { reused_from: Some(reuse.source.to_string_lossy().into_owned()), ..record.clone() };
        run.log(&format!(
            "stage {}: reused from {} ({}, {} env steps, final checkpoint {})",
            record.name,
            reuse.source.display(),
            record.status,
            record.env_steps.map(group_digits).unwrap_or_else(|| "?".into()),
            record.final_checkpoint.as_deref().unwrap_or("?")
        ));
    }
    run.write_manifest(manifest)?;
    Ok(())
}

/// Copies the regular files and directories under `from` into the existing directory `to`.
fn copy_tree(from: &Path, to: &Path) -> std::io::Result<()> {
    for entry in std::fs::read_dir(from)? {
        let entry = entry?;
        let target = to.join(entry.file_name());
        if entry.file_type()?.is_dir() {
            std::fs::create_dir(&target)?;
            copy_tree(&entry.path(), &target)?;
        } else {
            std::fs::copy(entry.path(), &target)?;
        }
    }
    Ok(())
}

/// The manifest of a run being resumed, after checking that it is the same experiment.
fn resume_manifest_checked(run: &RunDir, previous: Manifest, plan: &Plan) -> Result<Manifest> {
    if previous.seed != plan.seed || previous.backend != plan.backend || previous.num_envs != plan.num_envs {
        return Err(bad_input!(
            "run {} was started with seed {}, backend {}, num_envs {:?}; resuming with seed {}, backend {}, num_envs {:?} would not continue the same experiment",
            run.path().display(),
            previous.seed,
            previous.backend,
            previous.num_envs,
            plan.seed,
            plan.backend,
            plan.num_envs
        ));
    }
    let resolved = plan.curriculum.resolved_json();
    if previous.curriculum.resolved != resolved {
        return Err(bad_input!(
            "{} differs from the curriculum run {} was started with ({}); resume with that file",
            plan.curriculum_path.display(),
            run.path().display(),
            run.path().join(&previous.curriculum.copy).display()
        ));
    }
    Ok(previous)
}

/// How the stage loop stopped, when not by finishing every stage.
enum StageFailure {
    Interrupted(String),
    ThresholdMissed(String),
    Failed(anyhow::Error),
}

impl From<anyhow::Error> for StageFailure {
    fn from(err: anyhow::Error) -> Self {
        StageFailure::Failed(err)
    }
}


fn train_stages(
    facade: &Facade,
    plan: &Plan,
    run: &RunDir,
    manifest: &mut Manifest,
    interrupt: &Arc<AtomicBool>,
    console: &Console,
) -> Result<(), StageFailure> {
    for stage in &plan.stages {
        if manifest.stages[stage.index].status.is_finished() {
            continue;
        }
        if interrupt.load(Ordering::SeqCst) {
            return Err(StageFailure::Interrupted(format!("interrupted before stage {}", stage.name)));
        }
        train_stage(facade, plan, stage, run, manifest, interrupt, console)?;
    }
    Ok(())
}

fn train_stage(
    facade: &Facade,
    plan: &Plan,
    stage: &StagePlan,
    run: &RunDir,
    manifest: &mut Manifest,
    interrupt: &Arc<AtomicBool>,
    console: &Console,
) -> Result<(), StageFailure> {
    let stage_dir = run.stage_dir(&stage.name);
    std::fs::create_dir_all(&stage_dir).with_context(|| format!("cannot create {}", stage_dir.display()))?;
    let resume_checkpoint = latest_checkpoint(&stage_dir)?;

    // Where the weights come from: our own latest checkpoint (exact resume), else the expanded
    // final checkpoint of the stage named by init_from, else a fresh initialisation.
    let mut init_checkpoint = None;
    if resume_checkpoint.is_none() {
        if let Some(source) = stage.init_from {
            let source_record = &manifest.stages[source];
            let relative = source_record.final_checkpoint.clone().ok_or_else(|| {
                anyhow!("stage {} starts from stage {}, which has no final checkpoint", stage.name, source_record.name)
            })?;
            let source_dir = run.path().join(relative);
            let out = stage_dir.join("init");
            if out.exists() {
                std::fs::remove_dir_all(&out).with_context(|| format!("cannot remove {}", out.display()))?;
            }
            let report = checkpoint::expand_to_stage(&source_dir, &plan.curriculum.stages()[stage.index], &out)
                .with_context(|| format!("cannot expand {} into stage {}", source_dir.display(), stage.name))?;
            run.log(&format!("stage {}: expanded {} into {}: {report}", stage.name, source_dir.display(), out.display()));
            init_checkpoint = Some(out);
        }
    }

    // Metrics of a resumed stage stop at its checkpoint; later lines are replayed by training.
    let resumed_steps = match &resume_checkpoint {
        Some(dir) => Some(checkpoint_env_steps(dir)?),
        None => None,
    };
    let history = truncate_metrics(run, manifest, &stage.name, resumed_steps)?;

    let record = &mut manifest.stages[stage.index];
    record.status = Status::Running;
    record.started_at.get_or_insert_with(now_rfc3339);
    record.ended_at = None;
    if let Some(init) = &init_checkpoint {
        record.init_checkpoint = Some(run.relative(init));
    }
    run.write_manifest(manifest)?;
    run.log(&format!(
        "stage {} ({}): seed {}, {}",
        stage.name,
        stage.index,
        stage.seed,
        match (&resume_checkpoint, &init_checkpoint) {
            (Some(dir), _) => format!("resuming from {}", dir.display()),
            (None, Some(dir)) => format!("initialised from {}", dir.display()),
            (None, None) => "fresh initialisation".into(),
        }
    ));

    let monitor = Arc::new(Mutex::new(Monitor::new(plan, stage, run, interrupt.clone(), &history, console.clone())?));
    let request = TrainRequest {
        stage: stage.json.clone(),
        stage_name: stage.name.clone(),
        stage_dir: stage_dir.clone(),
        seed: stage.seed,
        backend: plan.backend.clone(),
        num_envs: plan.num_envs,
        init_checkpoint: init_checkpoint.clone(),
        resume_checkpoint: resume_checkpoint.clone(),
        log_file: run.log_path(),
    };
    let callback_monitor = Arc::clone(&monitor);
    let result = facade.call_with_progress(TrainRequest::FUNCTION, &request.to_json(), move |progress| {
        let mut monitor = callback_monitor.lock().unwrap_or_else(|p| p.into_inner());
        monitor.on_progress(progress).to_owned()
    });
    let mut monitor = monitor.lock().unwrap_or_else(|p| p.into_inner());
    monitor.finish();

    let record = &mut manifest.stages[stage.index];
    record.best_stand_rate = monitor.advance.best_stand_rate;
    record.ended_at = Some(now_rfc3339());
    let result = match result {
        Ok(result) => result,
        Err(err) => {
            record.status = Status::Failed;
            run.write_manifest(manifest)?;
            return Err(StageFailure::Failed(python_failure(
                &format!("stage {} failed", stage.name),
                err,
                &run.log_path(),
            )));
        }
    };
    let status = result.get("status").and_then(Value::as_str).unwrap_or("");
    if let Some(checkpoint) = result.get("checkpoint").and_then(Value::as_str) {
        record.final_checkpoint = Some(run.relative(Path::new(checkpoint)));
    }
    record.env_steps = result.get("env_steps").and_then(Value::as_u64).or(record.env_steps);
    let env_steps = record.env_steps.unwrap_or(0);
    if let Some(err) = monitor.error.take() {
        record.status = Status::Failed;
        record.final_checkpoint = None;
        run.write_manifest(manifest)?;
        return Err(StageFailure::Failed(err.context(format!("stage {} stopped", stage.name))));
    }
    match status {
        "interrupted" => {
            record.status = Status::Interrupted;
            record.final_checkpoint = None;
            run.write_manifest(manifest)?;
            let at = result.get("checkpoint").and_then(Value::as_str).unwrap_or("?");
            Err(StageFailure::Interrupted(format!(
                "interrupted in stage {} at {} env steps (checkpoint {})",
                stage.name,
                group_digits(env_steps),
                at
            )))
        }
        "completed" | "finished_early" => {
            let missed = stage.threshold.filter(|_| !monitor.advance.threshold_met);
            record.status = if missed.is_some() { Status::ThresholdMissed } else { Status::Completed };
            run.write_manifest(manifest)?;
            let mut line = format!(
                "stage {} {}: {} env steps, best stand rate {}",
                stage.name,
                if status == "finished_early" { "reached its threshold" } else { "used its budget" },
                group_digits(env_steps),
                monitor.advance.best_stand_rate.map(|r| format!("{r:.3}")).unwrap_or_else(|| "-".into())
            );
            if let (Some(latest), Some(best)) = (monitor.det.latest, monitor.det.best) {
                line.push_str(&format!(", deterministic stand rate {latest:.3} (best {best:.3})"));
            }
            run.log(&line);
            console.line(&line);
            match missed {
                Some(threshold) => {
                    let message = format!(
                        "stage {} missed its threshold: stand rate {} (mean of the last {} reports) < {} within its budget of {} env steps",
                        stage.name,
                        monitor.advance.window_mean().map(|m| format!("{m:.3}")).unwrap_or_else(|| "n/a".into()),
                        threshold.window,
                        threshold.min_stand_rate,
                        group_digits(stage.budget)
                    );
                    run.log(&message);
                    if threshold.on_miss_continue {
                        console.line(&format!("{message}; continuing (advance.on_miss = \"continue\")"));
                        Ok(())
                    } else {
                        Err(StageFailure::ThresholdMissed(format!(
                            "{message}; the run stops here (set advance.on_miss = \"continue\" to go on)"
                        )))
                    }
                }
                None => Ok(()),
            }
        }
        other => {
            record.status = Status::Failed;
            run.write_manifest(manifest)?;
            Err(StageFailure::Failed(anyhow!("facade.train_stage returned unknown status {other:?}")))
        }
    }
}

/// The checkpoint named by `<stage_dir>/checkpoints/LATEST`, if any.
fn latest_checkpoint(stage_dir: &Path) -> Result<Option<PathBuf>> {
    let latest = stage_dir.join("checkpoints").join("LATEST");
    let name = match std::fs::read_to_string(&latest) {
        Ok(name) => name.trim().to_owned(),
        Err(err) if err.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(err) => return Err(err).with_context(|| format!("cannot read {}", latest.display())),
    };
    let path = Path::new(&name);
    let dir = if path.is_absolute() { path.to_path_buf() } else { stage_dir.join("checkpoints").join(path) };
    if !dir.join("checkpoint.json").is_file() {
        bail!("{} names {}, which is not a checkpoint", latest.display(), dir.display());
    }
    Ok(Some(dir))
}

fn checkpoint_env_steps(dir: &Path) -> Result<u64> {
    let meta = checkpoint::read_meta(dir).with_context(|| format!("cannot read checkpoint {}", dir.display()))?;
    Ok(meta.env_steps)
}

/// Rewrites `metrics.jsonl` so that it holds what the run has really kept: every line of
/// completed stages, and of `stage` the lines up to its checkpoint's env steps (none when the
/// stage starts over). Returns this stage's kept lines (the advance window is rebuilt from them).
fn truncate_metrics(run: &RunDir, manifest: &Manifest, stage: &str, kept_steps: Option<u64>) -> Result<Vec<Value>> {
    let path = run.metrics_path();
    let lines = metrics::read_jsonl(&path).with_context(|| format!("cannot read {}", path.display()))?;
    if lines.is_empty() {
        return Ok(Vec::new());
    }
    let done: Vec<&str> = manifest
        .stages
        .iter()
        .filter(|s| s.status.is_finished())
        .map(|s| s.name.as_str())
        .collect();
    let mut kept = Vec::new();
    let mut history = Vec::new();
    for line in lines {
        let name = line.get("stage").and_then(Value::as_str).unwrap_or("");
        if done.contains(&name) {
            kept.push(line);
        } else if name == stage {
            let steps = line.get("env_steps").and_then(Value::as_u64).unwrap_or(u64::MAX);
            if kept_steps.is_some_and(|limit| steps <= limit) {
                history.push(line.clone());
                kept.push(line);
            }
        }
    }
    let mut text = String::new();
    for line in &kept {
        text.push_str(&serde_json::to_string(line)?);
        text.push('\n');
    }
    crate::atomic::write_file_atomic(&path, text.as_bytes()).with_context(|| format!("cannot write {}", path.display()))?;
    Ok(history)
}

/// Receives every progress report of one stage.
struct Monitor {
    stage: String,
    budget: u64,
    interrupt: Arc<AtomicBool>,
    metrics: MetricsLog,
    events: EventWriter,
    bar: ProgressBar,
    console: Console,
    /// Plain progress lines instead of a bar (stderr is not a terminal).
    plain: bool,
    last_plain: Option<Instant>,
    /// Time and env steps of the first report: the rate since then (compilation excluded)
    /// gives the ETA.
    first_report: Option<(Instant, u64)>,
    advance: AdvanceWindow,
    /// The deterministic monitor's latest and best mean stand rate (`monitor.mean_stand_rate`
    /// of the reports that carry one).
    det: DetMonitor,
    /// A failure inside the callback (e.g. a full disk): training is interrupted and the
    /// error reported once Python has returned.
    error: Option<anyhow::Error>,
}

impl Monitor {
    fn new(
        plan: &Plan,
        stage: &StagePlan,
        run: &RunDir,
        interrupt: Arc<AtomicBool>,
        history: &[Value],
        console: Console,
    ) -> Result<Monitor> {
        let metrics = MetricsLog::open(&run.metrics_path())
            .with_context(|| format!("cannot open {}", run.metrics_path().display()))?;
        let events = EventWriter::create(&run.tensorboard_dir(&stage.name), unix_time(), &host_name())
            .with_context(|| format!("cannot create an event file in {}", run.tensorboard_dir(&stage.name).display()))?;
        let term = if console.is_term() { console.term().ok() } else { None };
        let plain = term.is_none();
        let bar = match term {
            None => ProgressBar::hidden(),
            Some(term) => ProgressBar::with_draw_target(Some(stage.budget), ProgressDrawTarget::term(term, 10)),
        };
        bar.set_style(
            ProgressStyle::with_template(
                "{prefix:.bold} {bar:28.cyan/blue} {human_pos:>11}/{human_len} env steps  {msg}  [{elapsed_precise}]",
            )
            .expect("valid template")
            .progress_chars("=> "),
        );
        bar.set_prefix(format!("{} ({}/{})", stage.name, stage.index + 1, plan.stages.len()));
        bar.set_message("starting (compiling)…");
        if plain {
            console.line(&format!("stage {} ({}/{}): starting", stage.name, stage.index + 1, plan.stages.len()));
        } else {
            bar.enable_steady_tick(Duration::from_millis(500));
        }
        let mut monitor = Monitor {
            stage: stage.name.clone(),
            budget: stage.budget,
            interrupt,
            metrics,
            events,
            bar,
            console,
            plain,
            last_plain: None,
            first_report: None,
            advance: AdvanceWindow::new(stage.threshold),
            det: DetMonitor::default(),
            error: None,
        };
        for record in history {
            monitor.advance.observe(record);
            monitor.det.observe(record);
        }
        Ok(monitor)
    }

    fn on_progress(&mut self, progress: Value) -> &'static str {
        if let Err(err) = self.record(&progress) {
            self.error.get_or_insert(err);
        }
        self.det.observe(&progress);
        self.draw(&progress);
        // The threshold first: an iteration that meets it finishes the stage even if a signal
        // arrived meanwhile, exactly as an uninterrupted run would (the signal then stops the
        // run before the next stage).
        if self.advance.observe(&progress) {
            return "finish";
        }
        if self.error.is_some() || self.interrupt.load(Ordering::SeqCst) {
            return "interrupt";
        }
        "continue"
    }

    fn record(&mut self, progress: &Value) -> Result<()> {
        let Value::Object(fields) = progress else {
            bail!("facade.train_stage sent a progress report that is not a dict: {progress}");
        };
        let wall_time = unix_time();
        let mut record = Map::new();
        record.insert("stage".into(), json!(self.stage));
        record.insert("wall_time".into(), json!(wall_time));
        record.extend(fields.clone());
        self.metrics.append(&Value::Object(record)).context("cannot append to metrics.jsonl")?;
        let step = fields.get("env_steps").and_then(Value::as_i64).unwrap_or(0);
        let mut scalars = metrics::scalars(fields);
        if let Some(Value::String(phase)) = fields.get("phase") {
            if phase != "ppo" {
                for (tag, _) in &mut scalars {
                    *tag = format!("{phase}/{tag}");
                }
            }
        }
        self.events.scalars(step, wall_time, &scalars).context("cannot write the TensorBoard event file")?;
        self.events.flush().context("cannot write the TensorBoard event file")?;
        Ok(())
    }

    fn draw(&mut self, progress: &Value) {
        let get = |key: &str| progress.get(key).and_then(Value::as_f64);
        let steps = progress.get("env_steps").and_then(Value::as_u64).unwrap_or(0);
        let total = progress.get("total_env_steps").and_then(Value::as_u64).unwrap_or(self.budget);
        let phase = progress.get("phase").and_then(Value::as_str).unwrap_or("ppo");
        let mut message = format!("{:.0} steps/s", get("steps_per_s").unwrap_or(0.0));
        if let Some(ret) = get("episode_return") {
            message.push_str(&format!("  reward {ret:.2}"));
        }
        if let Some(rate) = get("stand_rate") {
            message.push_str(&format!("  stand {rate:.2}"));
        }
        if let Some(det) = self.det.latest {
            message.push_str(&format!("  det {det:.2}"));
        }
        if phase != "ppo" {
            message.push_str(&format!("  [{phase}]"));
        }
        let (t0, s0) = *self.first_report.get_or_insert((Instant::now(), steps));
        let elapsed = t0.elapsed().as_secs_f64();
        if steps > s0 && elapsed > 0.0 && total > steps {
            let eta = (total - steps) as f64 / ((steps - s0) as f64 / elapsed);
            message.push_str(&format!("  ETA {}", indicatif::HumanDuration(Duration::from_secs_f64(eta))));
        }
        if self.plain {
            let due = self.last_plain.is_none_or(|t| t.elapsed() >= Duration::from_secs(10));
            if due || steps >= total {
                self.last_plain = Some(Instant::now());
                self.console.line(&format!(
                    "stage {}: iteration {}  {}/{} env steps  {message}",
                    self.stage,
                    progress.get("iteration").and_then(Value::as_u64).unwrap_or(0),
                    group_digits(steps),
                    group_digits(total)
                ));
            }
        } else {
            self.bar.set_length(total);
            self.bar.set_position(steps.min(total));
            self.bar.set_message(message);
        }
    }

    fn finish(&mut self) {
        let _ = self.events.flush();
        self.bar.finish_and_clear();
    }
}

/// The advance criterion of a stage: the mean stand rate of its last `window` PPO progress
/// reports (reports without finished episodes, or made with an assisting force on, do not
/// count) against `min_stand_rate`.
#[derive(Debug)]
struct AdvanceWindow {
    threshold: Option<Threshold>,
    window: VecDeque<f64>,
    threshold_met: bool,
    best_stand_rate: Option<f64>,
}

impl AdvanceWindow {
    fn new(threshold: Option<Threshold>) -> AdvanceWindow {
        AdvanceWindow { threshold, window: VecDeque::new(), threshold_met: false, best_stand_rate: None }
    }

    /// Feeds one progress report; true once the threshold is met. Only the PPO phase counts:
    /// the adaptation phase that follows it does not change the policy being judged.
    fn observe(&mut self, progress: &Value) -> bool {
        if progress.get("phase").and_then(Value::as_str).unwrap_or("ppo") != "ppo" {
            return false;
        }
        // With `[stage.assist]` pulling the Trunk up, standing says nothing about the policy
        // on its own: those reports neither end the stage nor count as its best.
        if progress.get("assist_force").and_then(Value::as_f64).is_some_and(|force| force > 0.0) {
            return self.threshold_met;
        }
        let Some(rate) = progress.get("stand_rate").and_then(Value::as_f64) else { return self.threshold_met };
        self.best_stand_rate = Some(self.best_stand_rate.map_or(rate, |best| best.max(rate)));
        let Some(threshold) = self.threshold else { return false };
        self.window.push_back(rate);
        while self.window.len() > threshold.window {
            self.window.pop_front();
        }
        if self.window.len() == threshold.window && self.window_mean().is_some_and(|m| m >= threshold.min_stand_rate) {
            self.threshold_met = true;
        }
        self.threshold_met
    }

    fn window_mean(&self) -> Option<f64> {
        (!self.window.is_empty()).then(|| self.window.iter().sum::<f64>() / self.window.len() as f64)
    }
}

/// The deterministic monitor's mean stand rate over a stage's progress reports: the latest
/// value (shown as `det` on the progress line) and the best.
#[derive(Debug, Default)]
struct DetMonitor {
    latest: Option<f64>,
    best: Option<f64>,
}

impl DetMonitor {
    fn observe(&mut self, progress: &Value) {
        if let Some(rate) = metrics::monitor_mean_stand_rate(progress) {
            self.latest = Some(rate);
            self.best = Some(self.best.map_or(rate, |best| best.max(rate)));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_monitor_keeps_its_latest_and_best_mean() {
        let mut det = DetMonitor::default();
        det.observe(&json!({"stand_rate": 0.5}));
        assert_eq!((det.latest, det.best), (None, None), "reports without a monitor change nothing");
        det.observe(&json!({"monitor": {"stand_rate": {"supine": 0.8}, "mean_stand_rate": 0.8}}));
        det.observe(&json!({"stand_rate": 0.1, "max_height": null}));
        det.observe(&json!({"monitor": {"mean_stand_rate": 0.6}}));
        det.observe(&json!({"monitor": {"mean_stand_rate": null}}));
        assert_eq!((det.latest, det.best), (Some(0.6), Some(0.8)));
    }

    fn report(phase: &str, rate: Option<f64>) -> Value {
        json!({"phase": phase, "stand_rate": rate})
    }

    #[test]
    fn threshold_needs_a_full_window_above_the_minimum() {
        let threshold = Threshold { min_stand_rate: 0.7, window: 3, on_miss_continue: false };
        let mut advance = AdvanceWindow::new(Some(threshold));
        assert!(!advance.observe(&report("ppo", Some(0.9))));
        assert!(!advance.observe(&report("ppo", Some(0.9))), "window not full yet");
        assert!(!advance.observe(&report("ppo", None)), "reports without finished episodes do not count");
        assert!(!advance.observe(&report("ppo", Some(0.0))));
        assert!((advance.window_mean().unwrap() - 0.6).abs() < 1e-12);
        assert!(!advance.observe(&report("ppo", Some(0.9))));
        assert!(!advance.observe(&report("ppo", Some(0.9))));
        assert!(advance.observe(&report("ppo", Some(0.9))), "0.9, 0.9, 0.9");
    }

    #[test]
    fn threshold_is_judged_on_the_mean_of_the_last_reports() {
        let threshold = Threshold { min_stand_rate: 0.5, window: 2, on_miss_continue: false };
        let mut advance = AdvanceWindow::new(Some(threshold));
        for rate in [0.1, 0.8, 0.0] {
            assert!(!advance.observe(&report("ppo", Some(rate))));
        }
        assert!(!advance.observe(&report("adaptation", Some(1.0))), "adaptation reports do not count");
        assert!(advance.observe(&report("ppo", Some(1.0))), "mean(0.0, 1.0) = 0.5 meets 0.5");
        assert_eq!(advance.best_stand_rate, Some(1.0));
    }

    #[test]
    fn assisted_reports_are_not_judged() {
        let threshold = Threshold { min_stand_rate: 0.5, window: 2, on_miss_continue: false };
        let mut advance = AdvanceWindow::new(Some(threshold));
        let assisted = json!({"phase": "ppo", "stand_rate": 1.0, "assist_force": 90.0});
        assert!(!advance.observe(&assisted));
        assert!(!advance.observe(&assisted), "an assisted stand rate never ends the stage");
        assert_eq!(advance.best_stand_rate, None);
        let unassisted = json!({"phase": "ppo", "stand_rate": 0.6, "assist_force": 0.0});
        assert!(!advance.observe(&unassisted));
        assert!(advance.observe(&unassisted));
    }

    #[test]
    fn without_threshold_only_the_best_rate_is_kept() {
        let mut advance = AdvanceWindow::new(None);
        assert!(!advance.observe(&report("ppo", Some(1.0))));
        assert_eq!(advance.best_stand_rate, Some(1.0));
    }
}
