"""The stage table of a curriculum, checked and turned into a typed `StageConfig`.

The curriculum TOML (docs/contracts.md, "Curriculum TOML") is parsed and type-checked by the
Rust CLI; what reaches Python is the stage table as a dict. `parse_stage` turns it into the
frozen dataclasses of `jax_env.stage_config`, checking every value here, once: names against
the vocabularies their modules own (`jax_env.names`), ranges, mixtures that sum to 1, relations
between keys. Errors name the offending value and list the valid ones.

`check_stage` collects *all* problems with their key paths (for the CLI, which maps each path
to a TOML line); `parse_stage` raises the first one as `ConfigError`. This module is the one
owner of a stage's meaning (ranges, sums, relations between keys, joint symmetry); the CLI checks
only TOML syntax, types, names and the relations between stages, and prints these messages as
they are, so they use its words: `key = value` with numbers as the CLI prints them (`_show`).
"""

from __future__ import annotations

import dataclasses
import json
import math
from typing import Any, Mapping, Sequence

import numpy as np

from jax_env.features import mirror_joint_name
from jax_env.names import (ACTIVATIONS, DR_PARAMS, JOINT_NAMES, KEYFRAMES, REWARD_TERMS,
                           SCENARIOS, TERRAINS)
from jax_env.stage_config import (ACTION_MAPPINGS, DR_DISTRIBUTIONS, DR_OPERATIONS,
                                  LR_SCHEDULES, ON_MISS, SCHEDULE_KEYS, ActionConfig,
                                  AdvanceConfig, AssistConfig, ConstraintsConfig, DelayConfig,
                                  DomainRandomizationConfig, DRParam, ImitationConfig,
                                  MirrorConfig,
                                  MonitorConfig, PPOConfig, PushConfig, RewardParams,
                                  RewardShaping, RMAConfig, ScenarioParams, Schedule,
                                  SimConfig, StageConfig, SuccessConfig, TERMINATION_RULES,
                                  TerminationConfig, TerrainConfig)

__all__ = [
    "ConfigError", "check_stage", "parse_stage",
    # The typed stage (jax_env.stage_config), re-exported as this module's result types.
    "ActionConfig", "AdvanceConfig", "AssistConfig", "ConstraintsConfig", "DelayConfig",
    "DomainRandomizationConfig", "DRParam", "ImitationConfig", "MirrorConfig", "MonitorConfig",
    "PPOConfig", "PushConfig", "RewardParams", "RewardShaping", "RMAConfig", "ScenarioParams",
    "Schedule", "SimConfig", "StageConfig", "SuccessConfig", "TerminationConfig", "TerrainConfig",
]

_SUM_TOLERANCE = 1e-6


class ConfigError(ValueError):
  """A bad value in a stage table; `path` is relative to the stage table."""

  def __init__(self, path: Sequence[str | int], message: str):
    self.path = tuple(path)
    self.message = message
    where = ".".join(str(p) for p in self.path) or "<stage>"
    super().__init__(f"{where}: {message}")


def _valid(names: Sequence[str]) -> str:
  return "valid: " + ", ".join(names)


def _show(v) -> str:
  """A number as the CLI prints one (Rust's `{}`): an integer as it is, a float in its shortest
  round-trip digits, never with an exponent or a trailing ".0"."""
  if isinstance(v, int) and not isinstance(v, bool):
    return str(v)
  v = float(v)
  if math.isnan(v):
    return "NaN"
  if math.isinf(v):
    return "inf" if v > 0 else "-inf"
  return np.format_float_positional(v, trim="-")


def _pair(lo, hi) -> str:
  return f"[{_show(lo)}, {_show(hi)}]"


def parse_stage(d: Mapping[str, Any]) -> StageConfig:
  """Parses a stage table; raises ConfigError for the first problem found."""
  parser = _Parser()
  stage = parser.stage(d)
  if parser.errors:
    path, message, _ = parser.errors[0]
    raise ConfigError(path, message)
  return stage


def check_stage(d: Mapping[str, Any]) -> list[dict]:
  """Every problem in a stage table as [{"path": [...], "message": str, "at": "key"|"value"}]
  (empty when valid); `at` says which end of the `key = value` pair is at fault.

  A curriculum's stage is also refused where it parses but could never succeed (`hold_s` not
  shorter than the episode); stages derived in Python, such as a recording shorter than
  `hold_s`, stay valid for `parse_stage`.
  """
  parser = _Parser(curriculum=True)
  parser.stage(d)
  return [{"path": list(p), "message": m, "at": at} for p, m, at in parser.errors]


# ---------------------------------------------------------------------------------------------
# Parsing with error collection.

_MISSING = object()


class _Parser:
  """Builds the dataclasses while collecting (path, message) errors instead of raising.

  Every helper returns None for a bad value, so one pass reports all problems.
  """

  def __init__(self, curriculum: bool = False):
    self.errors: list[tuple[tuple, str, str]] = []
    self.curriculum = curriculum
    # The stage's episode length once it checked out (later sections compare against it).
    self.episode_s: float | None = None

  def err(self, path, message, at="key"):
    self.errors.append((tuple(path), message, at))

  def bad_value(self, path, message):
    self.err(path, message, at="value")

  # -- primitive helpers ----------------------------------------------------------------------

  def table(self, d, path, required: Sequence[str], optional: Sequence[str] = ()):
    if not isinstance(d, Mapping):
      self.err(path, f"expected a table, got {type(d).__name__}")
      return None
    known = set(required) | set(optional)
    for k in d:
      if k not in known:
        self.err(list(path) + [k], f"unknown key '{k}'; {_valid(list(required) + list(optional))}")
    for k in required:
      if k not in d:
        self.err(list(path) + [k], f"missing required key '{k}'")
    return d

  def number(self, d, key, path, *, minimum=None, exclusive=False, maximum=None, integer=False,
             default=_MISSING):
    p = list(path) + [key]
    if d is None or key not in d:
      return None if default is _MISSING else default
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)):
      self.bad_value(p, f"expected a number, got {v!r}")
      return None
    if integer and not (isinstance(v, int) or float(v).is_integer()):
      self.bad_value(p, f"expected an integer, got {v!r}")
      return None
    if not math.isfinite(v):
      self.bad_value(p, f"{key} = {_show(v)} must be a finite number")
      return None
    if ((minimum is not None and (v <= minimum if exclusive else v < minimum))
        or (maximum is not None and v > maximum)):
      if integer and exclusive and minimum == 0 and maximum is None:
        expected = "a positive integer"
      else:
        bounds = [] if minimum is None else [f"{'>' if exclusive else '>='} {_show(minimum)}"]
        bounds += [] if maximum is None else [f"<= {_show(maximum)}"]
        expected = " and ".join(bounds)
      self.bad_value(p, f"{key} = {_show(v)} is out of range; expected {expected}")
      return None
    return int(v) if integer else float(v)

  def boolean(self, d, key, path, default=None):
    if d is None or key not in d:
      return default
    v = d[key]
    if not isinstance(v, bool):
      self.err(list(path) + [key], f"expected true or false, got {v!r}")
      return None
    return v

  def choice(self, d, key, path, choices):
    if d is None or key not in d:
      return None
    v = d[key]
    if v not in choices:
      self.err(list(path) + [key], f"unknown value {v!r}; {_valid(choices)}")
      return None
    return v

  def string(self, d, key, path):
    if d is None or key not in d:
      return None
    v = d[key]
    if not isinstance(v, str) or not v:
      self.err(list(path) + [key], f"expected a non-empty string, got {v!r}")
      return None
    return v

  def int_list(self, d, key, path):
    if d is None or key not in d:
      return None
    v = d[key]
    if not isinstance(v, (list, tuple)):
      self.bad_value(list(path) + [key], f"expected a list of layer sizes, got {v!r}")
      return None
    ok = bool(v)
    if not v:
      self.bad_value(list(path) + [key], f"{key} is empty; expected at least one hidden layer size")
    for i, x in enumerate(v):
      if isinstance(x, bool) or not isinstance(x, int):
        self.bad_value(list(path) + [key, i], f"expected a positive integer, got {x!r}")
        ok = False
      elif x <= 0:
        self.bad_value(list(path) + [key, i], f"{key}[{i}] = {x}; layer sizes must be positive")
        ok = False
    return tuple(int(x) for x in v) if ok else None

  def pair(self, v, p, *, ordered=True):
    if (not isinstance(v, (list, tuple)) or len(v) != 2
        or any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in v)):
      self.bad_value(p, f"expected [min, max] (two numbers), got {v!r}")
      return None
    lo, hi = float(v[0]), float(v[1])
    if ordered and lo > hi:
      self.bad_value(p, f"min {_show(lo)} > max {_show(hi)}")
      return None
    return lo, hi

  def mixture(self, d, path, names, what, extra_keys=()):
    """Weights ≥ 0 over `names` (omitted ones 0) that sum to 1."""
    if not isinstance(d, Mapping):
      self.err(path, f"expected a table of {what} weights")
      return None
    weights = {n: 0.0 for n in names}
    ok = True
    for k, v in d.items():
      if k in extra_keys:
        continue
      if k not in names:
        self.err(list(path) + [k], f"unknown {what} '{k}'; {_valid(names)}")
        ok = False
        continue
      w = self.number(d, k, path)
      if w is None:
        ok = False
        continue
      if w < 0:
        self.bad_value(list(path) + [k], f"{what} weight {k} = {_show(w)} must be a finite "
                       "number >= 0")
        ok = False
        continue
      weights[k] = w
    if ok:
      # Summed in vocabulary order, as the CLI has always summed them.
      total = sum(weights.values())
      if abs(total - 1.0) > _SUM_TOLERANCE:
        parts = " + ".join(f"{k} = {_show(w)}" for k, w in weights.items() if w)
        self.err(path, f"{what} weights must sum to 1, got {_show(total)} "
                 f"({parts or 'nothing'})")
        ok = False
    return weights if ok else None

  def joints(self, d, key):
    if d is None or key not in d:
      return None
    v = d[key]
    if not isinstance(v, (list, tuple)):
      self.bad_value([key], f"expected a list of joint names, got {v!r}")
      return None
    if not v:
      self.bad_value([key], f"{key} is empty; expected a list of joint names")
      return None
    seen, ok = set(), True
    for i, j in enumerate(v):
      if j not in JOINT_NAMES:
        self.bad_value([key, i], f"unknown joint {json.dumps(j)}; valid joints: "
                       f"{', '.join(JOINT_NAMES)}")
        ok = False
      elif j in seen:
        self.bad_value([key, i], f"joint {json.dumps(j)} is listed twice in {key}")
        ok = False
      seen.add(j)
    if not ok:
      return None
    # The mirror loss permutes features within a list, so it must hold every mirror partner.
    missing = [f"{mirror_joint_name(j)} (mirror of {j})" for j in v
               if mirror_joint_name(j) not in seen]
    if missing:
      self.err([key], f"{key} must be left/right symmetric for the mirror loss; missing "
               f"{', '.join(missing)}")
      return None
    return tuple(j for j in JOINT_NAMES if j in seen)

  # -- sections -------------------------------------------------------------------------------

  def stage(self, d) -> StageConfig | None:
    sections = ("sim", "action", "constraints", "scenarios", "scenario_params", "terrain",
                "rewards", "reward_params", "success", "domain_randomization", "delay", "push",
                "ppo", "rma", "mirror", "advance")
    optional = ("reward_shaping", "termination", "monitor", "assist", "imitation")
    if self.table(d, [], ("name", "init_from", "controlled_joints", "observed_joints")
                  + sections, optional) is None:
      return None
    name = self.string(d, "name", [])
    init_from = self.string(d, "init_from", [])
    controlled = self.joints(d, "controlled_joints")
    observed = self.joints(d, "observed_joints")
    if controlled is not None and observed is not None:
      missing = [j for j in d["controlled_joints"] if j not in observed]
      if missing:
        self.err(["observed_joints"], "observed_joints must include every controlled joint; "
                 f"missing {', '.join(missing)}")
    sim = self.sim(d.get("sim"))
    out = dict(
        name=name, init_from=init_from, controlled_joints=controlled, observed_joints=observed,
        sim=sim,
        action=self.action(d.get("action")),
        constraints=self.constraints(d.get("constraints")),
        scenarios=self.scenarios(d.get("scenarios")),
        scenario_params=self.scenario_params(d.get("scenario_params")),
        terrain=self.terrain(d.get("terrain")),
        rewards=self.rewards(d.get("rewards")),
        reward_params=self.reward_params(d.get("reward_params")),
        success=self.success(d.get("success")),
        domain_randomization=self.domain_randomization(d.get("domain_randomization")),
        delay=self.delay(d.get("delay")),
        push=self.push(d.get("push")),
        ppo=self.ppo(d.get("ppo")),
        rma=self.rma(d.get("rma")),
        mirror=self.mirror(d.get("mirror")),
        advance=self.advance(d.get("advance")),
        reward_shaping=self.reward_shaping(d.get("reward_shaping", {})),
        termination=self.termination(d.get("termination", {})),
        monitor=self.monitor(d.get("monitor", {})),
        assist=self.assist(d.get("assist", {})),
        imitation=self.imitation(d.get("imitation", {})),
    )
    if self.errors or any(v is None for v in out.values()):
      return None
    return StageConfig(**out)

  def _section(self, d, name, required, optional=()):
    if d is None:
      return None  # already reported as missing by `stage`
    return self.table(d, [name], required, optional)

  def _all(self, cls, values):
    return None if any(v is None for v in values.values()) else cls(**values)

  def sim(self, d):
    p = ["sim"]
    d = self._section(d, "sim", ("timestep", "ctrl_dt", "episode_s"))
    timestep = self.number(d, "timestep", p, minimum=0.0, exclusive=True)
    ctrl_dt = self.number(d, "ctrl_dt", p, minimum=0.0, exclusive=True)
    episode_s = self.number(d, "episode_s", p, minimum=0.0, exclusive=True)
    if timestep and ctrl_dt:
      ratio = ctrl_dt / timestep
      if ratio < 1.0 - 1e-9 or abs(ratio - round(ratio)) > 1e-6:
        self.bad_value(p + ["ctrl_dt"], f"ctrl_dt = {_show(ctrl_dt)} must be an integer multiple "
                       f"of timestep = {_show(timestep)} (ratio {_show(ratio)})")
        ctrl_dt = None
    # Later sections compare with the episode length whatever became of ctrl_dt.
    self.episode_s = episode_s
    if ctrl_dt and episode_s is not None and episode_s <= ctrl_dt:
      self.bad_value(p + ["episode_s"], f"episode_s = {_show(episode_s)} must be > ctrl_dt = "
                     f"{_show(ctrl_dt)}")
      episode_s = None
    return self._all(SimConfig, dict(timestep=timestep, ctrl_dt=ctrl_dt, episode_s=episode_s))

  def action(self, d):
    p = ["action"]
    d = self._section(d, "action", ("mapping", "scale", "clip"))
    return self._all(ActionConfig, dict(
        mapping=self.choice(d, "mapping", p, ACTION_MAPPINGS),
        scale=self.number(d, "scale", p, minimum=0.0, exclusive=True),
        clip=self.number(d, "clip", p, minimum=0.0, exclusive=True)))

  def constraints(self, d):
    p = ["constraints"]
    keys = ("torque_limit_scale", "joint_range_scale", "velocity_limit_scale")
    d = self._section(d, "constraints", keys)
    return self._all(ConstraintsConfig,
                     {k: self.number(d, k, p, minimum=0.0, exclusive=True) for k in keys})

  def scenarios(self, d):
    if d is None:
      return None
    if isinstance(d, Mapping):
      # Key-state scenarios are named after keyframes: say so when the name is unknown.
      for k in d:
        if k.startswith("ksi_") and k not in SCENARIOS:
          self.err(["scenarios", k], f"unknown scenario '{k}': no keyframe '{k}' in the model "
                   f"(keyframes: {', '.join(KEYFRAMES)}); {_valid(SCENARIOS)}")
      d = {k: v for k, v in d.items() if not (k.startswith("ksi_") and k not in SCENARIOS)}
    return self.mixture(d, ["scenarios"], SCENARIOS, "scenario")

  def scenario_params(self, d):
    p = ["scenario_params"]
    d = self._section(d, "scenario_params", ("ksi_joint_noise", "settle_s"),
                      ("path_start_window_s",))
    settle = self.number(d, "settle_s", p, minimum=0.0)
    if settle is not None and self.episode_s is not None and settle >= self.episode_s:
      self.bad_value(p + ["settle_s"], f"settle_s = {_show(settle)} must be < episode_s = "
                     f"{_show(self.episode_s)}")
      settle = None
    windows = self.path_start_window(d.get("path_start_window_s", {}) if d else {},
                                     p + ["path_start_window_s"])
    return self._all(ScenarioParams, dict(
        ksi_joint_noise=self.number(d, "ksi_joint_noise", p, minimum=0.0), settle_s=settle,
        path_start_window_s=windows))

  def path_start_window(self, d, p):
    from jax_env.scenarios import PATH_SCENARIOS  # the path scenarios are the sampler's
    if not isinstance(d, Mapping):
      self.err(p, "expected a table of path scenario = seconds")
      return None
    out = {}
    for k in d:
      if k not in PATH_SCENARIOS:
        self.err(p + [k], f"unknown path scenario '{k}'; {_valid(list(PATH_SCENARIOS))}")
        continue
      out[k] = self.number(d, k, p, minimum=0.0, exclusive=True)
    return None if any(v is None for v in out.values()) or len(out) < len(d) else out

  def terrain(self, d):
    if d is None:
      return None
    p = ["terrain"]
    if "slope_max_deg" not in d:
      self.err(p + ["slope_max_deg"], "missing required key 'slope_max_deg'")
    slope = self.number(d, "slope_max_deg", p, minimum=0.0, maximum=30.0)
    weights = self.mixture(d, p, TERRAINS, "terrain", extra_keys=("slope_max_deg",))
    return self._all(TerrainConfig, dict(weights=weights, slope_max_deg=slope))

  def rewards(self, d):
    if d is None:
      return None
    if not isinstance(d, Mapping):
      self.err(["rewards"], "expected a table of reward weights")
      return None
    weights = {t: 0.0 for t in REWARD_TERMS}
    ok = True
    for k in d:
      if k not in REWARD_TERMS:
        self.err(["rewards", k], f"unknown reward term '{k}'; {_valid(REWARD_TERMS)}")
        ok = False
        continue
      w = self.number(d, k, ["rewards"])
      if w is None:
        ok = False
      else:
        weights[k] = w
    return weights if ok else None

  def reward_params(self, d):
    p = ["reward_params"]
    d = self._section(d, "reward_params",
                      ("base_height_target", "base_height_sigma", "hip_roll_ref"),
                      ("waist_height_target", "dof_pos_ref_band", "face_down_gate",
                       "head_down_gate"))
    gates = {k: self.gravity_gate(d, k, p) for k in ("face_down_gate", "head_down_gate")}
    params = self._all(RewardParams, dict(
        base_height_target=self.number(d, "base_height_target", p, minimum=0.0, exclusive=True),
        base_height_sigma=self.number(d, "base_height_sigma", p, minimum=0.0, exclusive=True),
        hip_roll_ref=self.number(d, "hip_roll_ref", p),
        waist_height_target=self.number(d, "waist_height_target", p, minimum=0.0,
                                        exclusive=True, default=RewardParams.waist_height_target),
        dof_pos_ref_band=self.number(d, "dof_pos_ref_band", p, minimum=0.0,
                                     default=RewardParams.dof_pos_ref_band)))
    # An absent gate is None (no gate); a gate given but invalid has been reported.
    if params is None or any(d is not None and k in d and v is None for k, v in gates.items()):
      return None
    return dataclasses.replace(params, **gates)

  def gravity_gate(self, d, key, p):
    """`[full, zero]`: a gate on a Trunk-frame gravity component, which lies in [-1, 1]."""
    if d is None or key not in d:
      return None
    pair = self.pair(d[key], p + [key], ordered=False)
    if pair is None:
      return None
    full, zero = pair
    if not -1.0 <= full < zero <= 1.0:
      self.bad_value(p + [key], f"{key} = {_pair(full, zero)}: expected [full, zero] with "
                     f"-1 <= full < zero <= 1 (gravity components in the Trunk frame)")
      return None
    return pair

  def reward_shaping(self, d):
    p = ["reward_shaping"]
    d = self._section(d, "reward_shaping", (),
                      ("scale_by_ctrl_dt", "clip_at_zero", "penalty_schedule"))
    if d is None:
      return None
    default = RewardShaping()
    out = dict(
        scale_by_ctrl_dt=self.boolean(d, "scale_by_ctrl_dt", p, default.scale_by_ctrl_dt),
        clip_at_zero=self.boolean(d, "clip_at_zero", p, default.clip_at_zero))
    schedule = None
    if "penalty_schedule" in d:
      schedule = self.penalty_schedule(d["penalty_schedule"], p + ["penalty_schedule"])
      if schedule is None:
        return None
    if any(v is None for v in out.values()):
      return None
    return RewardShaping(penalty_schedule=schedule, **out)

  def penalty_schedule(self, d, p):
    d = self.table(d, p, ("by", "points"))
    if d is None or "by" not in d or "points" not in d:
      return None
    by = self.choice(d, "by", p, SCHEDULE_KEYS)
    v = d["points"]
    if not isinstance(v, (list, tuple)) or not v:
      self.err(p + ["points"], f"expected a non-empty list of [x, scale] pairs, got {v!r}")
      return None
    points = []
    for i, pt in enumerate(v):
      pair = self.pair(pt, p + ["points", i], ordered=False)
      if pair is None:
        return None
      if pair[1] < 0:
        self.err(p + ["points", i], f"scale {pair[1]!r} must be >= 0")
        return None
      if points and pair[0] < points[-1][0]:
        self.err(p + ["points", i], f"x {pair[0]!r} is below the previous point's "
                 f"{points[-1][0]!r}; points must be in increasing x")
        return None
      points.append(pair)
    if by is None:
      return None
    if by == "stand_rate" and any(not 0.0 <= x <= 1.0 for x, _ in points):
      self.err(p + ["points"], "stand-rate points must have x in [0, 1]")
      return None
    return Schedule(by=by, points=tuple(points))

  def termination(self, d):
    p = ["termination"]
    # components of the unit gravity vector, ≤ 1
    gravity_limits = TERMINATION_RULES[1:] + ("upside_down_face_down_max_roll",)
    keys = ("low_height", "low_height_s") + gravity_limits
    d = self._section(d, "termination", (), keys)
    default = TerminationConfig()
    values = {k: self.number(d, k, p, minimum=0.0, default=getattr(default, k)) for k in keys}
    if values["low_height_s"] is not None and values["low_height_s"] <= 0:
      self.err(p + ["low_height_s"], f"{values['low_height_s']!r} must be > 0")
      values["low_height_s"] = None
    for k in gravity_limits:
      if values[k] is not None and values[k] > 1.0:
        self.err(p + [k], f"{values[k]!r} must be <= 1 (a component of the unit gravity "
                 "vector; 0 disables)")
        values[k] = None
    return self._all(TerminationConfig, values)

  def assist(self, d):
    p = ["assist"]
    d = self._section(d, "assist", (), ("force", "schedule"))
    force = self.number(d, "force", p, minimum=0.0, default=AssistConfig().force)
    valid, schedule = self.optional_schedule(d, p)
    if force is None or not valid:
      return None
    return AssistConfig(force=force, schedule=schedule)

  def imitation(self, d):
    p = ["imitation"]
    d = self._section(d, "imitation", (), ("weight", "schedule", "forcing"))
    weight = self.number(d, "weight", p, minimum=0.0, default=ImitationConfig().weight)
    forcing = self.number(d, "forcing", p, minimum=0.0, maximum=1.0,
                          default=ImitationConfig().forcing)
    valid, schedule = self.optional_schedule(d, p)
    if weight is None or forcing is None or not valid:
      return None
    return ImitationConfig(weight=weight, schedule=schedule, forcing=forcing)

  def optional_schedule(self, d, p):
    """A section's optional `schedule` (assist, imitation): (valid, the Schedule or None)."""
    if d is None or "schedule" not in d:
      return True, None
    schedule = self.penalty_schedule(d["schedule"], p + ["schedule"])
    return schedule is not None, schedule

  def monitor(self, d):
    p = ["monitor"]
    d = self._section(d, "monitor", (), ("every", "episodes", "scenarios", "keep_best"))
    default = MonitorConfig()
    every = self.number(d, "every", p, minimum=0, integer=True, default=default.every)
    episodes = self.number(d, "episodes", p, minimum=0, exclusive=True, integer=True,
                           default=default.episodes)
    scenarios = ()
    if d is not None and "scenarios" in d:
      v = d["scenarios"]
      if not isinstance(v, (list, tuple)) or not v:
        self.err(p + ["scenarios"], f"expected a non-empty list of scenario names, got {v!r}")
        return None
      for i, name in enumerate(v):
        if name not in SCENARIOS:
          self.err(p + ["scenarios", i], f"unknown scenario {name!r}; {_valid(SCENARIOS)}")
          return None
      scenarios = tuple(v)
    keep_best = self.boolean(d, "keep_best", p, default.keep_best)
    if keep_best and every == 0:
      self.err(p + ["keep_best"], "keep_best needs the monitor on (every > 0): it keeps the "
               "parameters of the best monitor point")
      return None
    if every is None or episodes is None:
      return None
    return MonitorConfig(every=every, episodes=episodes, scenarios=scenarios,
                         keep_best=keep_best)

  def success(self, d):
    p = ["success"]
    keys = ("height_tolerance", "upright_tolerance", "dof_tolerance", "hold_s")
    d = self._section(d, "success", keys)
    values = {k: self.number(d, k, p, minimum=0.0, exclusive=True) for k in keys}
    hold = values["hold_s"]
    if (self.curriculum and hold is not None and self.episode_s is not None
        and hold >= self.episode_s):
      self.bad_value(p + ["hold_s"], f"hold_s = {_show(hold)} must be < episode_s = "
                     f"{_show(self.episode_s)}: no episode could ever count as standing")
      values["hold_s"] = None
    return self._all(SuccessConfig, values)

  def domain_randomization(self, d):
    if d is None:
      return None
    p = ["domain_randomization"]
    if not isinstance(d, Mapping):
      self.err(p, "expected a table")
      return None
    if "enabled" not in d:
      self.err(p + ["enabled"], "missing required key 'enabled'")
    enabled = self.boolean(d, "enabled", p)
    params, ok = {}, True
    for k, v in d.items():
      if k == "enabled":
        continue
      if k not in DR_PARAMS:
        self.err(p + [k], f"unknown domain-randomization parameter '{k}'; {_valid(DR_PARAMS)}")
        ok = False
        continue
      q = p + [k]
      t = self.table(v, q, ("range", "operation", "distribution"))
      if t is None or any(x not in t for x in ("range", "operation", "distribution")):
        ok = False
        continue
      op = self.choice(t, "operation", q, DR_OPERATIONS)
      dist = self.choice(t, "distribution", q, DR_DISTRIBUTIONS)
      rng = self.pair(t["range"], q + ["range"], ordered=False)
      if rng is not None and dist == "uniform" and rng[0] > rng[1]:
        self.bad_value(q + ["range"], f"{k}.range = {_pair(*rng)}: min {_show(rng[0])} > max "
                       f"{_show(rng[1])} (uniform ranges are [low, high])")
        rng = None
      elif rng is not None and dist == "gaussian" and rng[1] < 0:
        self.bad_value(q + ["range"], f"{k}.range = {_pair(*rng)}: gaussian ranges are [mean, "
                       f"std] and std {_show(rng[1])} must be >= 0")
        rng = None
      if op is None or dist is None or rng is None:
        ok = False
        continue
      params[k] = DRParam(range=rng, operation=op, distribution=dist)
    if enabled is None or not ok:
      return None
    return DomainRandomizationConfig(enabled=enabled, params=params)

  def delay(self, d):
    d = self._section(d, "delay", ("max_s",))
    return self._all(DelayConfig, dict(max_s=self.number(d, "max_s", ["delay"], minimum=0.0)))

  def push(self, d):
    p = ["push"]
    d = self._section(d, "push", ("enabled", "interval_s", "duration_s", "force_max",
                                  "torque_max"))
    interval = None
    if d is not None and "interval_s" in d:
      interval = self.pair(d["interval_s"], p + ["interval_s"], ordered=False)
      if interval is not None and interval[0] <= 0:
        self.bad_value(p + ["interval_s"], f"interval_s = {_pair(*interval)}: both must be "
                       "finite and the min > 0")
        interval = None
      elif interval is not None and interval[0] > interval[1]:
        self.bad_value(p + ["interval_s"], f"interval_s = {_pair(*interval)}: min "
                       f"{_show(interval[0])} > max {_show(interval[1])}")
        interval = None
    return self._all(PushConfig, dict(
        enabled=self.boolean(d, "enabled", p), interval_s=interval,
        duration_s=self.number(d, "duration_s", p, minimum=0.0),
        force_max=self.number(d, "force_max", p, minimum=0.0),
        torque_max=self.number(d, "torque_max", p, minimum=0.0)))

  def ppo(self, d):
    p = ["ppo"]
    ints = ("num_envs", "unroll_length", "num_minibatches", "update_epochs", "checkpoint_every")
    pos = ("learning_rate", "desired_kl", "clip_epsilon", "reward_scaling", "initial_action_std")
    nonneg = ("entropy_cost", "value_loss_coef", "max_grad_norm")
    unit = ("discount", "gae_lambda")
    d = self._section(d, "ppo", ints + pos + nonneg + unit + (
        "lr_schedule", "normalize_observations", "policy_hidden", "value_hidden", "activation"),
        ("max_action_std", "action_std_schedule", "action_noise_correlation"))
    v = {k: self.number(d, k, p, minimum=0, exclusive=True, integer=True) for k in ints}
    if v["num_envs"] is not None and v["num_minibatches"] is not None:
      if v["num_envs"] % v["num_minibatches"]:
        self.bad_value(p + ["num_envs"], f"num_envs = {v['num_envs']} is not divisible by "
                       f"num_minibatches = {v['num_minibatches']} (each minibatch takes whole "
                       "environments)")
        v["num_envs"] = None
    v.update({k: self.number(d, k, p, minimum=0.0, exclusive=True) for k in pos})
    v.update({k: self.number(d, k, p, minimum=0.0) for k in nonneg})
    v.update({k: self.number(d, k, p, minimum=0.0, maximum=1.0) for k in unit})
    v.update(lr_schedule=self.choice(d, "lr_schedule", p, LR_SCHEDULES),
             normalize_observations=self.boolean(d, "normalize_observations", p),
             policy_hidden=self.int_list(d, "policy_hidden", p),
             value_hidden=self.int_list(d, "value_hidden", p),
             activation=self.choice(d, "activation", p, ACTIVATIONS))
    ppo = self._all(PPOConfig, v)
    if ppo is not None and d is not None and "action_noise_correlation" in d:
      # ρ = 1 would freeze the noise for a whole rollout: a fixed offset, not exploration.
      rho = self.number(d, "action_noise_correlation", p, minimum=0.0, maximum=1.0)
      if rho is not None and rho >= 1.0:
        self.err(p + ["action_noise_correlation"],
                 f"action_noise_correlation {rho!r} must be below 1")
        rho = None
      ppo = None if rho is None else dataclasses.replace(ppo, action_noise_correlation=rho)
    if ppo is not None and d is not None and "action_std_schedule" in d:
      ppo = self.action_std_schedule(d, p, ppo)
    if ppo is None or d is None or "max_action_std" not in d:
      return ppo
    bound = self.number(d, "max_action_std", p, minimum=0.0, exclusive=True)
    if bound is not None and bound < ppo.initial_action_std:
      self.err(p + ["max_action_std"], f"max_action_std {bound!r} is below "
               f"initial_action_std {ppo.initial_action_std!r}")
      bound = None
    return None if bound is None else dataclasses.replace(ppo, max_action_std=bound)

  def action_std_schedule(self, d, p, ppo):
    """`action_std_schedule`: a penalty-style schedule whose scales, in (0, 1], multiply
    `max_action_std` (which it needs: it tightens a bound, it does not make one)."""
    at = p + ["action_std_schedule"]
    schedule = self.penalty_schedule(d["action_std_schedule"], at)
    if schedule is None:
      return None
    if "max_action_std" not in d:
      self.err(at, "action_std_schedule scales max_action_std, which is not set")
      return None
    for i, (_, s) in enumerate(schedule.points):
      if not 0.0 < s <= 1.0:
        self.err(at + ["points", i], f"scale {s!r} must be in (0, 1]: the schedule tightens "
                 "max_action_std")
        return None
    return dataclasses.replace(ppo, action_std_schedule=schedule)

  def rma(self, d):
    p = ["rma"]
    d = self._section(d, "rma", ("enabled", "latent_dim", "encoder_hidden", "history_len",
                                 "adaptation_env_steps", "adaptation_learning_rate"),
                      ("latent_regularization",))
    rma = self._all(RMAConfig, dict(
        enabled=self.boolean(d, "enabled", p),
        latent_dim=self.number(d, "latent_dim", p, minimum=0, exclusive=True, integer=True),
        encoder_hidden=self.int_list(d, "encoder_hidden", p),
        history_len=self.number(d, "history_len", p, minimum=0, exclusive=True, integer=True),
        adaptation_env_steps=self.number(d, "adaptation_env_steps", p, minimum=0, integer=True),
        adaptation_learning_rate=self.number(d, "adaptation_learning_rate", p, minimum=0.0,
                                             exclusive=True)))
    if rma is None or "latent_regularization" not in d:
      return rma
    weight = self.number(d, "latent_regularization", p, minimum=0.0)
    if weight is not None and weight > 0 and not rma.enabled:
      self.err(p + ["latent_regularization"], f"latent_regularization {weight!r} needs "
               "enabled = true: without RMA there is no latent to regularize")
      weight = None
    return None if weight is None else dataclasses.replace(rma, latent_regularization=weight)

  def mirror(self, d):
    d = self._section(d, "mirror", ("weight",))
    return self._all(MirrorConfig, dict(weight=self.number(d, "weight", ["mirror"], minimum=0.0)))

  def advance(self, d):
    p = ["advance"]
    d = self._section(d, "advance", ("env_steps", "window", "on_miss"), ("min_stand_rate",))
    if d is None:
      return None
    values = dict(
        env_steps=self.number(d, "env_steps", p, minimum=0, exclusive=True, integer=True),
        window=self.number(d, "window", p, minimum=0, exclusive=True, integer=True),
        on_miss=self.choice(d, "on_miss", p, ON_MISS))
    if any(v is None for v in values.values()):
      return None
    rate = None
    if "min_stand_rate" in d:
      rate = self.number(d, "min_stand_rate", p, minimum=0.0, maximum=1.0)
      if rate is None:
        return None
    return AdvanceConfig(min_stand_rate=rate, **values)
