//! `checkpoint.json`: what a checkpoint's tensors mean (docs/contracts.md, "Checkpoint
//! directory").
//!
//! The documented keys are required and typed; other keys are kept as they are (the learner
//! may record more), so reading and writing back loses nothing.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};
use serde_json::{Map, Value};

use crate::curriculum::{FeatureKind, FeatureNames};

/// The `format_version` this build reads and writes.
pub const FORMAT_VERSION: u64 = 1;

/// The fill value that stands for ln(target stage's `ppo.initial_action_std`).
pub const LOG_INITIAL_ACTION_STD: &str = "log_initial_action_std";

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CheckpointMeta {
    pub format_version: u64,
    pub stage: String,
    pub env_steps: u64,
    pub iteration: u64,
    pub seed: u64,
    pub prng_key: Vec<u64>,
    pub obs_names: Vec<String>,
    pub privileged_names: Vec<String>,
    pub action_names: Vec<String>,
    pub network: Network,
    pub action: ActionMeta,
    pub tensors: BTreeMap<String, TensorMeta>,
    #[serde(flatten)]
    pub extra: Map<String, Value>,
}

/// Hidden layer sizes and module switches: what expansion must keep unchanged.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Network {
    pub policy_hidden: Vec<u64>,
    pub value_hidden: Vec<u64>,
    pub activation: String,
    pub latent_dim: u64,
    pub encoder_hidden: Vec<u64>,
    pub history_len: u64,
    pub rma: bool,
    #[serde(flatten)]
    pub extra: Map<String, Value>,
}

/// How actions become joint targets (the stage's `[stage.action]`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ActionMeta {
    pub mapping: String,
    pub scale: f64,
    pub clip: f64,
    #[serde(flatten)]
    pub extra: Map<String, Value>,
}

/// The annotation of one tensor: its shape, what each axis indexes, and how new entries are
/// initialised when an axis grows.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TensorMeta {
    pub shape: Vec<usize>,
    /// One entry per axis: `None` for an axis that never changes size, else its segments.
    /// Absent means every axis is fixed.
    #[serde(default)]
    pub axes: Vec<Option<Vec<Segment>>>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fill: Option<Fill>,
    #[serde(flatten)]
    pub extra: Map<String, Value>,
}

/// A run of entries along an annotated axis.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase", deny_unknown_fields)]
pub enum Segment {
    /// One entry per name of that feature list, in order.
    Features(FeatureKind),
    /// `n` entries that never change (e.g. the RMA latent appended to the observations).
    Fixed(usize),
}

/// The value new entries get: a number, or `"log_initial_action_std"`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Fill {
    Number(f64),
    Named(String),
}

impl Fill {
    /// The number this fill stands for, given the target stage's ln(initial_action_std).
    pub fn value(&self, log_initial_action_std: f64) -> Result<f64, String> {
        match self {
            Fill::Number(x) => Ok(*x),
            Fill::Named(name) if name == LOG_INITIAL_ACTION_STD => Ok(log_initial_action_std),
            Fill::Named(name) => Err(format!("unknown fill {name:?}; expected a number or {LOG_INITIAL_ACTION_STD:?}")),
        }
    }
}

impl CheckpointMeta {
    pub fn feature_names(&self) -> FeatureNames {
        FeatureNames {
            obs_names: self.obs_names.clone(),
            privileged_names: self.privileged_names.clone(),
            action_names: self.action_names.clone(),
        }
    }

    pub fn names(&self, kind: FeatureKind) -> &[String] {
        match kind {
            FeatureKind::Obs => &self.obs_names,
            FeatureKind::Privileged => &self.privileged_names,
            FeatureKind::Action => &self.action_names,
        }
    }

    /// Checks that the metadata agrees with itself: unique names, one axis annotation per
    /// dimension, annotated axes as long as their segments, valid fills.
    pub fn check(&self) -> Result<(), String> {
        for kind in FeatureKind::ALL {
            if let Some(name) = first_duplicate(self.names(kind)) {
                return Err(format!("{}_names lists {name:?} twice", kind.as_str()));
            }
        }
        for (name, tensor) in &self.tensors {
            if tensor.axes.is_empty() {
                continue;
            }
            if tensor.axes.len() != tensor.shape.len() {
                return Err(format!(
                    "tensor {name}: {} axis annotations for shape {:?} ({} axes)",
                    tensor.axes.len(),
                    tensor.shape,
                    tensor.shape.len()
                ));
            }
            for (axis, segments) in tensor.axes.iter().enumerate() {
                let Some(segments) = segments else { continue };
                let covered: usize = segments.iter().map(|s| self.segment_len(*s)).sum();
                if covered != tensor.shape[axis] {
                    return Err(format!(
                        "tensor {name}: axis {axis} has size {} but its annotation {} covers {covered} entries",
                        tensor.shape[axis],
                        describe_segments(segments)
                    ));
                }
            }
            if let Some(fill) = &tensor.fill {
                fill.value(0.0).map_err(|message| format!("tensor {name}: {message}"))?;
            }
        }
        Ok(())
    }

    /// Entries a segment covers under this checkpoint's name lists.
    pub fn segment_len(&self, segment: Segment) -> usize {
        match segment {
            Segment::Features(kind) => self.names(kind).len(),
            Segment::Fixed(n) => n,
        }
    }
}

pub fn describe_segments(segments: &[Segment]) -> String {
    let parts: Vec<String> = segments
        .iter()
        .map(|s| match s {
            Segment::Features(kind) => format!("{}_names", kind.as_str()),
            Segment::Fixed(n) => format!("fixed {n}"),
        })
        .collect();
    format!("[{}]", parts.join(" + "))
}

fn first_duplicate(names: &[String]) -> Option<&str> {
    let mut seen = std::collections::HashSet::new();
    names.iter().find(|n| !seen.insert(n.as_str())).map(String::as_str)
}
