//! `hifar check`: validate a curriculum without training.
//!
//! The Rust side (`curriculum::load`) checks syntax, keys, types and names (against the
//! vocabularies jax_env exports, `crate::names`) and the relations between stages; the Python
//! side (`facade.check_stage`, `jax_env/config.py`) alone checks what each stage means: ranges,
//! mixtures, relations between keys, symmetric joint lists. Python answers with key paths
//! inside a stage and whether the key or the value is at fault; they are mapped back to
//! `FILE:LINE:COL` here and sorted into file order, so both kinds of error read the same.

use std::path::Path;

use anyhow::{anyhow, Result};
use serde_json::Value;

use crate::cli::CheckArgs;
use crate::commands::facade::python_failure;
use crate::commands::setup;
use crate::ui::group_digits;
use crate::curriculum::{self, Curriculum, Location, Target};
use crate::python::Facade;
use crate::{bad_input, paths};

pub fn run(args: &CheckArgs) -> Result<()> {
    let curriculum = curriculum::load(&args.curriculum)?;
    let indices: Vec<usize> = match &args.stage {
        None => (0..curriculum.stages().len()).collect(),
        Some(name) => vec![stage_index(&curriculum, name, &args.curriculum)?],
    };
    let facade = setup::ensure_python()?;
    check_with_python(&facade, &curriculum, Some(&indices))?;

    println!("{}: ok ({} stage{})", args.curriculum.display(), curriculum.stages().len(), if curriculum.stages().len() == 1 { "" } else { "s" });
    for &index in &indices {
        let stage = &curriculum.stages()[index];
        let features = curriculum::feature_names(stage);
        let init = match curriculum.init_source(index) {
            Some(source) => format!("from {}", curriculum.stages()[source].name()),
            None => "fresh".into(),
        };
        println!(
            "  {}: {} obs, {} privileged, {} actions; budget {} env steps; init {}",
            stage.name(),
            features.obs_names.len(),
            features.privileged_names.len(),
            features.action_names.len(),
            group_digits(stage.advance().env_steps),
            init
        );
    }
    Ok(())
}

/// Index of the stage called `name`, or a bad-input error listing the stages.
pub fn stage_index(curriculum: &Curriculum, name: &str, file: &Path) -> Result<usize> {
    curriculum.stages().iter().position(|s| s.name() == name).ok_or_else(|| {
        let names: Vec<&str> = curriculum.stages().iter().map(|s| s.name()).collect();
        bad_input!("{}: no stage named {name:?}; stages: {}", file.display(), names.join(", "))
    })
}

/// Python's checks of the given stages (all when `None`), each problem reported as
/// `FILE:LINE:COL: message`.
pub fn check_with_python(facade: &Facade, curriculum: &Curriculum, stages: Option<&[usize]>) -> Result<()> {
    let all: Vec<usize> = (0..curriculum.stages().len()).collect();
    let stages = stages.unwrap_or(&all);
    let log = paths::command_log();
    let mut problems: Vec<(Location, String)> = Vec::new();
    for &index in stages {
        let stage = &curriculum.stages()[index];
        let issues = facade
            .call("check_stage", &[stage.to_json()])
            .map_err(|err| python_failure(&format!("facade.check_stage failed on stage {}", stage.name()), err, &log))?;
        let Value::Array(issues) = issues else {
            return Err(anyhow!("facade.check_stage returned {issues}, expected a list"));
        };
        for issue in issues {
            let message = issue.get("message").and_then(Value::as_str).unwrap_or("invalid value");
            let path: Vec<Value> = match issue.get("path") {
                Some(Value::Array(path)) => path.clone(),
                _ => Vec::new(),
            };
            let target = if issue.get("at").and_then(Value::as_str) == Some("value") { Target::Value } else { Target::Key };
            problems.push((curriculum.locate_at(index, &path, target), message.to_owned()));
        }
    }
    if !problems.is_empty() {
        problems.sort_by_key(|(at, _)| (at.line, at.col));
        let lines: Vec<String> = problems.iter().map(|(at, message)| format!("{at}: {message}")).collect();
        return Err(bad_input!("{}", lines.join("\n")));
    }
    Ok(())
}
