//! Checks on a typed curriculum that the types alone do not express and that belong to the
//! experiment rather than to one stage: plain names, unique stage names, references between
//! stages (`init_from`) and whether a stage can be expanded from the one it starts from. What a
//! stage means (ranges, mixtures that sum to 1, relations between its keys, symmetric joint
//! lists) is checked by Python, `jax_env/config.py` (`facade.check_stage`), alone; here remain
//! joint names (a vocabulary) and numbers JSON cannot carry to Python (NaN, infinities).
//!
//! Every check reports a key path and whether the key or the value is at fault; the caller
//! maps paths to `LINE:COL`. All problems are collected (in file order after sorting), so one
//! run of `hifar check` shows every mistake.

use super::schema::{CurriculumFile, StageTable};
use super::span::{PathSegment, Target};
use crate::names::{self, names};

/// A problem found by validation, before it is given a position.
#[derive(Debug, Clone)]
pub struct Finding {
    pub path: Vec<PathSegment>,
    pub target: Target,
    pub message: String,
}

/// Where a stage's weights come from, resolved from `init_from`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum InitSource {
    Fresh,
    Stage(usize),
}

#[derive(Default)]
struct Findings(Vec<Finding>);

impl Findings {
    fn push(&mut self, path: Vec<PathSegment>, target: Target, message: impl Into<String>) {
        self.0.push(Finding { path, target, message: message.into() });
    }
}

/// `[A-Za-z0-9_-]+`: names that become directory names.
pub fn is_plain_name(name: &str) -> bool {
    !name.is_empty() && name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
}

/// Checks the whole file (`document` is its TOML, for the numbers); returns the findings and
/// each stage's resolved init source (valid only where no finding concerns that stage's
/// `init_from`).
pub fn validate(file: &CurriculumFile, document: &toml::Table) -> (Vec<Finding>, Vec<InitSource>) {
    let mut f = Findings::default();
    for (key, value) in document {
        finite_numbers(&mut f, value, &mut vec![PathSegment::from(key.as_str())]);
    }
    if !is_plain_name(&file.name) {
        f.push(vec!["name".into()], Target::Value, format!("curriculum name {:?} must match [A-Za-z0-9_-]+", file.name));
    }
    if file.stage.is_empty() {
        f.push(vec!["stage".into()], Target::Key, "a curriculum needs at least one [[stage]]");
    }
    let mut seen: Vec<&str> = Vec::new();
    for (i, stage) in file.stage.iter().enumerate() {
        let p = |keys: &[&str]| -> Vec<PathSegment> {
            let mut path = vec![PathSegment::from("stage"), PathSegment::Index(i)];
            path.extend(keys.iter().map(|k| PathSegment::from(*k)));
            path
        };
        if !is_plain_name(&stage.name) {
            f.push(p(&["name"]), Target::Value, format!("stage name {:?} must match [A-Za-z0-9_-]+", stage.name));
        } else if let Some(first) = seen.iter().position(|n| *n == stage.name) {
            f.push(
                p(&["name"]),
                Target::Value,
                format!("duplicate stage name {:?} (stage {} has it too); stage names must be unique", stage.name, first + 1),
            );
        }
        seen.push(&stage.name);
        validate_stage(&mut f, stage, &p);
    }
    let sources = resolve_init(&mut f, file);
    for (i, source) in sources.iter().enumerate() {
        if let InitSource::Stage(from) = *source {
            check_compatible(&mut f, file, from, i);
        }
    }
    (f.0, sources)
}

fn resolve_init(f: &mut Findings, file: &CurriculumFile) -> Vec<InitSource> {
    let names: Vec<&str> = file.stage.iter().map(|s| s.name.as_str()).collect();
    let listing = names.join(", ");
    let mut sources = Vec::new();
    for (i, stage) in file.stage.iter().enumerate() {
        let path = vec![PathSegment::from("stage"), PathSegment::Index(i), PathSegment::from("init_from")];
        let source = match stage.init_from.as_str() {
            "none" => InitSource::Fresh,
            "previous" if i == 0 => {
                f.push(path, Target::Value, "init_from = \"previous\" in the first stage: there is no previous stage; use \"none\"");
                InitSource::Fresh
            }
            "previous" => InitSource::Stage(i - 1),
            name => match names.iter().position(|n| *n == name) {
                Some(j) if j == i => {
                    f.push(path, Target::Value, format!("stage {name:?} cannot start from itself; init_from names an earlier stage"));
                    InitSource::Fresh
                }
                Some(j) if j > i => {
                    f.push(
                        path,
                        Target::Value,
                        format!(
                            "init_from = {name:?} names a later stage (stage {} of {}); a stage can only start from an earlier one",
                            j + 1,
                            names.len()
                        ),
                    );
                    InitSource::Fresh
                }
                Some(j) => InitSource::Stage(j),
                None => {
                    f.push(
                        path,
                        Target::Value,
                        format!("init_from = {name:?}: no stage has that name; expected \"none\", \"previous\" or one of: {listing}"),
                    );
                    InitSource::Fresh
                }
            },
        };
        sources.push(source);
    }
    sources
}

/// Expansion can add features but never remove them or change hidden layers; say so now
/// rather than after the first stage has trained for hours.
fn check_compatible(f: &mut Findings, file: &CurriculumFile, from: usize, to: usize) {
    let (a, b) = (&file.stage[from], &file.stage[to]);
    let path = |keys: &[&str]| -> Vec<PathSegment> {
        let mut p = vec![PathSegment::from("stage"), PathSegment::Index(to)];
        p.extend(keys.iter().map(|k| PathSegment::from(*k)));
        p
    };
    for key in ["controlled_joints", "observed_joints"] {
        let (old, new) = match key {
            "controlled_joints" => (&a.controlled_joints, &b.controlled_joints),
            _ => (&a.observed_joints, &b.observed_joints),
        };
        let dropped: Vec<&str> = old.iter().filter(|j| !new.contains(j)).map(String::as_str).collect();
        if !dropped.is_empty() {
            f.push(
                path(&[key]),
                Target::Key,
                format!(
                    "stage {:?} starts from stage {:?} but drops {key} {}; expansion can only add joints",
                    b.name,
                    a.name,
                    dropped.join(", ")
                ),
            );
        }
    }
    let mut differ = |keys: &[&str], what: &str, old: String, new: String| {
        if old != new {
            f.push(
                path(keys),
                Target::Value,
                format!(
                    "{what} {new} differs from {old} in stage {:?}, which this stage starts from; expansion keeps hidden layers as they are",
                    a.name
                ),
            );
        }
    };
    differ(&["ppo", "policy_hidden"], "policy_hidden", format!("{:?}", a.ppo.policy_hidden), format!("{:?}", b.ppo.policy_hidden));
    differ(&["ppo", "value_hidden"], "value_hidden", format!("{:?}", a.ppo.value_hidden), format!("{:?}", b.ppo.value_hidden));
    differ(&["ppo", "activation"], "activation", format!("{:?}", a.ppo.activation.as_str()), format!("{:?}", b.ppo.activation.as_str()));
    differ(&["rma", "enabled"], "rma.enabled", a.rma.enabled.to_string(), b.rma.enabled.to_string());
    if a.rma.enabled && b.rma.enabled {
        differ(&["rma", "latent_dim"], "latent_dim", a.rma.latent_dim.to_string(), b.rma.latent_dim.to_string());
        differ(&["rma", "encoder_hidden"], "encoder_hidden", format!("{:?}", a.rma.encoder_hidden), format!("{:?}", b.rma.encoder_hidden));
        differ(&["rma", "history_len"], "history_len", a.rma.history_len.to_string(), b.rma.history_len.to_string());
    }
}

/// Names of joints are a vocabulary like the others the schema checks (what the lists must
/// hold besides, Python checks).
fn validate_stage(f: &mut Findings, s: &StageTable, p: &dyn Fn(&[&str]) -> Vec<PathSegment>) {
    for (key, joints) in [("controlled_joints", &s.controlled_joints), ("observed_joints", &s.observed_joints)] {
        for (i, joint) in joints.iter().enumerate() {
            if names::joint_index(joint).is_none() {
                let mut path = p(&[key]);
                path.push(PathSegment::Index(i));
                f.push(path, Target::Value, format!("unknown joint {joint:?}; valid joints: {}", names().joints.join(", ")));
            }
        }
    }
}

/// Numbers the stage tables cannot carry to Python: they cross as JSON, which has no NaN and no
/// infinities, so these are refused here, in the words the checks of those keys use.
fn finite_numbers(f: &mut Findings, value: &toml::Value, path: &mut Vec<PathSegment>) {
    let key = |path: &[PathSegment], back: usize| match path.len().checked_sub(back + 1).map(|i| &path[i]) {
        Some(PathSegment::Key(k)) => k.clone(),
        _ => String::new(),
    };
    match value {
        toml::Value::Float(v) if !v.is_finite() => {
            let name = key(path, 0);
            let message = match key(path, 1).as_str() {
                "rewards" if path.len() == 4 => format!("reward weight {name} = {v} must be a finite number"),
                table @ ("scenarios" | "terrain") if path.len() == 4 && name != "slope_max_deg" => {
                    format!("{} weight {name} = {v} must be a finite number >= 0", table.trim_end_matches('s'))
                }
                _ => format!("{name} = {v} must be a finite number"),
            };
            f.push(path.clone(), Target::Value, message);
        }
        toml::Value::Array(items) => {
            let floats: Vec<f64> = items.iter().filter_map(toml::Value::as_float).collect();
            let pair = floats.len() == 2 && items.len() == 2;
            let (name, parent) = (key(path, 0), key(path, 1));
            if pair && floats.iter().any(|v| !v.is_finite()) && (name == "range" || name == "interval_s") {
                let [a, b] = [floats[0], floats[1]];
                let message = if name == "range" {
                    format!("{parent}.range = [{a}, {b}] must hold finite numbers")
                } else {
                    format!("interval_s = [{a}, {b}]: both must be finite and the min > 0")
                };
                f.push(path.clone(), Target::Value, message);
                return;
            }
            for (i, item) in items.iter().enumerate() {
                path.push(PathSegment::Index(i));
                finite_numbers(f, item, path);
                path.pop();
            }
        }
        toml::Value::Table(table) => {
            for (k, item) in table {
                path.push(PathSegment::from(k.as_str()));
                finite_numbers(f, item, path);
                path.pop();
            }
        }
        _ => {}
    }
}

/// Why `num_envs` cannot be split into `num_minibatches` equal minibatches, if it cannot.
pub fn minibatch_problem(num_envs: u32, num_minibatches: u32) -> Option<String> {
    if num_minibatches > 0 && !num_envs.is_multiple_of(num_minibatches) {
        Some(format!(
            "num_envs = {num_envs} is not divisible by num_minibatches = {num_minibatches} (each minibatch takes whole environments)"
        ))
    } else {
        None
    }
}
