"""The reference get-up paths (jax_env.getup_paths) and the `supine_path` start scenario: the
stored path is a real get-up in C MuJoCo, the search that finds it is deterministic, the file
round-trips, and the environment starts episodes on the path's rise with its velocities."""

import json
import math

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from jax_env import getup_paths, robot
from jax_env.env import FallRecoveryEnv
from jax_env.names import SCENARIOS
from jax_env.scenarios import PATH_SCENARIOS

from test_getup_task import _stage


@pytest.fixture(scope="module")
def supine():
  return getup_paths.load()["supine"]


def _trunk_gravity(model, qpos):
  data = mujoco.MjData(model)
  data.qpos[:] = qpos
  mujoco.mj_kinematics(model, data)
  return data.xmat[model.body("Trunk").id].reshape(3, 3).T @ np.array([0.0, 0.0, -1.0])


def test_the_stored_supine_path_rocks_back_and_stands_up(supine):
  model = robot.load_model()
  rise = supine.qpos[:supine.stand_index]
  # It starts lying on the back at rest: Trunk low, chest up (gravity along the Trunk's −x).
  assert rise[0, 2] < 0.2
  assert _trunk_gravity(model, rise[0])[0] < -0.9
  assert np.max(np.abs(supine.qvel[0])) < 0.5
  # On the way it rocks back head-down onto the shoulders (the step PPO rarely finds) ...
  assert max(_trunk_gravity(model, q)[2] for q in rise) > 0.5
  # ... and carries momentum: these are not static key states.
  assert np.max(np.abs(supine.qvel[:supine.stand_index])) > 5.0
  # From the stand index on the robot stands: Trunk at the stand height, upright, held 1 s.
  hold = int(round(getup_paths.HOLD_S / getup_paths.CTRL_DT))
  stand = robot.keyframe(model, "stand")[0]
  for q in supine.qpos[supine.stand_index:supine.stand_index + hold]:
    assert abs(q[2] - stand[2]) <= 0.05
    g = _trunk_gravity(model, q)
    assert math.hypot(g[0], g[1]) <= 0.2


def test_the_stored_prone_path_rolls_onto_the_back_and_stands_up():
  model = robot.load_model()
  prone = getup_paths.load()["prone"]
  rise = prone.qpos[:prone.stand_index]
  assert rise[0, 2] < 0.2
  assert _trunk_gravity(model, rise[0])[0] > 0.9  # face down: gravity along the Trunk's +x
  assert min(_trunk_gravity(model, q)[0] for q in rise) < -0.9  # rolled onto the back
  hip_roll = [7 + robot.JOINT_NAMES.index(f"{side}_Hip_Roll") for side in ("Left", "Right")]
  assert np.max(np.abs(rise[:, hip_roll])) > 0.1  # a stage-2 motion: the hips roll
  assert prone.stand_index > 0


def test_the_stored_kneel_path_turns_onto_the_back_within_the_planar_limits_and_stands_up():
  model = robot.load_model()
  kneel = getup_paths.load()["kneel"]
  spec = getup_paths.PATHS["kneel"]
  rise = kneel.qpos[:kneel.stand_index]
  # It starts at ksi_prone_3: on the shins, hands down, leaning forward (gravity along +x).
  start = robot.keyframe(model, "ksi_prone_3")[0]
  assert np.max(np.abs(rise[0, 7:] - start[7:])) < 0.1
  assert _trunk_gravity(model, rise[0])[0] > 0.5
  gravity = np.array([_trunk_gravity(model, q) for q in rise])
  assert gravity[:, 0].min() < -0.9  # on the back on the way
  # Never where the planar stage ends an episode: on a side or head down.
  side_roll, upside_down = spec.within
  assert np.abs(gravity[:, 1]).max() <= side_roll and gravity[:, 2].max() <= upside_down
  # The planar stage's joints only: hip roll is held at the stand pose's 0 by its PD (impacts
  # knock it out for a moment).
  sagittal = {f"{side}_{j}" for side in ("Left", "Right") for j in getup_paths._SAGITTAL}
  assert set(spec.search.driven) <= sagittal and not spec.search.both_sides
  hip_roll = [7 + robot.JOINT_NAMES.index(f"{side}_Hip_Roll") for side in ("Left", "Right")]
  assert np.median(np.abs(rise[:, hip_roll])) < 0.05
  assert kneel.stand_index > 0


@pytest.mark.parametrize("name", tuple(getup_paths.PATHS))
def test_the_stored_knots_replay_the_stored_path(name):
  """Open-loop PD targets from the stored knots reproduce the stored states in C MuJoCo."""
  stored = getup_paths.load()[name]
  replay = getup_paths.replay(name, getup_paths.stored_knots())
  # Contact-rich motion amplifies rounding: compare the first half second tightly, and the
  # outcome (stands, at about the same time) over the whole motion.
  early = int(0.5 / getup_paths.CTRL_DT)
  assert np.allclose(replay.qpos[:early], stored.qpos[:early], atol=1e-6)
  assert replay.stand_index > 0
  assert abs(replay.stand_index - stored.stand_index) <= 5


def test_the_search_is_deterministic_for_a_seed():
  def run():
    return getup_paths.search("supine", seed=3, iterations=2, population=6, elites=2,
                              processes=1, log=lambda _: None)
  (knots_a, path_a), (knots_b, path_b) = run(), run()
  assert np.array_equal(knots_a, knots_b)
  assert np.array_equal(path_a.qpos, path_b.qpos)
  segment = getup_paths.PATHS["supine"].search
  assert knots_a.shape == (len(segment.knot_times), len(segment.driven))


def test_the_paths_file_round_trips_and_refuses_another_format(tmp_path, supine):
  out = tmp_path / "paths.safetensors"
  knots = getup_paths.stored_knots()["supine"]
  getup_paths.save({"supine": (knots, supine, {"seed": 0})}, out)
  loaded = getup_paths.load(out)["supine"]
  assert np.array_equal(loaded.qpos, supine.qpos) and np.array_equal(loaded.qvel, supine.qvel)
  assert loaded.stand_index == supine.stand_index
  knots_back, _, settings = getup_paths.stored(out)["supine"]
  assert np.allclose(knots_back, knots, atol=1e-6) and settings == {"seed": 0}

  from safetensors.numpy import save_file
  bad = tmp_path / "old.safetensors"
  save_file({"supine/qpos": supine.qpos}, str(bad), metadata={"format_version": "0"})
  with pytest.raises(ValueError, match="format_version 0 .*regenerate"):
    getup_paths.load(bad)


def _start_frames(env, path, state):
  """The rise frame each episode of `state` started on; asserts that it starts on one."""
  view = env.backend.view(state.physics)
  qpos, qvel = np.asarray(view.qpos), np.asarray(view.qvel)
  rise_q = path.qpos[:path.stand_index]
  rise_v = path.qvel[:path.stand_index]
  noise = 5 * env.stage.scenario_params.ksi_joint_noise
  frames = []
  for q, v in zip(qpos, qvel):
    # The joints are a rise frame's plus the key-state noise; the joint velocities, the Trunk-
    # frame angular velocity and the speed over the floor are that frame's exactly (the heading
    # is random, so the world-frame linear velocity is turned, not changed).
    joint_err = np.max(np.abs(rise_q[:, 7:] - q[7:]), axis=1)
    vel_err = np.max(np.abs(rise_v[:, 3:] - v[3:]), axis=1)
    i = int(np.argmin(vel_err))
    assert vel_err[i] < 1e-4 and joint_err[i] <= noise
    assert abs(np.hypot(*v[0:2]) - np.hypot(*rise_v[i, 0:2])) < 1e-4
    assert abs(v[2] - rise_v[i, 2]) < 1e-4
    frames.append(i)
  return frames


@pytest.mark.parametrize("scenario", tuple(PATH_SCENARIOS))
def test_path_scenarios_start_on_the_rise_with_its_velocities(scenario):
  path = getup_paths.load()[PATH_SCENARIOS[scenario]]
  env = FallRecoveryEnv(_stage(scenarios={scenario: 1.0}), backend="native")
  state = jax.jit(env.reset)(jax.random.split(jax.random.PRNGKey(7), 16))
  assert np.all(np.asarray(state.scenario) == SCENARIOS.index(scenario))
  assert np.all(np.asarray(state.control_active) == 1.0)  # acts from the first step
  frames = _start_frames(env, path, state)
  assert len(set(frames)) > 8  # drawn along the whole rise, not one state
  assert max(frames) > path.stand_index // 2
  assert np.max(np.abs(np.asarray(env.backend.view(state.physics).qvel))) > 1.0  # some move


def test_a_start_window_draws_a_paths_starts_from_its_first_seconds_only():
  """`path_start_window_s = { kneel_path = 0.3 }`: the kneel path's starts lie in its first
  0.3 s (15 stored frames at 50 Hz: the push-up before the roll), the supine path's on its
  whole rise."""
  d = _stage(scenarios={"kneel_path": 0.5, "supine_path": 0.5})
  d["scenario_params"]["path_start_window_s"] = {"kneel_path": 0.3}
  env = FallRecoveryEnv(d, backend="native")
  state = jax.jit(env.reset)(jax.random.split(jax.random.PRNGKey(7), 48))
  paths = getup_paths.load()
  for scenario, window in (("kneel_path", 15), ("supine_path", None)):
    on = np.asarray(state.scenario) == SCENARIOS.index(scenario)
    assert on.sum() > 12
    frames = _start_frames(env, paths[PATH_SCENARIOS[scenario]],
                           jax.tree_util.tree_map(lambda x: x[on], state))
    if window is None:
      assert max(frames) >= 15
    else:
      assert max(frames) < window and len(set(frames)) > 5


def test_path_scenarios_are_in_the_shared_vocabulary():
  names = json.loads((getup_paths.paths.REPO_ROOT / "jax_env" / "names.json").read_text())
  assert set(PATH_SCENARIOS) <= set(names["scenarios"])
