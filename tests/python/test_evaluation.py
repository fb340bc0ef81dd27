"""Evaluation protocols (jax_env/evaluation): the paper's values, the nominal setup, the
torso-frame scheduled push with the real physics (native C MuJoCo), per-cell conditions, and a
whole quick evaluation that gives the same eval.json for the same seed."""

import copy
import json
import math
import tomllib

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from jax_env import config as config_lib
from jax_env import features, names
from jax_env.env import FallRecoveryEnv
from jax_env.evaluation import conditions as cond_lib
from jax_env.evaluation import protocols, runner, stats
from jax_env.kinematics import rotate_inverse
from jax_env.learner import checkpoint as ckpt_lib
from jax_env.learner import networks as nets_lib
from jax_env.learner import ppo as ppo_lib
from jax_env.learner import train as train_lib
from jax_env.names import SCENARIOS, TERRAINS
from jax_env.paths import REPO_ROOT
from jax_env.stage_config import EPISODE_ENDS, TERMINATION_RULES


def _full_stage() -> dict:
  """The second stage of tests/data/tiny.toml (every joint group, 1 s episodes, DR, pushes,
  delay, slopes and obstacles in training)."""
  with open(REPO_ROOT / "tests" / "data" / "tiny.toml", "rb") as f:
    return tomllib.load(f)["stage"][1]


# ---------------------------------------------------------------------------------------------
# Protocol definitions and statistics (no physics).


def _cells(experiment, scenario=None):
  return [c for c in protocols.paper_cells()
          if c.experiment == experiment and (scenario is None or c.scenario == scenario)]


def test_paper_protocol_carries_the_papers_values():
  planar = _cells("planar_push")
  assert [c.value for c in planar if c.scenario == "prone"] == [50, 100, 150, 200, 250, 300]
  assert {c.condition.push_direction for c in planar if c.scenario == "prone"} == {"forward"}
  assert {c.condition.push_direction for c in planar if c.scenario == "supine"} == {"backward"}
  assert [c.paper_success_rate for c in _cells("planar_push", "prone")] == [1, 1, 1, 1, 0.8, 0]
  assert [c.paper_success_rate for c in _cells("planar_push", "supine")] == [1, 1, 1, 1, 1, 0.6]
  lateral = _cells("lateral_push")
  assert [c.value for c in lateral if c.scenario == "supine"] == [50, 100, 150, 200, 250]
  assert {c.condition.push_direction for c in lateral} == {"left"}
  assert [c.paper_success_rate for c in _cells("lateral_push", "prone")] == [1, 1, 1, 0.9, 0.1]
  assert [c.paper_success_rate for c in _cells("lateral_push", "supine")] == [1, 1, 1, 1, 0]
  for c in planar + lateral:
    assert c.condition.push_force == c.value
    assert (c.condition.push_start_s, c.condition.push_duration_s) == (0.8, 0.2)
  assert [c.condition.extra_torso_mass for c in _cells("load", "prone")] == [2.4, 5.9, 9.4, 11.7]
  assert [c.paper_success_rate for c in _cells("load", "supine")] == [1, 1, 1, 0]
  assert [c.condition.friction for c in _cells("friction", "prone")] == [0.8, 0.6, 0.4, 0.2, 0.1]
  assert [c.paper_success_rate for c in _cells("friction", "prone")] == [1, 1, 1, 0.9, 0]
  assert [c.paper_success_rate for c in _cells("friction", "supine")] == [1, 1, 1, 1, 0.9]
  assert [c.condition.torque_limit for c in _cells("torque_limit", "supine")] == [0.85, 0.75]
  assert [c.setting for c in _cells("torque_limit", "supine")] == ["85%", "75%"]
  assert [c.paper_success_rate for c in _cells("torque_limit", "supine")] == [1, 0.6]
  standard = _cells("standard")
  assert [c.scenario for c in standard] == ["prone", "supine"]
  for c in standard:
    assert c.condition == cond_lib.Condition(scenario=c.scenario)
    assert c.paper_success_rate == 1.0
  assert dict((c.scenario, c.paper_recovery_time) for c in standard) == {
      "supine": (2.711, 0.319), "prone": (2.875, 0.474)}
  assert [c.scenario for c in _cells("random_initial")] == [
      "lateral", "sitting", "crossed_legs", "random_drop"]
  assert {(c.scenario, c.condition.terrain) for c in _cells("terrain")} == {
      (s, t) for s in ("prone", "supine") for t in ("slope", "obstacle")}
  # Everything else stays at the standard setup.
  for c in protocols.paper_cells():
    d = c.condition
    changed = {k for k, v in d.to_dict().items()
               if v != cond_lib.Condition(scenario=d.scenario).to_dict()[k]}
    assert changed <= {"planar_push": {"push_force", "push_direction"},
                       "lateral_push": {"push_force", "push_direction"},
                       "load": {"extra_torso_mass"}, "friction": {"friction"},
                       "torque_limit": {"torque_limit"}, "terrain": {"terrain"}}.get(
                           c.experiment, set()), c.label
  labels = [c.label for c in protocols.paper_cells()]
  assert len(labels) == len(set(labels)) == 2 + 12 + 10 + 8 + 10 + 4 + 4 + 4


def test_quick_protocol_is_a_subset_covering_every_experiment():
  paper = {c.label: c for c in protocols.cells("paper")}
  quick = protocols.cells("quick")
  assert all(paper[c.label] == c for c in quick)
  assert {c.experiment for c in quick} == set(protocols.EXPERIMENTS) - {"keystate"}
  assert protocols.DEFAULT_TRIALS == {"paper": 100, "quick": 8, "keystate": 8}
  with pytest.raises(ValueError, match="unknown protocol 'full'; valid: paper, quick, keystate"):
    protocols.cells("full")


def test_keystate_protocol_has_one_nominal_cell_per_start_state():
  cells = protocols.cells("keystate")
  assert [c.scenario for c in cells] == [
      "stand", "ksi_prone_1", "ksi_prone_2", "ksi_prone_3", "ksi_supine_1", "ksi_supine_2",
      "ksi_supine_3", "supine", "prone"]
  for c in cells:
    assert c.experiment == "keystate" and c.setting == c.scenario and c.value is None
    assert c.condition == cond_lib.Condition(scenario=c.scenario)  # the standard setup
    assert c.paper_success_rate is None and c.paper_recovery_time is None
    assert c.label == f"keystate/{c.scenario}/{c.scenario}"
  assert all(c.scenario in SCENARIOS for c in cells)


def test_conditions_reject_bad_values():
  with pytest.raises(ValueError, match="unknown scenario 'sideways'"):
    cond_lib.Condition(scenario="sideways")
  with pytest.raises(ValueError, match="unknown push direction 'up'; valid: forward, backward"):
    cond_lib.Condition(push_direction="up")
  with pytest.raises(ValueError, match="friction -0.1"):
    cond_lib.Condition(friction=-0.1)


def test_wilson_interval_matches_known_values():
  # Reference values of the 95 % Wilson score interval (z = 1.96), e.g. Newcombe (1998),
  # Table I, and R's binom::binom.wilson.
  known = {(8, 10): (0.4902, 0.9433), (0, 10): (0.0, 0.2775), (10, 10): (0.7225, 1.0),
           (1, 10): (0.0179, 0.4042), (50, 100): (0.4038, 0.5962),
           (81, 263): (0.2553, 0.3662), (15, 148): (0.0624, 0.1605), (0, 20): (0.0, 0.1611)}
  for (k, n), (low, high) in known.items():
    got = stats.wilson_interval(k, n)
    assert got == pytest.approx((low, high), abs=1e-4), (k, n, got)
  assert stats.wilson_interval(0, 8)[0] == 0.0 and stats.wilson_interval(8, 8)[1] == 1.0
  with pytest.raises(ValueError):
    stats.wilson_interval(3, 0)
  assert stats.mean_std([]) == (None, None)
  assert stats.mean_std([2.0]) == (2.0, 0.0)
  mean, std = stats.mean_std([1.0, 2.0, 3.0, 4.0])
  assert mean == 2.5 and std == pytest.approx(math.sqrt(5 / 3))


def test_evaluation_stage_is_nominal_and_keeps_the_features():
  stage = _full_stage()
  nominal = cond_lib.evaluation_stage(stage)
  assert stage["domain_randomization"]["enabled"]  # the input is not modified
  cfg = config_lib.StageConfig.from_dict(nominal)
  assert all(cfg.domain_randomization.active(p) is None for p in names.DR_PARAMS)
  assert not cfg.push.enabled and cfg.delay.max_s == 0.0
  assert cfg.terrain.weights == {"flat": 1.0, "slope": 0.0, "obstacle": 0.0}
  assert cfg.terrain.slope_max_deg == stage["terrain"]["slope_max_deg"]
  assert features.feature_names(nominal) == features.feature_names(stage)
  assert nominal["sim"] == stage["sim"] and nominal["action"] == stage["action"]
  assert nominal["constraints"] == stage["constraints"]
  flat = copy.deepcopy(stage)
  flat["terrain"] = {"flat": 1.0, "slope_max_deg": 0.0}
  assert (cond_lib.evaluation_stage(flat)["terrain"]["slope_max_deg"]
          == cond_lib.DEFAULT_SLOPE_MAX_DEG)


# ---------------------------------------------------------------------------------------------
# Conditions on the real environment (native C MuJoCo).


@pytest.fixture(scope="module")
def nominal_env():
  stage = _full_stage()
  stage["sim"]["episode_s"] = 2.0  # room for the push at 0.8–1.0 s and what follows
  env = FallRecoveryEnv(cond_lib.evaluation_stage(stage), backend="native")
  return env, jax.jit(env.step)


def test_conditions_set_parameters_schedule_and_terrain(nominal_env):
  env, _ = nominal_env
  conditions = [
      cond_lib.Condition(scenario="sitting", extra_torso_mass=5.9, friction=0.2,
                         torque_limit=0.75, push_force=100.0, push_direction="left"),
      cond_lib.Condition(scenario="supine"),
      cond_lib.Condition(scenario="prone", terrain="slope"),
      cond_lib.Condition(scenario="supine", terrain="obstacle", push_force=300.0,
                         push_direction="backward"),
  ]
  arrays = cond_lib.condition_arrays(env, conditions)
  keys = jax.random.split(jax.random.PRNGKey(3), len(conditions))
  s = jax.jit(lambda k, a: cond_lib.start_arrays(env, k, a))(keys, arrays)
  p = jax.tree_util.tree_map(np.asarray, s.draw.params)
  m = env.mj_model
  trunk, floor = env.trunk, env.randomizer.floor
  # Scenarios and terrains as asked.
  assert list(np.asarray(s.scenario)) == [SCENARIOS.index(c.scenario) for c in conditions]
  assert list(np.asarray(s.draw.terrain)) == [TERRAINS.index(c.terrain) for c in conditions]
  slope = np.asarray(s.draw.slope)
  assert np.all(slope[[0, 1, 3]] == 0)
  assert 0 < np.linalg.norm(slope[2]) <= math.radians(env.stage.terrain.slope_max_deg) + 1e-6
  assert list(np.asarray(s.draw.obstacle)) == [0, 0, 0, 1]
  # Mass, inertia (same density), floor friction, torque limits.
  assert p.body_mass[0, trunk] == pytest.approx(m.body_mass[trunk] + 5.9, rel=1e-6)
  assert m.body_mass[trunk] == pytest.approx(11.7)
  np.testing.assert_allclose(p.body_inertia[0, trunk],
                             m.body_inertia[trunk] * (11.7 + 5.9) / 11.7, rtol=1e-5)
  np.testing.assert_allclose(p.body_mass[1], m.body_mass, rtol=1e-6)
  assert p.geom_friction[0, floor, 0] == pytest.approx(0.2)
  np.testing.assert_allclose(p.geom_friction[1:, floor, 0], 1.0)
  np.testing.assert_allclose(p.actuator_forcerange[0], 0.75 * m.actuator_forcerange, rtol=1e-6)
  np.testing.assert_allclose(p.actuator_forcerange[1], m.actuator_forcerange, rtol=1e-6)
  # The push: 0.8 s after control starts (after settling for the sitting start), 200 ms.
  never = np.iinfo(np.int32).max
  start, end = np.asarray(s.push.scheduled_start), np.asarray(s.push.scheduled_end)
  control = np.asarray(s.control_start)
  assert control[0] == env.settle_steps > 0 and control[1] == 0
  assert start[0] == env.settle_steps + 40 and end[0] == start[0] + 10
  assert start[3] == 40 and end[3] == 50
  assert start[1] == start[2] == end[1] == end[2] == never
  np.testing.assert_allclose(np.asarray(s.push.local_force),
                             [[0, 100, 0], [0, 0, 0], [0, 0, 0], [-300, 0, 0]])


def test_reset_without_forcing_keeps_training_pushes_off(nominal_env):
  env, _ = nominal_env
  s = env.reset(jax.random.split(jax.random.PRNGKey(0), 2))
  never = np.iinfo(np.int32).max
  assert np.all(np.asarray(s.push.scheduled_start) == never)
  assert np.all(np.asarray(s.push.local_force) == 0)


def _momentum(model, data, qpos, qvel):
  """Total linear momentum of the robot (the subtree of the Trunk)."""
  data.qpos[:], data.qvel[:] = qpos, qvel
  mujoco.mj_forward(model, data)
  mujoco.mj_subtreeVel(model, data)
  trunk = model.body("Trunk").id
  return data.subtree_linvel[trunk] * model.body_subtreemass[trunk]


def test_scheduled_push_time_duration_magnitude_and_torso_direction(nominal_env):
  """A free-floating robot (no contact, gravity ~0), pushed 150 N forward and 250 N to its left:
  the push acts from exactly 0.8 s after control starts for 200 ms, along the torso axis
  rotated with the Trunk at every control step, and the robot's momentum changes by its
  impulse (the physics receives what the privileged features report)."""
  env, step = nominal_env
  m = env.mj_model
  conditions = [cond_lib.Condition(scenario="prone", push_force=150.0, push_direction="forward"),
                cond_lib.Condition(scenario="supine", push_force=250.0, push_direction="left")]
  batch = len(conditions)
  # Two orientations far from the world axes: the torso frame is not the world frame.
  qpos = np.tile(m.key_qpos[m.key("stand").id], (batch, 1)).astype(np.float32)
  qpos[:, 2] = 2.0
  quats = [(0.5, 0.5, 0.5, 0.5), (math.cos(0.4), 0.0, math.sin(0.4), 0.0)]
  qpos[:, 3:7] = np.asarray(quats, np.float32)
  qvel = np.zeros((batch, m.nv), np.float32)
  keys = jax.random.split(jax.random.PRNGKey(5), batch)
  state = env.reset_to(keys, jnp.asarray(qpos), jnp.asarray(qvel))
  state = cond_lib.apply(env, state, cond_lib.condition_arrays(env, conditions))
  tiny_gravity = jnp.broadcast_to(jnp.asarray([0.0, 0.0, -1e-6]), (batch, 3))
  state = state.replace(draw=state.draw.replace(
      params=state.draw.params.replace(gravity=tiny_gravity)))

  data = mujoco.MjData(m)
  view = env.backend.view(state.physics)
  p0 = [_momentum(m, data, np.asarray(view.qpos[b], np.float64),
                  np.asarray(view.qvel[b], np.float64)) for b in range(batch)]
  i = env.privileged_names.index("push_force/x")
  action = jnp.zeros((batch, env.action_size))
  impulse = np.zeros((batch, 3))
  magnitude_impulse = np.zeros(batch)
  pushed_steps = []
  for k in range(60):
    quat = np.asarray(env.backend.view(state.physics).qpos[:, 3:7])
    state = step(state, action)
    force = np.asarray(state.privileged[:, i:i + 3], np.float64)
    active = np.asarray(state.push_active)
    assert np.all(active == (np.linalg.norm(force, axis=-1) > 0)), k
    if active.any():
      assert active.all()
      pushed_steps.append(k)
      local = np.asarray(rotate_inverse(jnp.asarray(quat), jnp.asarray(force, jnp.float32)))
      np.testing.assert_allclose(local, [[150, 0, 0], [0, 250, 0]], atol=1e-3)
    impulse += force * env.ctrl_dt
    magnitude_impulse += np.linalg.norm(force, axis=-1) * env.ctrl_dt
    assert float(np.asarray(state.done).max()) == 0.0, k
  # 0.8 s after the control start (step 40 of 20 ms steps), for 200 ms (10 steps).
  assert pushed_steps == list(range(40, 50))
  assert env.ctrl_dt * pushed_steps[0] == pytest.approx(0.8)
  view = env.backend.view(state.physics)
  for b, magnitude in enumerate((150.0, 250.0)):
    # The force follows the torso as the body turns, so only its magnitude adds up exactly.
    assert magnitude_impulse[b] == pytest.approx(magnitude * 0.2, rel=1e-5)
    assert np.linalg.norm(impulse[b]) == pytest.approx(magnitude * 0.2, rel=1e-2)
    p1 = _momentum(m, data, np.asarray(view.qpos[b], np.float64),
                   np.asarray(view.qvel[b], np.float64))
    # Within 1 % of the impulse: the body spins under the push, and momentum evaluated at
    # discrete configurations drifts by the integrator's O(timestep) error.
    np.testing.assert_allclose(p1 - p0[b], impulse[b], atol=1e-2 * magnitude * 0.2)


# ---------------------------------------------------------------------------------------------
# A whole evaluation.


@pytest.fixture(scope="module")
def fresh_checkpoint(tmp_path_factory):
  """An untrained checkpoint of the tiny full stage (fresh weights, saved as the learner does)."""
  stage = _full_stage()
  cfg = config_lib.StageConfig.from_dict(stage)
  env = FallRecoveryEnv(cfg, backend="native")
  net_cfg = train_lib.LearnerConfig.from_stage(cfg).network_config(env)
  nets = nets_lib.Networks(net_cfg)
  key = jax.random.PRNGKey(0)
  state = jax.jit(lambda k: ppo_lib.init_learner_state(nets, nets.init(k), 1.0, 3e-4))(key)
  directory = tmp_path_factory.mktemp("ckpt") / "000000000000"
  ckpt_lib.save(directory, state=state, config=net_cfg, stage="full", env_steps=0,
                iteration=0, seed=0, key=key, obs_names=env.obs_names,
                privileged_names=env.privileged_names, action_names=env.action_names,
                action=stage["action"], extra={ckpt_lib.STAGE_CONFIG_KEY: stage,
                                               "learner": _learner_section(stage)})
  return directory


def _learner_section(stage, adaptation_env_steps=None):
  """checkpoint.json's "learner" block as the learner writes it at the end of a stage (its
  adaptation phase run: the deployable actor may be evaluated)."""
  budget = stage["rma"]["adaptation_env_steps"]
  steps = budget if adaptation_env_steps is None else adaptation_env_steps
  return {"iteration": 0, "ppo_env_steps": 0, "adaptation_env_steps": steps,
          "phase": "done" if steps >= budget else "adaptation", "finished_early": False,
          "num_envs": stage["ppo"]["num_envs"], "devices": 1, "initial_action_std": 1.0,
          "ppo_budget": 0, "adaptation_budget": budget}


def test_quick_evaluation_is_reproducible(fresh_checkpoint, tmp_path):
  # An untrained policy never stands up; a lenient "standing" detector (the Trunk within 0.5 m
  # of its standing height, any orientation and posture) makes the success rates depend on each
  # trial's draws, so reproducibility is tested on results that vary.
  stage = _full_stage()
  stage["success"].update(height_tolerance=0.5, upright_tolerance=2.0, dof_tolerance=10.0,
                          hold_s=0.1)
  request = {"checkpoint": str(fresh_checkpoint), "stage": stage, "protocol": "quick",
             "trials": 2, "backend": "native", "seed": 1, "batch_size": 8}
  progress = []

  def callback(p):
    json.dumps(p)
    progress.append(p)
    return "continue"

  first = runner.evaluate({**request, "out_dir": str(tmp_path / "a")}, callback)
  assert first["status"] == "completed"
  assert sorted(first["files"]) == sorted(str(tmp_path / "a" / f) for f in runner.FILES)
  # 9 cells × 2 trials in batches of 8 (the last one padded).
  assert [p["trials_done"] for p in progress] == [8, 16, 18]
  assert [p["cells_done"] for p in progress] == [4, 8, 9]
  assert {p["cells_total"] for p in progress} == {9}
  second = runner.evaluate({**request, "out_dir": str(tmp_path / "b")})
  a = (tmp_path / "a" / "eval.json").read_bytes()
  assert a == (tmp_path / "b" / "eval.json").read_bytes()
  assert first["markdown"] == second["markdown"]

  doc = json.loads(a)
  assert doc["format_version"] == 2 and doc["protocol"] == "quick"
  assert doc["backend"] == "native" and doc["seed"] == 1 and doc["trials"] == 2
  assert doc["stage"] == "full" and doc["env_steps"] == 0
  assert doc["conditions"]["friction"] == 1.0
  assert doc["conditions"]["torso_mass_kg"] == pytest.approx(11.7)
  cells = doc["cells"]
  assert [f"{c['experiment']}/{c['scenario']}/{c['setting']}" for c in cells] == [
      c.label for c in protocols.quick_cells()]
  successes = [c["successes"] for c in cells]
  assert 0 < sum(successes) < 2 * len(cells), successes  # results that vary
  for c in cells:
    assert c["trials"] == 2 and c["success_rate"] == c["successes"] / 2
    assert c["ci95"] == pytest.approx(list(stats.wilson_interval(c["successes"], 2)))
    if c["successes"]:
      assert c["recovery_time_mean"] >= 0 and c["recovery_time_std"] >= 0
    else:
      assert c["recovery_time_mean"] is None and c["recovery_time_std"] is None
  assert cells[0]["paper_success_rate"] == 1.0
  assert cells[0]["paper_recovery_time"] == [2.875, 0.474]
  rows = (tmp_path / "a" / "eval.csv").read_text().splitlines()
  assert rows[0].split(",") == list(runner.CSV_FIELDS) and len(rows) == 1 + len(cells)
  md = (tmp_path / "a" / "eval.md").read_text()
  assert md == first["markdown"]
  assert "## Planar push" in md and "| Prone | " in md and " · 80%" in md

  # An interrupt at the first batch returns at once and writes nothing.
  stopped = runner.evaluate({**request, "out_dir": str(tmp_path / "c")},
                            lambda p: "interrupt")
  assert stopped == {"status": "interrupted", "files": [], "markdown": ""}
  assert not (tmp_path / "c").exists()


def test_keystate_evaluation_reports_every_start_state(fresh_checkpoint, tmp_path):
  # Same stage, backend and batch as the quick evaluation above: the compiled rollout is reused.
  stage = _full_stage()
  stage["success"].update(height_tolerance=0.5, upright_tolerance=2.0, dof_tolerance=10.0,
                          hold_s=0.1)
  result = runner.evaluate({"checkpoint": str(fresh_checkpoint), "stage": stage,
                            "protocol": "keystate", "trials": 2, "backend": "native", "seed": 1,
                            "batch_size": 8, "out_dir": str(tmp_path / "k")})
  assert result["status"] == "completed"
  doc = json.loads((tmp_path / "k" / "eval.json").read_text())
  assert doc["protocol"] == "keystate" and doc["trials"] == 2 and doc["actor"] == "deployable"
  cells = doc["cells"]
  assert [c["scenario"] for c in cells] == list(protocols.KEYSTATE_CELLS)
  for c in cells:
    assert c["experiment"] == "keystate" and c["setting"] == c["scenario"]
    assert c["trials"] == 2 and c["success_rate"] == c["successes"] / 2
    assert c["ci95"] == pytest.approx(list(stats.wilson_interval(c["successes"], 2)))
    assert c["paper_success_rate"] is None and c["paper_recovery_time"] is None
    assert c["condition"] == cond_lib.Condition(scenario=c["scenario"]).to_dict()
    # Every failed trial counted once by how it ended; this stage has no termination rules.
    assert set(c["failures"]) == set(runner.TRIAL_ENDS) == {"time_limit", "blow_up"}
    assert c["failures"]["time_limit"] == c["trials"] - c["successes"]
    assert sum(c["failures"].values()) == c["trials"] - c["successes"]
    assert c["within_rules"]["successes"] == c["successes"]
    assert set(c["within_rules"]["rule_met"]) == set(TERMINATION_RULES)
    assert not any(c["within_rules"]["rule_met"].values())
  md = result["markdown"]
  assert "## Start states of the key-state curriculum (nominal conditions)" in md
  assert ("| Start state | Success rate | 95 % Wilson interval | Successes | Recovery time (s) | "
          "Failed trials ended | Successes within the stage's rules |") in md
  assert "| `stand` | " in md and "| `ksi_supine_3` | " in md and "| `prone` | " in md
  assert "the paper's (Webots" not in md  # no paper numbers in this protocol
  rows = (tmp_path / "k" / "eval.csv").read_text().splitlines()
  assert len(rows) == 1 + 9 and rows[1].startswith("keystate,stand,stand,,2,")
  failed = [c["trials"] - c["successes"] for c in cells]
  assert [int(r.split(",")[runner.CSV_FIELDS.index("failed_time_limit")]) for r in rows[1:]] \
      == failed
  lying = cells[protocols.KEYSTATE_CELLS.index("supine")]
  assert lying["successes"] == 0  # an untrained policy does not get up from lying
  assert "| `supine` | 0% | " in md and "| 2 at the time limit |" in md


def test_a_cell_reports_its_successes_within_the_stage_rules():
  # Four trials run to the time limit (rules never end an evaluation trial): two stood up, one
  # of them after the face-down rule held for a moment (a roll out of the kneel); one never got
  # up after lying low too long; one got up with no rule met.
  i = EPISODE_ENDS.index
  cell = protocols.cells("keystate")[0]
  c = runner._cell_result(
      cell, success=np.array([1.0, 1.0, 0.0, 0.0]), recovery=np.array([1.5, 2.0, np.nan, np.nan]),
      end=np.full(4, i("time_limit")),
      rule_met=np.array([0, i("upside_down_face_down"), i("low_height"), 0]))
  assert c["successes"] == 2 and c["failures"] == {"time_limit": 2, "blow_up": 0}
  assert c["within_rules"] == {
      "successes": 1, "success_rate": 0.25,
      "rule_met": {"low_height": 1, "upside_down": 0, "upside_down_face_down": 1,
                   "side_roll": 0}}
  assert runner._within_rules(c) == "1/4 (1 low height, 1 upside down face down)"
  row = runner.render_csv([c]).splitlines()[1].split(",")
  assert row[runner.CSV_FIELDS.index("within_rules_successes")] == "1"
  assert row[runner.CSV_FIELDS.index("rule_met_upside_down_face_down")] == "1"


def test_failed_trials_are_described_by_how_they_ended():
  counts = dict.fromkeys(EPISODE_ENDS, 0)
  assert runner._failures(counts) == "—"
  counts.update(time_limit=2, upside_down_face_down=6, blow_up=1)
  assert runner._failures(counts) == (
      "2 at the time limit, 6 upside down face down, 1 numerical blow-up")


def test_an_untrained_adaptation_module_is_refused(fresh_checkpoint, tmp_path):
  """act, eval (and rollout, which loads the policy the same way) and export share one rule."""
  from jax_env import export as export_lib
  from jax_env import facade
  from jax_env.evaluation import policy as policy_lib

  stage = _full_stage()
  meta = json.loads((fresh_checkpoint / ckpt_lib.META_FILE).read_text())
  assert meta["network"]["rma"] is True
  untrained = tmp_path / "untrained"
  without = tmp_path / "without_learner"
  for d, learner in ((untrained, _learner_section(stage, 0)), (without, None)):
    d.mkdir()
    for f in (ckpt_lib.META_FILE, ckpt_lib.PARAMS_FILE):
      (d / f).write_bytes((fresh_checkpoint / f).read_bytes())
    m = {k: v for k, v in meta.items() if k != "learner"}
    if learner is not None:
      m["learner"] = learner
    (d / ckpt_lib.META_FILE).write_text(json.dumps(m))
  for d in (untrained, without):
    message = (f"{d}: its RMA adaptation module was never trained (stage full ended before its "
               "adaptation phase); train with rma.adaptation_env_steps > 0 or evaluate a later "
               "checkpoint")
    for call in (lambda: facade.act({"checkpoint": str(d),
                                      "obs": [[0.0] * len(meta["obs_names"])]}),
                 lambda: policy_lib.load(d),
                 lambda: runner.evaluate({"checkpoint": str(d), "protocol": "keystate",
                                          "backend": "native", "out_dir": str(tmp_path / "o")}),
                 lambda: facade.export_onnx({"checkpoint": str(d),
                                             "out": str(tmp_path / "x.onnx")})):
      with pytest.raises(ckpt_lib.CheckpointError) as e:
        call()
      assert str(e.value) == message and "\n" not in str(e.value)
    with pytest.raises(ckpt_lib.CheckpointError, match="was never trained"):
      export_lib.actor_spec(d)
  assert not (tmp_path / "o").exists() and not (tmp_path / "x.onnx").exists()
  # Without RMA there is no adaptation module to train: nothing to refuse.
  policy_lib.check_adaptation_trained({"network": {"rma": False}, "stage": "planar"}, untrained)
  policy_lib.check_adaptation_trained(meta, fresh_checkpoint)
  # A stage that trains the module beside PPO (ROA): its PPO checkpoints are deployable once
  # PPO has run, as Rust's checkpoint::check_deployable rules.
  def ppo_checkpoint(weight, ppo_env_steps):
    return {"network": {"rma": True}, "stage": "full",
            "learner": {"phase": "ppo", "ppo_env_steps": ppo_env_steps, "adaptation_env_steps": 0},
            ckpt_lib.STAGE_CONFIG_KEY: {"rma": {"latent_regularization": weight}}}
  policy_lib.check_adaptation_trained(ppo_checkpoint(0.5, 4096), untrained)
  for weight, steps in ((0.5, 0), (0.0, 4096)):
    with pytest.raises(ckpt_lib.CheckpointError, match="was never trained"):
      policy_lib.check_adaptation_trained(ppo_checkpoint(weight, steps), untrained)


def test_the_privileged_actor_acts_without_the_adaptation_module(fresh_checkpoint, tmp_path):
  """`actor = "privileged"` acts with the encoder's latent of the simulator's state (the actor the
  monitor measures), so a checkpoint of a stage's PPO phase can be evaluated; eval.json and
  eval.md say which actor acted."""
  from jax_env.evaluation import policy as policy_lib

  stage = _full_stage()
  untrained = tmp_path / "untrained"
  untrained.mkdir()
  for f in (ckpt_lib.META_FILE, ckpt_lib.PARAMS_FILE):
    (untrained / f).write_bytes((fresh_checkpoint / f).read_bytes())
  meta = json.loads((untrained / ckpt_lib.META_FILE).read_text())
  meta["learner"] = _learner_section(stage, 0)
  (untrained / ckpt_lib.META_FILE).write_text(json.dumps(meta))

  # One control step of each actor is env.step with that actor's mean action.
  policy = policy_lib.load(untrained, policy_lib.PRIVILEGED)
  env = FallRecoveryEnv(config_lib.StageConfig.from_dict(stage), backend="native")
  state = env.reset(jax.random.split(jax.random.PRNGKey(3), 2))
  history = policy.initial_history(2)
  for actor, action in (
      (policy_lib.PRIVILEGED, nets_lib.privileged_mean(policy.nets, policy.params,
                                                       policy.normalizer, state.obs,
                                                       state.privileged)),
      (policy_lib.DEPLOYABLE, policy.act(state.obs, history))):
    stepped, _ = policy_lib.episode_step(policy, env, actor)((state, history))
    np.testing.assert_array_equal(stepped.obs, env.step(state, action).obs)

  request = {"checkpoint": str(untrained), "stage": stage, "protocol": "keystate", "trials": 1,
             "backend": "native", "batch_size": 8}
  result = runner.evaluate({**request, "actor": "privileged", "out_dir": str(tmp_path / "p")})
  assert result["status"] == "completed"
  doc = json.loads((tmp_path / "p" / "eval.json").read_text())
  assert doc["actor"] == "privileged" and len(doc["cells"]) == len(protocols.KEYSTATE_CELLS)
  assert "the privileged actor (the base policy with the encoder's latent" in result["markdown"]
  # The deployable actor (the default) is still refused on this checkpoint.
  with pytest.raises(ckpt_lib.CheckpointError, match="was never trained"):
    runner.evaluate({**request, "out_dir": str(tmp_path / "d")})
  with pytest.raises(ValueError, match="unknown actor 'teacher'; valid: deployable, privileged"):
    runner.evaluate({**request, "actor": "teacher", "out_dir": str(tmp_path / "t")})
  assert not (tmp_path / "d").exists() and not (tmp_path / "t").exists()


def test_evaluate_rejects_bad_requests(tmp_path):
  base = {"checkpoint": str(tmp_path), "protocol": "quick", "backend": "native",
          "out_dir": str(tmp_path / "out")}
  with pytest.raises(ValueError, match="unknown request key"):
    runner.evaluate({**base, "bogus": 1})
  with pytest.raises(ValueError, match="unknown protocol 'full'; valid: paper, quick, keystate"):
    runner.evaluate({**base, "protocol": "full"})
  with pytest.raises(ValueError, match="unknown backend 'gpu'"):
    runner.evaluate({**base, "backend": "gpu"})
  with pytest.raises(ValueError, match="trials 0 must be >= 1"):
    runner.evaluate({**base, "trials": 0})
