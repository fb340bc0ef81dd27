//! `hifar export`: a checkpoint's deployable actor as an ONNX file, checked against `hifar act`.
//!
//! Everything that can be checked without Python is checked first (the target, the output's
//! directory, an existing output without `--force`), so a mistake exits 2 at once. Python
//! (`facade.export_onnx`) builds the graph, runs onnxruntime against the JAX actor and writes
//! the file atomically only when they agree.

use std::path::{Path, PathBuf};

use anyhow::Result;
use serde_json::Value;

use crate::checkpoint::CheckpointMeta;
use crate::cli::ExportArgs;
use crate::commands::facade::{python_failure, ExportRequest, Request};
use crate::commands::{setup, target};
use crate::ui::Status;
use crate::{bad_input, paths};

/// Largest accepted difference between onnxruntime and the JAX actor (docs/contracts.md).
pub const TOLERANCE: f64 = 1e-5;

/// A validated export: what to read, what to write.
#[derive(Debug)]
pub struct ExportPlan {
    pub checkpoint: PathBuf,
    pub meta: CheckpointMeta,
    /// The run's resolved stage table when the target was a run directory.
    pub stage: Option<Value>,
    pub out: PathBuf,
}

impl ExportPlan {
    pub fn new(args: &ExportArgs) -> Result<ExportPlan> {
        let policy = target::resolve(&args.target)?;
        let out = paths::absolute(args.onnx.clone());
        check_output(&args.onnx, &out, args.force)?;
        Ok(ExportPlan { checkpoint: policy.checkpoint, meta: policy.meta, stage: policy.stage, out })
    }

    pub fn request(&self) -> ExportRequest {
        ExportRequest { checkpoint: self.checkpoint.clone(), out: self.out.clone(), tolerance: TOLERANCE, stage: self.stage.clone() }
    }
}

fn check_output(given: &Path, out: &Path, force: bool) -> Result<()> {
    let shown = given.display();
    if out.is_dir() {
        return Err(bad_input!("{shown}: is a directory; --onnx takes the path of the file to write"));
    }
    match out.parent() {
        Some(parent) if parent.is_dir() => {}
        Some(parent) => return Err(bad_input!("{shown}: the directory {} does not exist (create it first)", parent.display())),
        None => return Err(bad_input!("{shown}: not a file path")),
    }
    if out.exists() && !force {
        return Err(bad_input!("{shown}: already exists (pass --force to replace it)"));
    }
    Ok(())
}

pub fn run(args: &ExportArgs) -> Result<()> {
    let plan = ExportPlan::new(args)?;
    let status = Status::start("export");
    status.step("starting Python");
    let facade = setup::ensure_python()?;
    status.step("building the ONNX graph and checking it against the JAX actor with onnxruntime");
    let result = facade
        .call(ExportRequest::FUNCTION, &[plan.request().to_json()])
        .map_err(|err| python_failure("facade.export_onnx failed", err, &paths::command_log()))?;
    status.finish("export: onnxruntime agrees with the JAX actor");
    println!("{}", summary(&plan, &result));
    Ok(())
}

/// What the command prints: the file, its inputs and outputs, and the parity numbers.
pub fn summary(plan: &ExportPlan, result: &Value) -> String {
    let ignored = result["history_input"] == "ignored";
    let tensors = |key: &str| -> String {
        let list = result[key].as_array().map(Vec::as_slice).unwrap_or_default();
        list.iter()
            .map(|t| {
                let name = t["name"].as_str().unwrap_or("?");
                let dims: Vec<String> =
                    t["shape"].as_array().map(Vec::as_slice).unwrap_or_default().iter().map(|d| d.as_str().map_or_else(|| d.to_string(), str::to_owned)).collect();
                let note = if name == "history" && ignored { " (ignored: no adaptation module)" } else { "" };
                format!("{name} [{}]{note}", dims.join(", "))
            })
            .collect::<Vec<_>>()
            .join(", ")
    };
    let number = |key: &str| result[key].as_f64().map_or_else(|| "?".to_owned(), |x| format!("{x:.2e}"));
    format!(
        "wrote {} (ONNX opset {}; stage {}, {} env steps)\n  inputs:  {}\n  outputs: {}\n  parity with `hifar act` over {} rows: max |onnx - jax| {} (scaled {}, tolerance {TOLERANCE:.0e}); joint_target max diff {}",
        result["path"].as_str().map_or_else(|| plan.out.display().to_string(), str::to_owned),
        result["opset"],
        plan.meta.stage,
        plan.meta.env_steps,
        tensors("inputs"),
        tensors("outputs"),
        result["parity_rows"],
        number("parity_max_abs_diff"),
        number("parity_max_scaled_diff"),
        number("joint_target_max_abs_diff"),
    )
}
