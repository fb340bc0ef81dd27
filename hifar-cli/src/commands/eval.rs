//! `hifar eval`: the paper's simulation protocols on a policy (docs/contracts.md,
//! "facade.evaluate").
//!
//! Everything that can be checked without Python is checked into a [`Plan`] first: `--trials`,
//! the target, the stage table of a run's curriculum, and the output directory, which must not
//! exist unless `--force`. The default output directory names the backend; when neither `--out`
//! nor `--backend` is given, the backend is the machine's default (`facade.doctor()`), so that
//! one check waits for Python to start, still before any evaluation work. SIGINT/SIGTERM answer
//! "interrupt" at the next batch: Python then returns without writing anything (exit 130).

use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::sync::Arc;

use anyhow::{anyhow, Context, Result};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use serde_json::Value;

use crate::cli::EvalArgs;
use crate::commands::facade::{default_backend, python_failure, EvaluateRequest, Request};
use crate::commands::{setup, target};
use crate::error::Interrupted;
use crate::names::names;
use crate::terminal::{self, Capture};
use crate::{bad_input, paths};

/// A validated `hifar eval` invocation, before the backend is known.
#[derive(Debug, Clone)]
pub struct Plan {
    pub checkpoint: PathBuf,
    pub run: Option<PathBuf>,
    /// The checkpoint's stage table from the run's resolved curriculum (None for a bare
    /// checkpoint: Python reads its `stage_config`).
    pub stage: Option<Value>,
    pub stage_name: String,
    pub protocol: &'static str,
    pub trials: Option<u32>,
    /// None: the deployable actor.
    pub actor: Option<String>,
    pub seed: u64,
    pub out: Option<PathBuf>,
    pub force: bool,
}

impl Plan {
    pub fn from_args(args: &EvalArgs) -> Result<Plan> {
        if args.trials == Some(0) {
            return Err(bad_input!("--trials 0: every protocol cell needs at least 1 trial"));
        }
        // A non-default actor does not act through the adaptation module: nothing to refuse.
        let actor = args.actor.clone().filter(|a| a.as_str() != names().actors[0]);
        let target = if actor.is_some() { target::resolve_any(&args.target)? } else { target::resolve(&args.target)? };
        Ok(Plan {
            checkpoint: target.checkpoint,
            run: target.run,
            stage: target.stage,
            stage_name: target.meta.stage,
            protocol: args.protocol.as_str(),
            trials: args.trials,
            actor,
            seed: args.seed,
            out: args.out.clone().map(paths::absolute),
            force: args.force,
        })
    }

    /// `--out`, else `<run or checkpoint>/eval/<protocol>-<backend>`, with `-<actor>` after a
    /// non-default actor (so that it does not take the deployable actor's place).
    pub fn out_dir(&self, backend: &str) -> PathBuf {
        if let Some(out) = &self.out {
            return out.clone();
        }
        let base = self.run.as_ref().unwrap_or(&self.checkpoint);
        let actor = self.actor.as_ref().map(|a| format!("-{a}")).unwrap_or_default();
        base.join("eval").join(format!("{}-{backend}{actor}", self.protocol))
    }

    /// Refuses an existing output directory unless `--force`.
    pub fn check_out(&self, out: &Path) -> Result<()> {
        if out.exists() && !self.force {
            return Err(bad_input!(
                "{}: the output directory exists; pass --force to overwrite its evaluation files, or --out DIR",
                out.display()
            ));
        }
        Ok(())
    }
}

pub fn run(args: &EvalArgs) -> Result<()> {
    let plan = Plan::from_args(args)?;
    let flag_backend = args.backend.clone();
    if plan.out.is_some() || flag_backend.is_some() {
        plan.check_out(&plan.out_dir(flag_backend.as_deref().unwrap_or_default()))?;
    }

    let facade = setup::ensure_python()?;
    let log = paths::command_log();
    let backend = match flag_backend {
        Some(backend) => backend,
        None => default_backend(&facade, &log)?,
    };
    let out = plan.out_dir(&backend);
    plan.check_out(&out)?;
    eprintln!(
        "evaluating {} (stage {}) with the {} protocol on the {backend} backend{} -> {}",
        plan.checkpoint.display(),
        plan.stage_name,
        plan.protocol,
        plan.actor.as_ref().map(|a| format!(", {a} actor")).unwrap_or_default(),
        out.display()
    );

    let request = EvaluateRequest {
        checkpoint: plan.checkpoint.clone(),
        stage: plan.stage.clone(),
        protocol: plan.protocol.to_owned(),
        trials: plan.trials,
        backend: backend.clone(),
        actor: plan.actor.clone(),
        seed: plan.seed,
        out_dir: out.clone(),
        batch_size: None,
    };
    crate::python::release_signals()
        .map_err(|err| python_failure("cannot reset Python's signal handlers", err, &log))?;
    let interrupt = terminal::interrupt_flag()?;
    let capture = Capture::start(&log).with_context(|| format!("cannot send output to {}", log.display()))?;
    let console = capture.console();
    let bar = match console.is_term().then(|| console.term()).transpose()? {
        Some(term) => ProgressBar::with_draw_target(None, ProgressDrawTarget::term(term, 10)),
        None => ProgressBar::hidden(),
    };
    bar.set_style(
        ProgressStyle::with_template("{bar:28.cyan/blue} {pos}/{len} trials  {msg}  [{elapsed_precise}<{eta}]")
            .expect("valid template")
            .progress_chars("=> "),
    );
    bar.set_message("compiling the rollout");
    let (callback_bar, callback_console, flag) = (bar.clone(), console.clone(), Arc::clone(&interrupt));
    let result = facade.call_with_progress(EvaluateRequest::FUNCTION, &request.to_json(), move |progress| {
        let count = |key: &str| progress.get(key).and_then(Value::as_u64).unwrap_or(0);
        let cell = progress.get("cell").and_then(Value::as_str).unwrap_or("");
        let message = format!("{}/{} cells  {cell}", count("cells_done"), count("cells_total"));
        callback_bar.set_length(count("trials_total"));
        callback_bar.set_position(count("trials_done"));
        callback_bar.set_message(message.clone());
        if !callback_console.is_term() {
            callback_console.line(&format!("eval: {}/{} trials, {message}", count("trials_done"), count("trials_total")));
        }
        if flag.load(Ordering::SeqCst) { "interrupt" } else { "continue" }.to_owned()
    });
    bar.finish_and_clear();
    drop(capture);

    let result = result.map_err(|err| python_failure("evaluation failed", err, &log))?;
    match result.get("status").and_then(Value::as_str) {
        Some("completed") => {}
        Some("interrupted") => {
            return Err(anyhow::Error::new(Interrupted(format!("evaluation interrupted; nothing written to {}", out.display()))));
        }
        other => return Err(anyhow!("facade.evaluate returned an unknown status {other:?}")),
    }
    if let Some(markdown) = result.get("markdown").and_then(Value::as_str) {
        println!("{}", markdown.trim_end());
    }
    let files: Vec<&str> = result.get("files").and_then(Value::as_array).into_iter().flatten().filter_map(Value::as_str).collect();
    eprintln!("wrote {}", files.join(", "));
    Ok(())
}

