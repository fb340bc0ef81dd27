"""The native backend (C MuJoCo through `mujoco.batch`, called from JAX via pure_callback).

What is pinned here:
- results are bit-identical at 1 and 2 threads, and equal, bit for bit, to a plain loop of
  `mj_step` on one MjData per environment with that environment's parameters: so ctrl rows per
  substep, held pushes, per-env parameters and the view convention are exactly C MuJoCo's;
- `step` is a pure function of (state, params, ctrl, xfrc): the same inputs give the same
  outputs, and a state carried through JAX resumes bit-exactly;
- per-env parameters change the physics (mass, friction, gravity, kp);
- a blow-up is reported as NaN and stays NaN, leaving the other environments untouched,
  while harmless warnings (arena full) never cut a step short;
- agreement with MJX (documented tolerance below) for a standing and a lying start, with a
  push and with the obstacle ball, including contact sensors.

MJX-vs-native tolerance (float32 MJX vs float64 C MuJoCo, same model, nominal parameters,
a 1.5 Hz, 0.2 rad sinusoid added to the holding targets): after the first control step
(4 physics steps) every qpos differs by < 2e-3 and body positions by < 1e-3 m (measured
~1e-4); after AGREE_STEPS = 25 control steps (100 physics steps, 0.5 s) qpos by < 0.05 and
body positions by < 0.02 m (measured 0.03 rad and 0.008 m). Beyond that, contact dynamics
amplify the float32 rounding and the trajectories drift apart, as any two engines do.
The obstacle ball touches the trunk only slightly (a few mm): with a ball sunk 11 cm into an
arm capsule the two engines' contacts differ (deep-penetration collision is not comparable)
and the arm swings differently within a few steps.
"""

import copy

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from jax_env import robot
from jax_env.physics import ModelParams, nominal_params
from jax_env.physics.native_backend import (NativeBackend, from_integration_rows,
                                            integration_rows)

N_SUB = 4
AGREE_STEPS = 25
PARKED = np.array([0.0, 0.0, -5.0], np.float32)


@pytest.fixture(scope="module")
def model():
  return robot.load_model()


def _start(model, keys, mocap=None):
  qpos = np.stack([robot.keyframe(model, k)[0] for k in keys]).astype(np.float32)
  qvel = np.zeros((len(keys), model.nv), np.float32)
  if mocap is None:
    mocap = np.tile(PARKED, (len(keys), model.nmocap, 1))
  return jnp.asarray(qpos), jnp.asarray(qvel), jnp.asarray(mocap, jnp.float32)


def _random_params(model, batch, seed=0):
  """Nominal parameters scaled per env, as domain randomization would."""
  rng = np.random.default_rng(seed)
  p = nominal_params(model, batch)
  u = lambda shape, lo, hi: jnp.asarray(rng.uniform(lo, hi, shape), jnp.float32)
  return p.replace(
      geom_friction=p.geom_friction * u((batch, 1, 1), 0.5, 1.5),
      body_mass=p.body_mass * u((batch, model.nbody), 0.8, 1.2),
      body_ipos=p.body_ipos + u((batch, model.nbody, 3), -0.01, 0.01),
      actuator_kp=p.actuator_kp * u((batch, model.nu), 0.8, 1.2),
      actuator_kd=p.actuator_kd * u((batch, model.nu), 0.8, 1.2),
      gravity=p.gravity + u((batch, 3), -0.5, 0.5))


def _random_ctrl(model, qpos, steps, seed=1):
  rng = np.random.default_rng(seed)
  noise = rng.normal(0.0, 0.3, (steps,) + (qpos.shape[0], N_SUB, model.nu))
  return jnp.asarray(np.asarray(qpos)[None, :, None, 7:] + noise, jnp.float32)


def _pushes(model, batch, steps, seed=2):
  rng = np.random.default_rng(seed)
  xfrc = np.zeros((steps, batch, model.nbody, 6), np.float32)
  trunk = model.body("Trunk").id
  xfrc[:, :, trunk, :2] = rng.uniform(-80, 80, (steps, batch, 2))
  return jnp.asarray(xfrc)


def _rollout(backend, model, params, qpos, qvel, mocap, ctrls, xfrcs):
  """Per-step states of a scanned rollout, with the initial state."""
  init = jax.jit(backend.init)(qpos, qvel, params, mocap)

  def body(state, inputs):
    ctrl, xfrc = inputs
    state = backend.step(state, params, ctrl, xfrc)
    return state, state

  _, states = jax.jit(lambda s: jax.lax.scan(body, s, (ctrls, xfrcs)))(init)
  return init, states


def _model_for(model, params, i):
  """A MjModel with env i's parameters, as the backend applies them."""
  m = copy.copy(model)
  g = lambda x: np.asarray(x[i], np.float64)
  m.geom_friction[:] = g(params.geom_friction)
  m.geom_solref[:] = g(params.geom_solref)
  m.body_mass[:] = g(params.body_mass)
  m.body_ipos[:] = g(params.body_ipos)
  m.body_inertia[:] = g(params.body_inertia)
  m.actuator_gainprm[:, 0] = g(params.actuator_kp)
  m.actuator_biasprm[:, 1] = -g(params.actuator_kp)
  m.actuator_biasprm[:, 2] = -g(params.actuator_kd)
  m.actuator_forcerange[:] = g(params.actuator_forcerange)
  m.opt.gravity[:] = g(params.gravity)
  return m


# ---------------------------------------------------------------------------------------------
# Exactness.


@pytest.fixture(scope="module")
def exact_case(model):
  keys = ["stand", "ksi_supine_1", "ksi_prone_2", "stand"]
  qpos, qvel, mocap = _start(model, keys)
  params = _random_params(model, len(keys))
  steps = 8
  return dict(qpos=qpos, qvel=qvel, mocap=mocap, params=params,
              ctrls=_random_ctrl(model, qpos, steps),
              xfrcs=_pushes(model, len(keys), steps))


def test_bit_identical_across_thread_counts(model, exact_case):
  c = exact_case
  out = []
  for nthread in (1, 2):
    backend = NativeBackend(model, nthread=nthread)
    out.append(_rollout(backend, model, c["params"], c["qpos"], c["qvel"], c["mocap"],
                        c["ctrls"], c["xfrcs"]))
  for a, b in zip(jax.tree_util.tree_leaves(out[0]), jax.tree_util.tree_leaves(out[1])):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_matches_mj_step_loop_bit_for_bit(model, exact_case):
  """Each env equals one MjData stepped by mj_step with that env's model parameters."""
  c = exact_case
  backend = NativeBackend(model)
  init, states = _rollout(backend, model, c["params"], c["qpos"], c["qvel"], c["mocap"],
                          c["ctrls"], c["xfrcs"])
  spec = mujoco.mjtState.mjSTATE_INTEGRATION
  rows0 = integration_rows(init.integration)
  rows = integration_rows(states.integration)  # [T, B, nstate]
  ctrls, xfrcs = np.asarray(c["ctrls"], np.float64), np.asarray(c["xfrcs"], np.float64)
  f32 = lambda x: np.asarray(x, np.float32)
  for i in range(rows0.shape[0]):
    m = _model_for(model, c["params"], i)
    d = mujoco.MjData(m)
    mujoco.mj_setState(m, d, rows0[i], spec)
    mujoco.mj_forward(m, d)
    # After init, every view field describes the initial state (mj_forward).
    np.testing.assert_array_equal(f32(init.xpos[i]), f32(d.xpos))
    np.testing.assert_array_equal(f32(init.sensordata[i]), f32(d.sensordata))
    np.testing.assert_array_equal(f32(init.qpos[i]), f32(d.qpos))
    for t in range(ctrls.shape[0]):
      d.xfrc_applied[:] = xfrcs[t, i]
      for k in range(N_SUB):
        d.ctrl[:] = ctrls[t, i, k]
        mujoco.mj_step(m, d)
      row = np.empty(rows0.shape[1])
      mujoco.mj_getState(m, d, row, spec)
      np.testing.assert_array_equal(rows[t, i], row)
      # Derived fields as mj_step leaves them: from the last substep's forward pass.
      for name in ("qacc", "actuator_force", "sensordata", "xpos", "xquat"):
        np.testing.assert_array_equal(f32(getattr(states, name)[t, i]), f32(getattr(d, name)),
                                      err_msg=f"{name} env {i} step {t}")
      np.testing.assert_array_equal(f32(states.qpos[t, i]), f32(d.qpos))
      np.testing.assert_array_equal(f32(states.time[t, i]), f32(d.time))


def test_step_is_a_pure_function_and_resumes_bit_exactly(model, exact_case):
  c = exact_case
  backend = NativeBackend(model)
  step = jax.jit(backend.step)
  s0 = jax.jit(backend.init)(c["qpos"], c["qvel"], c["params"], c["mocap"])
  a = step(s0, c["params"], c["ctrls"][0], c["xfrcs"][0])
  b = step(s0, c["params"], c["ctrls"][0], c["xfrcs"][0])
  for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
    np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
  # Interleaving another batch size (its own host batch) or another state changes nothing.
  other = jax.jit(backend.init)(c["qpos"][:2], c["qvel"][:2],
                                jax.tree_util.tree_map(lambda x: x[:2], c["params"]),
                                c["mocap"][:2])
  step(other, jax.tree_util.tree_map(lambda x: x[:2], c["params"]), c["ctrls"][0][:2],
       c["xfrcs"][0][:2])
  step(a, c["params"], c["ctrls"][1], c["xfrcs"][1])
  # Resume from a state that went through the host and back (as a checkpoint would).
  saved = from_integration_rows(integration_rows(a.integration))
  resumed = a.replace(integration=jnp.asarray(saved))
  r1 = step(a, c["params"], c["ctrls"][1], c["xfrcs"][1])
  r2 = step(resumed, c["params"], c["ctrls"][1], c["xfrcs"][1])
  for x, y in zip(jax.tree_util.tree_leaves(r1), jax.tree_util.tree_leaves(r2)):
    np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
  assert a.integration.dtype == jnp.uint32
  assert integration_rows(a.integration).dtype == np.float64


def test_init_of_some_rows_equals_init_of_all_on_those_rows(model, exact_case):
  """An auto-reset keeps only the episodes that ended: `init(..., only=mask)` computes just
  those rows, bit for bit as a full init would, and their first step follows suit."""
  c = exact_case
  backend = NativeBackend(model)
  init = jax.jit(backend.init)
  step = jax.jit(backend.step)
  full = init(c["qpos"], c["qvel"], c["params"], c["mocap"])
  only = jnp.asarray([False, True, False, True])
  calls = backend.stats["init_calls"]
  some = init(c["qpos"], c["qvel"], c["params"], c["mocap"], only=only)
  assert backend.stats["init_calls"] == calls + 1
  rows = np.flatnonzero(np.asarray(only))
  for a, b in zip(jax.tree_util.tree_leaves(full), jax.tree_util.tree_leaves(some)):
    np.testing.assert_array_equal(np.asarray(a)[rows], np.asarray(b)[rows])
  after_full = step(full, c["params"], c["ctrls"][0], c["xfrcs"][0])
  after_some = step(some, c["params"], c["ctrls"][0], c["xfrcs"][0])
  for a, b in zip(jax.tree_util.tree_leaves(after_full), jax.tree_util.tree_leaves(after_some)):
    np.testing.assert_array_equal(np.asarray(a)[rows], np.asarray(b)[rows])
  with pytest.raises(ValueError, match=r"only has shape \(3,\), expected \(4,\)"):
    backend.init(c["qpos"], c["qvel"], c["params"], c["mocap"], only=only[:3])


def test_bad_shapes_are_rejected_with_the_expected_shape(model, exact_case):
  c = exact_case
  backend = NativeBackend(model)
  s0 = backend.init(c["qpos"], c["qvel"], c["params"], c["mocap"])
  with pytest.raises(ValueError, match=r"ctrl has shape \(4, 23\)"):
    backend.step(s0, c["params"], c["ctrls"][0][:, 0], c["xfrcs"][0])
  with pytest.raises(ValueError, match="ModelParams.body_mass"):
    backend.step(s0, c["params"].replace(body_mass=c["params"].body_mass[:, :3]),
                 c["ctrls"][0], c["xfrcs"][0])


# ---------------------------------------------------------------------------------------------
# Per-env parameters and failures.


def _run_steps(backend, params, qpos, qvel, mocap, steps, ctrl=None):
  state = jax.jit(backend.init)(qpos, qvel, params, mocap)
  step = jax.jit(backend.step)
  if ctrl is None:
    ctrl = jnp.broadcast_to(qpos[:, None, 7:], (qpos.shape[0], N_SUB, qpos.shape[1] - 7))
  xfrc = jnp.zeros((qpos.shape[0], backend.mj_model.nbody, 6))
  for _ in range(steps):
    state = step(state, params, ctrl, xfrc)
  return state


def test_per_env_params_change_the_physics(model):
  backend = NativeBackend(model)
  keys = ["ksi_supine_1"] * 4 + ["stand"] * 2
  qpos, qvel, mocap = _start(model, keys)
  qvel = qvel.at[:2, 0].set(1.5)  # lying robots sliding along x
  p = nominal_params(model, len(keys))
  floor = model.geom("floor").id
  trunk = model.body("Trunk").id
  friction = p.geom_friction.at[0, floor, 0].set(0.1).at[1, floor, 0].set(1.5)
  mass = p.body_mass.at[3, trunk].multiply(3.0)
  gravity = p.gravity.at[5].set(0.0)
  kp = p.actuator_kp.at[4].multiply(0.2)
  params = p.replace(geom_friction=friction, body_mass=mass, gravity=gravity, actuator_kp=kp)
  s = _run_steps(backend, params, qpos, qvel, mocap, 15)
  x = np.asarray(s.qpos)
  # Low friction slides further than high friction.
  assert x[0, 0] > x[1, 0] + 0.05, x[:2, 0]
  # A heavier trunk lies lower (compresses the contact more) and moves differently.
  assert np.abs(x[3] - x[2]).max() > 1e-3
  # Weak servos sag; in zero gravity the robot does not come down at all.
  assert x[4, 2] < x[5, 2] - 0.01, x[4:, 2]
  assert abs(x[5, 2] - float(qpos[5, 2])) < 1e-3


def test_blowup_is_nan_and_stays_nan_without_touching_others(model):
  backend = NativeBackend(model)
  qpos, qvel, mocap = _start(model, ["stand"] * 3)
  params = nominal_params(model, 3)
  qvel = qvel.at[1, 10].set(1e12)
  two = jax.tree_util.tree_map(lambda x: x[::2], params)
  ok = _run_steps(backend, two, qpos[::2], qvel[::2], mocap[::2], 2)
  s = _run_steps(backend, params, qpos, qvel, mocap, 1)
  assert np.isnan(np.asarray(s.qpos[1])).all()
  assert np.isfinite(np.asarray(s.qpos)[[0, 2]]).all()
  s = jax.jit(backend.step)(s, params, jnp.broadcast_to(qpos[:, None, 7:], (3, N_SUB, 23)),
                            jnp.zeros((3, model.nbody, 6)))
  assert np.isnan(np.asarray(s.qpos[1])).all()
  np.testing.assert_array_equal(np.asarray(s.qpos)[[0, 2]], np.asarray(ok.qpos))


_CROWDED = """<mujoco><size memory="24K"/><worldbody><geom type="plane" size="5 5 .1"/>{}
</worldbody></mujoco>""".format("".join(
    f'<body pos="{0.25 * i} 0 {0.1 + 0.05 * i}"><freejoint/><geom type="box" size=".1 .1 .1"/>'
    "</body>" for i in range(4)))


def test_harmless_warnings_do_not_stop_a_simulation():
  """Arena-full warnings (here: too many constraints for a 24K arena) must not cut a step
  short: the result is still exactly that of an mj_step loop."""
  m = mujoco.MjModel.from_xml_string(_CROWDED)
  backend = NativeBackend(m)
  batch, steps = 2, 30
  qpos = jnp.asarray(np.tile(m.qpos0, (batch, 1)), jnp.float32)
  qvel = jnp.zeros((batch, m.nv))
  params = nominal_params(m, batch)
  state = backend.init(qpos, qvel, params, jnp.zeros((batch, 0, 3)))
  rows0 = integration_rows(state.integration)
  ctrl, xfrc = jnp.zeros((batch, N_SUB, 0)), jnp.zeros((batch, m.nbody, 6))
  for _ in range(steps):
    state = backend.step(state, params, ctrl, xfrc)
  d = mujoco.MjData(m)
  spec = mujoco.mjtState.mjSTATE_INTEGRATION
  mujoco.mj_setState(m, d, rows0[0], spec)
  mm = _model_for(m, params, 0)
  for _ in range(steps * N_SUB):
    mujoco.mj_step(mm, d)
  assert d.warning[mujoco.mjtWarning.mjWARN_CNSTRFULL].number > 0  # the case is exercised
  row = np.empty(rows0.shape[1])
  mujoco.mj_getState(mm, d, row, spec)
  for i in range(batch):
    np.testing.assert_array_equal(integration_rows(state.integration)[i], row)
  assert np.isfinite(np.asarray(state.qpos)).all()


# ---------------------------------------------------------------------------------------------
# Agreement with MJX. One batch covers a standing start, a pushed standing start, a lying start
# and a lying start with the obstacle ball pressed onto the trunk. MJX compiles are slow on a
# shared CPU (minutes), so both trajectories are computed once; the persistent compilation
# cache (tests/.cache/jax) makes later runs fast.

AGREE_KEYS = ["stand", "stand", "ksi_supine_1", "ksi_supine_1"]


def _ball_against_trunk(model, qpos, depth):
  """Obstacle ball centre pressing `depth` down onto the top of the (lying) trunk box."""
  d = mujoco.MjData(model)
  d.qpos[:] = qpos
  mujoco.mj_kinematics(model, d)
  g = model.geom("trunk").id
  radius = model.geom_size[model.body("obstacle").geomadr[0], 0]
  half_z = np.abs(d.geom_xmat[g].reshape(3, 3)[2] * model.geom_size[g]).sum()
  centre = d.geom_xpos[g].copy()
  centre[2] += half_z + radius - depth
  return centre


@pytest.fixture(scope="module")
def agreement(model):
  from jax_env.physics.mjx_backend import MjxBackend

  qpos, qvel, _ = _start(model, AGREE_KEYS)
  batch = len(AGREE_KEYS)
  mocap = np.tile(PARKED, (batch, model.nmocap, 1))
  mocap[3, 0] = _ball_against_trunk(model, np.asarray(qpos[3]), depth=0.02)
  mocap = jnp.asarray(mocap)
  params = nominal_params(model, batch)
  trunk = model.body("Trunk").id
  t = np.arange(AGREE_STEPS * N_SUB).reshape(AGREE_STEPS, 1, N_SUB, 1) * model.opt.timestep
  wave = 0.2 * np.sin(2 * np.pi * 1.5 * t)
  ctrls = jnp.asarray(np.asarray(qpos)[None, :, None, 7:] + wave, jnp.float32)
  xfrc = np.zeros((AGREE_STEPS, batch, model.nbody, 6), np.float32)
  xfrc[:10, 1, trunk, :3] = [60.0, 20.0, 0.0]  # a 0.2 s push on env 1
  xfrcs = jnp.asarray(xfrc)
  out = {}
  for name, backend in (("native", NativeBackend(model)), ("mjx", MjxBackend(model))):
    init = jax.jit(backend.init)(qpos, qvel, params, mocap)
    step = jax.jit(backend.step)
    views, state = [backend.view(init)], init
    for i in range(AGREE_STEPS):
      state = step(state, params, ctrls[i], xfrcs[i])
      views.append(jax.device_get(backend.view(state)))
    out[name] = jax.tree_util.tree_map(lambda *x: np.stack([np.asarray(v) for v in x]),
                                       *views)
  return out


def _diff(agreement, field, t):
  a, b = getattr(agreement["native"], field)[t], getattr(agreement["mjx"], field)[t]
  return np.abs(a - b).reshape(a.shape[0], -1).max(axis=1)


def test_agrees_with_mjx_at_init(model, agreement):
  for field in ("qpos", "qvel", "xpos", "xquat", "time"):
    assert _diff(agreement, field, 0).max() < 1e-5, field
  # Derived quantities of the same state: contact flags exactly.
  adr = np.array([robot.sensor_slice(model, s).start for s in robot.CONTACT_SENSOR_NAMES])
  a, b = agreement["native"].sensordata[0], agreement["mjx"].sensordata[0]
  np.testing.assert_array_equal(a[:, adr] > 0, b[:, adr] > 0)


def test_agrees_with_mjx_over_the_documented_horizon(agreement):
  assert _diff(agreement, "qpos", 1).max() < 2e-3
  assert _diff(agreement, "xpos", 1).max() < 1e-3
  np.testing.assert_allclose(agreement["native"].time, agreement["mjx"].time, atol=1e-5)
  for t in range(1, AGREE_STEPS + 1):
    assert _diff(agreement, "qpos", t).max() < 0.05, (t, _diff(agreement, "qpos", t))
    assert _diff(agreement, "xpos", t).max() < 0.02, (t, _diff(agreement, "xpos", t))


def test_push_and_obstacle_act_the_same_in_both(model, agreement):
  ids = robot.body_ids(model)  # robot bodies only: the ball itself is placed, not simulated
  effect = {}
  for name in ("native", "mjx"):
    x = agreement[name].xpos[-1][:, ids]  # [B, 24, 3]
    effect[name] = (x[1] - x[0], x[3] - x[2])
    # The push moved env 1 far more than the engines differ (measured 0.35 m).
    assert np.abs(x[1] - x[0]).max() > 0.1, name
    # The ball pressed on the lying trunk (measured 0.023 m native, 0.014 m MJX).
    assert np.abs(x[3] - x[2]).max() > 0.008, name
  np.testing.assert_allclose(effect["native"][0], effect["mjx"][0], atol=0.03)
  np.testing.assert_allclose(effect["native"][1], effect["mjx"][1], atol=0.015)


def test_contact_sensors_agree_with_mjx(model, agreement):
  adr = np.array([robot.sensor_slice(model, s).start for s in robot.CONTACT_SENSOR_NAMES])
  trunk = robot.CONTACT_SENSOR_NAMES.index("contact/Trunk")
  feet = [robot.CONTACT_SENSOR_NAMES.index(f"contact/{b}_foot_link") for b in ("left", "right")]
  for name in ("native", "mjx"):
    c = agreement[name].sensordata[:, :, adr] > 0  # [T, B, 13]
    assert c[1:, 0, feet].all(), name  # standing: both feet down once it settles
    assert not c[:, 0, trunk].any(), name
    assert c[:, 2, trunk].mean() > 0.8, name  # lying on the back: trunk on the floor
  n = agreement["native"].sensordata[:, :, adr] > 0
  m = agreement["mjx"].sensordata[:, :, adr] > 0
  assert (n == m).mean() > 0.97, (n != m).sum()
  gyro = robot.sensor_slice(model, robot.GYRO_SENSOR)
  g = np.abs(agreement["native"].sensordata[1:6, :, gyro] -
             agreement["mjx"].sensordata[1:6, :, gyro]).max()
  assert g < 0.2, g
