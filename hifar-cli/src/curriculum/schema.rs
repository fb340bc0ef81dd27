//! The curriculum TOML as typed structs (docs/contracts.md, "Curriculum TOML", schema 1).
//!
//! Every struct denies unknown keys, so a typo is an error with the key's position rather than
//! a silently ignored setting. Names from closed vocabularies (scenarios, reward terms, DR
//! parameters, mappings, …) are [`Name`]s of the lists jax_env exports (`crate::names`), so a
//! wrong name is reported by the deserializer with the valid ones, as for an enum.
//! Serialization gives back exactly the keys of the file (optional keys that were absent stay
//! absent), which is the stage table Python receives.
//!
//! The optional tables `[stage.reward_shaping]`, `[stage.termination]`, `[stage.monitor]`,
//! `[stage.assist]`, `[stage.imitation]` (and the optional keys
//! `scenario_params.path_start_window_s`, `reward_params.waist_height_target`,
//! `reward_params.dof_pos_ref_band`, `reward_params.face_down_gate`,
//! `reward_params.head_down_gate`, `ppo.max_action_std`, `ppo.action_std_schedule`,
//! `ppo.action_noise_correlation`) are typed here only for their keys and
//! types; their ranges and meaning are checked by Python (`jax_env/config.py`, `check_stage`),
//! whose key paths `hifar check` and `hifar train` map back to `FILE:LINE:COL`.

use std::collections::BTreeMap;
use std::fmt;
use std::marker::PhantomData;
use std::sync::LazyLock;

use serde::de::{DeserializeSeed, MapAccess, Visitor};
use serde::ser::SerializeMap;
use serde::{Deserialize, Deserializer, Serialize, Serializer};

pub use crate::names::{
    Activation, Backend, DrDistribution, DrOperation, DrParameter, LrSchedule, Mapping, OnMiss, RewardTerm, Scenario, ScheduleBy,
    Terrain,
};
use crate::names::{DrParameters, Name, Terrains, Vocabulary, AUTO_BACKEND};

/// The version this build reads.
pub const SCHEMA_VERSION: i64 = 1;

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
    Backend::parse(AUTO_BACKEND).expect("auto is a curriculum backend")
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
    pub terrain: TerrainTable,
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
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub assist: Option<Assist>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub imitation: Option<Imitation>,
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
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub path_start_window_s: Option<BTreeMap<String, f64>>,
}

/// `[stage.terrain]`: terrain mixture weights (omitted terrains weigh 0) and the slope range.
#[derive(Debug, Clone)]
pub struct TerrainTable {
    pub weights: BTreeMap<Terrain, f64>,
    pub slope_max_deg: f64,
}

const SLOPE_MAX_DEG: &str = "slope_max_deg";
static TERRAIN_KEYS: LazyLock<Vec<&'static str>> =
    LazyLock::new(|| [Terrains::names(), &[SLOPE_MAX_DEG]].concat());

impl TerrainTable {
    /// (name, weight) of the terrains the file sets, in vocabulary order.
    pub fn weights(&self) -> Vec<(&'static str, f64)> {
        self.weights.iter().map(|(name, w)| (name.as_str(), *w)).collect()
    }
}

impl Serialize for TerrainTable {
    fn serialize<S: Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        let mut map = serializer.serialize_map(Some(self.weights.len() + 1))?;
        for (name, weight) in &self.weights {
            map.serialize_entry(name, weight)?;
        }
        map.serialize_entry(SLOPE_MAX_DEG, &self.slope_max_deg)?;
        map.end()
    }
}

impl<'de> Deserialize<'de> for TerrainTable {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        let (weights, slope_max_deg) = deserializer.deserialize_map(NamedTable::new(SLOPE_MAX_DEG, &TERRAIN_KEYS))?;
        Ok(TerrainTable { weights, slope_max_deg })
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
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub face_down_gate: Option<Pair>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub head_down_gate: Option<Pair>,
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
    pub penalty_schedule: Option<Schedule>,
}

/// `{ by = "env_steps" | "stand_rate", points = [[x, scale], ...] }`: a piecewise-linear scale,
/// of the penalties (`penalty_schedule`), of the assisting force (`[stage.assist] schedule`),
/// of the imitation weight (`[stage.imitation] schedule`) or of the bound on the action std
/// (`ppo.action_std_schedule`).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Schedule {
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
    pub upside_down_face_down: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub upside_down_face_down_max_roll: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub side_roll: Option<f64>,
}

/// `[stage.assist]`: an upward force on the Trunk during training, scaled by a schedule
/// (jax_env/config.py owns the semantics and the range checks; every key is optional).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Assist {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub force: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub schedule: Option<Schedule>,
}

/// `[stage.imitation]`: PPO's loss also pulls the policy toward the stored get-up paths' plans
/// in episodes started on them, weighted by a schedule (jax_env/config.py owns the semantics
/// and the range checks; every key is optional).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Imitation {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub weight: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub schedule: Option<Schedule>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub forcing: Option<f64>,
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
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub keep_best: Option<bool>,
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

/// `[stage.domain_randomization]`: `enabled` plus any subset of the DR parameters.
#[derive(Debug, Clone)]
pub struct DomainRandomization {
    pub enabled: bool,
    pub params: BTreeMap<DrParameter, DrParam>,
}

const ENABLED: &str = "enabled";
static DR_KEYS: LazyLock<Vec<&'static str>> =
    LazyLock::new(|| [&[ENABLED], DrParameters::names()].concat());

impl DomainRandomization {
    /// The parameters the file sets, in vocabulary order.
    pub fn params(&self) -> Vec<(&'static str, &DrParam)> {
        self.params.iter().map(|(name, p)| (name.as_str(), p)).collect()
    }
}

impl Serialize for DomainRandomization {
    fn serialize<S: Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        let mut map = serializer.serialize_map(Some(self.params.len() + 1))?;
        map.serialize_entry(ENABLED, &self.enabled)?;
        for (name, param) in &self.params {
            map.serialize_entry(name, param)?;
        }
        map.end()
    }
}

impl<'de> Deserialize<'de> for DomainRandomization {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        let (params, enabled) = deserializer.deserialize_map(NamedTable::new(ENABLED, &DR_KEYS))?;
        Ok(DomainRandomization { enabled, params })
    }
}

/// Reads a table whose keys are names of a vocabulary, each optional, plus one required key of
/// the table's own (`slope_max_deg`, `enabled`), as a derived struct with `deny_unknown_fields`
/// would: an unknown key fails at the key with the valid `keys`, a missing own key at the table.
struct NamedTable<V, T, X> {
    own: &'static str,
    keys: &'static [&'static str],
    values: PhantomData<(V, T, X)>,
}

impl<V, T, X> NamedTable<V, T, X> {
    fn new(own: &'static str, keys: &'static [&'static str]) -> Self {
        NamedTable { own, keys, values: PhantomData }
    }
}

impl<'de, V: Vocabulary, T: Deserialize<'de>, X: Deserialize<'de>> Visitor<'de> for NamedTable<V, T, X> {
    type Value = (BTreeMap<Name<V>, T>, X);

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("a map")
    }

    fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<Self::Value, A::Error> {
        let mut named = BTreeMap::new();
        let mut own = None;
        while let Some(key) = map.next_key_seed(TableKey::<V> { own: self.own, keys: self.keys, vocabulary: PhantomData })? {
            match key {
                Some(name) => {
                    named.insert(name, map.next_value()?);
                }
                None => own = Some(map.next_value()?),
            }
        }
        let own = own.ok_or_else(|| serde::de::Error::missing_field(self.own))?;
        Ok((named, own))
    }
}

/// A key of a [`NamedTable`]: a name of the vocabulary, or None for the table's own key.
struct TableKey<V> {
    own: &'static str,
    keys: &'static [&'static str],
    vocabulary: PhantomData<V>,
}

impl<'de, V: Vocabulary> DeserializeSeed<'de> for TableKey<V> {
    type Value = Option<Name<V>>;

    fn deserialize<D: Deserializer<'de>>(self, deserializer: D) -> Result<Self::Value, D::Error> {
        deserializer.deserialize_str(self)
    }
}

impl<V: Vocabulary> Visitor<'_> for TableKey<V> {
    type Value = Option<Name<V>>;

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("a key")
    }

    fn visit_str<E: serde::de::Error>(self, key: &str) -> Result<Self::Value, E> {
        if key == self.own {
            return Ok(None);
        }
        Name::parse(key).map(Some).ok_or_else(|| E::unknown_field(key, self.keys))
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
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub action_std_schedule: Option<Schedule>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub action_noise_correlation: Option<f64>,
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
    /// Weight pulling the latent toward the adaptation module's estimate during PPO (0: off).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub latent_regularization: Option<f64>,
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
        self.on_miss.is("continue")
    }
}
