//! Cross-stage network expansion (the paper's "zero-initialized fully-connected layers" on
//! the input and output of the trained network), done on the checkpoint files.
//!
//! Every tensor axis annotated in `checkpoint.json` is rebuilt for the target stage's name
//! lists: each old entry moves to the position of its name, new entries get the tensor's
//! `fill` (0 for first-layer weight columns, output rows, biases and optimizer moments; 1 for
//! normalizer std; ln(initial_action_std) for `policy/log_std`). With zero columns for the new
//! inputs and zero rows for the new outputs, the expanded actor computes exactly the old
//! actions for the old action names, whatever values the new features take.
//!
//! Refused: a feature of the checkpoint that the target lacks, a change of hidden sizes,
//! activation or RMA layout (when the target stage is known), a growing axis without a fill,
//! and a growing axis of a dtype we cannot fill.

use std::fmt;
use std::path::{Path, PathBuf};

use safetensors::Dtype;

use super::meta::{describe_segments, ActionMeta, Segment};
use super::{load, save, Checkpoint, CheckpointError, Tensor};
use crate::curriculum::{FeatureKind, FeatureNames, Stage};

/// What an expansion did.
#[derive(Debug, Clone, PartialEq)]
pub struct ExpandReport {
    pub source_stage: String,
    pub stage: String,
    pub out_dir: PathBuf,
    pub added_obs: Vec<String>,
    pub added_privileged: Vec<String>,
    pub added_actions: Vec<String>,
    /// Tensors whose shape changed (or whose entries moved).
    pub resized: Vec<String>,
    /// Tensors copied unchanged.
    pub unchanged: usize,
}

impl ExpandReport {
    pub fn added(&self, kind: FeatureKind) -> &[String] {
        match kind {
            FeatureKind::Obs => &self.added_obs,
            FeatureKind::Privileged => &self.added_privileged,
            FeatureKind::Action => &self.added_actions,
        }
    }
}

impl fmt::Display for ExpandReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "expanded stage {} into stage {}:", self.source_stage, self.stage)?;
        for (kind, label) in [(FeatureKind::Obs, "obs"), (FeatureKind::Privileged, "privileged"), (FeatureKind::Action, "actions")] {
            let added = self.added(kind);
            if added.is_empty() {
                write!(f, " +0 {label};")?;
            } else {
                write!(f, " +{} {label} ({});", added.len(), added.join(", "))?;
            }
        }
        write!(f, " {} tensors resized, {} unchanged -> {}", self.resized.len(), self.unchanged, self.out_dir.display())
    }
}

/// `checkpoint.json` key holding the stage table the checkpoint's features come from.
pub const STAGE_CONFIG_KEY: &str = "stage_config";

/// Expands the checkpoint in `src` for a stage with the feature names `target` and writes the
/// result to `out_dir` (which must not exist). `rollout_state` is not carried over: a new stage
/// starts fresh rollouts.
pub fn expand(
    src: &Path,
    target: &FeatureNames,
    stage_name: &str,
    log_initial_action_std: f64,
    out_dir: &Path,
) -> Result<ExpandReport, CheckpointError> {
    let mut checkpoint = load(src)?;
    // The source stage's table no longer describes the expanded checkpoint.
    checkpoint.meta.extra.remove(STAGE_CONFIG_KEY);
    expand_loaded(checkpoint, target, stage_name, log_initial_action_std, None, out_dir)
}

/// [`expand`] for a curriculum stage: also refuses a change of hidden sizes, activation or RMA
/// layout, and records the stage's action mapping in the expanded checkpoint.
pub fn expand_to_stage(src: &Path, stage: &Stage, out_dir: &Path) -> Result<ExpandReport, CheckpointError> {
    let mut checkpoint = load(src)?;
    // Evaluation, rollouts and export rebuild the environment from this table.
    checkpoint.meta.extra.insert(STAGE_CONFIG_KEY.to_owned(), stage.to_json());
    let incompatible = |message: String| CheckpointError::Incompatible {
        source_dir: src.to_path_buf(),
        stage: stage.name().to_owned(),
        message,
    };
    let network = &checkpoint.meta.network;
    let widen = |sizes: &[u32]| sizes.iter().map(|&n| u64::from(n)).collect::<Vec<u64>>();
    let mut differences = Vec::new();
    let mut compare = |what: &str, old: String, new: String| {
        if old != new {
            differences.push(format!("{what} {old} -> {new}"));
        }
    };
    compare("policy_hidden", format!("{:?}", network.policy_hidden), format!("{:?}", widen(&stage.ppo.policy_hidden)));
    compare("value_hidden", format!("{:?}", network.value_hidden), format!("{:?}", widen(&stage.ppo.value_hidden)));
    compare("activation", network.activation.clone(), stage.ppo.activation.as_str().to_owned());
    compare("rma", network.rma.to_string(), stage.rma.enabled.to_string());
    if network.rma && stage.rma.enabled {
        compare("latent_dim", network.latent_dim.to_string(), stage.rma.latent_dim.to_string());
        compare("encoder_hidden", format!("{:?}", network.encoder_hidden), format!("{:?}", widen(&stage.rma.encoder_hidden)));
        compare("history_len", network.history_len.to_string(), stage.rma.history_len.to_string());
    }
    if !differences.is_empty() {
        return Err(incompatible(format!(
            "the network differs ({}); expansion only adds input and output features, hidden layers must stay as they are",
            differences.join(", ")
        )));
    }
    let action = ActionMeta {
        mapping: stage.action.mapping.as_str().to_owned(),
        scale: stage.action.scale,
        clip: stage.action.clip,
        extra: checkpoint.meta.action.extra.clone(),
    };
    let features = stage.feature_names();
    expand_loaded(checkpoint, &features, stage.name(), stage.initial_action_std().ln(), Some(action), out_dir)
}

fn expand_loaded(
    mut checkpoint: Checkpoint,
    target: &FeatureNames,
    stage_name: &str,
    log_initial_action_std: f64,
    action: Option<ActionMeta>,
    out_dir: &Path,
) -> Result<ExpandReport, CheckpointError> {
    let src = checkpoint.dir.clone();
    let incompatible =
        |message: String| CheckpointError::Incompatible { source_dir: src.clone(), stage: stage_name.to_owned(), message };
    if out_dir.exists() {
        return Err(CheckpointError::Exists(out_dir.to_path_buf()));
    }

    // Names: the target must keep every old feature (positions may change).
    let mut removed = Vec::new();
    for kind in FeatureKind::ALL {
        let new = target.get(kind);
        if let Some(name) = duplicate(new) {
            return Err(incompatible(format!("the target's {}_names lists {name:?} twice", kind.as_str())));
        }
        let missing: Vec<&str> =
            checkpoint.meta.names(kind).iter().filter(|n| !new.contains(n)).map(String::as_str).collect();
        if !missing.is_empty() {
            removed.push(format!("{} {}", kind.as_str(), missing.join(", ")));
        }
    }
    if !removed.is_empty() {
        return Err(incompatible(format!(
            "features of stage {} missing from the target: {}; expansion can add features, never remove them",
            checkpoint.meta.stage,
            removed.join("; ")
        )));
    }
    let added = |kind: FeatureKind| -> Vec<String> {
        target.get(kind).iter().filter(|n| !checkpoint.meta.names(kind).contains(n)).cloned().collect()
    };
    let mut report = ExpandReport {
        source_stage: checkpoint.meta.stage.clone(),
        stage: stage_name.to_owned(),
        out_dir: out_dir.to_path_buf(),
        added_obs: added(FeatureKind::Obs),
        added_privileged: added(FeatureKind::Privileged),
        added_actions: added(FeatureKind::Action),
        resized: Vec::new(),
        unchanged: 0,
    };

    // Tensors: rebuild every annotated axis.
    let old_names = checkpoint.meta.feature_names();
    for (name, annotation) in checkpoint.meta.tensors.iter_mut() {
        let tensor = checkpoint.tensors.get_mut(name).expect("load() pairs every annotation with a tensor");
        let maps: Vec<AxisMap> = tensor
            .shape
            .iter()
            .enumerate()
            .map(|(axis, &size)| match annotation.axes.get(axis).and_then(Option::as_ref) {
                None => AxisMap::identity(size),
                Some(segments) => AxisMap::build(segments, &old_names, target),
            })
            .collect();
        if maps.iter().all(AxisMap::is_identity) {
            report.unchanged += 1;
            continue;
        }
        let fill = match &annotation.fill {
            Some(fill) => fill.value(log_initial_action_std).map_err(|m| incompatible(format!("tensor {name}: {m}")))?,
            None => {
                let axis = maps.iter().position(|m| !m.is_identity()).unwrap_or(0);
                return Err(incompatible(format!(
                    "tensor {name}: axis {axis} ({}) changes but the tensor has no \"fill\" for new entries",
                    describe_segments(annotation.axes[axis].as_deref().unwrap_or_default())
                )));
            }
        };
        *tensor = remap(tensor, &maps, fill).map_err(|m| incompatible(format!("tensor {name}: {m}")))?;
        annotation.shape = tensor.shape.clone();
        report.resized.push(name.clone());
    }

    checkpoint.meta.stage = stage_name.to_owned();
    checkpoint.meta.obs_names = target.obs_names.clone();
    checkpoint.meta.privileged_names = target.privileged_names.clone();
    checkpoint.meta.action_names = target.action_names.clone();
    if let Some(action) = action {
        checkpoint.meta.action = action;
    }
    save(out_dir, &checkpoint)?;
    Ok(report)
}

fn duplicate(names: &[String]) -> Option<&str> {
    let mut seen = std::collections::HashSet::new();
    names.iter().find(|n| !seen.insert(n.as_str())).map(String::as_str)
}

/// Where each old index of one axis goes, and the axis's new size.
#[derive(Debug, Clone, PartialEq)]
struct AxisMap {
    to: Vec<usize>,
    new_len: usize,
}

impl AxisMap {
    fn identity(size: usize) -> Self {
        AxisMap { to: (0..size).collect(), new_len: size }
    }

    fn is_identity(&self) -> bool {
        self.new_len == self.to.len() && self.to.iter().enumerate().all(|(i, &j)| i == j)
    }

    /// The map of an annotated axis. Old names are all in the target (checked before).
    fn build(segments: &[Segment], old: &FeatureNames, new: &FeatureNames) -> Self {
        let mut to = Vec::new();
        let mut new_offset = 0;
        for segment in segments {
            match *segment {
                Segment::Fixed(n) => {
                    to.extend(new_offset..new_offset + n);
                    new_offset += n;
                }
                Segment::Features(kind) => {
                    let target = new.get(kind);
                    for name in old.get(kind) {
                        let position = target.iter().position(|t| t == name).expect("checked: no feature removed");
                        to.push(new_offset + position);
                    }
                    new_offset += target.len();
                }
            }
        }
        AxisMap { to, new_len: new_offset }
    }
}

/// The little-endian bytes of `value` in `dtype`, for the dtypes a growing axis may have.
fn fill_bytes(dtype: Dtype, value: f64) -> Result<Vec<u8>, String> {
    let integral = || {
        if value.fract() == 0.0 && value.is_finite() {
            Ok(value)
        } else {
            Err(format!("fill {value} is not an integer, but the tensor is {dtype:?}"))
        }
    };
    Ok(match dtype {
        Dtype::F32 => (value as f32).to_le_bytes().to_vec(),
        Dtype::F64 => value.to_le_bytes().to_vec(),
        Dtype::I32 => (integral()? as i32).to_le_bytes().to_vec(),
        Dtype::I64 => (integral()? as i64).to_le_bytes().to_vec(),
        other => return Err(format!("an axis of a {other:?} tensor cannot grow (only F32, F64, I32 and I64 can)")),
    })
}

/// A new tensor with shape `maps[i].new_len`, filled with `fill`, old entries at their new
/// positions.
fn remap(tensor: &Tensor, maps: &[AxisMap], fill: f64) -> Result<Tensor, String> {
    let element = fill_bytes(tensor.dtype, fill)?;
    let width = element.len();
    let new_shape: Vec<usize> = maps.iter().map(|m| m.new_len).collect();
    let count: usize = new_shape.iter().product();
    let mut data = Vec::with_capacity(count * width);
    for _ in 0..count {
        data.extend_from_slice(&element);
    }
    // Row-major strides, in elements.
    let strides = |shape: &[usize]| -> Vec<usize> {
        let mut s = vec![1; shape.len()];
        for i in (0..shape.len().saturating_sub(1)).rev() {
            s[i] = s[i + 1] * shape[i + 1];
        }
        s
    };
    let old_strides = strides(&tensor.shape);
    let new_strides = strides(&new_shape);
    let old_count: usize = tensor.shape.iter().product();
    let mut index = vec![0usize; tensor.shape.len()];
    for old_flat in 0..old_count {
        let mut rest = old_flat;
        for axis in 0..index.len() {
            index[axis] = rest / old_strides[axis];
            rest %= old_strides[axis];
        }
        let new_flat: usize = index.iter().enumerate().map(|(axis, &i)| maps[axis].to[i] * new_strides[axis]).sum();
        data[new_flat * width..(new_flat + 1) * width].copy_from_slice(&tensor.data[old_flat * width..(old_flat + 1) * width]);
    }
    Ok(Tensor { dtype: tensor.dtype, shape: new_shape, data })
}
