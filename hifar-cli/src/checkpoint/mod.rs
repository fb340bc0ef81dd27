//! Checkpoint directories: `params.safetensors` + `checkpoint.json` (+ the learner's
//! `rollout_state.safetensors`, which only Python reads). See docs/contracts.md.
//!
//! [`read_meta`] reads the metadata, [`load`] the metadata and the tensors with every
//! consistency check, and [`expand`] rebuilds a checkpoint for a stage with more features.
//! Every failure is a [`CheckpointError`] with a one-line message.

pub mod expand;
pub mod meta;

use std::collections::{BTreeMap, HashMap};
use std::io;
use std::path::{Path, PathBuf};

use safetensors::{Dtype, SafeTensors, View};

pub use crate::curriculum::{FeatureKind, FeatureNames};
pub use expand::{expand, expand_to_stage, ExpandReport, STAGE_CONFIG_KEY};
pub use meta::{ActionMeta, CheckpointMeta, Fill, Network, Segment, TensorMeta, FORMAT_VERSION};

pub const META_FILE: &str = "checkpoint.json";
pub const PARAMS_FILE: &str = "params.safetensors";
pub const ROLLOUT_FILE: &str = "rollout_state.safetensors";

#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    #[error("{0}: no such checkpoint directory")]
    NotFound(PathBuf),
    #[error("{dir}: not a checkpoint directory (no {file})")]
    MissingFile { dir: PathBuf, file: &'static str },
    #[error("{path}: {error}")]
    Io { path: PathBuf, error: io::Error },
    #[error("{path}:{line}:{column}: corrupt checkpoint metadata: {message}")]
    CorruptMeta { path: PathBuf, line: usize, column: usize, message: String },
    #[error("{path}: corrupt safetensors file: {message}")]
    CorruptTensors { path: PathBuf, message: String },
    #[error("{path}: unsupported checkpoint format_version {found}; this hifar reads format_version {FORMAT_VERSION}")]
    FormatVersion { path: PathBuf, found: String },
    #[error("{path}: {message}")]
    Invalid { path: PathBuf, message: String },
    #[error("cannot expand {source_dir} into stage {stage}: {message}")]
    Incompatible { source_dir: PathBuf, stage: String, message: String },
    #[error("{0} already exists; expansion never overwrites a directory")]
    Exists(PathBuf),
    #[error(
        "{dir}: its RMA adaptation module was never trained ({why}); train with rma.adaptation_env_steps > 0 or evaluate a later checkpoint"
    )]
    UntrainedAdaptation { dir: PathBuf, why: String },
}

fn io_error(path: &Path) -> impl FnOnce(io::Error) -> CheckpointError + '_ {
    move |error| CheckpointError::Io { path: path.to_path_buf(), error }
}

/// One tensor, its bytes in safetensors' little-endian layout.
#[derive(Debug, Clone, PartialEq)]
pub struct Tensor {
    pub dtype: Dtype,
    pub shape: Vec<usize>,
    pub data: Vec<u8>,
}

impl Tensor {
    pub fn from_f32(shape: Vec<usize>, values: &[f32]) -> Self {
        assert_eq!(shape.iter().product::<usize>(), values.len(), "shape {shape:?} for {} values", values.len());
        Tensor { dtype: Dtype::F32, shape, data: values.iter().flat_map(|v| v.to_le_bytes()).collect() }
    }

    /// The values of a float32 tensor.
    pub fn to_f32(&self) -> Option<Vec<f32>> {
        (self.dtype == Dtype::F32)
            .then(|| self.data.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect())
    }
}

impl View for &Tensor {
    fn dtype(&self) -> Dtype {
        self.dtype
    }
    fn shape(&self) -> &[usize] {
        &self.shape
    }
    fn data(&self) -> std::borrow::Cow<'_, [u8]> {
        std::borrow::Cow::Borrowed(&self.data)
    }
    fn data_len(&self) -> usize {
        self.data.len()
    }
}

/// A checkpoint in memory: metadata, tensors by name, and the safetensors header metadata.
#[derive(Debug, Clone)]
pub struct Checkpoint {
    pub dir: PathBuf,
    pub meta: CheckpointMeta,
    pub tensors: BTreeMap<String, Tensor>,
    pub header: Option<HashMap<String, String>>,
}

fn require_dir(dir: &Path) -> Result<(), CheckpointError> {
    if !dir.is_dir() {
        return Err(CheckpointError::NotFound(dir.to_path_buf()));
    }
    Ok(())
}

/// Reads and checks `checkpoint.json` of a checkpoint directory.
pub fn read_meta(dir: &Path) -> Result<CheckpointMeta, CheckpointError> {
    require_dir(dir)?;
    let path = dir.join(META_FILE);
    if !path.is_file() {
        return Err(CheckpointError::MissingFile { dir: dir.to_path_buf(), file: META_FILE });
    }
    let text = std::fs::read_to_string(&path).map_err(io_error(&path))?;
    parse_meta(&path, &text)
}

/// Parses `checkpoint.json` text (`path` for messages).
pub fn parse_meta(path: &Path, text: &str) -> Result<CheckpointMeta, CheckpointError> {
    let corrupt = |err: serde_json::Error| CheckpointError::CorruptMeta {
        path: path.to_path_buf(),
        line: err.line(),
        column: err.column(),
        message: err.to_string().split(" at line ").next().unwrap_or_default().to_owned(),
    };
    let value: serde_json::Value = serde_json::from_str(text).map_err(corrupt)?;
    // The version first: a newer format may differ in any other key.
    match value.get("format_version") {
        Some(v) if v.as_u64() == Some(FORMAT_VERSION) => {}
        Some(v) => return Err(CheckpointError::FormatVersion { path: path.to_path_buf(), found: v.to_string() }),
        None => return Err(CheckpointError::FormatVersion { path: path.to_path_buf(), found: "(missing)".into() }),
    }
    let meta: CheckpointMeta = serde_json::from_str(text).map_err(corrupt)?;
    meta.check().map_err(|message| CheckpointError::Invalid { path: path.to_path_buf(), message })?;
    Ok(meta)
}

/// Refuses a checkpoint whose deployable actor would act with an RMA adaptation module that
/// never trained: `network.rma` is true but the `"learner"` section of `checkpoint.json` is
/// missing or counts `adaptation_env_steps == 0` (a stage that ended, or was stopped, before
/// its adaptation phase) — unless the stage trains the module beside PPO
/// (`rma.latent_regularization` > 0 in its `stage_config`) and PPO has run (`ppo_env_steps` >
/// 0). `act`, `eval`, `rollout` and `export` call this before Python starts; Python's
/// `evaluation.policy.check_adaptation_trained` applies the same rule.
pub fn check_deployable(dir: &Path, meta: &CheckpointMeta) -> Result<(), CheckpointError> {
    if !meta.network.rma {
        return Ok(());
    }
    let learner = meta.extra.get(LEARNER_KEY);
    let count = |key: &str| learner.and_then(|l| l.get(key)).and_then(serde_json::Value::as_u64);
    let online = meta
        .extra
        .get(STAGE_CONFIG_KEY)
        .and_then(|stage| stage.get("rma")?.get("latent_regularization")?.as_f64())
        .is_some_and(|weight| weight > 0.0);
    if online && count("ppo_env_steps").is_some_and(|steps| steps > 0) {
        return Ok(());
    }
    let steps = count("adaptation_env_steps");
    let why = match (learner, steps) {
        (_, Some(steps)) if steps > 0 => return Ok(()),
        (_, Some(_)) => format!("stage {} ended before its adaptation phase", meta.stage),
        (None, None) => format!("{META_FILE} has no \"{LEARNER_KEY}\" section recording an adaptation phase"),
        (Some(_), None) => format!("the \"{LEARNER_KEY}\" section of {META_FILE} records no adaptation_env_steps"),
    };
    Err(CheckpointError::UntrainedAdaptation { dir: dir.to_path_buf(), why })
}

/// `checkpoint.json` key of the learner's counters and budgets (phase, `ppo_env_steps`,
/// `adaptation_env_steps`, …), written by `jax_env/learner/train.py`.
pub const LEARNER_KEY: &str = "learner";

/// Reads a checkpoint: metadata and tensors, checking that every tensor has an annotation,
/// every annotation a tensor, and that their shapes agree.
pub fn load(dir: &Path) -> Result<Checkpoint, CheckpointError> {
    let meta = read_meta(dir)?;
    let path = dir.join(PARAMS_FILE);
    if !path.is_file() {
        return Err(CheckpointError::MissingFile { dir: dir.to_path_buf(), file: PARAMS_FILE });
    }
    let bytes = std::fs::read(&path).map_err(io_error(&path))?;
    let corrupt = |err: safetensors::SafeTensorError| CheckpointError::CorruptTensors { path: path.clone(), message: err.to_string() };
    let (_, header) = SafeTensors::read_metadata(&bytes).map_err(corrupt)?;
    let file = SafeTensors::deserialize(&bytes).map_err(corrupt)?;
    let invalid = |message: String| CheckpointError::Invalid { path: path.clone(), message };

    let mut tensors = BTreeMap::new();
    for (name, view) in file.tensors() {
        let Some(annotation) = meta.tensors.get(&name) else {
            return Err(invalid(format!("tensor {name} has no entry in {META_FILE}")));
        };
        if annotation.shape != view.shape() {
            return Err(invalid(format!(
                "tensor {name} has shape {:?} but {META_FILE} says {:?}",
                view.shape(),
                annotation.shape
            )));
        }
        tensors.insert(name, Tensor { dtype: view.dtype(), shape: view.shape().to_vec(), data: view.data().to_vec() });
    }
    if let Some(name) = meta.tensors.keys().find(|n| !tensors.contains_key(*n)) {
        return Err(invalid(format!("{META_FILE} describes tensor {name}, which is not in the file")));
    }
    Ok(Checkpoint { dir: dir.to_path_buf(), meta, tensors, header: header.metadata().clone() })
}

/// Writes `params.safetensors` and `checkpoint.json` into `dir` (an existing, empty
/// directory: [`crate::atomic::write_dir_atomic`] hands out such a one).
pub fn write_files(dir: &Path, checkpoint: &Checkpoint) -> Result<(), CheckpointError> {
    let params = dir.join(PARAMS_FILE);
    let bytes = safetensors::serialize(checkpoint.tensors.iter().map(|(n, t)| (n.as_str(), t)), checkpoint.header.clone())
        .map_err(|err| CheckpointError::CorruptTensors { path: params.clone(), message: err.to_string() })?;
    std::fs::write(&params, bytes).map_err(io_error(&params))?;
    let meta_path = dir.join(META_FILE);
    let mut text = serde_json::to_string_pretty(&checkpoint.meta).expect("checkpoint metadata is plain data");
    text.push('\n');
    std::fs::write(&meta_path, text).map_err(io_error(&meta_path))?;
    Ok(())
}

/// Writes a checkpoint directory atomically (a temporary sibling, fsynced, renamed into
/// place). Refuses to replace an existing directory.
pub fn save(dir: &Path, checkpoint: &Checkpoint) -> Result<(), CheckpointError> {
    /// The atomic writer's own I/O errors, told apart from those of writing the files.
    enum Failure {
        Io(io::Error),
        Checkpoint(CheckpointError),
    }
    impl From<io::Error> for Failure {
        fn from(err: io::Error) -> Self {
            Failure::Io(err)
        }
    }
    if dir.exists() {
        return Err(CheckpointError::Exists(dir.to_path_buf()));
    }
    crate::atomic::write_dir_atomic(dir, crate::atomic::IfExists::Refuse, |tmp| {
        write_files(tmp, checkpoint).map_err(Failure::Checkpoint)
    })
    .map_err(|failure| match failure {
        Failure::Io(error) if error.kind() == io::ErrorKind::AlreadyExists => CheckpointError::Exists(dir.to_path_buf()),
        Failure::Io(error) => CheckpointError::Io { path: dir.to_path_buf(), error },
        Failure::Checkpoint(err) => err,
    })
}

#[cfg(test)]
mod tests;
