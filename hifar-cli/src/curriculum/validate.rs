//! Checks on a typed curriculum that the types alone do not express: ranges, sums, relations
//! between keys, joint names, and references between stages.
//!
//! Every check reports a key path and whether the key or the value is at fault; the caller
//! maps paths to `LINE:COL`. All problems are collected (in file order after sorting), so one
//! run of `hifar check` shows every mistake.

use std::collections::HashSet;

use super::schema::{CurriculumFile, StageTable};
use super::span::{PathSegment, Target};
use crate::names::{self, names};

/// Tolerance on mixture weights summing to 1 (docs/contracts.md).
pub const SUM_TOLERANCE: f64 = 1e-6;

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

/// Checks the whole file; returns the findings and each stage's resolved init source (valid
/// only where no finding concerns that stage's `init_from`).
pub fn validate(file: &CurriculumFile) -> (Vec<Finding>, Vec<InitSource>) {
    let mut f = Findings::default();
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

struct Check<'a, 'p> {
    f: &'a mut Findings,
    p: &'p dyn Fn(&[&str]) -> Vec<PathSegment>,
}

impl Check<'_, '_> {
    fn err(&mut self, keys: &[&str], message: impl Into<String>) {
        let path = (self.p)(keys);
        self.f.push(path, Target::Value, message);
    }

    fn err_key(&mut self, keys: &[&str], message: impl Into<String>) {
        let path = (self.p)(keys);
        self.f.push(path, Target::Key, message);
    }

    /// Finite and > 0. Returns whether it passed.
    fn positive(&mut self, keys: &[&str], v: f64) -> bool {
        self.range(keys, v, Bound::Open(0.0), None)
    }

    fn non_negative(&mut self, keys: &[&str], v: f64) -> bool {
        self.range(keys, v, Bound::Closed(0.0), None)
    }

    fn range(&mut self, keys: &[&str], v: f64, low: Bound, high: Option<f64>) -> bool {
        let name = keys.last().copied().unwrap_or("value");
        if !v.is_finite() {
            self.err(keys, format!("{name} = {v} must be a finite number"));
            return false;
        }
        let ok_low = match low {
            Bound::Open(x) => v > x,
            Bound::Closed(x) => v >= x,
            Bound::None => true,
        };
        if !ok_low {
            let (op, x) = match low {
                Bound::Open(x) => (">", x),
                Bound::Closed(x) => (">=", x),
                Bound::None => unreachable!(),
            };
            match high {
                Some(h) => self.err(keys, format!("{name} = {v} is out of range; expected {op} {x} and <= {h}")),
                None => self.err(keys, format!("{name} = {v} is out of range; expected {op} {x}")),
            }
            return false;
        }
        if let Some(h) = high {
            if v > h {
                let low_text = match low {
                    Bound::Open(x) => format!("> {x} and "),
                    Bound::Closed(x) => format!(">= {x} and "),
                    Bound::None => String::new(),
                };
                self.err(keys, format!("{name} = {v} is out of range; expected {low_text}<= {h}"));
                return false;
            }
        }
        true
    }

    fn positive_int(&mut self, keys: &[&str], v: u64) -> bool {
        if v == 0 {
            let name = keys.last().copied().unwrap_or("value");
            self.err(keys, format!("{name} = 0 is out of range; expected a positive integer"));
            return false;
        }
        true
    }

    fn layers(&mut self, keys: &[&str], sizes: &[u32]) {
        let name = keys.last().copied().unwrap_or("value");
        if sizes.is_empty() {
            self.err(keys, format!("{name} is empty; expected at least one hidden layer size"));
        }
        for (i, &n) in sizes.iter().enumerate() {
            if n == 0 {
                let mut path = (self.p)(keys);
                path.push(PathSegment::Index(i));
                self.f.push(path, Target::Value, format!("{name}[{i}] = 0; layer sizes must be positive"));
            }
        }
    }

    /// Mixture weights: each finite and >= 0, summing to 1.
    fn mixture(&mut self, table: &str, what: &str, weights: &[(&str, f64)]) {
        let mut ok = true;
        for (name, w) in weights {
            if !w.is_finite() || *w < 0.0 {
                self.err(&[table, name], format!("{what} weight {name} = {w} must be a finite number >= 0"));
                ok = false;
            }
        }
        if !ok {
            return;
        }
        let total: f64 = weights.iter().map(|(_, w)| w).sum();
        if (total - 1.0).abs() > SUM_TOLERANCE {
            let parts: Vec<String> = weights.iter().filter(|(_, w)| *w != 0.0).map(|(n, w)| format!("{n} = {w}")).collect();
            let parts = if parts.is_empty() { "nothing".to_owned() } else { parts.join(" + ") };
            self.err_key(&[table], format!("{what} weights must sum to 1, got {total} ({parts})"));
        }
    }

    fn joints(&mut self, key: &str, joints: &[String]) -> bool {
        if joints.is_empty() {
            self.err(&[key], format!("{key} is empty; expected a list of joint names"));
            return false;
        }
        let mut ok = true;
        let mut seen = HashSet::new();
        for (i, joint) in joints.iter().enumerate() {
            let mut path = (self.p)(&[key]);
            path.push(PathSegment::Index(i));
            if names::joint_index(joint).is_none() {
                self.f.push(path, Target::Value, format!("unknown joint {joint:?}; valid joints: {}", names().joints.join(", ")));
                ok = false;
            } else if !seen.insert(joint.as_str()) {
                self.f.push(path, Target::Value, format!("joint {joint:?} is listed twice in {key}"));
                ok = false;
            }
        }
        if !ok {
            return false;
        }
        // The mirror loss permutes features within a list, so lists must be left/right symmetric.
        let missing: Vec<String> = joints
            .iter()
            .filter_map(|j| names::mirror_joint(j).filter(|m| !seen.contains(m)).map(|m| format!("{m} (mirror of {j})")))
            .collect();
        if !missing.is_empty() {
            self.err_key(&[key], format!("{key} must be left/right symmetric for the mirror loss; missing {}", missing.join(", ")));
            return false;
        }
        true
    }
}

#[derive(Clone, Copy)]
enum Bound {
    Open(f64),
    Closed(f64),
    None,
}

fn validate_stage(f: &mut Findings, s: &StageTable, p: &dyn Fn(&[&str]) -> Vec<PathSegment>) {
    let mut c = Check { f, p };

    let controlled_ok = c.joints("controlled_joints", &s.controlled_joints);
    let observed_ok = c.joints("observed_joints", &s.observed_joints);
    if controlled_ok && observed_ok {
        let missing: Vec<&str> =
            s.controlled_joints.iter().filter(|j| !s.observed_joints.contains(j)).map(String::as_str).collect();
        if !missing.is_empty() {
            c.err_key(
                &["observed_joints"],
                format!("observed_joints must include every controlled joint; missing {}", missing.join(", ")),
            );
        }
    }

    // [stage.sim]
    let ts = c.positive(&["sim", "timestep"], s.sim.timestep);
    let dt = c.positive(&["sim", "ctrl_dt"], s.sim.ctrl_dt);
    let mut dt_ok = ts && dt;
    if dt_ok {
        let ratio = s.sim.ctrl_dt / s.sim.timestep;
        if ratio < 1.0 - 1e-9 || (ratio - ratio.round()).abs() > 1e-6 {
            c.err(
                &["sim", "ctrl_dt"],
                format!("ctrl_dt = {} must be an integer multiple of timestep = {} (ratio {ratio})", s.sim.ctrl_dt, s.sim.timestep),
            );
            dt_ok = false;
        }
    }
    let episode_ok = c.positive(&["sim", "episode_s"], s.sim.episode_s);
    if dt_ok && episode_ok && s.sim.episode_s <= s.sim.ctrl_dt {
        c.err(&["sim", "episode_s"], format!("episode_s = {} must be > ctrl_dt = {}", s.sim.episode_s, s.sim.ctrl_dt));
    }

    // [stage.action], [stage.constraints]
    c.positive(&["action", "scale"], s.action.scale);
    c.positive(&["action", "clip"], s.action.clip);
    c.positive(&["constraints", "torque_limit_scale"], s.constraints.torque_limit_scale);
    c.positive(&["constraints", "joint_range_scale"], s.constraints.joint_range_scale);
    c.positive(&["constraints", "velocity_limit_scale"], s.constraints.velocity_limit_scale);

    // [stage.scenarios], [stage.scenario_params]
    let weights: Vec<(&str, f64)> = s.scenarios.iter().map(|(k, v)| (k.as_str(), *v)).collect();
    c.mixture("scenarios", "scenario", &weights);
    c.non_negative(&["scenario_params", "ksi_joint_noise"], s.scenario_params.ksi_joint_noise);
    if c.non_negative(&["scenario_params", "settle_s"], s.scenario_params.settle_s)
        && episode_ok
        && s.scenario_params.settle_s >= s.sim.episode_s
    {
        c.err(
            &["scenario_params", "settle_s"],
            format!("settle_s = {} must be < episode_s = {}", s.scenario_params.settle_s, s.sim.episode_s),
        );
    }

    // [stage.terrain]
    c.mixture("terrain", "terrain", &s.terrain.weights());
    c.range(&["terrain", "slope_max_deg"], s.terrain.slope_max_deg, Bound::Closed(0.0), Some(30.0));

    // [stage.rewards], [stage.reward_params]
    for (term, w) in &s.rewards {
        if !w.is_finite() {
            c.err(&["rewards", term.as_str()], format!("reward weight {term} = {w} must be a finite number"));
        }
    }
    c.positive(&["reward_params", "base_height_target"], s.reward_params.base_height_target);
    c.positive(&["reward_params", "base_height_sigma"], s.reward_params.base_height_sigma);
    c.range(&["reward_params", "hip_roll_ref"], s.reward_params.hip_roll_ref, Bound::None, None);

    // [stage.success]
    c.positive(&["success", "height_tolerance"], s.success.height_tolerance);
    c.positive(&["success", "upright_tolerance"], s.success.upright_tolerance);
    c.positive(&["success", "dof_tolerance"], s.success.dof_tolerance);
    c.positive(&["success", "hold_s"], s.success.hold_s);
    if episode_ok && s.success.hold_s.is_finite() && s.success.hold_s >= s.sim.episode_s {
        c.err(
            &["success", "hold_s"],
            format!("hold_s = {} must be < episode_s = {}: no episode could ever count as standing", s.success.hold_s, s.sim.episode_s),
        );
    }

    // [stage.domain_randomization]
    for (name, param) in s.domain_randomization.params() {
        let [a, b] = param.range.0;
        if !a.is_finite() || !b.is_finite() {
            c.err(&["domain_randomization", name, "range"], format!("{name}.range = [{a}, {b}] must hold finite numbers"));
            continue;
        }
        if param.distribution.is("uniform") && a > b {
            c.err(
                &["domain_randomization", name, "range"],
                format!("{name}.range = [{a}, {b}]: min {a} > max {b} (uniform ranges are [low, high])"),
            );
        } else if param.distribution.is("gaussian") && b < 0.0 {
            c.err(
                &["domain_randomization", name, "range"],
                format!("{name}.range = [{a}, {b}]: gaussian ranges are [mean, std] and std {b} must be >= 0"),
            );
        }
    }

    // [stage.delay], [stage.push]
    c.non_negative(&["delay", "max_s"], s.delay.max_s);
    let [lo, hi] = s.push.interval_s.0;
    if !lo.is_finite() || !hi.is_finite() || lo <= 0.0 {
        c.err(&["push", "interval_s"], format!("interval_s = [{lo}, {hi}]: both must be finite and the min > 0"));
    } else if lo > hi {
        c.err(&["push", "interval_s"], format!("interval_s = [{lo}, {hi}]: min {lo} > max {hi}"));
    }
    c.non_negative(&["push", "duration_s"], s.push.duration_s);
    c.non_negative(&["push", "force_max"], s.push.force_max);
    c.non_negative(&["push", "torque_max"], s.push.torque_max);

    // [stage.ppo]
    let ppo = &s.ppo;
    let envs_ok = c.positive_int(&["ppo", "num_envs"], ppo.num_envs.into());
    c.positive_int(&["ppo", "unroll_length"], ppo.unroll_length.into());
    let mb_ok = c.positive_int(&["ppo", "num_minibatches"], ppo.num_minibatches.into());
    c.positive_int(&["ppo", "update_epochs"], ppo.update_epochs.into());
    c.positive_int(&["ppo", "checkpoint_every"], ppo.checkpoint_every.into());
    if envs_ok && mb_ok {
        if let Some(message) = minibatch_problem(ppo.num_envs, ppo.num_minibatches) {
            c.err(&["ppo", "num_envs"], message);
        }
    }
    c.positive(&["ppo", "learning_rate"], ppo.learning_rate);
    c.positive(&["ppo", "desired_kl"], ppo.desired_kl);
    c.non_negative(&["ppo", "entropy_cost"], ppo.entropy_cost);
    c.positive(&["ppo", "clip_epsilon"], ppo.clip_epsilon);
    c.non_negative(&["ppo", "value_loss_coef"], ppo.value_loss_coef);
    c.range(&["ppo", "discount"], ppo.discount, Bound::Closed(0.0), Some(1.0));
    c.range(&["ppo", "gae_lambda"], ppo.gae_lambda, Bound::Closed(0.0), Some(1.0));
    c.non_negative(&["ppo", "max_grad_norm"], ppo.max_grad_norm);
    c.positive(&["ppo", "reward_scaling"], ppo.reward_scaling);
    c.layers(&["ppo", "policy_hidden"], &ppo.policy_hidden);
    c.layers(&["ppo", "value_hidden"], &ppo.value_hidden);
    c.positive(&["ppo", "initial_action_std"], ppo.initial_action_std);

    // [stage.rma], [stage.mirror]
    c.positive_int(&["rma", "latent_dim"], s.rma.latent_dim.into());
    c.layers(&["rma", "encoder_hidden"], &s.rma.encoder_hidden);
    c.positive_int(&["rma", "history_len"], s.rma.history_len.into());
    c.positive(&["rma", "adaptation_learning_rate"], s.rma.adaptation_learning_rate);
    c.non_negative(&["mirror", "weight"], s.mirror.weight);

    // [stage.advance]
    c.positive_int(&["advance", "env_steps"], s.advance.env_steps);
    if let Some(rate) = s.advance.min_stand_rate {
        c.range(&["advance", "min_stand_rate"], rate, Bound::Closed(0.0), Some(1.0));
    }
    c.positive_int(&["advance", "window"], s.advance.window.into());
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
