"""The typed shape of one curriculum stage: frozen dataclasses, and the closed vocabularies of
the stage table's enumerated settings.

`jax_env.config` builds these from the stage table the Rust CLI sends (checking every value);
the environment and the learner read them, and never look up string keys at run time. The
names of things the stage *selects* (joints, scenarios, terrains, reward terms, DR parameters)
belong to the modules that implement them and are gathered in `jax_env.names`.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping

# Values of the stage table's enumerated settings.
DR_OPERATIONS: tuple[str, ...] = ("additive", "scaling")
DR_DISTRIBUTIONS: tuple[str, ...] = ("gaussian", "uniform")
ACTION_MAPPINGS: tuple[str, ...] = ("current", "default")
LR_SCHEDULES: tuple[str, ...] = ("fixed", "adaptive_kl")
ON_MISS: tuple[str, ...] = ("stop", "continue")
# What a penalty schedule's points are keyed on: the stage's env steps so far, or the
# training stand rate (the fraction of episodes that ended standing, last iteration).
SCHEDULE_KEYS: tuple[str, ...] = ("env_steps", "stand_rate")


@dataclasses.dataclass(frozen=True)
class SimConfig:
  timestep: float
  ctrl_dt: float
  episode_s: float

  @property
  def n_substeps(self) -> int:
    return int(round(self.ctrl_dt / self.timestep))

  @property
  def episode_steps(self) -> int:
    return int(round(self.episode_s / self.ctrl_dt))


@dataclasses.dataclass(frozen=True)
class ActionConfig:
  mapping: str
  scale: float
  clip: float


@dataclasses.dataclass(frozen=True)
class ConstraintsConfig:
  torque_limit_scale: float
  joint_range_scale: float
  velocity_limit_scale: float


@dataclasses.dataclass(frozen=True)
class ScenarioParams:
  ksi_joint_noise: float
  settle_s: float
  # Per path scenario (`supine_path`, `prone_path`, `kneel_path`): its starts are drawn from the
  # path's first this-many seconds only (default, or longer than the rise: the whole rise) —
  # to practise the start of a path, e.g. the kneel path's roll out of ksi_prone_3.
  path_start_window_s: Mapping[str, float] = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True)
class TerrainConfig:
  weights: Mapping[str, float]  # every terrain in TERRAINS, omitted ones 0
  slope_max_deg: float


@dataclasses.dataclass(frozen=True)
class RewardParams:
  base_height_target: float
  base_height_sigma: float
  hip_roll_ref: float
  # Waist body height target of `waist_height` (mjlab's T1 get-up: 0.55 m, against sitting).
  waist_height_target: float = 0.55
  # `dof_pos_ref` applies only within this distance of the target height (0: everywhere);
  # the paper's code pays it only near standing (|h - 0.68| < 0.1).
  dof_pos_ref_band: float = 0.0
  # Gates on the Trunk-frame gravity, each (full, zero): 1 for g ≤ full, 0 for g ≥ zero, linear
  # between; None: no gate. `face_down_gate` (on g_x) takes the height terms (base_height,
  # trunk_height, waist_height) away with the chest towards the floor, so that a face-down
  # push-up into a head-down kneel is not paid more than lying on the back (the prone trap,
  # docs/experiments.md); `head_down_gate` (on g_z) takes the heights and `not_prone` away with the
  # Trunk pitched head-down.
  face_down_gate: tuple[float, float] | None = None
  head_down_gate: tuple[float, float] | None = None


@dataclasses.dataclass(frozen=True)
class Schedule:
  """A piecewise-linear scale over `by` (SCHEDULE_KEYS): of every penalty (negative weight) in
  `RewardShaping.penalty_schedule`, of the assisting force in `AssistConfig.schedule`.

  points: ((x0, s0), (x1, s1), ...) with x increasing; constant beyond the ends. With
  by = "stand_rate" the scale is a ratchet within a stage (the learner's `ScheduleScale`):
  penalties never decrease (a dip in the stand rate does not take the smoothing pressure away
  again) and the assist never increases.
  """

  by: str
  points: tuple[tuple[float, float], ...]

  def scale(self, x: float) -> float:
    xs = [p[0] for p in self.points]
    ys = [p[1] for p in self.points]
    if x <= xs[0]:
      return ys[0]
    for (x0, y0), (x1, y1) in zip(self.points, self.points[1:]):
      if x <= x1:
        return y0 + (y1 - y0) * (x - x0) / (x1 - x0) if x1 > x0 else y1
    return ys[-1]


@dataclasses.dataclass(frozen=True)
class RewardShaping:
  """How the weighted terms become one reward (defaults: a plain weighted sum)."""

  scale_by_ctrl_dt: bool = False  # weights × control period (the paper's code, legged_gym)
  clip_at_zero: bool = False  # total clipped at 0 from below (`only_positive_rewards`)
  penalty_schedule: Schedule | None = None  # None: penalties at full weight always


@dataclasses.dataclass(frozen=True)
class TerminationConfig:
  """True terminations (no value bootstrap), apart from the time limit; 0 disables each."""

  low_height: float = 0.0  # Trunk below this (m) ...
  low_height_s: float = 2.0  # ... for longer than this (s) ends the episode
  upside_down: float = 0.0  # projected gravity z above this (head down) ends it
  # ... and above this with the chest toward the floor (projected gravity x > 0): a head-first
  # dive from the kneel, apart from the supine get-up's rock-back onto the shoulders (face up),
  # which reaches the same g_z
  upside_down_face_down: float = 0.0
  # ... but only while |projected gravity y| is below this: the pike and the dive pitch over the
  # head (g_y near 0), the get-up from the kneel rolls out over a shoulder (|g_y| 0.27–0.59 as it
  # passes g_z 0.6, docs/experiments.md); 0: no exception
  upside_down_face_down_max_roll: float = 0.0
  side_roll: float = 0.0  # |projected gravity y| above this (lying on a side) ends it


# The termination rules, each named by its threshold's field above, in the order the environment
# reports the first that held (`episode_metrics["end"]`).
TERMINATION_RULES = ("low_height", "upside_down", "upside_down_face_down", "side_roll")
# How an episode ended (the environment's `episode_metrics["end"]`, an index into this tuple): at
# its time limit, by the first termination rule that held (no value bootstrap), or by a numerical
# blow-up.
EPISODE_ENDS = ("time_limit",) + TERMINATION_RULES + ("blow_up",)


@dataclasses.dataclass(frozen=True)
class AssistConfig:
  """An upward force on the Trunk while training, to help discover standing up (HoST's and
  holosoma's vertical-pull curriculum): `force` newtons times the schedule's scale. With
  by = "stand_rate" the scale never increases within a stage (a downward ratchet). Evaluation,
  the monitor and exported policies never see it; a schedule should reach 0 before the stage
  ends, so that the final policy stands up by itself."""

  force: float = 0.0  # N at scale 1; 0: off
  schedule: Schedule | None = None  # None: the full force throughout


@dataclasses.dataclass(frozen=True)
class ImitationConfig:
  """Learning from the stored get-up paths (ours; kickstarting, Schmitt et al. 2018): in an
  episode that started on a path (`supine_path`, `prone_path`, `kneel_path`), PPO's loss adds
  `weight` × the schedule's scale × the mean squared difference between the policy's mean
  action and the action the path's plan issued at the same time since the start (a
  behaviour-cloning term on the policy's own states; no reward reads the path). With
  by = "stand_rate" the scale never increases within a stage (a downward ratchet). A
  schedule should reach 0 before the stage ends, so that PPO alone shapes the final policy."""

  weight: float = 0.0  # at scale 1; 0: off
  schedule: Schedule | None = None  # None: the full weight throughout
  # The share of path episodes that act with the plan's action (plus the policy's noise)
  # instead of the policy's while the imitation weight is on: their states stay on the path,
  # where the plan's action is a function of the state (on the policy's own states, a plan
  # indexed by time asks different things of one state). They train only the imitation term.
  forcing: float = 0.0


@dataclasses.dataclass(frozen=True)
class MonitorConfig:
  """The deterministic stand-rate monitor during training (no action noise)."""

  every: int = 0  # iterations between monitor rollouts; 0: off
  episodes: int = 4  # episodes per start scenario
  scenarios: tuple[str, ...] = ()  # empty: every scenario of the mixture, plus `stand`
  # The stage ends (adaptation phase, final checkpoint) from the PPO parameters of its monitor
  # point with the highest mean stand rate (the latest of equals), not from the last iteration.
  keep_best: bool = False


@dataclasses.dataclass(frozen=True)
class SuccessConfig:
  height_tolerance: float
  upright_tolerance: float
  dof_tolerance: float
  hold_s: float


@dataclasses.dataclass(frozen=True)
class DRParam:
  """One row of the paper's DR table: gaussian range = (mean, std); uniform = (low, high)."""

  range: tuple[float, float]
  operation: str
  distribution: str


@dataclasses.dataclass(frozen=True)
class DomainRandomizationConfig:
  enabled: bool
  params: Mapping[str, DRParam]  # only the parameters the stage names

  def active(self, name: str) -> DRParam | None:
    return self.params.get(name) if self.enabled else None


@dataclasses.dataclass(frozen=True)
class DelayConfig:
  max_s: float


@dataclasses.dataclass(frozen=True)
class PushConfig:
  enabled: bool
  interval_s: tuple[float, float]
  duration_s: float
  force_max: float
  torque_max: float


@dataclasses.dataclass(frozen=True)
class PPOConfig:
  num_envs: int
  unroll_length: int
  num_minibatches: int
  update_epochs: int
  learning_rate: float
  lr_schedule: str
  desired_kl: float
  entropy_cost: float
  clip_epsilon: float
  value_loss_coef: float
  discount: float
  gae_lambda: float
  max_grad_norm: float
  reward_scaling: float
  normalize_observations: bool
  policy_hidden: tuple[int, ...]
  value_hidden: tuple[int, ...]
  activation: str
  initial_action_std: float
  checkpoint_every: int
  max_action_std: float | None = None  # the policy's std is kept at or below this
  # A scale (0, 1] of max_action_std over the stage (by env steps or stand rate; a ratchet
  # that only tightens): explore widely first, then train the policy that is deployed, its
  # mean, with little noise (docs/experiments.md, "The deterministic gap"). None: the bound is
  # constant.
  action_std_schedule: Schedule | None = None
  # ρ of the AR(1) exploration noise per control step (0: white noise, brax's sampling).
  action_noise_correlation: float = 0.0


@dataclasses.dataclass(frozen=True)
class RMAConfig:
  enabled: bool
  latent_dim: int
  encoder_hidden: tuple[int, ...]
  history_len: int
  adaptation_env_steps: int
  adaptation_learning_rate: float
  # Regularized online adaptation (Fu et al., "Deep Whole-Body Control", CoRL 2022): during
  # PPO the encoder's latent is pulled toward the adaptation module's estimate with this weight
  # and the module learns beside PPO, so that the latent the policy relies on is one the
  # deployable actor can estimate. 0: RMA as Kumar et al. (the module learns only at the end).
  latent_regularization: float = 0.0


@dataclasses.dataclass(frozen=True)
class MirrorConfig:
  weight: float


@dataclasses.dataclass(frozen=True)
class AdvanceConfig:
  env_steps: int
  min_stand_rate: float | None
  window: int
  on_miss: str


@dataclasses.dataclass(frozen=True)
class StageConfig:
  """One curriculum stage. Joint tuples are in canonical order, whatever the TOML's order."""

  name: str
  init_from: str
  controlled_joints: tuple[str, ...]
  observed_joints: tuple[str, ...]
  sim: SimConfig
  action: ActionConfig
  constraints: ConstraintsConfig
  scenarios: Mapping[str, float]  # every scenario in SCENARIOS, omitted ones 0
  scenario_params: ScenarioParams
  terrain: TerrainConfig
  rewards: Mapping[str, float]  # every term in REWARD_TERMS, omitted ones 0
  reward_params: RewardParams
  success: SuccessConfig
  domain_randomization: DomainRandomizationConfig
  delay: DelayConfig
  push: PushConfig
  ppo: PPOConfig
  rma: RMAConfig
  mirror: MirrorConfig
  advance: AdvanceConfig
  reward_shaping: RewardShaping = RewardShaping()
  termination: TerminationConfig = TerminationConfig()
  monitor: MonitorConfig = MonitorConfig()
  assist: AssistConfig = AssistConfig()
  imitation: ImitationConfig = ImitationConfig()

  @property
  def monitor_scenarios(self) -> tuple[str, ...]:
    """The start scenarios the monitor measures, in SCENARIOS order (`scenarios` holds every
    scenario in that order)."""
    if self.monitor.scenarios:
      return tuple(s for s in self.scenarios if s in self.monitor.scenarios)
    return tuple(s for s, weight in self.scenarios.items() if weight > 0 or s == "stand")

  @classmethod
  def from_dict(cls, d: Mapping[str, Any]) -> "StageConfig":
    """Parses a stage table; raises `config.ConfigError` for the first problem found."""
    # Imported here: the parser checks names against the modules that own them, and those
    # modules import these dataclasses.
    from jax_env import config
    return config.parse_stage(d)
