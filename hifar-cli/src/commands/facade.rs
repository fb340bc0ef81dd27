//! Calling `jax_env.facade` from a command: the typed requests, Python failures as one-line
//! errors whose traceback goes to a log, and the questions several commands ask Python.
//!
//! Each request is a serde struct with the fields of its dataclass in
//! `jax_env/facade_requests.py`, in the same order (docs/contracts.md, "The facade"). Python
//! checks every request it receives against that dataclass (unknown keys and missing required
//! ones are errors), and the test `facade_requests_match_the_python_dataclasses` compares the
//! two field lists, so neither side keeps a list of keys by hand.

use std::path::{Path, PathBuf};

use anyhow::{anyhow, Result};
use serde::Serialize;
use serde_json::Value;

use crate::python::{Facade, PythonError};

/// The physics backend `backend = "auto"` means on this machine (`facade.doctor()`).
pub fn default_backend(facade: &Facade, log: &Path) -> Result<String> {
    default_backend_and_reason(facade, log).map(|(backend, _)| backend)
}

/// [`default_backend`], and why `facade.doctor()` chose it.
pub fn default_backend_and_reason(facade: &Facade, log: &Path) -> Result<(String, String)> {
    let report = facade.call("doctor", &[]).map_err(|err| python_failure("facade.doctor() failed", err, log))?;
    let backend = report
        .get("default_backend")
        .and_then(Value::as_str)
        .map(str::to_owned)
        .ok_or_else(|| anyhow!("facade.doctor() returned no default_backend: {report}"))?;
    let reason = report.get("reason").and_then(Value::as_str).unwrap_or("auto").to_owned();
    Ok((backend, reason))
}

/// Turns a Python exception into a one-line error, its traceback appended to `log`.
pub fn python_failure(context: &str, err: PythonError, log: &Path) -> anyhow::Error {
    match err.write_traceback(log) {
        Ok(()) => anyhow!("{context}: {} (traceback in {})", err.summary, log.display()),
        Err(_) => anyhow!("{context}: {}", err.summary),
    }
}

/// A request of one `jax_env.facade` function.
pub trait Request: Serialize {
    /// The facade function that takes it.
    const FUNCTION: &'static str;

    /// The request as the JSON-like dict Python receives.
    fn to_json(&self) -> Value {
        serde_json::to_value(self).expect("requests are plain data")
    }
}

/// `facade.train_stage`: one stage of a run.
#[derive(Debug, Clone, Default, Serialize)]
pub struct TrainRequest {
    /// The stage table, exactly the keys of the curriculum file.
    pub stage: Value,
    pub stage_name: String,
    pub stage_dir: PathBuf,
    /// The stage seed.
    pub seed: u64,
    /// "mjx" | "native" ("auto" is resolved before).
    pub backend: String,
    /// `--num-envs`, overriding the stage's `ppo.num_envs`.
    pub num_envs: Option<u32>,
    /// Start from these weights (the previous stage's, expanded), fresh optimizer counters.
    pub init_checkpoint: Option<PathBuf>,
    /// Continue exactly from this checkpoint.
    pub resume_checkpoint: Option<PathBuf>,
    pub log_file: PathBuf,
}

impl Request for TrainRequest {
    const FUNCTION: &'static str = "train_stage";
}

/// `facade.evaluate`: one evaluation protocol on a checkpoint.
#[derive(Debug, Clone, Default, Serialize)]
pub struct EvaluateRequest {
    pub checkpoint: PathBuf,
    /// The run's stage table (None: the checkpoint's own `stage_config`).
    pub stage: Option<Value>,
    pub protocol: String,
    /// None: the protocol's default.
    pub trials: Option<u32>,
    pub backend: String,
    /// None: the deployable actor.
    pub actor: Option<String>,
    pub seed: u64,
    pub out_dir: PathBuf,
    /// None: the backend's default batch.
    pub batch_size: Option<u32>,
}

impl Request for EvaluateRequest {
    const FUNCTION: &'static str = "evaluate";
}

/// `facade.rollout`: one recorded episode.
#[derive(Debug, Clone, Default, Serialize)]
pub struct RolloutRequest {
    pub checkpoint: PathBuf,
    pub stage: Option<Value>,
    pub scenario: String,
    pub terrain: String,
    pub push_force: Option<f64>,
    /// None: Python's default for the scenario (the result says which it used).
    pub push_direction: Option<String>,
    pub seed: u64,
    pub backend: String,
    /// None: the stage's episode length.
    pub duration_s: Option<f64>,
    pub video: Option<PathBuf>,
    pub filmstrip: Option<PathBuf>,
}

impl Request for RolloutRequest {
    const FUNCTION: &'static str = "rollout";
}

/// `facade.report`: plots and report.md of a run.
#[derive(Debug, Clone, Default, Serialize)]
pub struct ReportRequest {
    pub run: PathBuf,
    pub out_dir: PathBuf,
}

impl Request for ReportRequest {
    const FUNCTION: &'static str = "report";
}

/// `facade.export_onnx`: the deployable actor as ONNX, checked against `act`.
#[derive(Debug, Clone, Default, Serialize)]
pub struct ExportRequest {
    pub checkpoint: PathBuf,
    pub out: PathBuf,
    /// Parity tolerance of onnxruntime against the JAX actor.
    pub tolerance: f64,
    pub stage: Option<Value>,
}

impl Request for ExportRequest {
    const FUNCTION: &'static str = "export_onnx";
}

/// `facade.act`: deterministic actions of a checkpoint's deployable actor.
#[derive(Debug, Clone, Default, Serialize)]
pub struct ActRequest {
    pub checkpoint: PathBuf,
    /// Observation rows [N][n_obs], in the checkpoint's `obs_names` order.
    pub obs: Vec<Value>,
    /// [N][history_len][n_obs], oldest first (None: zeros).
    pub history: Option<Value>,
}

impl Request for ActRequest {
    const FUNCTION: &'static str = "act";
}

/// The field names of every request, by facade function, in declaration order (compared with
/// the Python dataclasses by a test).
pub fn request_fields() -> Vec<(&'static str, Vec<String>)> {
    fn fields<R: Request + Default>() -> (&'static str, Vec<String>) {
        let keys = match R::default().to_json() {
            Value::Object(map) => map.keys().cloned().collect(),
            other => panic!("{} serializes to {other}, not a dict", R::FUNCTION),
        };
        (R::FUNCTION, keys)
    }
    vec![
        fields::<TrainRequest>(),
        fields::<EvaluateRequest>(),
        fields::<RolloutRequest>(),
        fields::<ReportRequest>(),
        fields::<ExportRequest>(),
        fields::<ActRequest>(),
    ]
}
