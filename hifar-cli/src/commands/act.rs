//! `hifar act`: deterministic actions of a checkpoint's deployable actor.
//!
//! The input is validated against the checkpoint's `checkpoint.json` before Python starts:
//! every observation row must have one value per `obs_names` entry, and an optional history
//! must be N × history_len × n_obs.

use std::path::Path;

use anyhow::{Context, Result};
use serde_json::{json, Value};

use crate::cli::ActArgs;
use crate::commands::facade::{python_failure, ActRequest, Request};
use crate::commands::setup;
use crate::{bad_input, checkpoint, paths};

pub fn run(args: &ActArgs) -> Result<()> {
    let meta = checkpoint::read_meta(&args.checkpoint)?;
    checkpoint::check_deployable(&args.checkpoint, &meta)?;
    let n_obs = meta.obs_names.len();
    let input = read_input(&args.input)?;
    let file = args.input.display();
    let Some(Value::Array(rows)) = input.get("obs") else {
        return Err(bad_input!("{file}: expected an object with \"obs\": [[...], ...]"));
    };
    if rows.is_empty() {
        return Err(bad_input!("{file}: \"obs\" has no rows"));
    }
    for (i, row) in rows.iter().enumerate() {
        let width = numeric_row(row).ok_or_else(|| bad_input!("{file}: obs[{i}] is not a list of numbers"))?;
        if width != n_obs {
            return Err(bad_input!(
                "{file}: obs[{i}] has {width} values, the checkpoint expects {n_obs} (its obs_names, from {} to {})",
                meta.obs_names.first().map(String::as_str).unwrap_or("-"),
                meta.obs_names.last().map(String::as_str).unwrap_or("-")
            ));
        }
    }
    let history = match input.get("history") {
        None | Some(Value::Null) => None,
        Some(history) => {
            check_history(history, rows.len(), meta.network.history_len as usize, n_obs).map_err(|message| bad_input!("{file}: history: {message}"))?;
            Some(history.clone())
        }
    };
    if let Some(key) = input.as_object().and_then(|m| m.keys().find(|k| *k != "obs" && *k != "history")) {
        return Err(bad_input!("{file}: unknown key {key:?} (expected \"obs\" and optionally \"history\")"));
    }

    let facade = setup::ensure_python()?;
    let checkpoint_dir = paths::absolute(args.checkpoint.clone());
    let request = ActRequest { checkpoint: checkpoint_dir, obs: rows.clone(), history };
    let actions = facade
        .call(ActRequest::FUNCTION, &[request.to_json()])
        .map_err(|err| python_failure("facade.act failed", err, &paths::command_log()))?;
    let out = json!({"action_names": meta.action_names, "actions": actions});
    println!("{}", serde_json::to_string(&out)?);
    Ok(())
}

fn read_input(path: &Path) -> Result<Value> {
    let text = std::fs::read_to_string(path)
        .map_err(|err| bad_input!("{}: cannot read: {err}", path.display()))
        .context("reading the act input")?;
    serde_json::from_str(&text).map_err(|err| {
        bad_input!("{}:{}:{}: invalid JSON: {err}", path.display(), err.line(), err.column())
    })
}

/// Length of a row of numbers, or None if it is not one.
fn numeric_row(row: &Value) -> Option<usize> {
    let row = row.as_array()?;
    row.iter().all(Value::is_number).then_some(row.len())
}

fn check_history(history: &Value, n_rows: usize, history_len: usize, n_obs: usize) -> Result<(), String> {
    let batches = history.as_array().ok_or("expected a list (N × history_len × n_obs)")?;
    if batches.len() != n_rows {
        return Err(format!("has {} entries, obs has {n_rows} rows (expected N × {history_len} × {n_obs})", batches.len()));
    }
    for (i, batch) in batches.iter().enumerate() {
        let rows = batch.as_array().ok_or_else(|| format!("history[{i}] is not a list"))?;
        if rows.len() != history_len {
            return Err(format!("history[{i}] has {} steps, the checkpoint's history_len is {history_len}", rows.len()));
        }
        for (t, row) in rows.iter().enumerate() {
            match numeric_row(row) {
                Some(width) if width == n_obs => {}
                Some(width) => return Err(format!("history[{i}][{t}] has {width} values, expected {n_obs}")),
                None => return Err(format!("history[{i}][{t}] is not a list of numbers")),
            }
        }
    }
    Ok(())
}
