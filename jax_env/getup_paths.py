"""Reference get-up paths (ours): simulated get-ups whose states serve as start states.

The paper's KSI starts episodes from six static key states. The supine get-up of the sagittal
stage is dynamic: the policies that learned it rock back onto the shoulders and swing forward
onto the feet, through states with momentum that no static key state holds, and PPO at the
CPU budgets of cpu.toml found that motion on about one seed in three (docs/experiments.md).
Reference state initialisation (DeepMimic's RSI; "backplay") starts episodes on such a motion
instead: a policy first learns to finish the get-up from its late states, then from ever earlier
ones.

A path here is not a demonstration the policy imitates — no reward term reads it — but a
sequence of physically consistent start states. It is found, not drawn by hand: open-loop PD
targets (`Segment`: offsets from the stand pose, piecewise linear in time through knots, the
stand pose after the last knot), optimised by a cross-entropy search in plain
C MuJoCo (the scene as loaded: real torque limits, joint ranges and velocity limits) from a
lying start, scored by Trunk height and uprightness and by the time it then stands (the
environment's success detector). `PATHS` names the start of each path (lying, or a key state)
and the knots the search starts from. The states along the found motion — qpos and qvel after every control step, from
the start until the robot meets the standing condition — are stored in
`assets/t1/getup_paths.safetensors` with the knots and the search settings in its metadata, so
that the environment only reads them.

Regenerate (a minute for the supine path, a few for the prone and kneel ones, on 2 cores;
deterministic for a seed on one machine; each path has its own seed):

    .venv/bin/python -m jax_env.getup_paths [--seed N] [--iterations N] [--only NAME]
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import json
import math
import multiprocessing
import os
import sys
import time

import mujoco
import numpy as np

from jax_env import files, paths, robot

PATHS_FILE = paths.T1_DIR / "getup_paths.safetensors"
FORMAT_VERSION = 1
# The physics of the search and of the stored states: cpu.toml's (and the quickstart's).
TIMESTEP = 0.005
CTRL_DT = 0.02
ACTION_CLIP = 3.0  # rad, as the curricula's [stage.action] clip
# Stable standing, as the curricula's [stage.success]: 5 cm, ‖g_xy‖ ≤ 0.2, 0.3 rad, held 1 s.
STAND_TOLERANCES = (0.05, 0.2, 0.3)
HOLD_S = 1.0
SETTLE_S = 0.5  # the lying start rests on the floor, held at the stand pose, this long first
KNOT_DECIMALS = 6  # knots are stored rounded; a later path's search continues with these

# Postures (left-side joint angles) the supine search starts from, in the order of the motion.
_ROCK = {"Shoulder_Pitch": -1.8, "Elbow_Yaw": 0.0, "Hip_Pitch": 1.55, "Knee_Pitch": 2.0,
         "Ankle_Pitch": -0.9}  # rocked back onto the shoulders (scenarios.ROCK_BACK)
_SQUAT = {"Shoulder_Pitch": 0.5, "Elbow_Yaw": -0.4, "Hip_Pitch": -1.46, "Knee_Pitch": 1.64,
          "Ankle_Pitch": -0.41}  # the paper code's deep squat, arms forward
_SAGITTAL = ("Shoulder_Pitch", "Elbow_Yaw", "Hip_Pitch", "Knee_Pitch", "Ankle_Pitch")
# The joints of cpu.toml's stage 2 (sagittal plus hip roll), each side on its own.
_STAGE2 = tuple(f"{side}_{j}" for side in ("Left", "Right")
                for j in ("Shoulder_Pitch", "Elbow_Yaw", "Hip_Pitch", "Hip_Roll", "Knee_Pitch",
                          "Ankle_Pitch"))


@dataclasses.dataclass(frozen=True)
class Segment:
  """Open-loop PD targets over a stretch of time: offsets from the stand pose of the `driven`
  joints, piecewise linear through `knot_times` (s from the segment's start), then the stand
  pose until the next segment starts, `duration` s after this one (or the path ends)."""

  driven: tuple[str, ...]  # joint names; with `both_sides`, names without the side prefix
  # One offset per name for the Left_ and the Right_ joint alike: the mirror image for pitch
  # joints, not for the elbow yaw, whose axes are opposite (the found supine path bends one
  # elbow as it straightens the other; a truly mirrored search would flip its sign).
  both_sides: bool
  knot_times: tuple[float, ...]
  duration: float
  initial: tuple           # the search's initial mean, per knot (fraction, posture): that
                           # fraction of the way from the stand pose to a posture {joint: angle}
  initial_std: float


@dataclasses.dataclass(frozen=True)
class PathSpec:
  """A path: its start (lying with the Trunk pitched `pitch` about y, −π/2 on the back, or a
  model keyframe), the segment the search finds, and optionally a stored path whose segment
  follows it (`then`)."""

  pitch: float | None  # lying starts
  search: Segment
  then: str | None
  score_from: float  # s: progress counts in full from here on (0.3× before)
  iterations: int    # of the cross-entropy search (the stored path's)
  seed: int = 0      # of the stored path's search
  keyframe: str | None = None  # starts at this keyframe instead (settled, held at its joints)
  # What the search pays before `score_from`: "rise" (height and uprightness, 0.3×) or "back"
  # (turning onto the back, for a path that continues with the supine one: 0.1× the Trunk's
  # chest-up component, 0.3× in the last 0.75 s, so that it lies on the back when it hands over).
  early_goal: str = "rise"
  # (side roll |g_y|, upside down g_z) the path must stay within: the planar stage's
  # terminations (curricula [stage.termination]) for a path that stage starts on; a sample that
  # crosses them loses 100 points.
  within: tuple[float, float] | None = None


PATHS: dict[str, PathSpec] = {
    # On the back: rock back onto the shoulders, swing forward into a squat, rise.
    "supine": PathSpec(
        pitch=-math.pi / 2,
        search=Segment(driven=_SAGITTAL, both_sides=True,
                       knot_times=(0.0, 0.25, 0.5, 0.75, 1.0, 1.25, 1.5, 1.75), duration=3.5,
                       initial=((0.0, None), (0.5, _ROCK), (1.0, _ROCK), (1.0, _ROCK),
                                (1.0, _SQUAT), (1.0, _SQUAT), (0.5, _SQUAT), (0.0, None)),
                       initial_std=0.8),
        then=None, score_from=1.0, iterations=40),
    # On the front: roll onto the back with stage 2's joints (hip roll included), come to rest
    # at the stand pose, then the supine path's get-up — the way our stage 2 learns it.
    "prone": PathSpec(
        pitch=math.pi / 2,
        search=Segment(driven=_STAGE2, both_sides=False,
                       knot_times=(0.0, 0.25, 0.5, 0.75, 1.0, 1.25), duration=2.0,
                       initial=((0.0, None),) * 6, initial_std=1.0),
        then="supine", score_from=3.0, iterations=12),
    # Kneeling on the shins, hands down (ksi_prone_3): onto the back with the sagittal joints
    # alone, each side free — the planar stage's action space — then the supine get-up. The
    # direct rise onto the feet from there was never found (docs/experiments.md); this way round is.
    "kneel": PathSpec(
        pitch=None, keyframe="ksi_prone_3",
        search=Segment(driven=tuple(f"{side}_{j}" for side in ("Left", "Right")
                                    for j in _SAGITTAL), both_sides=False,
                       knot_times=(0.0, 0.292, 0.583, 0.875, 1.167, 1.458, 1.75), duration=2.5,
                       initial=((0.0, None),) * 7, initial_std=1.0),
        then="supine", score_from=2.5, iterations=20, early_goal="back", within=(0.8, 0.9),
        seed=2),  # seeds 0, 1 and 3 found it only across the limits (a roll on the side)
}


@dataclasses.dataclass(frozen=True)
class Path:
  """The stored states of one path: after every control step from the lying start."""

  qpos: np.ndarray  # [T, nq]
  qvel: np.ndarray  # [T, nv]
  stand_index: int  # first frame of the standing streak: frames [0, stand_index) are the rise


# ---------------------------------------------------------------------------------------------
# Simulation of one open-loop attempt.


class _Sim:
  """The scene, its PD servos and the stand pose, for open-loop rollouts."""

  def __init__(self):
    self.model = robot.load_model()
    self.model.opt.timestep = TIMESTEP
    self.substeps = int(round(CTRL_DT / TIMESTEP))
    m = self.model
    jid = [m.joint(n).id for n in robot.JOINT_NAMES]
    self.qadr = np.array([m.jnt_qposadr[j] for j in jid])
    self.dadr = np.array([m.jnt_dofadr[j] for j in jid])
    # load_model checks that actuator i drives joint i of robot.JOINT_NAMES.
    self.act = np.arange(len(robot.JOINT_NAMES))
    joints = robot.joint_arrays(m)
    self.lo, self.hi = joints.range_low, joints.range_high
    self.kp, self.kd, self.v_max = joints.kp, joints.kd, joints.velocity_limit
    self.stand = np.asarray(robot.stand_pose(m), np.float64)
    self.stand_height = float(robot.keyframe(m, "stand")[0][2])
    self.trunk = m.body("Trunk").id
    self.index = {n: i for i, n in enumerate(robot.JOINT_NAMES)}

  def columns(self, seg: Segment) -> list[np.ndarray]:
    """Joint indices each knot column drives: both sides (`both_sides`), else the named one."""
    if seg.both_sides:
      sides = [np.array([self.index[f"{side}_{j}"] for j in seg.driven])
               for side in ("Left", "Right")]
      return sides
    return [np.array([self.index[j] for j in seg.driven])]

  def initial_mean(self, seg: Segment) -> np.ndarray:
    """[knots, driven] offsets from the stand pose of the segment's initial postures."""
    stand = self.stand[self.columns(seg)[0]]
    return np.stack([np.zeros(len(seg.driven)) if posture is None else
                     fraction * (np.array([posture[j] for j in seg.driven]) - stand)
                     for fraction, posture in seg.initial])

  def start(self, spec: PathSpec) -> mujoco.MjData:
    """The keyframe, or lying with the stand pose's joints placed on the floor; settled."""
    d = mujoco.MjData(self.model)
    if spec.keyframe is not None:
      d.qpos[:] = robot.keyframe(self.model, spec.keyframe)[0]
      mujoco.mj_forward(self.model, d)
      d.ctrl[self.act] = np.clip(d.qpos[self.qadr], self.lo, self.hi)
      for _ in range(int(round(SETTLE_S / TIMESTEP))):
        mujoco.mj_step(self.model, d)
      return d
    quat = np.zeros(4)
    mujoco.mju_axisAngle2Quat(quat, np.array([0.0, 1.0, 0.0]), spec.pitch)
    d.qpos[3:7] = quat
    d.qpos[self.qadr] = self.stand
    d.qpos[2] = 0.3
    for _ in range(60):  # lower in 5 mm steps until it touches, then out of any penetration
      mujoco.mj_forward(self.model, d)
      if d.ncon:
        d.qpos[2] -= min(0.0, min(d.contact.dist[i] for i in range(d.ncon)))
        break
      d.qpos[2] -= 0.005
    d.ctrl[self.act] = np.clip(self.stand, self.lo, self.hi)
    for _ in range(int(round(SETTLE_S / TIMESTEP))):
      mujoco.mj_step(self.model, d)
    return d

  def planned(self, plan, t: float) -> np.ndarray:
    """The plan's PD targets at time t [(Segment, knots)], segments back to back, before the
    velocity-limit rule and the joint ranges."""
    target = self.stand.copy()
    begin = 0.0
    for seg, knots in plan:
      local = t - begin
      if local < seg.duration:
        if local < seg.knot_times[-1]:
          a = np.array([np.interp(local, seg.knot_times, knots[:, k])
                        for k in range(len(seg.driven))])
          for cols in self.columns(seg):
            target[cols] = self.stand[cols] + np.clip(a, -ACTION_CLIP, ACTION_CLIP)
        break
      begin += seg.duration
    return target

  def targets(self, plan, t: float, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
    """The PD targets applied at time t: the plan's, then as the environment and the
    plain-MuJoCo evaluator apply any target (velocity limit, joint ranges)."""
    target = self.planned(plan, t)
    # As the environment and the plain-MuJoCo evaluator: no torque along q̇ beyond the limit.
    free = q + self.kd * qd / self.kp
    target = np.where(qd >= self.v_max, np.minimum(target, free), target)
    target = np.where(qd <= -self.v_max, np.maximum(target, free), target)
    return np.clip(target, self.lo, self.hi)

  def standing(self, d: mujoco.MjData) -> bool:
    h_tol, up_tol, dof_tol = STAND_TOLERANCES
    g = d.xmat[self.trunk].reshape(3, 3).T @ np.array([0.0, 0.0, -1.0])
    return (abs(d.qpos[2] - self.stand_height) <= h_tol and math.hypot(g[0], g[1]) <= up_tol
            and float(np.max(np.abs(d.qpos[self.qadr] - self.stand))) <= dof_tol)

  def rollout(self, start: mujoco.MjData, plan, spec: PathSpec, record: bool = False):
    """(score, Path | None): the attempt's score, and its states where `record`."""
    score_from = spec.score_from
    crossed = False
    d = mujoco.MjData(self.model)
    d.qpos[:], d.qvel[:] = start.qpos, start.qvel
    mujoco.mj_forward(self.model, d)
    hold = int(round(HOLD_S / CTRL_DT))
    duration = sum(seg.duration for seg, _ in plan)
    score, streak, best, streak_start = 0.0, 0, 0, -1
    qpos, qvel = [d.qpos.copy()], [d.qvel.copy()]
    for step in range(int(round(duration / CTRL_DT))):
      t = step * CTRL_DT
      d.ctrl[self.act] = self.targets(plan, t, d.qpos[self.qadr], d.qvel[self.dadr])
      for _ in range(self.substeps):
        mujoco.mj_step(self.model, d)
      if not (np.all(np.isfinite(d.qpos)) and np.all(np.isfinite(d.qvel))):
        return -1e3, None
      if record:
        qpos.append(d.qpos.copy())
        qvel.append(d.qvel.copy())
      g = d.xmat[self.trunk].reshape(3, 3).T @ np.array([0.0, 0.0, -1.0])
      if spec.within is not None:
        crossed |= bool(abs(g[1]) > spec.within[0] or g[2] > spec.within[1])
      progress = min(d.qpos[2], self.stand_height) / self.stand_height - 0.5 * g[2]
      if t >= score_from:
        score += progress
      elif spec.early_goal == "back":  # lying on the back: the Trunk's x axis points up
        score += (0.3 if t >= score_from - 0.75 else 0.1) * -g[0]
      else:
        score += 0.3 * progress
      streak = streak + 1 if self.standing(d) else 0
      if streak == 1 and best < hold:
        streak_start = step + 1  # qpos[step + 1] is the state after this step
      best = max(best, streak)
    score += 2.0 * best - (100.0 if crossed else 0.0)
    if not record:
      return score, None
    return score, Path(np.array(qpos), np.array(qvel), streak_start if best >= hold else -1)


def plan_of(name: str, knots: dict[str, np.ndarray]) -> list:
  """[(Segment, knots)] of path `name`: its own segment, then those of the path it continues
  with, from `knots` (path name -> the knots of its searched segment)."""
  plan = []
  while name is not None:
    plan.append((PATHS[name].search, np.asarray(knots[name])))
    name = PATHS[name].then
  return plan


def teacher_offsets(name: str, knots: dict[str, np.ndarray], frames: int) -> np.ndarray:
  """[frames, 23] the PD targets the path's plan issues in each stored state (frame f is the
  state after f control steps; its targets are those at t = f·CTRL_DT), within the joint
  ranges, as offsets from the stand pose: the action of the "default" mapping (scale 1) that
  reproduces the path, for a policy that learns from it (`[stage.imitation]`)."""
  sim = _worker_sim()
  plan = plan_of(name, knots)
  return np.stack([np.clip(sim.planned(plan, f * CTRL_DT), sim.lo, sim.hi) - sim.stand
                   for f in range(frames)])


def driven_joints(name: str) -> frozenset[str]:
  """The joints path `name`'s plan moves away from the stand pose (its segments' and those of
  the paths it continues with)."""
  joints = set()
  while name is not None:
    seg = PATHS[name].search
    joints |= ({f"{side}_{j}" for side in ("Left", "Right") for j in seg.driven}
               if seg.both_sides else set(seg.driven))
    name = PATHS[name].then
  return frozenset(joints)


def replay(name: str, knots: dict[str, np.ndarray]) -> Path:
  """The path `name` simulated again from its start with the given knots."""
  sim = _worker_sim()
  return sim.rollout(_worker_start(name), plan_of(name, knots), PATHS[name], record=True)[1]


@functools.cache
def _worker_sim() -> _Sim:
  return _Sim()


def _score(args) -> float:
  name, plan = args
  return _worker_sim().rollout(_worker_start(name), plan, PATHS[name])[0]


@functools.cache
def _worker_start(name: str) -> mujoco.MjData:
  return _worker_sim().start(PATHS[name])


# ---------------------------------------------------------------------------------------------
# The search.


def search(name: str, found: dict[str, np.ndarray] | None = None, seed: int = 0,
           iterations: int | None = None, population: int = 96, elites: int = 12,
           processes: int | None = None, log=print) -> tuple[np.ndarray, Path]:
  """Cross-entropy search for the knots [knots, driven joints] of path `name`'s segment (the
  knots of the path it continues with come from `found`); returns the best knots found and
  their recorded path."""
  spec = PATHS[name]
  iterations = spec.iterations if iterations is None else iterations
  sim = _worker_sim()
  mean = sim.initial_mean(spec.search)
  std = np.full_like(mean, spec.search.initial_std)
  rng = np.random.default_rng(seed)
  best_score, best = -math.inf, mean
  found = dict(found or {})

  def plan(knots):
    return plan_of(name, {**found, name: knots})

  processes = processes or os.cpu_count() or 1
  # Fork-started workers (a fresh interpreter per worker would re-import MuJoCo); one process
  # maps in place, as a caller that has started JAX's threads must (fork after threads is unsafe).
  ctx = multiprocessing.get_context("fork")
  with (ctx.Pool(processes) if processes > 1 else contextlib.nullcontext()) as pool:
    mapper = pool.map if pool is not None else lambda f, xs: list(map(f, xs))
    for it in range(iterations):
      t0 = time.time()
      samples = mean + std * rng.standard_normal((population,) + mean.shape)
      samples[0] = best
      scores = np.array(mapper(_score, [(name, plan(s)) for s in samples]))
      elite = np.argsort(-scores, kind="stable")[:elites]
      mean = 0.8 * samples[elite].mean(0) + 0.2 * mean
      std = np.maximum(0.8 * samples[elite].std(0) + 0.2 * std, 0.05)
      if scores[elite[0]] > best_score:
        best_score, best = float(scores[elite[0]]), samples[elite[0]].copy()
      log(f"{name}: iteration {it + 1}/{iterations}  best score {best_score:.1f}  "
          f"elite mean {scores[elite].mean():.1f}  ({time.time() - t0:.1f} s)")
  return best, replay(name, {**found, name: best})


# ---------------------------------------------------------------------------------------------
# The stored file.


def save(found: dict[str, tuple[np.ndarray, Path, dict]], out=PATHS_FILE) -> None:
  """Writes the paths (name -> (knots, path, search settings)) atomically."""
  from safetensors.numpy import save as st_save

  tensors = {}
  meta = {"format_version": str(FORMAT_VERSION), "timestep": str(TIMESTEP),
          "ctrl_dt": str(CTRL_DT)}
  for name, (knots, path, settings) in found.items():
    tensors[f"{name}/qpos"] = path.qpos.astype(np.float64)
    tensors[f"{name}/qvel"] = path.qvel.astype(np.float64)
    meta[f"{name}/stand_index"] = str(path.stand_index)
    meta[f"{name}/knots"] = json.dumps(np.round(knots, KNOT_DECIMALS).tolist())
    meta[f"{name}/search"] = json.dumps(settings)
  files.write_atomic(out, st_save(tensors, metadata=meta))


def _read(path) -> tuple[dict, dict]:
  """(tensors, metadata) of a paths file, its format checked."""
  from safetensors.numpy import load_file
  from safetensors import safe_open

  with safe_open(str(path), framework="numpy") as f:
    meta = f.metadata() or {}
  if meta.get("format_version") != str(FORMAT_VERSION):
    raise ValueError(f"{path}: format_version {meta.get('format_version')} is not "
                     f"{FORMAT_VERSION}; regenerate it with `python -m jax_env.getup_paths`")
  return load_file(str(path)), meta


@functools.cache
def load(path=PATHS_FILE) -> dict[str, Path]:
  """The stored paths by name (read once per process)."""
  tensors, meta = _read(path)
  return {name: Path(tensors[f"{name}/qpos"], tensors[f"{name}/qvel"],
                     int(meta[f"{name}/stand_index"]))
          for name in PATHS if f"{name}/stand_index" in meta}


def stored(path=PATHS_FILE) -> dict[str, tuple[np.ndarray, Path, dict]]:
  """Every stored path with its knots ([knots, driven joints]) and search settings."""
  _, meta = _read(path)
  return {name: (np.array(json.loads(meta[f"{name}/knots"])), p,
                 json.loads(meta.get(f"{name}/search", "{}")))
          for name, p in load.__wrapped__(path).items()}


def stored_knots(path=PATHS_FILE) -> dict[str, np.ndarray]:
  """The knots of every stored path (path name -> [knots, driven joints]), as found."""
  return {name: knots for name, (knots, _, _) in stored(path).items()}


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(prog="python -m jax_env.getup_paths", description=__doc__
                                   .split("\n\n")[0])
  parser.add_argument("--seed", type=int,
                      help="of each search (default: each path's own, as stored)")
  parser.add_argument("--iterations", type=int,
                      help="of each search (default: each path's own, as stored)")
  parser.add_argument("--only", choices=tuple(PATHS), action="append",
                      help="search only these paths; keep the others as stored in --out")
  parser.add_argument("--out", default=str(PATHS_FILE))
  args = parser.parse_args(argv)
  kept = stored(args.out) if args.only else {}
  found = {}  # in PATHS order: a path's `then` is searched (or kept) before it
  for name in PATHS:
    if args.only and name not in args.only:
      if name not in kept:
        print(f"error: {args.out} holds no {name} path to keep; search it too", file=sys.stderr)
        return 1
      found[name] = kept[name]
      continue
    # The paths this one continues with, as the file will hold them (rounded), so that a
    # search with --only reproduces a full one.
    earlier = {n: np.round(k, KNOT_DECIMALS) for n, (k, _, _) in found.items()}
    seed = PATHS[name].seed if args.seed is None else args.seed
    knots, path = search(name, earlier, seed=seed, iterations=args.iterations)
    if path.stand_index < 0:
      print(f"error: the search found no {name} get-up that stands {HOLD_S} s; try another "
            "--seed or more --iterations", file=sys.stderr)
      return 1
    print(f"{name}: stands after {path.stand_index * CTRL_DT:.2f} s")
    iterations = PATHS[name].iterations if args.iterations is None else args.iterations
    found[name] = (knots, path, {"seed": seed, "iterations": iterations,
                                 "segment": dataclasses.asdict(PATHS[name].search),
                                 "then": PATHS[name].then})
  save(found, args.out)
  print(f"wrote {args.out}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
