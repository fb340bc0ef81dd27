"""The nominal evaluation setup and the conditions of one protocol cell (docs/contracts.md,
"Nominal conditions").

The paper's simulation experiments start from a standard setup — supine or prone, the torso's
11.7 kg, floor friction 1.0, no disturbance — and change one thing per experiment: a push fixed
in the torso frame, extra torso mass, the floor friction, the torque limit, the initial state or
the terrain. `evaluation_stage` turns a training stage into that setup (every randomization off),
and a `Condition` names the one change. The change is applied as *data* on top of a reset
(`ConditionArrays`, one row per env), so a single compiled rollout serves every cell, and a batch
may mix cells.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jax_env.randomization import TERRAINS
from jax_env.scenarios import SCENARIOS

# The paper's standard setup: floor friction 1.0 (the torso keeps the model's 11.7 kg).
STANDARD_FRICTION = 1.0
# A stage trained without slopes (slope_max_deg = 0) is evaluated on the slopes of the paper-scale
# curriculum's second stage (curricula/hifar.toml): up to 10 degrees.
DEFAULT_SLOPE_MAX_DEG = 10.0
# Torso-frame directions of a push: the T1's torso x axis points forward, y to its left.
PUSH_DIRECTIONS: dict[str, tuple[float, float, float]] = {
    "forward": (1.0, 0.0, 0.0), "backward": (-1.0, 0.0, 0.0),
    "left": (0.0, 1.0, 0.0), "right": (0.0, -1.0, 0.0),
}
_NEVER = np.iinfo(np.int32).max


def evaluation_stage(stage: dict) -> dict:
  """The same stage under nominal conditions: no domain randomization, no random pushes, no
  control delay, flat terrain (a forced slope uses the stage's slope_max_deg, or
  DEFAULT_SLOPE_MAX_DEG where the stage has none). Features, action mapping, constraints, episode
  length, settling and the success detector are the stage's own."""
  s = copy.deepcopy(dict(stage))
  s["domain_randomization"] = {"enabled": False}
  s["push"] = {**s["push"], "enabled": False}
  s["delay"] = {**s["delay"], "max_s": 0.0}
  slope = float(s["terrain"].get("slope_max_deg", 0.0)) or DEFAULT_SLOPE_MAX_DEG
  s["terrain"] = {"flat": 1.0, "slope_max_deg": slope}
  return s


def planar_direction(scenario: str) -> str:
  """The paper's planar push: forward when recovering from prone, backward otherwise (supine)."""
  return "forward" if "prone" in scenario else "backward"


@dataclasses.dataclass(frozen=True)
class Condition:
  """One protocol cell's deviation from the standard setup.

  friction None keeps STANDARD_FRICTION; torque_limit scales the stage's actuator force limits
  (1.0: the limits the policy was trained with); a push of `push_force` newtons acts on the Trunk
  along a torso-frame direction, `push_start_s` after control starts (after settling, if any),
  for `push_duration_s` (both quantised to control steps).
  """

  scenario: str = "prone"
  terrain: str = "flat"
  extra_torso_mass: float = 0.0
  friction: float | None = None
  torque_limit: float = 1.0
  push_force: float = 0.0
  push_direction: str = "forward"
  push_start_s: float = 0.8
  push_duration_s: float = 0.2

  def __post_init__(self):
    if self.scenario not in SCENARIOS:
      raise ValueError(f"unknown scenario {self.scenario!r}; valid: {', '.join(SCENARIOS)}")
    if self.terrain not in TERRAINS:
      raise ValueError(f"unknown terrain {self.terrain!r}; valid: {', '.join(TERRAINS)}")
    if self.push_direction not in PUSH_DIRECTIONS:
      raise ValueError(f"unknown push direction {self.push_direction!r}; valid: "
                       f"{', '.join(PUSH_DIRECTIONS)}")
    checks = [("extra_torso_mass", self.extra_torso_mass, 0.0),
              ("torque_limit", self.torque_limit, 0.0), ("push_force", self.push_force, 0.0),
              ("push_start_s", self.push_start_s, 0.0),
              ("push_duration_s", self.push_duration_s, 0.0)]
    if self.friction is not None:
      checks.append(("friction", self.friction, 0.0))
    for name, value, low in checks:
      if not (math.isfinite(value) and value >= low):
        raise ValueError(f"condition {name} {value!r} must be a finite number >= {low}")

  @property
  def floor_friction(self) -> float:
    return STANDARD_FRICTION if self.friction is None else float(self.friction)

  def to_dict(self) -> dict:
    return dataclasses.asdict(self)


@struct.dataclass
class ConditionArrays:
  """Conditions as data, one row per env [B] (see `condition_arrays`)."""

  scenario: jax.Array  # [B] int32 index into SCENARIOS
  terrain: jax.Array  # [B] int32 index into TERRAINS
  extra_torso_mass: jax.Array  # [B] kg
  friction: jax.Array  # [B] floor sliding friction
  torque_limit: jax.Array  # [B] × the stage's actuator force limits
  local_force: jax.Array  # [B, 3] Trunk frame, N
  push_start: jax.Array  # [B] int32 control steps after the control start (never: no push)
  push_steps: jax.Array  # [B] int32 control steps the push lasts


def condition_arrays(env, conditions: Condition | Sequence[Condition],
                     batch: int | None = None) -> ConditionArrays:
  """Rows of `ConditionArrays` for a list of conditions (or `batch` copies of one)."""
  if isinstance(conditions, Condition):
    conditions = [conditions] * (1 if batch is None else batch)
  conditions = list(conditions)
  dt = env.ctrl_dt

  def steps(seconds):
    return int(round(seconds / dt))

  def col(values, dtype):
    return jnp.asarray(np.asarray(values, dtype))

  pushed = [c.push_force > 0 and steps(c.push_duration_s) > 0 for c in conditions]
  return ConditionArrays(
      scenario=col([SCENARIOS.index(c.scenario) for c in conditions], np.int32),
      terrain=col([TERRAINS.index(c.terrain) for c in conditions], np.int32),
      extra_torso_mass=col([c.extra_torso_mass for c in conditions], np.float32),
      friction=col([c.floor_friction for c in conditions], np.float32),
      torque_limit=col([c.torque_limit for c in conditions], np.float32),
      local_force=col([np.asarray(PUSH_DIRECTIONS[c.push_direction]) * c.push_force
                       for c in conditions], np.float32),
      push_start=col([steps(c.push_start_s) if p else _NEVER
                      for c, p in zip(conditions, pushed)], np.int32),
      push_steps=col([steps(c.push_duration_s) if p else 0
                      for c, p in zip(conditions, pushed)], np.int32))


def apply(env, state, arrays: ConditionArrays):
  """An env state with its episodes' physical parameters and push schedule set to `arrays`.

  Acts on the current episode only: an auto-reset draws the nominal parameters again. Extra torso
  mass keeps the Trunk's density (its inertia scales with the mass, as DR's torso_mass does).
  """
  draw = state.draw
  p = draw.params
  trunk, floor = env.trunk, env.randomizer.floor
  m = p.body_mass[:, trunk]
  ratio = (m + arrays.extra_torso_mass) / m
  params = p.replace(
      body_mass=p.body_mass.at[:, trunk].multiply(ratio),
      body_inertia=p.body_inertia.at[:, trunk].multiply(ratio[:, None]),
      geom_friction=p.geom_friction.at[:, floor, 0].set(arrays.friction),
      actuator_forcerange=p.actuator_forcerange * arrays.torque_limit[:, None, None])
  trunk_col = int(np.flatnonzero(np.asarray(env.randomizer.body_ids) == trunk)[0])
  draw = draw.replace(params=params, friction=arrays.friction,
                      mass_scale=draw.mass_scale.at[:, trunk_col].multiply(ratio))
  never = jnp.int32(_NEVER)
  pushed = arrays.push_start != never
  start = jnp.where(pushed, state.control_start + arrays.push_start, never)
  end = jnp.where(pushed, start + arrays.push_steps, never)
  push = state.push.replace(local_force=arrays.local_force, scheduled_start=start,
                            scheduled_end=end)
  return state.replace(draw=draw, push=push)


def start_arrays(env, keys: jax.Array, arrays: ConditionArrays):
  """Resets B episodes [keys: B] under per-env conditions (pure; jit it with the rollout)."""
  state = env.reset(keys, scenario=arrays.scenario, terrain=arrays.terrain)
  return apply(env, state, arrays)


def start(env, keys: jax.Array, condition: Condition):
  """Reset of B episodes under one condition. `env` must be built from `evaluation_stage`."""
  return start_arrays(env, keys, condition_arrays(env, condition, batch=keys.shape[0]))


def nominal_setup(env) -> dict:
  """The standard setup every cell starts from, as recorded in eval.json."""
  s = env.stage
  trunk_mass = float(env.mj_model.body_mass[env.trunk])
  return {
      "torso_mass_kg": trunk_mass, "friction": STANDARD_FRICTION,
      "domain_randomization": False, "random_pushes": False, "control_delay_s": 0.0,
      "terrain": "flat", "slope_max_deg": s.terrain.slope_max_deg,
      "torque_limit_scale": s.constraints.torque_limit_scale,
      "episode_s": s.sim.episode_s, "ctrl_dt": s.sim.ctrl_dt, "timestep": s.sim.timestep,
      "settle_s": s.scenario_params.settle_s,
      "success": dataclasses.asdict(s.success),
  }
