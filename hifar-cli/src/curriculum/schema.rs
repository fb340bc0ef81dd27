//! The curriculum TOML as typed structs (docs/contracts.md, "Curriculum TOML", schema 1).
//!
//! Every struct denies unknown keys, so a typo is an error with the key's position rather than
//! a silently ignored setting. Closed vocabularies (backends, mappings, scenario and reward
//! names, …) are enums, so a wrong name is reported by the deserializer with the valid ones.
//! Serialization gives back exactly the keys of the file (optional keys that were absent stay
//! absent), which is the stage table Python receives.
//!
//! The optional tables `[stage.reward_shaping]`, `[stage.termination]`, `[stage.monitor]` (and
//! the optional keys `reward_params.waist_height_target`, `reward_params.dof_pos_ref_band`,
//! `ppo.max_action_std`) are typed here only for their keys and types; their ranges and
//! meaning are checked by Python (`jax_env/config.py`, `check_stage`), whose key paths
//! `hifar check` and `hifar train` map back to `FILE:LINE:COL`.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

/// The version this build reads.
pub const SCHEMA_VERSION: i64 = 1;

/// Declares a unit enum of snake_case names with `as_str` and the list of all variants.
macro_rules! names {
    ($(#[$meta:meta])* $name:ident { $($variant:ident = $text:literal),+ $(,)? }) => {
        $(#[$meta])*
        #[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
        pub enum $name {
            $(#[serde(rename = $text)] $variant),+
        }

        impl $name {
            pub const ALL: &'static [$name] = &[$($name::$variant),+];

            pub fn as_str(self) -> &'static str {
                match self {
                    $($name::$variant => $text),+
                }
            }
        }

        impl std::fmt::Display for $name {
            fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str(self.as_str())
            }
        }
    };
}

names!(
    /// Physics backend; `auto` lets `facade.doctor()` choose (MJX on an accelerator).
    Backend { Auto = "auto", Mjx = "mjx", Native = "native" }
);
names!(
    /// `current`: target = q + scale·a; `default`: target = q_stand + scale·a.
    Mapping { Current = "current", Default = "default" }
);
names!(LrSchedule { Fixed = "fixed", AdaptiveKl = "adaptive_kl" });
names!(Activation { Elu = "elu", Swish = "swish", Tanh = "tanh", Relu = "relu" });
names!(OnMiss { Stop = "stop", Continue = "continue" });
names!(DrOperation { Additive = "additive", Scaling = "scaling" });
names!(DrDistribution { Gaussian = "gaussian", Uniform = "uniform" });
names!(
    /// Initial-state scenarios (robot::SCENARIOS); `ksi_*` start at the keyframe of that name.
    Scenario {
        KsiProne1 = "ksi_prone_1",
        KsiProne2 = "ksi_prone_2",
        KsiProne3 = "ksi_prone_3",
        KsiSupine1 = "ksi_supine_1",
        KsiSupine2 = "ksi_supine_2",
        KsiSupine3 = "ksi_supine_3",
        Supine = "supine",
        Prone = "prone",
        Lateral = "lateral",
        Sitting = "sitting",
        CrossedLegs = "crossed_legs",
        RandomDrop = "random_drop",
        Stand = "stand",
        Squat = "squat",
    }
);
names!(
    /// Reward terms of the paper's reward table (robot::REWARD_TERMS).
    RewardTerm {
        Survival = "survival",
        BaseHeight = "base_height",
        Standing = "standing",
        Orientation = "orientation",
        DofPosRef = "dof_pos_ref",
        Torques = "torques",
        DofVel = "dof_vel",
        DofAcc = "dof_acc",
        RootAcc = "root_acc",
        ActionRate = "action_rate",
        DofPosLimits = "dof_pos_limits",
        TorqueFatigue = "torque_fatigue",
        Power = "power",
        HipRoll = "hip_roll",
        TrunkHeight = "trunk_height",
        WaistHeight = "waist_height",
        Upright = "upright",
    }
);
names!(
    /// What a penalty schedule's `points` are indexed by.
    ScheduleBy { EnvSteps = "env_steps", StandRate = "stand_rate" }
);

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CurriculumFile {
    pub schema_version: i64,
    pub name: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub description: Option<String>,
    #[serde(default)]
    pub seed: u64,
    #[serde(default = "default_backend")]
    pub backend: Backend,
    pub stage: Vec<StageTable>,
}

fn default_backend() -> Backend {
    Backend::Auto
}

/// One `[[stage]]` table.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StageTable {
    pub name: String,
    pub init_from: String,
    pub controlled_joints: Vec<String>,
    pub observed_joints: Vec<String>,
    pub sim: Sim,
    pub action: Action,
    pub constraints: Constraints,
    pub scenarios: BTreeMap<Scenario, f64>,
    pub scenario_params: ScenarioParams,
    pub terrain: Terrain,
    pub rewards: BTreeMap<RewardTerm, f64>,
    pub reward_params: RewardParams,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reward_shaping: Option<RewardShaping>,
    pub success: Success,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub termination: Option<Termination>,
    pub domain_randomization: DomainRandomization,
    pub delay: Delay,
    pub push: Push,
    pub ppo: Ppo,
    pub rma: Rma,
    pub mirror: Mirror,
    pub advance: Advance,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub monitor: Option<Monitor>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Sim {
    pub timestep: f64,
    pub ctrl_dt: f64,
    pub episode_s: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Action {
    pub mapping: Mapping,
    pub scale: f64,
    pub clip: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Constraints {
    pub torque_limit_scale: f64,
    pub joint_range_scale: f64,
    pub velocity_limit_scale: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScenarioParams {
    pub ksi_joint_noise: f64,
    pub settle_s: f64,
}

/// Terrain mixture weights (omitted terrains weigh 0) and the slope range.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Terrain {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub flat: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub slope: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub obstacle: Option<f64>,
    pub slope_max_deg: f64,
}

impl Terrain {
    /// (name, weight) of the terrains the file sets, in robot::TERRAINS order.
    pub fn weights(&self) -> Vec<(&'static str, f64)> {
        [("flat", self.flat), ("slope", self.slope), ("obstacle", self.obstacle)]
            .into_iter()
            .filter_map(|(name, w)| w.map(|w| (name, w)))
            .collect()
    }
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RewardParams {
    pub base_height_target: f64,
    pub base_height_sigma: f64,
    pub hip_roll_ref: f64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub waist_height_target: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dof_pos_ref_band: Option<f64>,
}

/// `[stage.reward_shaping]`: how the weighted reward terms are combined (jax_env/config.py
/// owns the semantics and the range checks; every key is optional).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RewardShaping {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scale_by_ctrl_dt: Option<bool>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub clip_at_zero: Option<bool>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub penalty_schedule: Option<PenaltySchedule>,
}

/// `penalty_schedule = { by = "env_steps" | "stand_rate", points = [[x, scale], ...] }`.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PenaltySchedule {
    pub by: ScheduleBy,
    pub points: Vec<SchedulePoint>,
}

/// `[x, scale]`: exactly two numbers.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
#[serde(transparent)]
pub struct SchedulePoint(pub [f64; 2]);

impl<'de> Deserialize<'de> for SchedulePoint {
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        let values = Vec::<f64>::deserialize(deserializer)?;
        match values[..] {
            [x, scale] => Ok(SchedulePoint([x, scale])),
            _ => Err(serde::de::Error::invalid_length(values.len(), &"an array of two numbers [x, scale]")),
        }
    }
}

/// `[stage.termination]`: early-termination conditions (jax_env/config.py owns the semantics
/// and the range checks; every key is optional, 0 switches a condition off).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Termination {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub low_height: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub low_height_s: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub upside_down: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub side_roll: Option<f64>,
}

/// `[stage.monitor]`: the deterministic-policy monitor run during training (jax_env/config.py
/// owns the semantics and the range checks; every key is optional).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Monitor {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub every: Option<u32>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub episodes: Option<u32>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scenarios: Option<Vec<Scenario>>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Success {
    pub height_tolerance: f64,
    pub upright_tolerance: f64,
    pub dof_tolerance: f64,
    pub hold_s: f64,
}

/// `[a, b]`: exactly two numbers (a plain `[f64; 2]` would let TOML arrays of three pass).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
#[serde(transparent)]
pub struct Pair(pub [f64; 2]);

impl<'de> Deserialize<'de> for Pair {
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        let values = Vec::<f64>::deserialize(deserializer)?;
        match values[..] {
            [a, b] => Ok(Pair([a, b])),
            _ => Err(serde::de::Error::invalid_length(values.len(), &"an array of two numbers [min, max]")),
        }
    }
}

/// One row of the paper's DR table. gaussian: `range = [mean, std]`; uniform: `[low, high]`.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DrParam {
    pub range: Pair,
    pub operation: DrOperation,
    pub distribution: DrDistribution,
}

/// `enabled` plus any subset of the DR parameters (robot::DR_PARAMETERS).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DomainRandomization {
    pub enabled: bool,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dof_position: Option<DrParam>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub base_xy_position: Option<DrParam>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub base_linear_velocity: Option<DrParam>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub joint_stiffness: Option<DrParam>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub joint_damping: Option<DrParam>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub terrain_friction: Option<DrParam>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub terrain_compliance: Option<DrParam>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub terrain_restitution: Option<DrParam>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub torso_com: Option<DrParam>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub torso_mass: Option<DrParam>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub other_com: Option<DrParam>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub other_mass: Option<DrParam>,
}

impl DomainRandomization {
    /// The parameters the file sets, in robot::DR_PARAMETERS order.
    pub fn params(&self) -> Vec<(&'static str, &DrParam)> {
        [
            ("dof_position", &self.dof_position),
            ("base_xy_position", &self.base_xy_position),
            ("base_linear_velocity", &self.base_linear_velocity),
            ("joint_stiffness", &self.joint_stiffness),
            ("joint_damping", &self.joint_damping),
            ("terrain_friction", &self.terrain_friction),
            ("terrain_compliance", &self.terrain_compliance),
            ("terrain_restitution", &self.terrain_restitution),
            ("torso_com", &self.torso_com),
            ("torso_mass", &self.torso_mass),
            ("other_com", &self.other_com),
            ("other_mass", &self.other_mass),
        ]
        .into_iter()
        .filter_map(|(name, p)| p.as_ref().map(|p| (name, p)))
        .collect()
    }
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Delay {
    pub max_s: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Push {
    pub enabled: bool,
    pub interval_s: Pair,
    pub duration_s: f64,
    pub force_max: f64,
    pub torque_max: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Ppo {
    pub num_envs: u32,
    pub unroll_length: u32,
    pub num_minibatches: u32,
    pub update_epochs: u32,
    pub learning_rate: f64,
    pub lr_schedule: LrSchedule,
    pub desired_kl: f64,
    pub entropy_cost: f64,
    pub clip_epsilon: f64,
    pub value_loss_coef: f64,
    pub discount: f64,
    pub gae_lambda: f64,
    pub max_grad_norm: f64,
    pub reward_scaling: f64,
    pub normalize_observations: bool,
    pub policy_hidden: Vec<u32>,
    pub value_hidden: Vec<u32>,
    pub activation: Activation,
    pub initial_action_std: f64,
    pub checkpoint_every: u32,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_action_std: Option<f64>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Rma {
    pub enabled: bool,
    pub latent_dim: u32,
    pub encoder_hidden: Vec<u32>,
    pub history_len: u32,
    pub adaptation_env_steps: u64,
    pub adaptation_learning_rate: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Mirror {
    pub weight: f64,
}

/// When a stage ends: its env-step budget, and optionally a stand-rate threshold.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Advance {
    pub env_steps: u64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub min_stand_rate: Option<f64>,
    pub window: u32,
    pub on_miss: OnMiss,
}

impl Advance {
    /// Whether a stage that misses `min_stand_rate` within its budget lets the run go on.
    pub fn on_miss_continue(&self) -> bool {
        self.on_miss == OnMiss::Continue
    }
}
