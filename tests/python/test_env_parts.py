"""Scenarios, kinematics, randomization, pushes, delays, rewards and the success detector.

Each element of the environment is tested on its own here, against C MuJoCo where physics is
involved (fast to run); the full jitted environment is tested in test_env_env.py.
"""

import copy
import dataclasses
import itertools
import math
import types

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from jax_env import config, kinematics, names, rewards, robot
from jax_env.config import StageConfig
from jax_env.defaults import default_stage_dict
from jax_env.names import SCENARIOS
from jax_env.randomization import (OBSTACLE_PARK, Pusher, Randomizer,
                                   constrained_model, delayed_ctrl, dampratio_to_restitution,
                                   restitution_to_dampratio, slope_gravity,
                                   velocity_limited_target)
from jax_env.scenarios import PATH_SCENARIOS, REST_CLEARANCE, SETTLING_SCENARIOS, ScenarioSampler

B_PER_SCENARIO = 3


@pytest.fixture(scope="module")
def full_stage():
  return StageConfig.from_dict(default_stage_dict("full"))


@pytest.fixture(scope="module")
def model(full_stage):
  return constrained_model(full_stage)


@pytest.fixture(scope="module")
def randomizer(full_stage, model):
  return Randomizer(full_stage, model)


@pytest.fixture(scope="module")
def draw_fn(randomizer):
  """Per-env draws from per-env keys, as the environment makes them."""
  return jax.jit(jax.vmap(lambda k: jax.tree_util.tree_map(lambda x: x[0],
                                                           randomizer.draw(k, 1))))


@pytest.fixture(scope="module")
def sampler(full_stage, model, randomizer):
  return ScenarioSampler(full_stage, model, randomizer)


@pytest.fixture(scope="module")
def initial(sampler, draw_fn):
  """B_PER_SCENARIO initial states of every scenario, with the full stage's DR."""
  n = len(SCENARIOS) * B_PER_SCENARIO
  keys = jax.random.split(jax.random.PRNGKey(0), n)
  draw = draw_fn(keys)
  scenario = jnp.repeat(jnp.arange(len(SCENARIOS), dtype=jnp.int32), B_PER_SCENARIO)
  init = jax.jit(sampler.sample)(jax.random.split(jax.random.PRNGKey(1), n), draw, scenario)
  return jax.tree_util.tree_map(np.asarray, init), jax.tree_util.tree_map(np.asarray, draw)


def _apply_params(m, params, i):
  m = copy.deepcopy(m)
  p = jax.tree_util.tree_map(lambda x: np.asarray(x[i], np.float64), params)
  m.geom_friction[:] = p.geom_friction
  m.geom_solref[:] = p.geom_solref
  m.body_mass[:] = p.body_mass
  m.body_ipos[:] = p.body_ipos
  m.body_inertia[:] = p.body_inertia
  m.actuator_gainprm[:, 0] = p.actuator_kp
  m.actuator_biasprm[:, 1] = -p.actuator_kp
  m.actuator_biasprm[:, 2] = -p.actuator_kd
  m.actuator_forcerange[:] = p.actuator_forcerange
  m.opt.gravity[:] = p.gravity
  return m


# ---------------------------------------------------------------------------------------------
# Kinematics.


def test_kinematics_match_mujoco(model):
  kin = kinematics.Kinematics(model)
  fk = jax.jit(lambda q: (kin.bodies(q), kin.lowest_point(q)))
  data = mujoco.MjData(model)
  rng = np.random.default_rng(0)
  for _ in range(3):
    q = np.zeros(model.nq)
    q[:3] = rng.normal(size=3)
    quat = rng.normal(size=4)
    q[3:7] = quat / np.linalg.norm(quat)
    q[7:] = rng.uniform(model.jnt_range[1:, 0], model.jnt_range[1:, 1])
    data.qpos[:] = q
    mujoco.mj_kinematics(model, data)
    (pos, quat_fk), low = fk(jnp.asarray(q, jnp.float32))
    ids = kin.body_ids
    np.testing.assert_allclose(np.asarray(pos)[ids], data.xpos[ids], atol=1e-5)
    dots = np.abs(np.sum(np.asarray(quat_fk)[ids] * data.xquat[ids], -1))
    np.testing.assert_allclose(dots, 1.0, atol=1e-5)
    # Brute-force lowest point over sphere, capsule end caps and box corners.
    lows = []
    for g in kin.geom_ids:
      c, r, s = data.geom_xpos[g], data.geom_xmat[g].reshape(3, 3), model.geom_size[g]
      if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_SPHERE:
        lows.append(c[2] - s[0])
      elif model.geom_type[g] == mujoco.mjtGeom.mjGEOM_CAPSULE:
        lows.append(min(c[2] + r[2, 2] * s[1], c[2] - r[2, 2] * s[1]) - s[0])
      else:
        lows.append(min((c + r @ (np.array(sg) * s))[2]
                        for sg in itertools.product([-1, 1], repeat=3)))
    assert float(low) == pytest.approx(min(lows), abs=1e-5)


# ---------------------------------------------------------------------------------------------
# Scenarios.


def test_every_scenario_reset_is_valid(initial, model, full_stage):
  init, draw = initial
  data = mujoco.MjData(model)
  floor = model.geom("floor").id
  kin = kinematics.Kinematics(model)
  low = jax.jit(jax.vmap(kin.lowest_point))(jnp.asarray(init.qpos))
  jnt = np.array([model.joint(j).id for j in robot.JOINT_NAMES])
  lo, hi = model.jnt_range[jnt, 0], model.jnt_range[jnt, 1]
  for i in range(init.qpos.shape[0]):
    name = SCENARIOS[init.scenario[i]]
    assert init.scenario[i] == i // B_PER_SCENARIO
    q = init.qpos[i]
    assert np.all(np.isfinite(q)) and np.all(np.isfinite(init.qvel[i]))
    assert np.linalg.norm(q[3:7]) == pytest.approx(1.0, abs=1e-5)
    assert np.all(q[7:] >= lo - 1e-5) and np.all(q[7:] <= hi + 1e-5), name
    assert bool(init.settles[i]) == (name in SETTLING_SCENARIOS)
    # The lowest point sits just above the floor (drops: up to 0.3 m above it; a state on a
    # get-up path where the path had it, never lower: the swing of the supine path leaves the
    # floor for a moment).
    if name == "random_drop":
      assert 0.05 - 1e-4 <= low[i] <= 0.3 + 1e-4
    elif name in PATH_SCENARIOS:
      assert REST_CLEARANCE - 1e-4 <= low[i] <= 0.3, name
    else:
      assert low[i] == pytest.approx(REST_CLEARANCE, abs=1e-4), name
    # No robot geom touches the floor at the start.
    data.qpos[:] = q
    data.mocap_pos[:] = init.mocap_pos[i]
    mujoco.mj_forward(model, data)
    for c in data.contact[:data.ncon]:
      assert floor not in (c.geom1, c.geom2), name
    # The obstacle is parked away unless the terrain is `obstacle`.
    if draw.obstacle[i] > 0:
      assert init.mocap_pos[i, 0, 2] == pytest.approx(0.101, abs=1e-3)
    else:
      np.testing.assert_allclose(init.mocap_pos[i, 0], OBSTACLE_PARK)


def test_key_state_resets_are_the_keyframes_with_noise(full_stage, model, randomizer):
  d = default_stage_dict("full")
  d["scenario_params"]["ksi_joint_noise"] = 0.0
  d["domain_randomization"] = {"enabled": False}
  d["terrain"] = {"flat": 1.0, "slope_max_deg": 0.0}  # no obstacle: legs not spread
  stage = StageConfig.from_dict(d)
  rnd = Randomizer(stage, model)
  sampler = ScenarioSampler(stage, model, rnd)
  keys = jax.random.split(jax.random.PRNGKey(3), 6)
  draw = jax.tree_util.tree_map(lambda x: x[:, 0], jax.vmap(lambda k: rnd.draw(k, 1))(keys))
  init = jax.jit(sampler.sample)(keys, draw, jnp.arange(6, dtype=jnp.int32))
  for i, name in enumerate(names.KSI_SCENARIOS):
    key_qpos, _ = robot.keyframe(model, name)
    np.testing.assert_allclose(np.asarray(init.qpos[i, 7:]), key_qpos[7:], atol=1e-5)
    # Same tilt as the keyframe (only the heading is random).
    r_key = np.asarray(kinematics.quat_to_mat(jnp.asarray(key_qpos[3:7])))
    r_new = np.asarray(kinematics.quat_to_mat(init.qpos[i, 3:7]))
    np.testing.assert_allclose(r_new[2], r_key[2], atol=1e-4)
  # And with noise, the joints move by about the configured std.
  init2 = jax.jit(ScenarioSampler(full_stage, model, rnd).sample)(
      jax.random.split(jax.random.PRNGKey(4), 64), jax.tree_util.tree_map(
          lambda x: jnp.repeat(x[:1], 64, 0), draw), jnp.zeros(64, jnp.int32))
  key_qpos, _ = robot.keyframe(model, "ksi_prone_1")
  std = np.std(np.asarray(init2.qpos[:, 7:]) - key_qpos[7:])
  assert 0.03 < std < 0.07


def test_fresh_draws_differ_between_episodes(sampler, draw_fn):
  keys_a = jax.random.split(jax.random.PRNGKey(10), 8)
  keys_b = jax.random.split(jax.random.PRNGKey(11), 8)
  sample = jax.jit(sampler.sample)
  a = sample(keys_a, draw_fn(keys_a))
  b = sample(keys_b, draw_fn(keys_b))
  assert not np.allclose(np.asarray(a.qpos), np.asarray(b.qpos))
  assert len(set(np.asarray(a.scenario).tolist())) > 1  # a mixture, not one cached state


# ---------------------------------------------------------------------------------------------
# Domain randomization.

def test_every_dr_parameter_changes_the_model_and_stays_in_range(randomizer, draw_fn, model):
  n = 256
  d = jax.tree_util.tree_map(np.asarray, draw_fn(jax.random.split(jax.random.PRNGKey(5), n)))
  p = d.params
  floor = model.geom("floor").id
  trunk = model.body("Trunk").id
  ids = robot.body_ids(model)
  others = ids[ids != trunk]
  dr = randomizer.dr.params

  def in_range(x, name):
    lo, hi = dr[name].range
    assert x.min() >= lo - 1e-6 and x.max() <= hi + 1e-6, name
    assert x.std() > 0.1 * (hi - lo) / math.sqrt(12), name  # it varies

  # Terrain: friction, compliance (spring), restitution (damper) of the floor.
  in_range(p.geom_friction[:, floor, 0], "terrain_friction")
  in_range(d.compliance, "terrain_compliance")
  in_range(d.restitution, "terrain_restitution")
  k = -p.geom_solref[:, floor, 0]
  b = -p.geom_solref[:, floor, 1]
  tau0 = model.geom_solref[floor, 0]
  np.testing.assert_allclose(k, 1 / np.maximum(tau0 * d.compliance, 2 * model.opt.timestep) ** 2,
                             rtol=1e-4)
  np.testing.assert_allclose(b, 2 * restitution_to_dampratio(d.restitution) * np.sqrt(k),
                             rtol=1e-4)
  # Other geoms keep their contact parameters.
  np.testing.assert_allclose(np.delete(p.geom_friction, floor, 1),
                             np.broadcast_to(np.delete(model.geom_friction, floor, 0),
                                             (n, model.ngeom - 1, 3)), rtol=1e-6)
  # Masses (and inertia with them) and CoMs.
  in_range(p.body_mass[:, trunk] / model.body_mass[trunk], "torso_mass")
  in_range(p.body_mass[:, others] / model.body_mass[others], "other_mass")
  np.testing.assert_allclose(p.body_inertia[:, ids] / model.body_inertia[ids],
                             np.repeat(d.mass_scale[..., None], 3, -1), rtol=1e-4)
  in_range(p.body_ipos[:, trunk] - model.body_ipos[trunk], "torso_com")
  in_range(p.body_ipos[:, others] - model.body_ipos[others], "other_com")
  np.testing.assert_allclose(d.com_offset, p.body_ipos[:, ids] - model.body_ipos[ids],
                             atol=1e-6)
  # PD gains.
  in_range(p.actuator_kp / model.actuator_gainprm[:, 0], "joint_stiffness")
  in_range(p.actuator_kd / -model.actuator_biasprm[:, 2], "joint_damping")
  np.testing.assert_allclose(d.kp_scale, p.actuator_kp / model.actuator_gainprm[:, 0],
                             rtol=1e-5)
  # Initial-state draws: gaussian (mean, std) and uniform.
  assert abs(d.dof_position.mean()) < 0.01 and d.dof_position.std() == pytest.approx(0.05,
                                                                                     rel=0.1)
  in_range(d.base_xy, "base_xy_position")
  assert d.base_lin_vel.std() == pytest.approx(0.1, rel=0.15)
  # Delay: whole timesteps in [0, max].
  assert set(np.unique(d.delay_substeps)) == set(range(randomizer.max_delay_substeps + 1))
  np.testing.assert_allclose(d.delay_s, d.delay_substeps * model.opt.timestep, rtol=1e-6)
  assert d.delay_s.max() <= 0.02 + 1e-9
  # Terrain: slopes up to slope_max_deg by tilting gravity, obstacles flagged.
  tilt = np.arccos(-p.gravity[:, 2] / np.linalg.norm(p.gravity, axis=-1))
  assert tilt.max() <= math.radians(10.0) + 1e-4 and tilt.max() > math.radians(5.0)
  slope_envs = d.terrain == names.TERRAINS.index("slope")
  assert np.all(tilt[~slope_envs] < 1e-6) and np.all(d.slope[~slope_envs] == 0)
  assert 0.2 < slope_envs.mean() < 0.4 and 0.03 < d.obstacle.mean() < 0.2
  np.testing.assert_allclose(np.linalg.norm(p.gravity, axis=-1), 9.81, rtol=1e-5)


def test_disabled_dr_gives_the_nominal_model(model):
  d = default_stage_dict("full")
  d["domain_randomization"]["enabled"] = False
  rnd = Randomizer(StageConfig.from_dict(d), model)
  draw = jax.tree_util.tree_map(np.asarray, rnd.draw(jax.random.PRNGKey(0), 4))
  np.testing.assert_allclose(draw.params.body_mass, np.broadcast_to(model.body_mass,
                                                                    (4, model.nbody)))
  np.testing.assert_allclose(draw.params.actuator_kp, np.broadcast_to(
      model.actuator_gainprm[:, 0], (4, model.nu)), rtol=1e-6)
  np.testing.assert_allclose(draw.kp_scale, 1.0)
  np.testing.assert_allclose(draw.mass_scale, 1.0)
  np.testing.assert_allclose(draw.com_offset, 0.0)
  floor = model.geom("floor").id
  # Nominal contact: the same spring-damper as the model's (timeconst, dampratio=1).
  tau0 = model.geom_solref[floor, 0]
  np.testing.assert_allclose(-draw.params.geom_solref[:, floor], [[1 / tau0 ** 2, 2 / tau0]] * 4,
                             rtol=1e-5)
  assert draw.restitution[0] == 0.0 and draw.compliance[0] == 1.0


def test_randomized_parameters_change_the_simulation(initial, model):
  """Two draws of the same initial state evolve differently in C MuJoCo."""
  init, draw = initial
  finals = []
  for i in (0, 1):
    m = _apply_params(model, draw.params, i)
    data = mujoco.MjData(m)
    data.qpos[:] = init.qpos[0]
    data.ctrl[:] = init.qpos[0, 7:]
    for _ in range(100):
      mujoco.mj_step(m, data)
    finals.append(data.qpos.copy())
  assert np.abs(finals[0] - finals[1]).max() > 1e-3


def test_restitution_mapping_bounces_as_specified():
  """A ball dropped on the floor with the mapped solref keeps about e of its speed."""
  xml = """<mujoco><option timestep="0.001"/><worldbody>
    <geom name="floor" type="plane" size="0 0 1" priority="1" solimp="0.9 0.95 0.001"/>
    <body pos="0 0 0.5"><freejoint/><geom type="sphere" size="0.05" mass="1"/></body>
    </worldbody></mujoco>"""
  for e in (0.1, 0.5, 0.9):
    m = mujoco.MjModel.from_xml_string(xml)
    tau = 0.02
    k = 1 / tau ** 2
    m.geom_solref[0] = [-k, -2 * float(restitution_to_dampratio(e)) * math.sqrt(k)]
    d = mujoco.MjData(m)
    v_in, v_out = None, 0.0
    for _ in range(2000):
      mujoco.mj_step(m, d)
      if d.ncon and v_in is None:
        v_in = -d.qvel[2]
      if v_in is not None and d.ncon == 0:
        v_out = d.qvel[2]
        break
    assert v_out / v_in == pytest.approx(e, abs=0.12), e
  assert float(dampratio_to_restitution(restitution_to_dampratio(0.3))) == pytest.approx(0.3)


def test_slope_gravity_points_downhill():
  g = np.asarray(slope_gravity(jnp.array([[0.1, 0.0], [0.0, -0.2], [0.0, 0.0]]), 9.81))
  np.testing.assert_allclose(np.linalg.norm(g, axis=-1), 9.81, rtol=1e-6)
  assert g[0, 0] < 0 and abs(g[0, 1]) < 1e-6  # ground rises along +x: gravity pulls to -x
  assert g[1, 1] > 0
  assert math.acos(-g[0, 2] / 9.81) == pytest.approx(0.1, rel=1e-4)
  np.testing.assert_allclose(g[2], [0, 0, -9.81])


def test_constraints_scale_ranges_and_torques():
  base = robot.load_model()
  d = default_stage_dict("planar")
  m = constrained_model(StageConfig.from_dict(d), base)
  jnt = np.array([base.joint(j).id for j in robot.JOINT_NAMES])
  lo, hi = base.jnt_range[jnt, 0], base.jnt_range[jnt, 1]
  mid, half = (lo + hi) / 2, (hi - lo) / 2
  np.testing.assert_allclose(m.jnt_range[jnt, 0], np.maximum(mid - 1.2 * half, -math.pi))
  np.testing.assert_allclose(m.jnt_range[jnt, 1], np.minimum(mid + 1.2 * half, math.pi))
  np.testing.assert_allclose(m.actuator_ctrlrange, m.jnt_range[jnt])
  np.testing.assert_allclose(m.actuator_forcerange, 1.5 * base.actuator_forcerange)
  assert base.jnt_range[jnt[3], 0] == lo[3]  # the source model is untouched


def test_velocity_limit_stops_driving_beyond_the_limit():
  kp, kd, vmax = jnp.array(200.0), jnp.array(5.0), jnp.array(10.0)
  q = jnp.zeros(4)
  qd = jnp.array([5.0, 12.0, -12.0, 12.0])
  target = jnp.array([1.0, 1.0, -1.0, -1.0])
  out = np.asarray(velocity_limited_target(target, q, qd, kp, kd, vmax))
  assert out[0] == 1.0  # below the limit: untouched
  tau = kp * (out - q) - kd * qd
  assert float(tau[1]) == pytest.approx(0.0, abs=1e-4)  # no more drive along +q̇
  assert float(tau[2]) == pytest.approx(0.0, abs=1e-4)  # nor along −q̇
  assert out[3] == -1.0  # braking is always allowed


# ---------------------------------------------------------------------------------------------
# Delay and pushes.


def test_delay_shifts_when_a_new_target_takes_effect():
  n_substeps, history = 4, 3  # up to 2 control periods of delay
  old, new = 1.0, 2.0
  hist = jnp.stack([jnp.full((1, 1), new), jnp.full((1, 1), old), jnp.full((1, 1), 0.0)], 1)
  for d in range(9):
    rows = np.asarray(delayed_ctrl(jnp.broadcast_to(hist, (1, history, 1)),
                                   jnp.array([d]), n_substeps))[0, :, 0]
    # The new target applies from substep d on; before it, the target it replaced.
    first_new = next((k for k, r in enumerate(rows) if r == new), n_substeps)
    assert first_new == min(d, n_substeps), d
    assert np.all(rows[:min(d, n_substeps)] == (old if d <= n_substeps else
                                                np.where(np.arange(n_substeps) < d - 4, 0.0,
                                                         old)[:min(d, n_substeps)]))


def test_push_schedule_force_and_duration():
  d = default_stage_dict("full")
  d["push"] = {"enabled": True, "interval_s": [0.5, 0.5], "duration_s": 0.1, "force_max": 80.0,
               "torque_max": 5.0}
  pusher = Pusher(StageConfig.from_dict(d))
  batch = 16
  keys = jax.random.split(jax.random.PRNGKey(0), batch)
  control_start = jnp.where(jnp.arange(batch) < 8, 0, 50).astype(jnp.int32)
  push = pusher.reset(keys, control_start)
  np.testing.assert_array_equal(push.next_step, control_start + 25)  # 0.5 s at 50 Hz
  update = jax.jit(pusher.update)
  active_log, forces = [], []
  for step in range(120):
    keys = jax.vmap(lambda k: jax.random.split(k)[0])(keys)
    push, active = update(keys, push, jnp.full((batch,), step, jnp.int32))
    active_log.append(np.asarray(active))
    forces.append(np.asarray(push.force))
  active_log = np.array(active_log)
  # Pushes of 5 control steps (0.1 s) every 25 steps, from the control start on.
  expected = np.zeros((120, batch), bool)
  for b in range(batch):
    for start in range(int(control_start[b]) + 25, 120, 25):
      expected[start:start + 5, b] = True
  np.testing.assert_array_equal(active_log, expected)
  f = np.array(forces)[active_log]
  assert np.all(np.abs(f[:, 2]) < 1e-6)  # horizontal
  assert np.linalg.norm(f, axis=-1).max() <= 80.0 + 1e-4
  assert np.linalg.norm(f, axis=-1).std() > 5.0


# ---------------------------------------------------------------------------------------------
# Rewards and success.


def _quantities(batch=2, **kw):
  nj, na = robot.NUM_JOINTS, 3
  base = dict(
      base_height=jnp.full((batch,), 0.67), waist_height=jnp.full((batch,), 0.55),
      gravity=jnp.tile(jnp.array([0.0, 0.0, -1.0]), (batch, 1)),
      q=jnp.zeros((batch, nj)), q_ref=jnp.zeros(nj), qd=jnp.zeros((batch, nj)),
      qdd=jnp.zeros((batch, nj)), root_acc=jnp.zeros((batch, 3)),
      torque=jnp.zeros((batch, nj)), torque_limit=jnp.full((batch, nj), 10.0),
      range_low=jnp.full(nj, -1.0), range_high=jnp.full(nj, 1.0),
      action=jnp.zeros((batch, na)), prev_action=jnp.zeros((batch, na)),
      prev_prev_action=jnp.zeros((batch, na)), hip_roll=jnp.zeros((batch, 2)),
      standing=jnp.zeros((batch,), bool), com=jnp.tile(jnp.array([0.0, 0.0, 0.58]), (batch, 1)),
      feet=jnp.tile(jnp.array([[0.0, 0.1, 0.03], [0.0, -0.1, 0.03]]), (batch, 1, 1)))
  base.update(kw)
  return rewards.Quantities(**base)


PARAMS = config.RewardParams(base_height_target=0.67, base_height_sigma=20.0, hip_roll_ref=0.1)


def test_reward_terms_on_constructed_states():
  nj = robot.NUM_JOINTS
  r = lambda fn, **kw: np.asarray(fn(_quantities(**kw), PARAMS))
  np.testing.assert_allclose(r(rewards.survival), [1, 1])
  np.testing.assert_allclose(r(rewards.base_height, base_height=jnp.array([0.67, 0.17])),
                             [1.0, math.exp(-20 * 0.25)], rtol=1e-5)
  np.testing.assert_allclose(r(rewards.standing, standing=jnp.array([True, False])), [1, 0])
  g = jnp.array([[0.0, 0.0, -1.0], [0.6, 0.0, -0.8]])
  np.testing.assert_allclose(r(rewards.orientation, gravity=g), [0, 0.36], atol=1e-6)
  q = jnp.zeros((2, nj)).at[1, 3].set(0.5).at[1, 5].set(-1.5)
  np.testing.assert_allclose(r(rewards.dof_pos_ref, q=q), [0, 0.25 + 2.25], rtol=1e-6)
  np.testing.assert_allclose(r(rewards.dof_pos_limits, q=q), [0, 1])  # |−1.5| > 1 only
  tau = jnp.zeros((2, nj)).at[1, 0].set(3.0).at[1, 1].set(-4.0)
  qd = jnp.zeros((2, nj)).at[1, 0].set(2.0).at[1, 1].set(1.0)
  np.testing.assert_allclose(r(rewards.torques, torque=tau), [0, 25], rtol=1e-6)
  np.testing.assert_allclose(r(rewards.torque_fatigue, torque=tau), [0, 0.25], rtol=1e-6)
  np.testing.assert_allclose(r(rewards.power, torque=tau, qd=qd), [0, 6 + 4], rtol=1e-6)
  np.testing.assert_allclose(r(rewards.dof_vel, qd=qd), [0, 5], rtol=1e-6)
  np.testing.assert_allclose(r(rewards.dof_acc, qdd=2 * qd), [0, 20], rtol=1e-6)
  np.testing.assert_allclose(r(rewards.root_acc, root_acc=jnp.array([[0, 0, 0], [1, 2, 2.0]])),
                             [0, 9], rtol=1e-6)
  a2, a1, a0 = jnp.array([[0, 0, 0], [1, 0, 0.0]]), jnp.zeros((2, 3)), jnp.array(
      [[0, 0, 0], [0, 0, 1.0]])
  # first difference |a − a1|² = 1; second |a − 2a1 + a2|² = |(0,0,1) + (1,0,0)|²= 2
  np.testing.assert_allclose(r(rewards.action_rate, action=a0, prev_action=a1,
                               prev_prev_action=a2), [0, 3], rtol=1e-6)
  # Hip roll: the reference mirrors (left +ref, right −ref).
  np.testing.assert_allclose(r(rewards.hip_roll, hip_roll=jnp.array([[0.1, -0.1], [0.0, 0.0]])),
                             [0, 0.02], rtol=1e-5)


GETUP_PARAMS = config.RewardParams(base_height_target=0.67, base_height_sigma=10.0, hip_roll_ref=0.0,
                             waist_height_target=0.55, dof_pos_ref_band=0.1)




def test_feet_under_com_pays_the_centre_of_mass_over_feet_on_the_floor():
  feet = jnp.array([[0.3, 0.1, 0.03], [0.3, -0.1, 0.03]])
  com = jnp.array([[0.3, 0.0, 0.5], [0.1, 0.0, 0.3], [0.3, 0.0, 0.5], [0.3, 0.0, 0.5]])
  raised = feet.at[0, 2].set(0.25)  # the left foot in the air
  x = _quantities(4, com=com, feet=jnp.stack([feet, feet, raised, feet.at[0, 1].set(0.0)]))
  out = np.asarray(rewards.feet_under_com(x, GETUP_PARAMS))
  sigma = rewards.FEET_UNDER_COM_SIGMA
  # over the feet; 0.2 m behind them (sitting); a foot off the floor; the midpoint of the feet
  # (0.3, -0.05), the left foot moved in, is 0.05 m from the centre of mass
  np.testing.assert_allclose(out, [1.0, math.exp(-(0.2 / sigma) ** 2), 0.0,
                                   math.exp(-(0.05 / sigma) ** 2)], rtol=1e-5)


@pytest.fixture(scope="module")
def native_env_for_com():
  from jax_env.env import FallRecoveryEnv
  return FallRecoveryEnv(default_stage_dict("planar"), backend="native")


def test_centre_of_mass_and_feet_of_the_key_states(native_env_for_com):
  # The env's centre of mass is MuJoCo's (subtree_com of the Trunk), and the term orders the
  # supine key states from lying to the crouch to standing.
  import mujoco
  env = native_env_for_com
  m = env.mj_model
  d = mujoco.MjData(m)
  paid = []
  for name in ("ksi_supine_1", "ksi_supine_2", "ksi_supine_3", "stand"):
    mujoco.mj_resetDataKeyframe(m, d, m.key(name).id)
    mujoco.mj_forward(m, d)
    view = types.SimpleNamespace(xpos=jnp.asarray(d.xpos)[None], xquat=jnp.asarray(d.xquat)[None])
    com = np.asarray(env._com(view))[0]
    np.testing.assert_allclose(com, d.subtree_com[env.trunk], atol=1e-5)
    x = _quantities(1, com=jnp.asarray(com)[None], feet=jnp.asarray(d.xpos[env.feet])[None])
    paid.append(float(rewards.feet_under_com(x, GETUP_PARAMS)[0]))
  assert paid == sorted(paid) and paid[0] < 0.1 and paid[-1] > 0.95, paid


def test_height_terms_rise_from_the_floor_and_saturate_at_the_target():
  h = jnp.array([0.0, 0.2, 0.4, 0.67, 0.9])
  x = _quantities(5, base_height=h, waist_height=h - 0.12)
  trunk = np.asarray(rewards.trunk_height(x, GETUP_PARAMS))
  waist = np.asarray(rewards.waist_height(x, GETUP_PARAMS))
  assert trunk[0] == pytest.approx(0.0, abs=1e-6)
  assert np.all(np.diff(trunk[:4]) > 0.05)  # a gradient all the way from lying
  assert trunk[3] == pytest.approx(1.0) and trunk[4] == pytest.approx(1.0)
  assert waist[3] == pytest.approx(1.0, abs=1e-6)  # waist 0.55 at the trunk target
  # The paper's Gaussian is flat on the floor: what the new terms are for.
  gauss = np.asarray(rewards.base_height(x, GETUP_PARAMS))
  assert gauss[1] - gauss[0] < trunk[1] - trunk[0]


def test_upright_is_one_upright_and_small_lying():
  g = jnp.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
  up = np.asarray(rewards.upright(_quantities(3, gravity=g), GETUP_PARAMS))
  assert up[0] == pytest.approx(1.0)
  assert up[1] == pytest.approx(math.exp(-4.0))  # lying: ‖(−1, 0, 1)‖² = 2
  assert up[2] == pytest.approx(math.exp(-8.0))  # upside down


def test_not_prone_rises_from_face_down_and_leaves_the_supine_get_up_alone():
  # Trunk-frame gravity of: lying prone, ksi_prone_3 (hands and knees), ksi_supine_3's forward
  # lean, standing, lying supine, lying on the side (the keyframes' values, rounded).
  g = jnp.array([[1.0, 0.0, -0.07], [0.85, 0.0, -0.52], [0.26, 0.0, -0.96], [0.0, 0.0, -1.0],
                 [-1.0, 0.0, 0.09], [0.0, 1.0, 0.0]])
  value = np.asarray(rewards.not_prone(_quantities(6, gravity=g), GETUP_PARAMS))
  np.testing.assert_allclose(value, [0.0, 0.3, 1.0, 1.0, 1.0, 1.0], atol=1e-6)
  # A gradient all the way from face down: a small roll already pays.
  rolled = jnp.array([[math.cos(0.2), math.sin(0.2), 0.0]])
  assert float(rewards.not_prone(_quantities(1, gravity=rolled), GETUP_PARAMS)[0]) > 0.03


def test_gravity_gates_take_the_heights_away_face_down_and_head_down():
  # Trunk-frame gravity of: standing, lying supine, ksi_supine_3's forward lean, ksi_prone_3
  # (hands and knees), lying prone, the head-down kneel of the prone trap, and a half-way lean.
  g = jnp.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.09], [0.26, 0.0, -0.96], [0.85, 0.0, -0.52],
                 [1.0, 0.0, -0.07], [0.60, -0.03, 0.80], [0.45, 0.0, -0.89]])
  x = _quantities(7, gravity=g, base_height=jnp.full(7, 0.4), waist_height=jnp.full(7, 0.3))
  gated = dataclasses.replace(GETUP_PARAMS, face_down_gate=(0.3, 0.6), head_down_gate=(0.0, 0.5))
  for term in (rewards.trunk_height, rewards.waist_height, rewards.base_height):
    plain, value = np.asarray(term(x, GETUP_PARAMS)), np.asarray(term(x, gated))
    # Lying supine the Trunk tilts slightly head-down (g_z 0.09): 0.82 of the pay.
    np.testing.assert_allclose(value / plain, [1, 0.82, 1, 0, 0, 0, 0.5], atol=1e-5,
                               err_msg=str(term))
  # not_prone keeps its pay face up, loses it head-down (the kneel paid 0.063 a step ungated).
  np.testing.assert_allclose(np.asarray(rewards.not_prone(x, gated)),
                             [1.0, 0.82, 1.0, 0.3, 0.0, 0.0, 1.0], atol=1e-5)
  assert float(rewards.not_prone(x, GETUP_PARAMS)[5]) == pytest.approx(0.8)
  # Each gate alone: the head-down one leaves the hands-and-knees posture paid.
  head_only = dataclasses.replace(GETUP_PARAMS, head_down_gate=(0.0, 0.5))
  np.testing.assert_allclose(np.asarray(rewards.trunk_height(x, head_only))[[3, 5]],
                             [float(rewards.trunk_height(x, GETUP_PARAMS)[3]), 0.0], atol=1e-6)


def test_dof_pos_ref_applies_only_near_the_target_height():
  q = jnp.full((2, robot.NUM_JOINTS), 0.1)
  x = _quantities(2, q=q, base_height=jnp.array([0.65, 0.3]))
  err = np.asarray(rewards.dof_pos_ref(x, GETUP_PARAMS))
  assert err[0] == pytest.approx(robot.NUM_JOINTS * 0.01, rel=1e-5)
  assert err[1] == 0.0
  everywhere = config.RewardParams(0.67, 10.0, 0.0)  # band 0: the old behaviour
  assert np.all(np.asarray(rewards.dof_pos_ref(x, everywhere)) > 0)


def test_shaping_scales_by_ctrl_dt_clips_at_zero_and_scales_penalties():
  weights = {t: 0.0 for t in names.REWARD_TERMS} | {"survival": 1.0, "dof_vel": -1.0}
  qd = jnp.zeros((2, robot.NUM_JOINTS)).at[1, 0].set(3.0)  # env 1: penalty 9 > survival 1
  x = _quantities(2, qd=qd)
  plain, _ = rewards.compute(x, weights, GETUP_PARAMS)
  assert np.allclose(plain, [1.0, -8.0])
  shaping = config.RewardShaping(scale_by_ctrl_dt=True, clip_at_zero=True)
  total, terms = rewards.compute(x, weights, GETUP_PARAMS, shaping, ctrl_dt=0.02)
  assert np.allclose(total, [0.02, 0.0])
  assert np.allclose(terms["reward/dof_vel"], [0.0, -0.18])  # metrics stay unclipped
  half, terms = rewards.compute(x, weights, GETUP_PARAMS, config.RewardShaping(), 1.0, 0.5)
  assert np.allclose(terms["reward/dof_vel"], [0.0, -4.5])  # penalties scaled ...
  assert np.allclose(terms["reward/survival"], [1.0, 1.0])  # ... rewards not
  assert np.allclose(half, [1.0, -3.5])


def test_reward_weights_and_metrics():
  stage = StageConfig.from_dict(default_stage_dict("full"))
  x = _quantities(standing=jnp.array([True, False]))
  total, metrics = rewards.compute(x, stage.rewards, stage.reward_params)
  assert set(metrics) == {f"reward/{t}" for t in names.REWARD_TERMS}
  np.testing.assert_allclose(total, sum(metrics.values()), rtol=1e-6)
  np.testing.assert_allclose(metrics["reward/standing"], [stage.rewards["standing"], 0])
  zero = dict(stage.rewards, survival=0.0)
  _, m = rewards.compute(x, zero, stage.reward_params)
  np.testing.assert_allclose(m["reward/survival"], 0.0)


def test_success_detector_needs_standing_held_for_hold_s():
  cfg = config.SuccessConfig(height_tolerance=0.05, upright_tolerance=0.1, dof_tolerance=0.3,
                             hold_s=1.0)
  ctrl_dt, hold = 0.02, 50
  nj = robot.NUM_JOINTS
  q_stand = jnp.zeros(nj)
  up = jnp.array([[0.0, 0.0, -1.0]])
  observed = jnp.ones(nj)
  standing = lambda h, g, q: rewards.is_standing(jnp.array([h]), g, q, q_stand, 0.67,
                                                 observed, cfg)
  assert bool(standing(0.67, up, jnp.zeros((1, nj)))[0])
  assert not bool(standing(0.55, up, jnp.zeros((1, nj)))[0])  # too low
  assert not bool(standing(0.67, jnp.array([[0.2, 0.0, -0.98]]), jnp.zeros((1, nj)))[0])
  assert not bool(standing(0.67, up, jnp.zeros((1, nj)).at[0, 14].set(0.5))[0])
  # Unobserved joints do not count.
  mask = jnp.ones(nj).at[14].set(0.0)
  assert bool(rewards.is_standing(jnp.array([0.67]), up, jnp.zeros((1, nj)).at[0, 14].set(0.5),
                                  q_stand, 0.67, mask, cfg)[0])

  def run(pattern, control_start=0):
    s = rewards.success_init(1)
    for step, on in enumerate(pattern):
      s = rewards.success_update(s, jnp.array([on]), jnp.array([step]),
                                 jnp.array([control_start]), hold, ctrl_dt)
    return bool(s.success[0]), float(s.recovery_time[0])

  # Held stand from the first step: success, recovery time 0.
  ok, t = run([True] * 60)
  assert ok and t == pytest.approx(0.0)
  # Lying all along: no success.
  assert not run([False] * 300)[0]
  # A transient pass through standing (0.5 s) then falling: no success.
  assert not run([False] * 40 + [True] * 25 + [False] * 200)[0]
  # Standing began at step 100 (2 s) after control started at step 50: recovery 1 s.
  ok, t = run([False] * 100 + [True] * 60, control_start=50)
  assert ok and t == pytest.approx(1.0)
  # Standing while still settling does not count.
  assert not run([True] * 50 + [False] * 10, control_start=40)[0]
  # Success latches (a later fall does not undo it) and keeps the first recovery time.
  ok, t = run([False] * 10 + [True] * 50 + [False] * 20 + [True] * 60)
  assert ok and t == pytest.approx(0.2)
