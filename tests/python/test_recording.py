"""`facade.rollout` (jax_env/evaluation/recording.py): one recorded episode on the real env with
the native C MuJoCo backend, its per-step lists, the scheduled push seen in the recording, and
the offscreen video / filmstrip (skipped where no offscreen OpenGL works).

The policy is a freshly initialised checkpoint of a small planar stage (what a stage's first
checkpoint holds before learning): the recording's plumbing does not depend on what was learned,
and building it costs no training run.
"""

import copy
import json
import math
import types
from pathlib import Path

import jax
import mujoco
import numpy as np
import pytest

from jax_env import config as config_lib
from jax_env import defaults, features
from jax_env import facade
from jax_env import rewards as rewards_lib
from jax_env import robot
from jax_env.evaluation import recording
from jax_env.learner import checkpoint as ckpt_lib
from jax_env.learner import networks as nets_lib
from jax_env.learner import ppo as ppo_lib
from jax_env.learner import train

DURATION_S = 1.1  # long enough for the paper's push (0.8 s after control starts, 0.2 s long)
PUSH_N = 100.0


def _stage():
  s = copy.deepcopy(defaults.default_stage_dict("planar"))
  s["sim"]["episode_s"] = 0.4
  s["scenario_params"]["settle_s"] = 0.04
  s["ppo"].update(num_envs=8, policy_hidden=[16, 16], value_hidden=[16, 16])
  s["rma"].update(latent_dim=4, encoder_hidden=[16], history_len=4)
  return s


def _fresh_checkpoint(path, stage_dict):
  stage = config_lib.StageConfig.from_dict(stage_dict)
  learner = train.LearnerConfig.from_stage(stage)
  obs, priv, act = features.feature_names(stage)
  sizes = types.SimpleNamespace(obs_size=len(obs), privileged_size=len(priv),
                                action_size=len(act))
  net_cfg = learner.network_config(sizes)
  nets = nets_lib.Networks(net_cfg)
  key = jax.random.PRNGKey(3)
  state = ppo_lib.init_learner_state(nets, nets.init(key), 1.0, 3e-4)
  return ckpt_lib.save(path, state=state, config=net_cfg, stage=stage.name, env_steps=0,
                       iteration=0, seed=3, key=key, obs_names=obs, privileged_names=priv,
                       action_names=act, action=learner.action,
                       extra={ckpt_lib.STAGE_CONFIG_KEY: stage_dict,
                              # as after the stage's RMA adaptation phase (else it is refused)
                              "learner": {"phase": "done", "adaptation_env_steps": 64}})


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
  return str(_fresh_checkpoint(tmp_path_factory.mktemp("ckpt") / "000000000000", _stage()))


@pytest.fixture(scope="module")
def episode(checkpoint):
  """One prone episode with the paper's planar push (compiled once for the module)."""
  return facade.rollout({
      "checkpoint": checkpoint, "stage": None, "scenario": "prone", "terrain": "flat",
      "push_force": PUSH_N, "push_direction": None, "seed": 5, "backend": "native",
      "duration_s": DURATION_S, "video": None, "filmstrip": None})


def test_every_per_step_array_has_one_entry_per_control_step(episode):
  arrays = {k: v for k, v in episode.items() if isinstance(v, np.ndarray)}
  rest = {k: v for k, v in episode.items() if k not in arrays}
  json.dumps(rest, allow_nan=False)  # the rest is JSON-like and finite, as the Rust side needs
  dt = episode["dt"]
  steps = int(round(DURATION_S / dt))
  assert dt == pytest.approx(0.02)
  assert episode["time"] == pytest.approx([i * dt for i in range(steps)])
  assert episode["body_names"] == list(robot.BODY_NAMES)
  assert episode["joint_names"] == list(robot.JOINT_NAMES)
  assert episode["reward_term_names"] == list(rewards_lib.TERMS)
  # The CLI reads each array in one copy and insists on these shapes and dtypes: float64 for
  # what the host computed in float64, float32 for what the environment computed.
  f64, f32 = np.dtype(np.float64), np.dtype(np.float32)
  expected = {"time": ((steps,), f64), "body_pos": ((steps, 24, 3), f64),
              "body_quat": ((steps, 24, 4), f64), "torso_pitch": ((steps,), f64),
              "joint_pos": ((steps, 23), f32), "joint_vel": ((steps, 23), f32),
              "joint_torque": ((steps, 23), f32), "reward": ((steps,), f32),
              "reward_terms": ((steps, len(rewards_lib.TERMS)), f32),
              "standing": ((steps,), f32), "succeeded": ((steps,), f32),
              "push_force": ((steps, 3), f32)}
  assert sorted(arrays) == sorted(expected)
  for key, (shape, dtype) in expected.items():
    assert (arrays[key].shape, arrays[key].dtype) == (shape, dtype), key
    assert arrays[key].flags.c_contiguous and np.all(np.isfinite(arrays[key])), key
  total = episode["reward_terms"].sum(axis=-1)
  np.testing.assert_allclose(total, episode["reward"], rtol=1e-4, atol=1e-5)
  assert isinstance(episode["success"], bool)
  assert episode["recovery_time"] is None or episode["recovery_time"] >= 0
  assert set(np.unique(episode["standing"])) <= {0.0, 1.0}
  assert episode["truncated_at"] is None
  assert episode["video"] is None and episode["filmstrip"] is None
  assert episode["scenario"] == "prone" and episode["push_direction"] == "forward"


def test_body_poses_are_the_recorded_joint_states_forward_kinematics(episode):
  m = robot.load_model()
  d = mujoco.MjData(m)
  quat = np.asarray(episode["body_quat"])
  np.testing.assert_allclose(np.linalg.norm(quat, axis=-1), 1.0, atol=1e-9)
  trunk = robot.BODY_NAMES.index("Trunk")
  for t in (0, len(episode["time"]) // 2, len(episode["time"]) - 1):
    pos = np.asarray(episode["body_pos"][t])
    # The Trunk is the free body: its pose is qpos[:7]; the rest follow from the joints.
    d.qpos[:3], d.qpos[3:7] = pos[trunk], quat[t, trunk]
    d.qpos[7:] = episode["joint_pos"][t]
    mujoco.mj_kinematics(m, d)
    ids = [m.body(b).id for b in robot.BODY_NAMES]
    np.testing.assert_allclose(d.xpos[ids], pos, atol=1e-9)
  # Lying prone the torso is pitched forward by about 90 degrees.
  assert episode["torso_pitch"][0] == pytest.approx(math.pi / 2, abs=0.35)


def test_the_paper_push_is_recorded_at_its_time_along_the_torso(episode):
  dt = episode["dt"]
  force = np.asarray(episode["push_force"])
  pushed = np.flatnonzero(np.linalg.norm(force, axis=-1) > 0)
  # Step k's push shows in entry k + 1 (the state after the step); it starts 0.8 s after the
  # control start and lasts 0.2 s.
  first = int(round(episode["control_start_s"] / dt)) + int(round(0.8 / dt)) + 1
  np.testing.assert_array_equal(pushed, np.arange(first, first + int(round(0.2 / dt))))
  np.testing.assert_allclose(np.linalg.norm(force[pushed], axis=-1), PUSH_N, rtol=1e-4)
  # "forward" is the torso's +x axis at the step the force acted in.
  trunk = robot.BODY_NAMES.index("Trunk")
  for i in pushed:
    w, x, y, z = episode["body_quat"][i - 1][trunk]
    x_axis = np.array([1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)])
    assert force[i] @ x_axis / PUSH_N > 0.999


def test_scene_geoms_are_the_robot_primitives_and_the_floor():
  m = robot.load_model()
  geoms = recording.scene_geoms(m)
  robot_geoms = [g for g in geoms if g["body"] != "world"]
  assert {g["body"] for g in robot_geoms} <= set(robot.BODY_NAMES)
  assert len(robot_geoms) == sum(int(m.geom_bodyid[g]) in {m.body(b).id for b in robot.BODY_NAMES}
                                 for g in range(m.ngeom))
  assert {g["type"] for g in robot_geoms} <= {"sphere", "capsule", "box"}
  floor = [g for g in geoms if g["name"] == "floor"]
  assert floor and floor[0]["type"] == "box"
  assert floor[0]["pos"][2] + floor[0]["size"][2] == pytest.approx(0.0)  # top face at z = 0
  with_ball = recording.scene_geoms(m, obstacle_pos=[0.1, 0.0, 0.1])
  assert [g["name"] for g in with_ball][-1] == "obstacle"


def test_torso_pitch_sign_convention():
  def gravity_in_torso(quat):
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, np.asarray(quat, np.float64))
    return mat.reshape(3, 3).T @ np.array([0.0, 0.0, -1.0])

  half = math.sqrt(0.5)
  quats = [[1, 0, 0, 0], [half, 0, half, 0], [half, 0, -half, 0],
           [math.cos(0.2), 0, 0, math.sin(0.2)]]  # upright, nose down, nose up, yawed
  gravity = np.stack([gravity_in_torso(q) for q in quats])
  np.testing.assert_allclose(recording.torso_pitch(gravity), [0, math.pi / 2, -math.pi / 2, 0],
                             atol=1e-12)


def test_bad_requests_name_the_value_and_the_valid_ones(checkpoint):
  base = {"checkpoint": checkpoint, "backend": "native"}
  with pytest.raises(ValueError, match="unknown request key"):
    facade.rollout({**base, "bogus": 1})
  with pytest.raises(ValueError, match="unknown scenario 'standing'; valid: ksi_prone_1"):
    facade.rollout({**base, "scenario": "standing"})
  with pytest.raises(ValueError, match="unknown push direction 'up'; valid: forward, backward"):
    facade.rollout({**base, "push_direction": "up"})
  with pytest.raises(ValueError, match="unknown terrain 'ice'"):
    facade.rollout({**base, "terrain": "ice"})
  with pytest.raises(ValueError, match="shorter than two control steps"):
    facade.rollout({**base, "duration_s": 0.03})
  with pytest.raises(ValueError, match=r"longer than the stage's settle_s \(0.04 s"):
    facade.rollout({**base, "duration_s": 0.04})


def test_an_untrained_adaptation_module_is_refused(checkpoint, tmp_path):
  meta = ckpt_lib.read_meta(checkpoint)
  meta["learner"]["adaptation_env_steps"] = 0  # a checkpoint of the stage's PPO phase
  d = tmp_path / "ppo_phase"
  d.mkdir()
  (d / ckpt_lib.PARAMS_FILE).write_bytes((Path(checkpoint) / ckpt_lib.PARAMS_FILE).read_bytes())
  (d / ckpt_lib.META_FILE).write_text(json.dumps(meta))
  with pytest.raises(ckpt_lib.CheckpointError, match=r"its RMA adaptation module was never "
                     r"trained \(stage planar ended before its adaptation phase\)"):
    facade.rollout({"checkpoint": str(d), "backend": "native", "scenario": "prone"})


@pytest.fixture(scope="module")
def gl():
  platform = recording.offscreen_gl()
  if platform is None:
    pytest.skip("no offscreen OpenGL (EGL or OSMesa) works on this machine")
  return platform


def test_video_and_filmstrip_of_the_recorded_episode(episode, gl, tmp_path):
  import av
  from matplotlib import image

  m = robot.load_model()
  qpos = np.concatenate([np.asarray(episode["body_pos"])[:, 0],
                         np.asarray(episode["body_quat"])[:, 0],
                         np.asarray(episode["joint_pos"])], axis=-1)
  mocap = np.asarray([m.body_pos[b] for b in range(m.nbody) if m.body_mocapid[b] >= 0])
  video, strip = tmp_path / "episode.mp4", tmp_path / "episode.png"
  written = recording.render(m, qpos, mocap, episode["dt"], lookat_xy=[0.0, 0.0],
                             video=str(video), filmstrip=str(strip))
  assert written == {"video": str(video), "filmstrip": str(strip)}
  with av.open(str(video)) as container:
    stream = container.streams.video[0]
    frames = [f.to_ndarray(format="rgb24") for f in container.decode(stream)]
  assert len(frames) == len(episode["time"])
  assert frames[0].shape == (recording.VIDEO_SIZE[1], recording.VIDEO_SIZE[0], 3)
  assert float(stream.average_rate) == pytest.approx(1 / episode["dt"])
  assert frames[0].std() > 5  # a picture, not a blank frame
  png = image.imread(str(strip))
  assert png.ndim == 3 and png.shape[1] > 4 * png.shape[0]  # six snapshots side by side
  assert sorted(p.name for p in tmp_path.iterdir()) == ["episode.mp4", "episode.png"]


def test_rendering_without_any_working_gl_fails_in_one_line(episode, monkeypatch, tmp_path):
  monkeypatch.delenv("MUJOCO_GL", raising=False)
  monkeypatch.setattr(recording, "GL_PLATFORMS", ("no-such-gl",))
  m = robot.load_model()
  qpos = np.tile(m.qpos0, (2, 1))
  with pytest.raises(recording.RenderingUnavailable) as err:
    recording.render(m, qpos, np.zeros((m.nmocap, 3)), 0.02, lookat_xy=[0, 0],
                     video=str(tmp_path / "v.mp4"), filmstrip=None)
  message = str(err.value)
  assert "\n" not in message and "no-such-gl" in message and "EGL" in message
  assert not any(tmp_path.iterdir())
