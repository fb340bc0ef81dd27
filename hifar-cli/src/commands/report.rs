//! `hifar report`: PNG plots and a markdown summary of a run directory.
//!
//! Rust checks that the argument is a run directory (its `manifest.json` reads as a hifar
//! manifest) and where the report goes before Python starts; `facade.report` reads the
//! manifest, `metrics.jsonl` and every `eval/*/eval.json` and writes the files. The run is only
//! read, so the training lock is not taken: a report of a run still training is allowed (it
//! shows the run as far as it got). The report directory holds derived output only, so its
//! files are replaced on every report.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use serde_json::Value;

use crate::cli::ReportArgs;
use crate::commands::facade::{python_failure, ReportRequest, Request};
use crate::commands::setup;
use crate::ui::Status;
use crate::run_dir::{Manifest, MANIFEST};
use crate::{bad_input, paths};

/// Where the report of which run goes, checked.
#[derive(Debug)]
struct Plan {
    run: PathBuf,
    out: PathBuf,
    name: String,
    stages: usize,
}

impl Plan {
    fn new(args: &ReportArgs) -> Result<Plan> {
        let run = paths::absolute(args.run.clone());
        if !run.is_dir() {
            return Err(bad_input!("run directory {} does not exist", args.run.display()));
        }
        if !run.join(MANIFEST).is_file() {
            return Err(bad_input!("{} is not a run directory (no {MANIFEST})", args.run.display()));
        }
        let manifest = Manifest::read(&run).map_err(|err| bad_input!("{err:#}"))?;
        let out = match &args.out {
            Some(out) => paths::absolute(out.clone()),
            None => run.join("report"),
        };
        if out.exists() && !out.is_dir() {
            return Err(bad_input!("--out {} exists and is not a directory", out.display()));
        }
        Ok(Plan { run, out, name: manifest.name, stages: manifest.stages.len() })
    }
}

pub fn run(args: &ReportArgs) -> Result<()> {
    let plan = Plan::new(args)?;
    let facade = setup::ensure_python()?;
    let status = Status::start("hifar report");
    status.step(&format!("plotting run {} ({} stages) into {}", plan.name, plan.stages, plan.out.display()));
    let request = ReportRequest { run: plan.run.clone(), out_dir: plan.out.clone() };
    let result = facade
        .call(ReportRequest::FUNCTION, &[request.to_json()])
        .map_err(|err| python_failure("facade.report failed", err, &paths::command_log()))?;
    let (markdown, plots) = parse_result(&result).context("facade.report returned an unexpected result")?;
    status.finish(&format!(
        "report of run {}: {} plot{} and {}",
        plan.name,
        plots,
        if plots == 1 { "" } else { "s" },
        relative_to_cwd(&markdown).display()
    ));
    println!("{}", markdown.display());
    Ok(())
}

/// The markdown path and the number of plots of `{"markdown": path, "plots": [paths]}`.
fn parse_result(result: &Value) -> Result<(PathBuf, usize)> {
    let markdown = result["markdown"].as_str().with_context(|| format!("no \"markdown\" path in {result}"))?;
    let plots = result["plots"].as_array().with_context(|| format!("no \"plots\" list in {result}"))?;
    Ok((PathBuf::from(markdown), plots.len()))
}

fn relative_to_cwd(path: &Path) -> PathBuf {
    std::env::current_dir()
        .ok()
        .and_then(|cwd| path.strip_prefix(cwd).ok().map(Path::to_path_buf))
        .unwrap_or_else(|| path.to_path_buf())
}
