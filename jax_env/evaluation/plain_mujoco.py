"""Sim-to-sim check: an exported ONNX actor driven in plain C MuJoCo, stand rate per start state.

This is the "plain MuJoCo" measurement beside `hifar eval`: it shares no code with the
environment (`jax_env.env`, `jax_env.scenarios`, `jax_env.physics`, `jax_env.randomization`,
the learner). Everything it needs comes from two places:

  * the ONNX file's metadata (`jax_env.export.metadata_props`): obs_names, action_names,
    history_len, ctrl_dt, the action mapping {mapping, scale, clip} and q_stand; a stage table
    under `stage_config` (or top-level `timestep` / `success` entries), where an export carries
    one, gives the physics timestep and the success tolerances;
  * the MJCF scene `assets/t1/scene.xml` (`jax_env.robot.load_model`): joints, actuators, the
    IMU site and gyro, keyframes, torque limits and joint ranges as loaded. The one number
    MuJoCo has no field for, the joint velocity limits, is `jax_env.robot.VELOCITY_LIMITS`.

One control step (every ctrl_dt):
  1. obs in the order of obs_names, from `mujoco.MjData` as a plain `mj_step` loop leaves it:
     `gravity/*` = unit gravity (opt.gravity) in the IMU site frame; `ang_vel/*` = the gyro
     sensor (the Trunk's body-frame angular velocity where the model has no gyro);
     `joint_pos/<J>` = q − q_stand; `joint_vel/<J>` = q̇; `prev_action/<J>` = the previous
     action as applied (clipped; 0 at the start). Sensors and frame orientations are those of
     the last substep's forward pass, positions and velocities those after it — the same
     snapshot the environment's native and MJX backends observe.
  2. action = the ONNX `action` output for (obs, history); history [H, n_obs] holds the H
     observations before obs, oldest first, zeros at the start (after each step: drop the
     oldest, append obs) — the convention of `hifar act` and of the export's description.
  3. PD targets: controlled joints base + scale · clip(action, ±clip) with base = q_stand
     ("default") or the measured q ("current"); every other joint its `stand` keyframe angle.
     As the export's description asks of the robot's controller, a target may not drive a joint
     that is already at its velocity limit any faster (τ = kp(target − q) − kd q̇ gets no
     component along q̇), and every target is clamped to the joint range.
  4. ctrl_dt / timestep substeps of `mj_step` with those targets as actuator ctrl.

Physics: the scene as loaded (the real robot's torque limits, joint ranges and velocity limits,
whatever a stage's `constraints` relaxed in training; floor friction 1.0), no randomization, no
delay, no pushes; the timestep is the metadata's (the curriculum's) if it has one, else the
scene's `opt.timestep`. As in `hifar eval` (and the paper) no termination rule ends a trial:
every trial runs `duration_s` or until it succeeds.

Start states: the model's keyframes of the given names (`mj_resetDataKeyframe`). Trial 0 starts
at the keyframe exactly; later trials add N(0, 0.05²) rad to every joint (seeded, clipped to the
joint range) and lift the base out of any floor penetration that causes (the heading is the
keyframe's; the environment's resets also turn the robot to a random heading).

Success: the environment's detector — after each control step, "standing" is
|Trunk height − stand height| ≤ height_tolerance, ‖gravity_xy‖ ≤ upright_tolerance and every
observed joint (a `joint_pos/<J>` input) within dof_tolerance of `stand`; success is hold_s of
consecutive standing steps, and the recovery time is the start of that streak (0 for a robot
that stands from the first step). Without tolerances in the metadata: 0.05 m, 0.2, 0.3 rad, 1 s.
A numerical blow-up (non-finite state or a MuJoCo instability warning) fails the trial.

CLI: `python -m jax_env.evaluation.plain_mujoco MODEL.onnx [--trials N] [--duration S]
[--seed N] [--json OUT]` prints one row per start state: successes/trials and the mean recovery
time.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path

import mujoco
import numpy as np

from jax_env import robot

FORMAT_VERSION = 1
START_STATES = ("stand", "ksi_prone_1", "ksi_prone_2", "ksi_prone_3", "ksi_supine_1",
                "ksi_supine_2", "ksi_supine_3")
# The environment's detector defaults of our curricula (docs/contracts.md, stage.success).
DEFAULT_SUCCESS = {"height_tolerance": 0.05, "upright_tolerance": 0.2, "dof_tolerance": 0.3,
                   "hold_s": 1.0}
JOINT_NOISE = 0.05  # rad, std of the joint noise of trials after the first
STAND_KEY = "stand"
IMU_SITE = "imu"
GYRO_SENSOR = "gyro"
TRUNK_BODY = "Trunk"
FLOOR_GEOM = "floor"
# MuJoCo's warnings that mean the simulation was reset or is no longer trustworthy.
_BLOWUP_WARNINGS = (mujoco.mjtWarning.mjWARN_BADQACC, mujoco.mjtWarning.mjWARN_BADQPOS,
                    mujoco.mjtWarning.mjWARN_BADQVEL)


# ---------------------------------------------------------------------------------------------
# What the ONNX file says.


@dataclasses.dataclass(frozen=True)
class ActorMeta:
  """The deployable actor's interface, parsed from the ONNX metadata."""

  obs_names: tuple[str, ...]
  action_names: tuple[str, ...]
  history_len: int
  ctrl_dt: float
  mapping: str
  scale: float
  clip: float
  q_stand: np.ndarray | None  # [n_act] stand angle of each controlled joint, if given
  timestep: float | None      # physics timestep of the stage, if the metadata has one
  success: dict               # height_tolerance, upright_tolerance, dof_tolerance, hold_s
  success_source: str         # "metadata" or "default"


def _loads(value: str):
  try:
    return json.loads(value)
  except (json.JSONDecodeError, TypeError):
    return value


def read_metadata(onnx_path) -> dict:
  """The ONNX file's metadata_props, JSON values decoded (plain strings kept as they are)."""
  import onnx

  model = onnx.load(str(onnx_path), load_external_data=False)
  return {p.key: _loads(p.value) for p in model.metadata_props}


def _stage_table(props: dict) -> dict:
  for key in ("stage_config", "stage"):
    value = props.get(key)
    if isinstance(value, dict):
      return value
  return {}


def actor_meta(props: dict, where: str = "ONNX", ctrl_dt: float | None = None,
               timestep: float | None = None) -> ActorMeta:
  """Parses the metadata `jax_env.export.metadata_props` writes; `ctrl_dt`/`timestep` override
  (ctrl_dt is required where the export had no stage table to take it from)."""
  missing = [k for k in ("obs_names", "action_names", "history_len", "mapping", "scale", "clip")
             if k not in props]
  if missing:
    raise ValueError(f"{where}: metadata lacks {', '.join(missing)}; is this a `hifar export` "
                     "file?")
  stage = _stage_table(props)
  if ctrl_dt is None:
    ctrl_dt = props.get("ctrl_dt", stage.get("sim", {}).get("ctrl_dt"))
  if ctrl_dt is None:
    raise ValueError(f"{where}: metadata has no ctrl_dt (exported without a stage table); "
                     "give it with --ctrl-dt")
  if timestep is None:
    timestep = props.get("timestep", stage.get("sim", {}).get("timestep"))
  mapping = str(props["mapping"])
  if mapping not in ("default", "current"):
    raise ValueError(f"{where}: unknown action mapping {mapping!r}; valid: default, current")
  success_table = props.get("success", stage.get("success"))
  success = dict(DEFAULT_SUCCESS)
  if isinstance(success_table, dict):
    success.update({k: float(success_table[k]) for k in DEFAULT_SUCCESS if k in success_table})
  q_stand = props.get("q_stand")
  return ActorMeta(
      obs_names=tuple(props["obs_names"]), action_names=tuple(props["action_names"]),
      history_len=int(props["history_len"]), ctrl_dt=float(ctrl_dt), mapping=mapping,
      scale=float(props["scale"]), clip=float(props["clip"]),
      q_stand=None if q_stand is None else np.asarray(q_stand, np.float64),
      timestep=None if timestep is None else float(timestep), success=success,
      success_source="metadata" if isinstance(success_table, dict) else "default")


class OnnxActor:
  """onnxruntime session of the exported actor, one row at a time."""

  def __init__(self, onnx_path, meta: ActorMeta):
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    options.inter_op_num_threads = 1
    options.log_severity_level = 3  # a non-RMA actor's unused `history` input is fine
    self.session = ort.InferenceSession(str(onnx_path), options,
                                        providers=["CPUExecutionProvider"])
    inputs = {i.name for i in self.session.get_inputs()}
    outputs = [o.name for o in self.session.get_outputs()]
    if "obs" not in inputs or "action" not in outputs:
      raise ValueError(f"{onnx_path}: expected input `obs` and output `action`, got inputs "
                       f"{sorted(inputs)} and outputs {outputs}")
    self.has_history = "history" in inputs
    self.outputs = ["action"] + (["joint_target"] if "joint_target" in outputs else [])
    self.meta = meta

  def __call__(self, obs: np.ndarray, history: np.ndarray):
    """(action [n_act], joint_target [n_act] | None) for one observation and its history."""
    feed = {"obs": obs[None].astype(np.float32)}
    if self.has_history:
      feed["history"] = history[None].astype(np.float32)
    out = self.session.run(self.outputs, feed)
    return out[0][0], (out[1][0] if len(out) > 1 else None)


# ---------------------------------------------------------------------------------------------
# The robot as the scene describes it.


class Robot:
  """Indices, gains and limits of the scene's hinge joints, read from the MjModel by name."""

  def __init__(self, model: mujoco.MjModel, meta: ActorMeta, velocity_limit: bool = True):
    self.model = model
    self.joint_names = tuple(model.joint(j).name for j in range(model.njnt)
                             if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE)
    jid = [model.joint(n).id for n in self.joint_names]
    self.qadr = np.array([model.jnt_qposadr[j] for j in jid])
    self.dadr = np.array([model.jnt_dofadr[j] for j in jid])
    self.range_lo = np.array([model.jnt_range[j, 0] for j in jid])
    self.range_hi = np.array([model.jnt_range[j, 1] for j in jid])
    # The position servo driving each joint: ctrl = target, gain kp, bias -kp q - kd q̇.
    act = {}
    for a in range(model.nu):
      if model.actuator_trntype[a] == mujoco.mjtTrn.mjTRN_JOINT:
        act[int(model.actuator_trnid[a, 0])] = a
    missing = [n for n, j in zip(self.joint_names, jid) if j not in act]
    if missing:
      raise ValueError(f"the scene has no actuator for joint(s) {', '.join(missing)}")
    self.act = np.array([act[j] for j in jid])
    self.kp = model.actuator_gainprm[self.act, 0].copy()
    self.kd = -model.actuator_biasprm[self.act, 2].copy()
    vlim = dict(zip(robot.JOINT_NAMES, robot.VELOCITY_LIMITS))
    self.v_max = np.array([vlim.get(n, np.inf) for n in self.joint_names])
    self.velocity_limit = velocity_limit
    index = {n: i for i, n in enumerate(self.joint_names)}

    stand = model.key(STAND_KEY)
    self.q_stand = np.asarray(stand.qpos)[self.qadr].copy()
    self.stand_height = float(stand.qpos[model.jnt_qposadr[self._free_joint()] + 2])
    unknown = [a for a in meta.action_names if a not in index]
    if unknown:
      raise ValueError(f"action_names {', '.join(unknown)} are not joints of the scene")
    self.ctrl = np.array([index[a] for a in meta.action_names])
    # The mapping's base of "default" is the metadata's q_stand; it must be the scene's stand.
    self.q_stand_ctrl = (self.q_stand[self.ctrl] if meta.q_stand is None
                         else np.asarray(meta.q_stand, np.float64))
    if self.q_stand_ctrl.shape != self.ctrl.shape:
      raise ValueError(f"q_stand has {self.q_stand_ctrl.size} entries for "
                       f"{self.ctrl.size} action_names")
    self.q_stand_mismatch = float(np.max(np.abs(self.q_stand_ctrl - self.q_stand[self.ctrl]),
                                         initial=0.0))
    if self.q_stand_mismatch > 1e-4:
      raise ValueError(f"the metadata's q_stand differs from the scene's `stand` keyframe by "
                       f"{self.q_stand_mismatch:.3g} rad: not the robot this actor was "
                       "exported for")
    self.trunk = model.body(TRUNK_BODY).id
    self.free_qadr = int(model.jnt_qposadr[self._free_joint()])
    try:
      self.imu_site = model.site(IMU_SITE).id
    except KeyError:
      self.imu_site = None
    try:
      gyro = model.sensor(GYRO_SENSOR)
      self.gyro = slice(int(gyro.adr[0]), int(gyro.adr[0]) + 3)
    except KeyError:
      self.gyro = None
    try:
      self.floor = model.geom(FLOOR_GEOM).id
    except KeyError:
      self.floor = None
    self.observe = self._observation(meta, index)
    self.observed = np.array(sorted({index[n.split("/", 1)[1]] for n in meta.obs_names
                                     if n.startswith("joint_pos/")}), np.int64)

  def _free_joint(self) -> int:
    free = [j for j in range(self.model.njnt)
            if self.model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE]
    if len(free) != 1:
      raise ValueError(f"expected one free joint in the scene, found {len(free)}")
    return free[0]

  # -- features --------------------------------------------------------------------------------

  def imu_rotation(self, data: mujoco.MjData) -> np.ndarray:
    """World-from-IMU rotation (the imu site's frame, else the Trunk's)."""
    if self.imu_site is not None:
      return data.site_xmat[self.imu_site].reshape(3, 3)
    return data.xmat[self.trunk].reshape(3, 3)

  def gravity(self, data: mujoco.MjData) -> np.ndarray:
    g = np.asarray(self.model.opt.gravity, np.float64)
    return self.imu_rotation(data).T @ (g / np.linalg.norm(g))

  def angular_velocity(self, data: mujoco.MjData) -> np.ndarray:
    if self.gyro is not None:
      return np.asarray(data.sensordata[self.gyro], np.float64)
    # The free joint's angular velocity is already in the Trunk's body frame.
    dof = self.model.jnt_dofadr[self._free_joint()]
    return np.asarray(data.qvel[dof + 3:dof + 6], np.float64)

  def _observation(self, meta: ActorMeta, index: dict):
    """A function (data, prev_action) -> obs [n_obs] float32 in the order of obs_names."""
    axis = {"x": 0, "y": 1, "z": 2}
    action_index = {a: i for i, a in enumerate(meta.action_names)}
    picks = []  # (source, column)
    for name in meta.obs_names:
      kind, _, rest = name.partition("/")
      if kind in ("gravity", "ang_vel") and rest in axis:
        picks.append((kind, axis[rest]))
      elif kind in ("joint_pos", "joint_vel") and rest in index:
        picks.append((kind, index[rest]))
      elif kind == "prev_action" and rest in action_index:
        picks.append((kind, action_index[rest]))
      else:
        raise ValueError(f"observation {name!r} has no plain-MuJoCo implementation here "
                         "(known: gravity/{x,y,z}, ang_vel/{x,y,z}, joint_pos/<J>, "
                         "joint_vel/<J>, prev_action/<controlled J>)")
    kinds = np.array([k for k, _ in picks])
    cols = np.array([c for _, c in picks], np.int64)

    def observe(data: mujoco.MjData, prev_action: np.ndarray) -> np.ndarray:
      sources = {
          "gravity": self.gravity(data),
          "ang_vel": self.angular_velocity(data),
          "joint_pos": np.asarray(data.qpos[self.qadr]) - self.q_stand,
          "joint_vel": np.asarray(data.qvel[self.dadr]),
          "prev_action": np.asarray(prev_action, np.float64),
      }
      out = np.empty(len(picks), np.float64)
      for kind, values in sources.items():
        where = kinds == kind
        out[where] = values[cols[where]]
      return out.astype(np.float32)

    return observe

  # -- control ---------------------------------------------------------------------------------

  def targets(self, data: mujoco.MjData, action: np.ndarray, meta: ActorMeta) -> np.ndarray:
    """PD targets [n_joints] for an action (already clipped)."""
    q = np.asarray(data.qpos[self.qadr], np.float64)
    qd = np.asarray(data.qvel[self.dadr], np.float64)
    target = self.q_stand.copy()
    base = q[self.ctrl] if meta.mapping == "current" else self.q_stand_ctrl
    target[self.ctrl] = base + meta.scale * np.asarray(action, np.float64)
    if self.velocity_limit:
      # No torque along q̇ for a joint at or beyond its velocity limit: τ = 0 at `free`.
      free = q + self.kd * qd / self.kp
      target = np.where(qd >= self.v_max, np.minimum(target, free), target)
      target = np.where(qd <= -self.v_max, np.maximum(target, free), target)
    return np.clip(target, self.range_lo, self.range_hi)

  def standing(self, data: mujoco.MjData, success: dict) -> bool:
    height = float(data.qpos[self.free_qadr + 2])
    g = self.gravity(data)
    q = np.asarray(data.qpos[self.qadr])
    dof_err = float(np.max(np.abs(q - self.q_stand)[self.observed], initial=0.0))
    return (abs(height - self.stand_height) <= success["height_tolerance"]
            and math.hypot(g[0], g[1]) <= success["upright_tolerance"]
            and dof_err <= success["dof_tolerance"])

  def lift_out_of_floor(self, data: mujoco.MjData) -> float:
    """Raises the base until no contact with the floor penetrates; returns the lift (m)."""
    lifted = 0.0
    for _ in range(3):
      mujoco.mj_forward(self.model, data)
      depth = [data.contact.dist[i] for i in range(data.ncon)
               if self.floor in (data.contact.geom1[i], data.contact.geom2[i])]
      low = min(depth, default=0.0)
      if low >= 0.0:
        break
      data.qpos[self.free_qadr + 2] += -low
      lifted += -low
    return lifted


# ---------------------------------------------------------------------------------------------
# Episodes.


def _blowup_count(data: mujoco.MjData) -> int:
  return sum(int(data.warning[w].number) for w in _BLOWUP_WARNINGS)


def run_trial(model: mujoco.MjModel, rob: Robot, actor: OnnxActor, meta: ActorMeta,
              start_state: str, rng: np.random.Generator | None, n_steps: int,
              n_substeps: int) -> dict:
  """One episode from `start_state` (with joint noise where `rng` is given)."""
  data = mujoco.MjData(model)
  mujoco.mj_resetDataKeyframe(model, data, model.key(start_state).id)
  lifted = 0.0
  if rng is not None:
    noise = rng.normal(0.0, JOINT_NOISE, rob.qadr.size)
    data.qpos[rob.qadr] = np.clip(data.qpos[rob.qadr] + noise, rob.range_lo, rob.range_hi)
    lifted = rob.lift_out_of_floor(data)
  data.qvel[:] = 0.0
  mujoco.mj_forward(model, data)

  n_obs, n_act = len(meta.obs_names), len(meta.action_names)
  history = np.zeros((meta.history_len, n_obs), np.float32)
  prev_action = np.zeros(n_act, np.float32)
  obs = rob.observe(data, prev_action)
  hold_steps = max(int(math.ceil(meta.success["hold_s"] / meta.ctrl_dt - 1e-9)), 1)
  streak, success, recovery = 0, False, None
  max_height = float(data.qpos[rob.free_qadr + 2])
  mapping_diff = 0.0
  blowups, blew_up, steps = _blowup_count(data), False, 0
  for step in range(n_steps):
    raw, joint_target = actor(obs, history)
    action = np.clip(raw, -meta.clip, meta.clip).astype(np.float32)
    if joint_target is not None:  # the graph's own mapping, before limits: a consistency check
      base = (rob.q_stand_ctrl if meta.mapping == "default"
              else np.asarray(data.qpos[rob.qadr])[rob.ctrl])
      mapping_diff = max(mapping_diff, float(np.max(np.abs(
          joint_target - (base + meta.scale * action.astype(np.float64))))))
    data.ctrl[rob.act] = rob.targets(data, action, meta)
    for _ in range(n_substeps):
      mujoco.mj_step(model, data)
    steps = step + 1
    if (_blowup_count(data) > blowups or not np.all(np.isfinite(data.qpos))
        or not np.all(np.isfinite(data.qvel))):
      blew_up = True
      break
    if history.shape[0]:
      history = np.concatenate([history[1:], obs[None]], axis=0)
    prev_action = action
    obs = rob.observe(data, prev_action)
    max_height = max(max_height, float(data.qpos[rob.free_qadr + 2]))
    streak = streak + 1 if rob.standing(data, meta.success) else 0
    if streak >= hold_steps:
      success, recovery = True, round((step + 1 - streak) * meta.ctrl_dt, 9)
      break  # latched: nothing later changes the outcome
  return {"success": success, "recovery_time": recovery, "blew_up": blew_up,
          "steps": steps, "max_trunk_height": max_height,
          "final_trunk_height": float(data.qpos[rob.free_qadr + 2]),
          "initial_lift": lifted, "joint_target_max_abs_diff": mapping_diff}


def run(onnx_path, start_states=START_STATES, trials: int = 4, duration_s: float = 6.0,
        seed: int = 0, *, ctrl_dt: float | None = None, timestep: float | None = None,
        velocity_limit: bool = True, scene=None) -> dict:
  """Stand rate of the deterministic actor per start state in plain C MuJoCo.

  Returns {"format_version", "onnx", "mujoco", "seed", "trials", "duration_s", "ctrl_dt",
  "timestep", "n_substeps", "mapping", "scale", "clip", "history_len", "velocity_limit",
  "success_criterion" (tolerances and where they came from), "start_states": [{"start_state",
  "trials", "successes", "success_rate", "recovery_time_mean", "recovery_time_std" (s, over
  successes; None if none), "results": [per trial]}], "joint_target_max_abs_diff"}.
  """
  if trials < 1:
    raise ValueError(f"trials must be at least 1, got {trials}")
  if not duration_s > 0:
    raise ValueError(f"duration must be positive, got {duration_s}")
  onnx_path = Path(onnx_path)
  meta = actor_meta(read_metadata(onnx_path), str(onnx_path), ctrl_dt, timestep)
  model = robot.load_model(scene)
  if meta.timestep is not None:
    model.opt.timestep = meta.timestep
  ratio = meta.ctrl_dt / model.opt.timestep
  n_substeps = int(round(ratio))
  if n_substeps < 1 or abs(ratio - n_substeps) > 1e-6:
    raise ValueError(f"ctrl_dt {meta.ctrl_dt} is not a multiple of the timestep "
                     f"{model.opt.timestep}")
  keys = {model.key(i).name for i in range(model.nkey)}
  unknown = [s for s in start_states if s not in keys]
  if unknown:
    raise ValueError(f"unknown start state(s) {', '.join(unknown)}; the scene's keyframes: "
                     f"{', '.join(sorted(keys))}")
  rob = Robot(model, meta, velocity_limit=velocity_limit)
  actor = OnnxActor(onnx_path, meta)
  n_steps = int(round(duration_s / meta.ctrl_dt))

  cells, mapping_diff = [], 0.0
  for c, name in enumerate(start_states):
    results = []
    for t in range(trials):
      rng = None if t == 0 else np.random.default_rng([seed, c, t])
      r = run_trial(model, rob, actor, meta, name, rng, n_steps, n_substeps)
      mapping_diff = max(mapping_diff, r.pop("joint_target_max_abs_diff"))
      results.append({"trial": t, "joint_noise": 0.0 if rng is None else JOINT_NOISE, **r})
    times = [r["recovery_time"] for r in results if r["success"]]
    cells.append({
        "start_state": name, "trials": trials, "successes": len(times),
        "success_rate": len(times) / trials,
        "recovery_time_mean": float(np.mean(times)) if times else None,
        "recovery_time_std": float(np.std(times)) if times else None,
        "results": results})
  return {
      "format_version": FORMAT_VERSION, "onnx": str(onnx_path.resolve()),
      "mujoco": mujoco.__version__, "seed": seed, "trials": trials, "duration_s": duration_s,
      "ctrl_dt": meta.ctrl_dt, "timestep": float(model.opt.timestep),
      "timestep_source": "metadata" if meta.timestep is not None else "scene",
      "n_substeps": n_substeps, "mapping": meta.mapping, "scale": meta.scale, "clip": meta.clip,
      "history_len": meta.history_len, "velocity_limit": velocity_limit,
      "success_criterion": {**meta.success, "source": meta.success_source,
                            "stand_height": rob.stand_height,
                            "observed_joints": [rob.joint_names[i] for i in rob.observed]},
      "start_states": cells, "joint_target_max_abs_diff": mapping_diff}


def format_table(result: dict) -> str:
  rows = [("start state", "successes", "recovery time (s)")]
  for c in result["start_states"]:
    rt = ("-" if c["recovery_time_mean"] is None
          else f"{c['recovery_time_mean']:.2f} ± {c['recovery_time_std']:.2f}")
    rows.append((c["start_state"], f"{c['successes']}/{c['trials']}", rt))
  widths = [max(len(r[i]) for r in rows) for i in range(3)]
  lines = ["  ".join(v.ljust(w) for v, w in zip(r, widths)).rstrip() for r in rows]
  lines.insert(1, "  ".join("-" * w for w in widths))
  total = sum(c["successes"] for c in result["start_states"])
  n = sum(c["trials"] for c in result["start_states"])
  lines.append(f"plain MuJoCo {result['mujoco']}: {total}/{n} stood; ctrl_dt "
               f"{result['ctrl_dt']} s, timestep {result['timestep']} s "
               f"({result['timestep_source']}), {result['duration_s']} s per trial, "
               f"mapping {result['mapping']}")
  return "\n".join(lines)


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(
      prog="python -m jax_env.evaluation.plain_mujoco",
      description="Stand rate of an exported ONNX actor per start state in plain C MuJoCo "
                  "(independent of jax_env's environment).")
  parser.add_argument("onnx", help="the .onnx file `hifar export` wrote")
  parser.add_argument("--trials", type=int, default=4)
  parser.add_argument("--duration", type=float, default=6.0, help="seconds per trial")
  parser.add_argument("--seed", type=int, default=0)
  parser.add_argument("--start-states", default=",".join(START_STATES),
                      help="comma-separated keyframe names")
  parser.add_argument("--ctrl-dt", type=float, default=None,
                      help="override (needed when the metadata has no ctrl_dt)")
  parser.add_argument("--timestep", type=float, default=None,
                      help="physics timestep (default: the metadata's, else the scene's)")
  parser.add_argument("--no-velocity-limit", action="store_true",
                      help="do not limit targets by the joint velocity limits")
  parser.add_argument("--json", default=None, help="write the full result here")
  args = parser.parse_args(argv)
  try:
    result = run(args.onnx, tuple(s for s in args.start_states.split(",") if s),
                 trials=args.trials, duration_s=args.duration, seed=args.seed,
                 ctrl_dt=args.ctrl_dt, timestep=args.timestep,
                 velocity_limit=not args.no_velocity_limit)
  except (ValueError, OSError) as e:
    print(f"error: {e}", file=sys.stderr)
    return 2
  print(format_table(result))
  if args.json:
    Path(args.json).write_text(json.dumps(result, indent=1) + "\n")
  return 0


if __name__ == "__main__":
  sys.exit(main())
