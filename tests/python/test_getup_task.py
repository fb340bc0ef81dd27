"""The get-up task design of issue 10, each part on its own (its reward terms and the reward
shaping are tested with the others in test_env_parts.py): the `stand` and `squat` start states, the true terminations, staggered
episode clocks, the bounded action std, the penalty schedule, and the deterministic stand-rate
monitor on a held `stand`.

Physics runs on the native (C MuJoCo) backend: it compiles in seconds on a CPU.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jax_env import config, robot
from jax_env.config import StageConfig
from jax_env.defaults import default_stage_dict
from jax_env.names import SCENARIOS
from jax_env.env import FallRecoveryEnv
from jax_env.stage_config import EPISODE_ENDS
from jax_env.kinematics import axis_angle_quat, quat_mul, rotate_inverse
from jax_env.learner import monitor as monitor_lib
from jax_env.learner import networks as nets_lib
from jax_env.learner import ppo as ppo_lib
from jax_env.learner import train as train_lib
from jax_env.scenarios import (REST_CLEARANCE, ROCK_BACK, ROCK_BACK_PITCH, SQUAT, SQUAT_PITCH,
                               TOE_CROUCH, TOE_CROUCH_PITCH, toe_crouch_joints)

B = 4


def _stage(**sections) -> dict:
  d = default_stage_dict("planar")
  d["action"] = {"mapping": "default", "scale": 1.0, "clip": 3.0}
  d["constraints"] = {"torque_limit_scale": 1.0, "joint_range_scale": 1.0,
                      "velocity_limit_scale": 1.0}
  d["sim"]["episode_s"] = 1.0
  d["scenario_params"]["settle_s"] = 0.2
  d["domain_randomization"] = {"enabled": False}
  for k, v in sections.items():
    d[k] = v
  return d


# -- start states -------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def upright_env():
  scenarios = {"stand": 0.5, "squat": 0.5}
  return FallRecoveryEnv(_stage(scenarios=scenarios), backend="native")


def test_stand_and_squat_start_on_their_feet_without_settling(upright_env):
  env = upright_env
  scenario = jnp.array([SCENARIOS.index("stand")] * 2 + [SCENARIOS.index("squat")] * 2)
  state = jax.jit(env.reset)(jax.random.split(jax.random.PRNGKey(0), 4), scenario)
  qpos = np.asarray(env.backend.view(state.physics).qpos)
  stand, _ = robot.keyframe(env.mj_model, "stand")
  noise = env.stage.scenario_params.ksi_joint_noise
  assert np.all(np.abs(qpos[:2, 7:] - stand[7:]) < 5 * noise + 1e-6)
  assert np.allclose(qpos[:2, 2], stand[2], atol=0.03)
  j = {n: i for i, n in enumerate(robot.JOINT_NAMES)}
  for joint, value in SQUAT.items():
    assert np.allclose(qpos[2:, 7 + j[f"Left_{joint}"]], value, atol=5 * noise)
  assert np.all(qpos[2:, 2] < stand[2] - 0.1)  # crouched
  # Trunk pitched forward by SQUAT_PITCH: gravity in the Trunk frame leans to +x.
  assert np.all(np.asarray(state.obs[2:, 0]) == pytest.approx(math.sin(SQUAT_PITCH), abs=0.05))
  assert np.all(np.asarray(state.control_active) == 1.0)  # no settling: the policy acts at once


def _trunk_pitch(qpos):
  """Pitch of pure-pitch base quaternions (w, x, y, z) [B, 4] up to heading (the sampler adds a
  random yaw about world z; the pitch is the tilt of the Trunk's z axis)."""
  x, y = qpos[:, 4], qpos[:, 5]
  zz = 1 - 2 * (x * x + y * y)  # world-z component of the Trunk's z axis
  return np.arccos(np.clip(zz, -1.0, 1.0))


def test_kneel_to_crouch_starts_lie_between_the_kneel_and_the_crouch():
  env = FallRecoveryEnv(_stage(scenarios={"kneel_to_crouch": 1.0}), backend="native")
  n = 32
  state = jax.jit(env.reset)(jax.random.split(jax.random.PRNGKey(3), n))
  assert np.all(np.asarray(state.scenario) == SCENARIOS.index("kneel_to_crouch"))
  qpos = np.asarray(env.backend.view(state.physics).qpos)
  kneel, _ = robot.keyframe(env.mj_model, "ksi_prone_3")
  j = {name: 7 + i for i, name in enumerate(robot.JOINT_NAMES)}
  slack = 5 * env.stage.scenario_params.ksi_joint_noise
  for joint, value in TOE_CROUCH.items():
    ends = sorted([kneel[j[f"Left_{joint}"]], value])
    assert np.all(qpos[:, j[f"Left_{joint}"]] >= ends[0] - slack), joint
    assert np.all(qpos[:, j[f"Left_{joint}"]] <= ends[1] + slack), joint
  pitch = _trunk_pitch(qpos)
  kneel_pitch = _trunk_pitch(kneel[None])[0]
  assert np.all((pitch > TOE_CROUCH_PITCH - 0.05) & (pitch < kneel_pitch + 0.05))
  # Spread along the line, not bunched at one end.
  assert pitch.max() - pitch.min() > 0.5 * (kneel_pitch - TOE_CROUCH_PITCH)
  assert np.all(np.asarray(state.control_active) == 1.0)


def test_sit_to_crouch_starts_lie_between_sitting_and_the_crouch():
  env = FallRecoveryEnv(_stage(scenarios={"sit_to_crouch": 1.0}), backend="native")
  state = jax.jit(env.reset)(jax.random.split(jax.random.PRNGKey(4), 32))
  assert np.all(np.asarray(state.scenario) == SCENARIOS.index("sit_to_crouch"))
  qpos = np.asarray(env.backend.view(state.physics).qpos)
  sit, _ = robot.keyframe(env.mj_model, "ksi_supine_2")
  crouch, _ = robot.keyframe(env.mj_model, "ksi_supine_3")
  slack = 5 * env.stage.scenario_params.ksi_joint_noise
  lo, hi = np.minimum(sit[7:], crouch[7:]) - slack, np.maximum(sit[7:], crouch[7:]) + slack
  assert np.all((qpos[:, 7:] >= lo) & (qpos[:, 7:] <= hi))
  # Trunk-frame gravity: sitting leans back (g_x = −sin 0.79), the crouch forward (sin 0.27);
  # the starts spread over most of the way between.
  g_x = np.asarray(state.obs[:, 0])
  assert np.all((g_x > -math.sin(0.79) - 0.05) & (g_x < math.sin(0.27) + 0.05))
  assert g_x.max() - g_x.min() > 0.5 * (math.sin(0.27) + math.sin(0.79))
  assert np.all(np.asarray(state.control_active) == 1.0)


def test_rock_back_starts_rocked_onto_the_shoulders_head_down():
  env = FallRecoveryEnv(_stage(scenarios={"rock_back": 1.0}), backend="native")
  state = jax.jit(env.reset)(jax.random.split(jax.random.PRNGKey(5), 16))
  assert np.all(np.asarray(state.scenario) == SCENARIOS.index("rock_back"))
  qpos = np.asarray(env.backend.view(state.physics).qpos)
  j = {name: 7 + i for i, name in enumerate(robot.JOINT_NAMES)}
  slack = 5 * env.stage.scenario_params.ksi_joint_noise
  for joint, value in ROCK_BACK.items():  # pitch joints, and an elbow yaw of 0: both sides alike
    for side in ("Left", "Right"):
      assert np.all(np.abs(qpos[:, j[f"{side}_{joint}"]] - value) <= slack), (side, joint)
  # Trunk-frame gravity of a Trunk pitched ROCK_BACK_PITCH: chest up (g_x < 0), head down
  # (g_z > 0); lying flat on the back would read (−1, 0, 0).
  g = np.asarray(state.obs[:, :3])
  assert np.allclose(g[:, 0], math.sin(ROCK_BACK_PITCH), atol=0.02)
  assert np.allclose(g[:, 2], -math.cos(ROCK_BACK_PITCH), atol=0.02)
  assert np.all(qpos[:, 2] > 0.2)  # on the shoulders with the hips up, not lying flat
  assert np.all(np.asarray(state.control_active) == 1.0)


def test_zero_action_stands_up_from_the_crouch_end_but_not_from_the_kneel():
  """The bridge's premise, in plain C MuJoCo: PD targets at the stand pose (the "default"
  mapping's zero action) raise the T1 from the crouch on its toes, not from `ksi_prone_3`."""
  import mujoco  # pylint: disable=import-outside-toplevel
  from jax_env import kinematics, paths  # pylint: disable=import-outside-toplevel
  model = mujoco.MjModel.from_xml_path(str(paths.SCENE_XML))
  lowest_point = kinematics.Kinematics(model).lowest_point
  stand, _ = robot.keyframe(model, "stand")
  kneel, _ = robot.keyframe(model, "ksi_prone_3")
  crouch = stand.copy()
  crouch[7:] = toe_crouch_joints(stand[7:])
  crouch[3:7] = [math.cos(TOE_CROUCH_PITCH / 2), 0.0, math.sin(TOE_CROUCH_PITCH / 2), 0.0]

  def stood(qpos):
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    data.qpos[2] = 0.0  # placed by its lowest point below
    data.qpos[2] = REST_CLEARANCE - float(lowest_point(jnp.asarray(data.qpos, jnp.float32)))
    trunk = model.body("Trunk").id
    held = 0.0
    for _ in range(int(3.0 / model.opt.timestep)):
      data.ctrl[:] = stand[7:]
      mujoco.mj_step(model, data)
      upright = data.xmat[trunk][8] > math.cos(0.2) and abs(data.xpos[trunk][2] - 0.67) < 0.05
      held = held + model.opt.timestep if upright else 0.0
    return held >= 1.0

  assert stood(crouch)
  assert not stood(kneel)


# -- terminations and clocks --------------------------------------------------------------------


def _reset_to_pose(env, quat, height, n=B):
  stand, _ = robot.keyframe(env.mj_model, "stand")
  qpos = np.tile(stand, (n, 1)).astype(np.float32)
  qpos[:, 3:7] = np.asarray(quat)
  qpos[:, 2] = height
  return jax.jit(env.reset_to)(jax.random.split(jax.random.PRNGKey(1), n), jnp.asarray(qpos),
                               jnp.zeros((n, env.mj_model.nv)))


def _run(env, state, steps):
  """(done, truncation, how it ended: a name of EPISODE_ENDS, or None while it runs) of the first
  env after each of `steps` zero-action steps."""
  step = jax.jit(env.step)
  a = jnp.zeros((state.obs.shape[0], env.action_size))
  out = []
  for _ in range(steps):
    state = step(state, a)
    done = float(state.done[0])
    end = EPISODE_ENDS[int(state.episode_metrics["end"][0])] if done else None
    out.append((done, float(state.truncation[0]), end))
  return out


def test_terminations_end_episodes_without_bootstrap():
  term = {"low_height": 0.3, "low_height_s": 0.1, "upside_down": 0.9, "side_roll": 0.8}
  env = FallRecoveryEnv(_stage(termination=term), backend="native")
  x = np.array([1.0, 0.0, 0.0])
  # Upside down (head on the floor): ends at the first controlled step.
  upside = axis_angle_quat(jnp.asarray(x, jnp.float32), math.pi)
  assert _run(env, _reset_to_pose(env, upside, 0.8), 1) == [(1.0, 0.0, "upside_down")]
  # On its side: ends at once too.
  side = axis_angle_quat(jnp.asarray(x, jnp.float32), math.pi / 2)
  assert _run(env, _reset_to_pose(env, side, 0.3), 1) == [(1.0, 0.0, "side_roll")]
  # Lying on the back below 0.3 m: ends after more than low_height_s = 5 steps, not before.
  y = jnp.asarray([0.0, 1.0, 0.0], jnp.float32)
  supine = axis_angle_quat(y, -math.pi / 2)
  ends = _run(env, _reset_to_pose(env, supine, 0.15), 6)
  assert ends[:5] == [(0.0, 0.0, None)] * 5 and ends[5] == (1.0, 0.0, "low_height")
  # Without the termination table nothing ends early.
  plain = FallRecoveryEnv(_stage(), backend="native")
  assert all(d == 0.0 for d, _, _ in _run(plain, _reset_to_pose(plain, supine, 0.15), 6))


def test_face_down_limit_ends_the_head_first_dive_not_the_rock_back():
  # Head down at 30° from vertical: chest toward the floor (a dive from the kneel, g_x = +0.5)
  # or toward the sky (the supine get-up's rock-back onto the shoulders, g_x = -0.5); g_z 0.87.
  term = {"upside_down": 0.9, "upside_down_face_down": 0.8}
  env = FallRecoveryEnv(_stage(termination=term), backend="native")
  y = jnp.asarray([0.0, 1.0, 0.0], jnp.float32)
  dive_quat, rock_back_quat = (axis_angle_quat(y, s * math.pi * 5 / 6) for s in (1, -1))
  down = jnp.asarray([0.0, 0.0, -1.0])
  assert np.allclose(rotate_inverse(dive_quat, down), [0.5, 0.0, 0.866], atol=1e-3)
  assert np.allclose(rotate_inverse(rock_back_quat, down), [-0.5, 0.0, 0.866], atol=1e-3)
  assert _run(env, _reset_to_pose(env, dive_quat, 0.5), 1) == [
      (1.0, 0.0, "upside_down_face_down")]
  assert _run(env, _reset_to_pose(env, rock_back_quat, 0.5), 1) == [(0.0, 0.0, None)]
  # The rule that ended the episode is the one it records as met.
  ended = jax.jit(env.step)(_reset_to_pose(env, dive_quat, 0.5), jnp.zeros((B, env.action_size)))
  assert int(ended.episode_metrics["rule_met"][0]) == EPISODE_ENDS.index("upside_down_face_down")


def test_face_down_limit_spares_the_roll_over_a_shoulder():
  # The same dive, turned 60° about the spine: chest down, head down (g_z 0.87) and over a
  # shoulder (|g_y| 0.43), as the get-up from the kneel rolls out. With a roll limit of 0.3 the
  # face-down rule spares it (the plain upside-down limit still applies); the straight dive
  # (g_y 0) still ends; without the limit both end.
  y, z = (jnp.asarray(v, jnp.float32) for v in ([0.0, 1.0, 0.0], [0.0, 0.0, 1.0]))
  dive_quat = axis_angle_quat(y, math.pi * 5 / 6)
  roll_quat = quat_mul(dive_quat, axis_angle_quat(z, math.pi / 3))
  g = rotate_inverse(roll_quat, jnp.asarray([0.0, 0.0, -1.0]))
  assert g[0] > 0 and abs(g[1]) > 0.4 and g[2] > 0.86
  term = {"upside_down": 0.9, "upside_down_face_down": 0.8}
  spared = FallRecoveryEnv(
      _stage(termination=term | {"upside_down_face_down_max_roll": 0.3}), backend="native")
  assert _run(spared, _reset_to_pose(spared, roll_quat, 0.5), 1) == [(0.0, 0.0, None)]
  assert _run(spared, _reset_to_pose(spared, dive_quat, 0.5), 1) == [
      (1.0, 0.0, "upside_down_face_down")]
  strict = FallRecoveryEnv(_stage(termination=term), backend="native")
  assert _run(strict, _reset_to_pose(strict, roll_quat, 0.5), 1) == [
      (1.0, 0.0, "upside_down_face_down")]


def test_rules_that_do_not_end_episodes_are_recorded():
  # The evaluation's environment (`rules_end_episodes=False`, as in the paper's evaluation): the
  # head-first dive runs on to its time limit and keeps the rule that held first (the training
  # environment ends it there: test_face_down_limit_ends_the_head_first_dive_not_the_rock_back).
  term = {"upside_down": 0.9, "upside_down_face_down": 0.8}
  y = jnp.asarray([0.0, 1.0, 0.0], jnp.float32)
  dive_quat = axis_angle_quat(y, math.pi * 5 / 6)
  face_down = EPISODE_ENDS.index("upside_down_face_down")
  env = FallRecoveryEnv(_stage(termination=term), backend="native", rules_end_episodes=False)
  state = _reset_to_pose(env, dive_quat, 0.5)
  step = jax.jit(env.step)
  a = jnp.zeros((B, env.action_size))
  state = step(state, a)
  assert float(state.done[0]) == 0.0 and int(state.rule_met[0]) == face_down
  steps = 1
  while float(state.done[0]) == 0.0:
    state, steps = step(state, a), steps + 1
  assert steps == env.episode_steps and float(state.truncation[0]) == 1.0
  assert EPISODE_ENDS[int(state.episode_metrics["end"][0])] == "time_limit"
  assert int(state.episode_metrics["rule_met"][0]) == face_down
  assert int(state.rule_met[0]) == 0  # the next episode starts clean


def test_staggered_clocks_end_first_episodes_at_different_steps(upright_env):
  env = upright_env
  n = 16
  state = jax.jit(env.reset)(jax.random.split(jax.random.PRNGKey(2), n))
  state = jax.jit(env.stagger)(state, jax.random.PRNGKey(3))
  limit = np.asarray(state.episode_limit)
  assert np.all(limit > np.asarray(state.control_start)) and np.all(limit <= env.episode_steps)
  assert len(set(limit.tolist())) > n // 3  # spread, not lockstep
  step = jax.jit(env.step)
  a = jnp.zeros((n, env.action_size))
  ended_at = np.full(n, -1)
  for t in range(env.episode_steps):
    state = step(state, a)
    done, trunc = np.asarray(state.done), np.asarray(state.truncation)
    first = (done > 0) & (ended_at < 0)
    assert np.all(trunc[first] == 1.0)  # a time-out, bootstrapped
    end = np.asarray(state.episode_metrics["end"])
    assert np.all(end[first] == EPISODE_ENDS.index("time_limit"))
    ended_at[first] = t + 1
  assert np.array_equal(ended_at, limit)
  # The episodes that follow run the full length.
  assert np.all(np.asarray(state.episode_limit) == env.episode_steps)


def test_auto_reset_of_the_rows_that_ended_equals_a_reset_of_every_row():
  """On the native backend auto-resets compute fresh episodes for the rows that ended,
  env.reset_rows at a time (gathered); the batch after the step is, bit for bit, what a reset of
  every row (kept where done) gives, with one, reset_rows and more rows ending at once."""
  env = FallRecoveryEnv(default_stage_dict("planar"), backend="native")  # randomized draws
  few = env.reset_rows
  n = few + 4
  state = jax.jit(env.reset)(jax.random.split(jax.random.PRNGKey(4), n))
  a = 0.3 * jax.random.normal(jax.random.PRNGKey(5), (n, env.action_size))
  gathered = jax.jit(lambda s, a: env.step(s, a))
  for _ in range(3):
    state = gathered(state, a)
  every_row = jax.jit(lambda s, a: env.step(s, a))  # traced below, with every row
  for ending in ([5], list(range(1, 1 + few)), list(range(n - 3))):
    limit = state.episode_limit.at[jnp.asarray(ending)].set(state.step_count[0] + 1)
    s = state.replace(episode_limit=limit)
    x = gathered(s, a)
    env.reset_rows = 0  # read when the step is traced
    y = every_row(s, a)
    env.reset_rows = few
    assert np.flatnonzero(np.asarray(x.done)).tolist() == ending
    assert np.all(np.asarray(x.step_count)[ending] == 0)  # fresh episodes
    assert few in env.backend._batches  # the gathered rows' own host batch: the path ran
    for p, q in zip(jax.tree_util.tree_leaves(x), jax.tree_util.tree_leaves(y)):
      np.testing.assert_array_equal(np.asarray(p), np.asarray(q))


def test_assist_force_lifts_the_trunk_and_survives_resets():
  env = FallRecoveryEnv(_stage(), backend="native")
  y = jnp.asarray([0.0, 1.0, 0.0], jnp.float32)
  supine = axis_angle_quat(y, -math.pi / 2)
  start = _reset_to_pose(env, supine, 0.15, n=2)
  weight = float(env.mj_model.body_subtreemass[env.trunk]) * 9.81
  lifted = env.with_assist_force(start, jnp.asarray([0.0, 2.0 * weight]))
  assert np.allclose(np.asarray(lifted.assist_force), [0.0, 2.0 * weight])
  step = jax.jit(env.step)
  a = jnp.zeros((2, env.action_size))
  for _ in range(10):
    lifted = step(lifted, a)
  height = np.asarray(env.backend.view(lifted.physics).qpos[:, 2])
  assert height[0] < 0.2 and height[1] > 0.3  # twice the weight pulls the robot up
  # The schedule's value holds across auto-resets (only the learner changes it) and a
  # fresh reset has none (evaluation never sees an assist).
  done = lifted.replace(episode_limit=lifted.step_count + 1)
  after = step(done, a)
  assert float(after.done[1]) == 1.0
  assert float(after.assist_force[1]) == pytest.approx(2.0 * weight)
  assert np.all(np.asarray(start.assist_force) == 0.0)


# -- learner: std bound, penalty schedule -------------------------------------------------------


def test_action_std_is_projected_to_its_bound():
  params = {"policy": {"log_std": jnp.log(jnp.array([0.1, 0.5, 3.0]))}, "value": {}}
  out = ppo_lib.bound_action_std(params, 0.5)
  assert np.allclose(np.exp(out["policy"]["log_std"]), [0.1, 0.5, 0.5])
  assert ppo_lib.bound_action_std(params, None) is params


def test_action_std_stays_bounded_under_a_large_entropy_bonus(tmp_path):
  # An entropy bonus that dominates the loss pushes the std up at every step (hifar's run B:
  # 0.5 -> 2.8); the bound holds it at max_action_std.
  from toy_env import ToyStandUpEnv, learner_config
  bound = 0.6
  cfg = learner_config(env_steps=8 * 2048, ppo={"entropy_cost": 1.0, "max_action_std": bound},
                       rma={"adaptation_env_steps": 0})
  stds = []

  def callback(progress):
    stds.append(progress["losses"]["action_std"])
    return "continue"

  train_lib.train_stage(ToyStandUpEnv(), cfg, stage_dir=tmp_path, seed=0, callback=callback)
  assert stds[-1] == pytest.approx(bound, rel=1e-5)
  assert max(stds) <= bound * (1 + 1e-5)


def test_max_action_std_is_validated():
  d = default_stage_dict("planar")
  d["ppo"]["max_action_std"] = 0.5  # below initial_action_std = 1.0
  assert config.check_stage(d) == [{"path": ["ppo", "max_action_std"], "message":
                                    "max_action_std 0.5 is below initial_action_std 1.0",
                                    "at": "key"}]


def test_action_std_schedule_tightens_the_bound_during_a_stage(tmp_path):
  # The entropy bonus holds the std at its bound; the schedule halves the bound after the
  # fourth iteration (4 × 2048 env steps) and the std follows it down, reported per iteration.
  from toy_env import ToyStandUpEnv, learner_config
  bound = 0.6
  schedule = config.Schedule("env_steps", ((0.0, 1.0), (4 * 2048.0, 1.0), (5 * 2048.0, 0.5)))
  cfg = learner_config(env_steps=8 * 2048, ppo={"entropy_cost": 1.0, "max_action_std": bound,
                                                "action_std_schedule": schedule},
                       rma={"adaptation_env_steps": 0})
  seen = []

  def callback(progress):
    seen.append((progress["max_action_std"], progress["losses"]["action_std"]))
    return "continue"

  train_lib.train_stage(ToyStandUpEnv(), cfg, stage_dir=tmp_path, seed=0, callback=callback)
  bounds = [b for b, _ in seen]
  assert bounds == pytest.approx([bound] * 5 + [bound / 2] * 3)
  assert seen[3][1] == pytest.approx(bound, rel=1e-5)  # at the bound before the schedule moves
  assert seen[-1][1] == pytest.approx(bound / 2, rel=1e-5)
  # (An iteration's reported std is its minibatches' mean: the first one at a new bound still
  # samples the old std, projected after its step.)
  assert all(std <= bound * (1 + 1e-5) for _, std in seen)


def test_action_std_schedule_is_validated():
  d = default_stage_dict("planar")
  d["ppo"]["max_action_std"] = 1.0
  d["ppo"]["action_std_schedule"] = {"by": "env_steps", "points": [[0, 1.0], [100, 0.1]]}
  assert config.check_stage(d) == []
  assert config.parse_stage(d).ppo.action_std_schedule.scale(50) == pytest.approx(0.55)
  d["ppo"]["action_std_schedule"]["points"][1][1] = 0.0  # a zero std is no policy
  assert config.check_stage(d) == [{"path": ["ppo", "action_std_schedule", "points", 1],
                                    "message": "scale 0.0 must be in (0, 1]: the schedule "
                                    "tightens max_action_std", "at": "key"}]
  del d["ppo"]["max_action_std"]
  d["ppo"]["action_std_schedule"]["points"][1][1] = 0.5
  assert config.check_stage(d) == [{"path": ["ppo", "action_std_schedule"], "message":
                                    "action_std_schedule scales max_action_std, which is not "
                                    "set", "at": "key"}]


def test_penalty_schedule_by_env_steps_and_by_stand_rate():
  by_steps = config.Schedule("env_steps", ((0.0, 0.0), (100.0, 0.0), (300.0, 1.0)))
  scale = train_lib.ScheduleScale(by_steps)
  assert scale.initial == 0.0
  assert [scale.after(0.0, s, None) for s in (50, 100, 200, 300, 900)] == [0, 0, 0.5, 1, 1]
  by_rate = train_lib.ScheduleScale(config.Schedule("stand_rate", ((0.2, 0.0),
                                                                         (0.6, 1.0))))
  s = by_rate.after(by_rate.initial, 0, 0.4)
  assert s == pytest.approx(0.5)
  assert by_rate.after(s, 0, 0.1) == pytest.approx(0.5)  # a ratchet: it never goes back
  assert by_rate.after(s, 0, None) == pytest.approx(0.5)
  assert train_lib.ScheduleScale(None).after(0.3, 10, 0.5) == 1.0


def test_assist_schedule_ratchets_down_and_is_validated():
  fade = config.Schedule("stand_rate", ((0.0, 1.0), (0.5, 0.0)))
  assist = train_lib.ScheduleScale(fade, ratchet=min)
  assert assist.initial == 1.0
  s = assist.after(1.0, 0, 0.25)
  assert s == pytest.approx(0.5)
  assert assist.after(s, 0, 0.0) == pytest.approx(0.5)  # a dip does not bring the force back
  d = default_stage_dict("planar")
  d["assist"] = {"force": 150.0, "schedule": {"by": "stand_rate", "points": [[0, 1], [0.5, 0]]}}
  assert config.check_stage(d) == []
  stage = config.StageConfig.from_dict(d)
  assert stage.assist == config.AssistConfig(150.0, fade)
  assert train_lib.LearnerConfig.from_stage(stage).assist == stage.assist
  d["assist"] = {"force": -1.0, "schedul": {}}
  assert sorted(tuple(e["path"]) for e in config.check_stage(d)) == [("assist", "force"),
                                                                     ("assist", "schedul")]


def test_new_sections_are_validated_with_key_paths():
  d = default_stage_dict("planar")
  d["reward_shaping"] = {"clip_at_zero": "yes",
                         "penalty_schedule": {"by": "env_steps", "points": [[10, 1], [5, 1]]}}
  d["termination"] = {"upside_down": 1.5, "upside_down_face_down_max_roll": 1.2,
                      "low_hieght": 0.2}
  d["monitor"] = {"every": 5, "scenarios": ["stand", "kneeling"]}
  paths = sorted(tuple(e["path"]) for e in config.check_stage(d))
  assert paths == sorted([("reward_shaping", "clip_at_zero"),
                          ("reward_shaping", "penalty_schedule", "points", 1),
                          ("termination", "low_hieght"), ("termination", "upside_down"),
                          ("termination", "upside_down_face_down_max_roll"),
                          ("monitor", "scenarios", 1)])


def test_keep_best_needs_the_monitor_on_and_a_boolean():
  d = default_stage_dict("planar")
  d["monitor"] = {"every": 0, "keep_best": True}
  assert config.check_stage(d) == [{"path": ["monitor", "keep_best"], "message":
                                    "keep_best needs the monitor on (every > 0): it keeps the "
                                    "parameters of the best monitor point", "at": "key"}]
  d["monitor"] = {"every": 5, "keep_best": "yes"}
  assert [e["path"] for e in config.check_stage(d)] == [["monitor", "keep_best"]]
  d["monitor"] = {"every": 5, "keep_best": True}
  assert config.StageConfig.from_dict(d).monitor.keep_best is True


# -- the deterministic monitor ------------------------------------------------------------------


def _zero_output_policy(table):
  """(networks, parameters, normalizer) of a stage's policy whose output layer is zero."""
  stage = StageConfig.from_dict(table)
  env = FallRecoveryEnv(stage, backend="native")
  nets = nets_lib.Networks(train_lib.LearnerConfig.from_stage(stage).network_config(env))
  params = nets.init(jax.random.PRNGKey(0))
  params["policy"] = jax.tree_util.tree_map(jnp.zeros_like, params["policy"])
  return nets, params, nets_lib.init_normalizer(nets.config)


def test_monitor_reports_a_held_stand_as_standing():
  # With the "default" mapping a zero action holds the PD targets at `stand`: a policy whose
  # output layer is zero holds the robot standing, and lying does not get up by itself.
  table = _stage(scenarios={"stand": 0.5, "supine": 0.5})
  table["sim"]["episode_s"] = 2.0  # hold_s is 1 s
  nets, params, normalizer = _zero_output_policy(table)
  monitor = monitor_lib.make_monitor(
      config.MonitorConfig(every=1, episodes=2, scenarios=("stand", "supine")), table, nets,
      "native", jax.random.PRNGKey(4))
  out = monitor(params, normalizer)
  assert out["stand_rate"] == {"stand": 1.0, "supine": 0.0}
  assert out["recovery_time"]["stand"] == pytest.approx(0.0)
  assert out["recovery_time"]["supine"] is None
  assert out["max_height"]["stand"] > 0.6 > out["max_height"]["supine"]
  assert out["mean_stand_rate"] == pytest.approx(0.5)
  assert out["terminated"] == {"stand": 0.0, "supine": 0.0}  # no termination rules here
  assert out["actor"] == "privileged"
  assert monitor(params, normalizer) == out  # the same episodes every call
  # The deployable actor (the adaptation phase's monitor) reads the observation history; the
  # zero output layer holds the stand whatever latent the module estimates.
  deployable = monitor(params, normalizer, "deployable")
  assert deployable["actor"] == "deployable"
  assert deployable["stand_rate"] == out["stand_rate"]


def test_monitor_applies_the_stage_terminations_as_the_evaluation_does():
  # A termination the held stand trips at once (Trunk "low" below 0.9 m for 0.1 s) ends every
  # monitor episode before the 1 s hold: the monitor counts what `hifar eval` counts.
  table = _stage(scenarios={"stand": 1.0})
  table["sim"]["episode_s"] = 2.0
  table["termination"] = {"low_height": 0.9, "low_height_s": 0.1}
  nets, params, normalizer = _zero_output_policy(table)
  monitor = monitor_lib.make_monitor(
      config.MonitorConfig(every=1, episodes=2, scenarios=("stand",)), table, nets, "native",
      jax.random.PRNGKey(4))
  out = monitor(params, normalizer)
  assert out["stand_rate"] == {"stand": 0.0} and out["terminated"] == {"stand": 1.0}
