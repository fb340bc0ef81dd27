"""One recorded episode of a checkpoint's policy (docs/contracts.md, "facade.rollout").

The episode runs under the nominal evaluation conditions (`conditions.evaluation_stage`,
`conditions.start`): one environment, the deployable actor, and a `jax.lax.scan` over the
control steps that keeps what a viewer needs at every step (joint state and torques, reward
terms, the standing flag, the push). Everything else is derived on the host from the recorded
`qpos` with C MuJoCo: body poses (`mj_kinematics`), torso pitch, and, when asked for, video
frames and a filmstrip. Replaying `qpos` makes the pictures independent of the physics backend
that produced the episode, and it gives the initial state its real body poses (the env's reset
view carries no kinematics).

Per-step data leaves as C-contiguous NumPy arrays, which the CLI reads through the buffer
protocol in one copy: float32 for what the environment computed (float32 in JAX), float64 for
what the host computed in float64 (time, body poses, torso pitch), so that nothing is rounded on
the way and the MCAP holds exactly the values computed here.

Rendering runs in a child Python process (`python -m jax_env.evaluation.recording render …`):
MuJoCo and PyOpenGL pick their OpenGL platform once, when they are first imported, so a process
that already imported `mujoco` (the CLI's embedded interpreter has) cannot switch to EGL, nor
fall back from EGL to OSMesa. A fresh child per attempt can.
"""

from __future__ import annotations

import copy
import dataclasses
import fractions
import json
import math
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from jax_env import facade_requests
from jax_env.files import write_atomic

# The floor as a primitive: a large flat box whose top face is the plane z = 0.
FLOOR_HALF_SIZE = (10.0, 10.0, 0.01)
FLOOR_RGBA = (0.55, 0.57, 0.6, 1.0)

# Offscreen rendering: OpenGL platforms tried in order (after a user's own MUJOCO_GL).
GL_PLATFORMS = ("egl", "osmesa")
VIDEO_SIZE = (640, 480)  # width, height (even, for yuv420p)
FILMSTRIP_FRAMES = 6
FILMSTRIP_WIDTH = 440  # px kept of each frame's centre: the robot, not the empty floor
# A side view of the sagittal plane, the plane the paper's snapshot figures show.
CAMERA_DISTANCE = 2.2
CAMERA_AZIMUTH = 90.0
CAMERA_ELEVATION = -20.0
CAMERA_HEIGHT = 0.35


def rollout(request: dict) -> dict:
  """Runs and records one episode; see the module docstring and docs/contracts.md."""
  import jax

  from jax_env import robot
  from jax_env import rewards as rewards_lib
  from jax_env.names import SCENARIOS, TERRAINS
  from jax_env.env import FallRecoveryEnv
  from jax_env.evaluation import conditions
  from jax_env.evaluation import policy as policy_lib
  from jax_env.learner import train

  req = _checked_request(request, SCENARIOS, TERRAINS, conditions)
  policy = policy_lib.load(req.checkpoint)
  stage = conditions.evaluation_stage(policy_lib.stage_of(policy, req.stage))
  stage = _with_duration(stage, req.duration_s)
  env = FallRecoveryEnv(stage, backend=req.backend, rules_end_episodes=False)  # as `evaluate`
  policy_lib.check_features(policy, env)

  condition = conditions.Condition(
      scenario=req.scenario, terrain=req.terrain, push_force=req.push_force,
      push_direction=req.push_direction)
  keys = jax.random.split(train.seed_key(req.seed), 1)
  arrays = conditions.condition_arrays(env, condition, batch=1)

  push_at = env.privileged_names.index("push_force/x")
  gravity_at = env.obs_names.index("gravity/x")
  obstacle = env.mj_model.body(robot.OBSTACLE_BODY).id
  terms = tuple(rewards_lib.TERMS)

  def frame(s) -> dict[str, Any]:
    """What the recording keeps of a state (env 0 of the batch of one)."""
    view = env.backend.view(s.physics)
    return {
        "qpos": view.qpos[0], "qvel": view.qvel[0], "torque": view.actuator_force[0],
        "gravity": s.obs[0, gravity_at:gravity_at + 3],
        "reward": s.reward[0], "standing": s.metrics["standing"][0],
        "terms": {t: s.metrics[f"reward/{t}"][0] for t in terms},
        "push": s.privileged[0, push_at:push_at + 3], "succeeded": s.success.success[0],
        "recovery_time": s.success.recovery_time[0], "done": s.done[0],
        "obstacle": view.xpos[0, obstacle]}

  step = policy_lib.episode_step(policy, env)
  n_steps = env.episode_steps - 1  # T entries, the initial state first; no auto-reset

  @jax.jit
  def episode(keys, arrays):
    s = conditions.start_arrays(env, keys, arrays)

    def body(carry, _):
      carry = step(carry)
      return carry, frame(carry[0])

    _, frames = jax.lax.scan(body, (s, policy.initial_history(1)), None, length=n_steps)
    return frame(s), frames, s.control_start[0], s.draw.obstacle[0]

  first, frames, control_start, has_obstacle = jax.device_get(episode(keys, arrays))
  rec = jax.tree_util.tree_map(lambda a, b: np.concatenate([np.asarray(a)[None], b]), first,
                               frames)
  # The obstacle is a mocap body: the view after any step has its (fixed) position.
  obstacle_pos = np.asarray(frames["obstacle"])[-1] if has_obstacle > 0 else None
  return _result(env, req, stage, rec, int(control_start), obstacle_pos)


def _checked_request(request: dict, scenarios: Sequence[str], terrains: Sequence[str],
                     conditions) -> facade_requests.RolloutRequest:
  """The request with its defaults filled in; bad values raise one-line errors naming them."""
  req = facade_requests.parse("rollout", facade_requests.RolloutRequest, request)
  facade_requests.check_choice("rollout", "scenario", req.scenario, scenarios)
  facade_requests.check_choice("rollout", "terrain", req.terrain, terrains)
  facade_requests.check_backend("rollout", req.backend)
  force = float(req.push_force)
  if not (math.isfinite(force) and force >= 0):
    raise ValueError(f"push force {req.push_force!r} must be a number >= 0 (newtons)")
  direction = req.push_direction
  if direction is None:
    direction = conditions.planar_direction(req.scenario)
  facade_requests.check_choice("rollout", "push direction", direction,
                               tuple(conditions.PUSH_DIRECTIONS))
  duration = req.duration_s
  if duration is not None and not (math.isfinite(float(duration)) and float(duration) > 0):
    raise ValueError(f"duration {duration!r} must be a number of seconds > 0")
  return dataclasses.replace(req, push_force=force, push_direction=direction, seed=int(req.seed))


def _with_duration(stage: dict, duration_s: float | None) -> dict:
  """The stage with its episode length set to the recording's duration (so the environment
  never auto-resets inside the recording)."""
  if duration_s is None:
    return stage
  sim = stage["sim"]
  ctrl_dt = float(sim["ctrl_dt"])
  settle = float(stage.get("scenario_params", {}).get("settle_s", 0.0))
  if duration_s < 2 * ctrl_dt - 1e-9:
    raise ValueError(f"duration {duration_s} s is shorter than two control steps "
                     f"(ctrl_dt {ctrl_dt} s)")
  if duration_s <= settle:
    raise ValueError(f"duration {duration_s} s must be longer than the stage's settle_s "
                     f"({settle} s, while a dropped robot settles before control starts)")
  stage = copy.deepcopy(stage)
  stage["sim"]["episode_s"] = float(duration_s)
  return stage


# ---------------------------------------------------------------------------------------------
# Host-side results.


def _result(env, req: facade_requests.RolloutRequest, stage: dict, rec: dict,
            control_start: int, obstacle_pos) -> dict:
  from jax_env import rewards as rewards_lib
  from jax_env import robot

  qpos = np.asarray(rec["qpos"], np.float64)
  ended = np.flatnonzero(np.asarray(rec["done"]) > 0)
  truncated_at = None
  if ended.size:  # a numerical blow-up ended the episode (and the env started a fresh one)
    qpos = qpos[:ended[0]]
    rec = {k: (v[:ended[0]] if not isinstance(v, dict) else
               {t: a[:ended[0]] for t, a in v.items()}) for k, v in rec.items()}
    truncated_at = float(ended[0] * env.ctrl_dt)
  n = qpos.shape[0]
  success = bool(rec["succeeded"][-1])
  recovery_time = float(rec["recovery_time"][-1])
  m = env.mj_model
  bodies = [m.body(b).id for b in robot.BODY_NAMES]
  pos, quat = body_poses(m, qpos, bodies)
  joint_pos = qpos[:, 7:]

  def f32(a) -> np.ndarray:
    return np.ascontiguousarray(a, np.float32)

  def f64(a) -> np.ndarray:
    return np.ascontiguousarray(a, np.float64)

  terms = tuple(rewards_lib.TERMS)
  out = {
      "dt": float(env.ctrl_dt),
      "time": f64(np.arange(n) * env.ctrl_dt),
      "body_names": list(robot.BODY_NAMES),
      "body_pos": f64(pos),
      "body_quat": f64(quat),
      "joint_names": list(robot.JOINT_NAMES),
      "joint_pos": f32(joint_pos),
      "joint_vel": f32(np.asarray(rec["qvel"])[:, 6:]),
      "joint_torque": f32(rec["torque"]),
      "torso_pitch": f64(torso_pitch(rec["gravity"])),
      "reward": f32(rec["reward"]),
      "reward_term_names": list(terms),
      "reward_terms": f32(np.stack([np.asarray(rec["terms"][t]) for t in terms], axis=-1)),
      "standing": f32(rec["standing"]),
      "succeeded": f32(rec["succeeded"]),
      "push_force": f32(rec["push"]),
      "success": success,
      "recovery_time": recovery_time if success and math.isfinite(recovery_time) else None,
      "truncated_at": truncated_at,
      "control_start_s": float(control_start * env.ctrl_dt),
      "geoms": scene_geoms(m, obstacle_pos),
      "scenario": req.scenario, "terrain": req.terrain, "backend": req.backend,
      "seed": req.seed, "push_direction": req.push_direction,
      "push_force_n": req.push_force, "checkpoint": str(req.checkpoint),
      "stage": stage.get("name"),
      "video": None, "filmstrip": None,
  }
  if req.video or req.filmstrip:
    mocap = np.zeros((m.nmocap, 3))
    for b in np.flatnonzero(m.body_mocapid >= 0):
      mocap[m.body_mocapid[b]] = m.body_pos[b]
    if obstacle_pos is not None:
      mocap[m.body(robot.OBSTACLE_BODY).mocapid[0]] = obstacle_pos
    written = render(m, qpos, mocap, env.ctrl_dt, lookat_xy=pos[..., :2].mean(axis=(0, 1)),
                     video=req.video, filmstrip=req.filmstrip)
    out.update(written)
  return out


def body_poses(m, qpos: np.ndarray, bodies: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
  """World positions [T, nb, 3] and quaternions [T, nb, 4] (w, x, y, z) of `bodies` at every
  recorded `qpos` (forward kinematics in C MuJoCo, float64)."""
  import mujoco

  d = mujoco.MjData(m)
  pos = np.zeros((qpos.shape[0], len(bodies), 3))
  quat = np.zeros((qpos.shape[0], len(bodies), 4))
  for t, q in enumerate(qpos):
    d.qpos[:] = q
    mujoco.mj_kinematics(m, d)
    pos[t] = d.xpos[bodies]
    quat[t] = d.xquat[bodies]
  return pos, quat


def torso_pitch(gravity: np.ndarray) -> np.ndarray:
  """Pitch of the torso [T] (rad) from the gravity direction in the torso frame [T, 3] (the
  observation's `gravity/*`, true gravity also on a slope): the rotation about the torso's y
  axis away from upright, positive leaning forward (+π/2 lying prone, −π/2 lying supine),
  atan2(g_x, −g_z); upright, g = (0, 0, −1)."""
  g = np.asarray(gravity, np.float64)
  return np.arctan2(g[..., 0], -g[..., 2])


def scene_geoms(m, obstacle_pos=None) -> list[dict]:
  """The robot's collision primitives in their bodies' frames, the floor as a large flat box,
  and the obstacle ball (world frame) when the episode has one."""
  import mujoco

  from jax_env import robot

  kinds = {int(mujoco.mjtGeom.mjGEOM_SPHERE): "sphere",
           int(mujoco.mjtGeom.mjGEOM_CAPSULE): "capsule",
           int(mujoco.mjtGeom.mjGEOM_BOX): "box"}
  robot_bodies = {m.body(b).id: b for b in robot.BODY_NAMES}
  out = []
  for g in range(m.ngeom):
    body = int(m.geom_bodyid[g])
    if body not in robot_bodies:
      continue
    kind = kinds.get(int(m.geom_type[g]))
    if kind is None:
      raise ValueError(f"geom {m.geom(g).name!r} of body {robot_bodies[body]!r} has type "
                       f"{int(m.geom_type[g])}; recordings support spheres, capsules and boxes")
    out.append({"name": m.geom(g).name, "body": robot_bodies[body], "type": kind,
                "size": np.asarray(m.geom_size[g], np.float64).tolist(),
                "pos": np.asarray(m.geom_pos[g], np.float64).tolist(),
                "quat": np.asarray(m.geom_quat[g], np.float64).tolist(),
                "rgba": np.asarray(m.geom_rgba[g], np.float64).tolist()})
  out.append({"name": "floor", "body": "world", "type": "box", "size": list(FLOOR_HALF_SIZE),
              "pos": [0.0, 0.0, -FLOOR_HALF_SIZE[2]], "quat": [1.0, 0.0, 0.0, 0.0],
              "rgba": list(FLOOR_RGBA)})
  if obstacle_pos is not None:
    g = int(m.body(robot.OBSTACLE_BODY).geomadr[0])
    out.append({"name": "obstacle", "body": "world", "type": "sphere",
                "size": np.asarray(m.geom_size[g], np.float64).tolist(),
                "pos": np.asarray(obstacle_pos, np.float64).tolist(),
                "quat": [1.0, 0.0, 0.0, 0.0],
                "rgba": np.asarray(m.geom_rgba[g], np.float64).tolist()})
  return out


# ---------------------------------------------------------------------------------------------
# Offscreen rendering (in a child process, see the module docstring).


class RenderingUnavailable(RuntimeError):
  """No offscreen OpenGL platform works on this machine."""


def _platforms() -> list[str]:
  user = os.environ.get("MUJOCO_GL", "").strip().lower()
  first = [user] if user in GL_PLATFORMS else []
  return first + [p for p in GL_PLATFORMS if p not in first]


def _child(platform: str, args: list[str], timeout: float) -> subprocess.CompletedProcess:
  env = dict(os.environ, MUJOCO_GL=platform, PYOPENGL_PLATFORM=platform)
  return subprocess.run([sys.executable, "-m", "jax_env.evaluation.recording", *args], env=env,
                        capture_output=True, text=True, timeout=timeout, check=False)


def _last_line(text: str) -> str:
  lines = [line for line in text.strip().splitlines() if line.strip()]
  return lines[-1].strip() if lines else "no output"


def offscreen_gl() -> str | None:
  """The first OpenGL platform ("egl" | "osmesa") that renders offscreen here, or None."""
  for platform in _platforms():
    try:
      if _child(platform, ["probe"], timeout=120).returncode == 0:
        return platform
    except (OSError, subprocess.TimeoutExpired):
      continue
  return None


def render(m, qpos: np.ndarray, mocap_pos: np.ndarray, ctrl_dt: float, *,
           lookat_xy: Sequence[float], video: str | None, filmstrip: str | None) -> dict:
  """Renders the replayed episode to an MP4 and/or a PNG filmstrip; returns the written paths
  as {"video", "filmstrip"}. The camera looks at `lookat_xy` (the robot's mean ground position)
  from the side. Tries EGL, then OSMesa; raises RenderingUnavailable (one line naming what
  failed) when neither works."""
  import mujoco

  with tempfile.TemporaryDirectory(prefix="hifar-render-") as tmp:
    model_path = os.path.join(tmp, "model.mjb")
    mujoco.mj_saveModel(m, model_path, None)
    np.savez(os.path.join(tmp, "episode.npz"), qpos=qpos, mocap_pos=mocap_pos,
             ctrl_dt=np.float64(ctrl_dt), lookat_xy=np.asarray(lookat_xy, np.float64))
    job = {"model": model_path, "episode": os.path.join(tmp, "episode.npz"),
           "video": str(video) if video else None,
           "filmstrip": str(filmstrip) if filmstrip else None}
    job_path = os.path.join(tmp, "job.json")
    Path(job_path).write_text(json.dumps(job))
    failures = []
    for platform in _platforms():
      try:
        done = _child(platform, ["render", job_path], timeout=3600)
      except (OSError, subprocess.TimeoutExpired) as e:
        failures.append(f"{platform}: {e}")
        continue
      if done.returncode == 0:
        return {"video": job["video"], "filmstrip": job["filmstrip"]}
      failures.append(f"{platform}: {_last_line(done.stderr)}")
  raise RenderingUnavailable(
      "offscreen rendering failed (" + "; ".join(failures) + "): --video and --filmstrip need "
      "EGL (libEGL, e.g. apt install libegl1) or OSMesa (libOSMesa, e.g. apt install "
      "libosmesa6); the MCAP recording does not")


def _camera(mujoco, lookat_xy: np.ndarray):
  cam = mujoco.MjvCamera()
  cam.type = mujoco.mjtCamera.mjCAMERA_FREE
  cam.lookat[:] = [float(lookat_xy[0]), float(lookat_xy[1]), CAMERA_HEIGHT]
  cam.distance, cam.azimuth, cam.elevation = CAMERA_DISTANCE, CAMERA_AZIMUTH, CAMERA_ELEVATION
  return cam


def _frames(model_path: str, episode_path: str, indices: np.ndarray | None) -> tuple:
  """RGB frames [n, H, W, 3] of the replayed episode (every step, or `indices`), the camera
  fixed on the robot's mean ground position."""
  import mujoco

  m = mujoco.MjModel.from_binary_path(model_path)
  ep = np.load(episode_path)
  qpos, mocap = ep["qpos"], ep["mocap_pos"]
  width, height = VIDEO_SIZE
  m.vis.global_.offwidth = max(m.vis.global_.offwidth, width)
  m.vis.global_.offheight = max(m.vis.global_.offheight, height)
  d = mujoco.MjData(m)
  option = mujoco.MjvOption()
  option.geomgroup[:] = 1  # the robot is drawn with its collision primitives (group 3)
  cam = _camera(mujoco, ep["lookat_xy"])
  renderer = mujoco.Renderer(m, height, width)
  try:
    frames = []
    for t in (range(qpos.shape[0]) if indices is None else indices):
      d.qpos[:] = qpos[t]
      if m.nmocap:
        d.mocap_pos[:] = mocap
      mujoco.mj_forward(m, d)
      renderer.update_scene(d, camera=cam, scene_option=option)
      frames.append(renderer.render().copy())
  finally:
    renderer.close()
  return np.stack(frames), float(ep["ctrl_dt"])


def write_video(frames: np.ndarray, fps: float, path: str) -> str:
  """H.264 MP4 (libx264 where the PyAV wheel has it, else MPEG-4 part 2), written atomically.
  Returns the codec used."""
  import av

  codec = "libx264" if "libx264" in av.codecs_available else "mpeg4"
  def encode(tmp):
    with av.open(str(tmp), mode="w", format="mp4") as container:
      stream = container.add_stream(codec, rate=fractions.Fraction(fps).limit_denominator(1000))
      stream.height, stream.width = frames.shape[1:3]
      stream.pix_fmt = "yuv420p"
      if codec == "libx264":
        stream.options = {"crf": "20", "preset": "medium"}
      else:
        stream.bit_rate = 4_000_000
      for rgb in frames:
        for packet in stream.encode(av.VideoFrame.from_ndarray(rgb, format="rgb24")):
          container.mux(packet)
      for packet in stream.encode():
        container.mux(packet)

  write_atomic(path, encode)
  return codec


def filmstrip_indices(n_frames: int, count: int = FILMSTRIP_FRAMES) -> np.ndarray:
  """`count` evenly spaced step indices from the first to the last (fewer for short episodes)."""
  return np.unique(np.round(np.linspace(0, n_frames - 1, min(count, n_frames))).astype(int))


def write_filmstrip(frames: np.ndarray, times: Sequence[float], path: str) -> None:
  """The snapshots side by side, each labelled with its time, as one PNG (written atomically),
  like the paper's snapshot figures."""
  from matplotlib.backends.backend_agg import FigureCanvasAgg
  from matplotlib.figure import Figure

  width = frames.shape[2]
  keep = min(FILMSTRIP_WIDTH, width)
  left = (width - keep) // 2
  crops = frames[:, :, left:left + keep]
  n, h, w = crops.shape[:3]
  panel = 2.2  # inches per snapshot's width
  fig = Figure(figsize=(panel * n, panel * h / w + 0.35), dpi=w / panel)
  FigureCanvasAgg(fig)
  for i, (img, t) in enumerate(zip(crops, times)):
    ax = fig.add_axes((i / n, 0.0, 1.0 / n, h / w * panel / (panel * h / w + 0.35)))
    ax.imshow(img, interpolation="nearest")
    ax.set_axis_off()
    ax.set_title(f"t = {t:.2f} s", fontsize=9, pad=3)
  write_atomic(path, lambda tmp: fig.savefig(tmp, format="png", dpi=w / panel))


def _main(argv: list[str]) -> int:
  """Child-process entry: `probe` (render one small frame) or `render JOB.json`."""
  if argv[:1] == ["probe"]:
    import mujoco

    from jax_env import robot
    m = robot.load_model()
    renderer = mujoco.Renderer(m, 32, 32)
    try:
      d = mujoco.MjData(m)
      mujoco.mj_forward(m, d)
      renderer.update_scene(d)
      renderer.render()
    finally:
      renderer.close()
    return 0
  if argv[:1] == ["render"] and len(argv) == 2:
    job = json.loads(Path(argv[1]).read_text())
    n = np.load(job["episode"])["qpos"].shape[0]
    if job["video"]:
      frames, ctrl_dt = _frames(job["model"], job["episode"], None)
      write_video(frames, 1.0 / ctrl_dt, job["video"])
      if job["filmstrip"]:
        idx = filmstrip_indices(n)
        write_filmstrip(frames[idx], idx * ctrl_dt, job["filmstrip"])
    elif job["filmstrip"]:
      idx = filmstrip_indices(n)
      frames, ctrl_dt = _frames(job["model"], job["episode"], idx)
      write_filmstrip(frames, idx * ctrl_dt, job["filmstrip"])
    return 0
  print("usage: python -m jax_env.evaluation.recording probe | render JOB.json", file=sys.stderr)
  return 2


if __name__ == "__main__":
  sys.exit(_main(sys.argv[1:]))
