"""The T1 model (assets/t1) and its description in code (jax_env.robot).

Physics checks use C MuJoCo (fast, deterministic); one smoke test runs the model through
MJX to prove that mjx.put_model accepts it and a jitted mjx.step reproduces C MuJoCo.
"""

import mujoco
import numpy as np
import pytest

from jax_env import robot

# Range A (URDF-A = MEN = PG = MJL), T1-FACTS §2, canonical order.
RANGE_A = {
    "AAHead_yaw": (-1.57, 1.57), "Head_pitch": (-0.35, 1.22),
    "Left_Shoulder_Pitch": (-3.31, 1.22), "Left_Shoulder_Roll": (-1.74, 1.57),
    "Left_Elbow_Pitch": (-2.27, 2.27), "Left_Elbow_Yaw": (-2.44, 0.0),
    "Right_Shoulder_Pitch": (-3.31, 1.22), "Right_Shoulder_Roll": (-1.57, 1.74),
    "Right_Elbow_Pitch": (-2.27, 2.27), "Right_Elbow_Yaw": (0.0, 2.44),
    "Waist": (-1.57, 1.57),
    "Left_Hip_Pitch": (-1.8, 1.57), "Left_Hip_Roll": (-0.2, 1.57), "Left_Hip_Yaw": (-1.0, 1.0),
    "Left_Knee_Pitch": (0.0, 2.34), "Left_Ankle_Pitch": (-0.87, 0.35),
    "Left_Ankle_Roll": (-0.44, 0.44),
    "Right_Hip_Pitch": (-1.8, 1.57), "Right_Hip_Roll": (-1.57, 0.2),
    "Right_Hip_Yaw": (-1.0, 1.0), "Right_Knee_Pitch": (0.0, 2.34),
    "Right_Ankle_Pitch": (-0.87, 0.35), "Right_Ankle_Roll": (-0.44, 0.44),
}

# URDF-A efforts (N·m) per group, T1-FACTS §4.
URDF_A_EFFORT = {"head": 7, "arm": 18, "waist": 30, "hip_pitch": 45, "hip_roll": 30,
                 "hip_yaw": 30, "knee": 60, "ankle_pitch": 20, "ankle_roll": 15}

LYING_KEYS = [k for k in robot.KEYFRAME_NAMES if k != "stand"]


@pytest.fixture(scope="module")
def model():
  return robot.load_model()


def _data_at_key(model, name):
  data = mujoco.MjData(model)
  mujoco.mj_resetDataKeyframe(model, data, model.key(name).id)
  mujoco.mj_forward(model, data)
  return data


def _hold(model, name, seconds):
  """Steps PD holding the key's own ctrl; returns the Trunk positions over time."""
  data = _data_at_key(model, name)
  base = [data.qpos[:3].copy()]
  for _ in range(int(round(seconds / model.opt.timestep))):
    mujoco.mj_step(model, data)
    base.append(data.qpos[:3].copy())
  return np.array(base), data


def _sensor(model, data, name):
  return data.sensordata[robot.sensor_slice(model, name)]


# --- names, order, masses, limits -------------------------------------------------------


def test_joint_actuator_and_body_order(model):
  assert model.nu == 23 and model.nq == 30 and model.nv == 29
  assert model.jnt_type[0] == mujoco.mjtJoint.mjJNT_FREE
  assert tuple(model.joint(i).name for i in range(1, 24)) == robot.JOINT_NAMES
  assert tuple(model.actuator(i).name for i in range(23)) == robot.JOINT_NAMES
  actuated = tuple(model.joint(model.actuator_trnid[i, 0]).name for i in range(23))
  assert actuated == robot.JOINT_NAMES
  # qpos[7:] is the canonical order.
  assert [model.jnt_qposadr[model.joint(j).id] for j in robot.JOINT_NAMES] == list(range(7, 30))
  assert tuple(model.body(i).name for i in range(1, 25)) == robot.BODY_NAMES
  assert model.body("obstacle").mocapid[0] >= 0
  assert set(robot.SAGITTAL_JOINTS) | set(robot.LATERAL_JOINTS) | set(robot.HELD_JOINTS) == set(
      robot.JOINT_NAMES)
  assert len(robot.SAGITTAL_JOINTS) == 10 and len(robot.HELD_JOINTS) == 11


def test_total_mass(model):
  robot_mass = model.body_mass[robot.body_ids(model)].sum()
  assert abs(robot_mass - 31.61) < 0.01


def test_ranges_are_range_a(model):
  arrays = robot.joint_arrays(model)
  expected = np.array([RANGE_A[j] for j in robot.JOINT_NAMES])
  np.testing.assert_allclose(arrays.range_low, expected[:, 0])
  np.testing.assert_allclose(arrays.range_high, expected[:, 1])
  # Position targets are limited to the joint range.
  np.testing.assert_allclose(model.actuator_ctrlrange, expected)


def test_joint_arrays_from_model(model):
  arrays = robot.joint_arrays(model)
  np.testing.assert_allclose(
      arrays.torque_limit, [URDF_A_EFFORT[robot.JOINT_GROUP[j]] for j in robot.JOINT_NAMES])
  np.testing.assert_allclose(model.actuator_forcerange[:, 0], -arrays.torque_limit)
  assert np.all(arrays.kp > 0) and np.all(arrays.kd > 0)
  np.testing.assert_allclose(model.actuator_biasprm[:, 1], -arrays.kp)
  np.testing.assert_allclose(arrays.frictionloss, 0.1)
  assert np.all(arrays.armature > 0)
  assert arrays.velocity_limit[robot.JOINT_NAMES.index("Left_Knee_Pitch")] == 11.7
  # Same group, same numbers.
  for field in ("torque_limit", "kp", "kd", "armature", "velocity_limit"):
    values = getattr(arrays, field)
    for group in set(robot.JOINT_GROUP.values()):
      members = [i for i, j in enumerate(robot.JOINT_NAMES) if robot.JOINT_GROUP[j] == group]
      assert np.ptp(values[members]) == 0, (field, group)


def test_physics_options(model):
  assert model.opt.timestep == 0.005
  assert model.opt.integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST
  assert model.opt.cone == mujoco.mjtCone.mjCONE_PYRAMIDAL


def test_sensors_present(model):
  dims = {"gyro": 3, "accelerometer": 3, "orientation": 4, "local_linvel": 3}
  for name, dim in dims.items():
    assert model.sensor(name).dim[0] == dim
  site = model.site(robot.IMU_SITE)
  assert model.site_bodyid[site.id] == model.body("Trunk").id
  np.testing.assert_allclose(model.site_pos[site.id], 0.0)
  for body, name in zip(robot.CONTACT_BODIES, robot.CONTACT_SENSOR_NAMES):
    sensor = model.sensor(name)
    assert sensor.type[0] == mujoco.mjtSensor.mjSENS_CONTACT and sensor.dim[0] == 1
    geom = sensor.objid[0]
    assert model.geom_bodyid[geom] == model.body(body).id
    assert sensor.refid[0] == model.geom(robot.FLOOR_GEOM).id
  # Contact sensors appear in CONTACT_BODIES order.
  adrs = [model.sensor(n).adr[0] for n in robot.CONTACT_SENSOR_NAMES]
  assert adrs == sorted(adrs)


def test_collision_filtering(model):
  """Robot geoms touch floor and obstacle but never each other outside the explicit pairs."""
  floor, ball = model.geom(robot.FLOOR_GEOM).id, model.geom("obstacle").id
  collide = lambda a, b: bool(model.geom_contype[a] & model.geom_conaffinity[b]
                              or model.geom_contype[b] & model.geom_conaffinity[a])
  robot_geoms = [g for g in range(model.ngeom) if g not in (floor, ball)]
  # Every contact body has exactly one collision geom (contact sensors match geoms).
  owners = [model.body(model.geom_bodyid[g]).name for g in robot_geoms]
  assert sorted(owners) == sorted(robot.CONTACT_BODIES)
  for g in robot_geoms:
    assert int(model.geom_type[g]) in (int(mujoco.mjtGeom.mjGEOM_SPHERE),
                                       int(mujoco.mjtGeom.mjGEOM_CAPSULE),
                                       int(mujoco.mjtGeom.mjGEOM_BOX))
    assert collide(g, floor) and collide(g, ball)
    assert not any(collide(g, h) for h in robot_geoms)
  assert not collide(floor, ball)
  assert 0 < model.npair <= 8
  assert model.geom_priority[floor] > 0


def test_obstacle_collides_and_parks(model):
  data = _data_at_key(model, "stand")
  ball = model.geom("obstacle").id
  touching = lambda: any(ball in (data.contact.geom1[i], data.contact.geom2[i])
                         for i in range(data.ncon))
  assert not touching()  # parked at z = -5
  data.mocap_pos[model.body("obstacle").mocapid[0]] = data.xpos[model.body("Shank_Left").id]
  mujoco.mj_forward(model, data)
  assert touching()


# --- mirror maps ------------------------------------------------------------------------


def test_mirror_maps_are_involutions(model):
  for perm in (robot.JOINT_MIRROR_PERM, robot.BODY_MIRROR_PERM, robot.CONTACT_MIRROR_PERM):
    np.testing.assert_array_equal(perm[perm], np.arange(len(perm)))
  sign = robot.JOINT_MIRROR_SIGN
  np.testing.assert_array_equal(sign[robot.JOINT_MIRROR_PERM], sign)
  np.testing.assert_array_equal(sign * sign, 1.0)
  np.testing.assert_allclose(robot.mirror_signs_from_model(model), sign, atol=1e-5)
  x = np.random.default_rng(0).normal(size=(4, 23)).astype(np.float32)
  np.testing.assert_array_equal(robot.mirror_joint_vector(robot.mirror_joint_vector(x)), x)
  v = np.arange(6.0).reshape(2, 3)
  np.testing.assert_array_equal(robot.mirror_vec3(v)[:, 1], -v[:, 1])
  np.testing.assert_array_equal(robot.mirror_pseudovec3(v)[:, [0, 2]], -v[:, [0, 2]])
  names = robot.JOINT_NAMES
  assert names[robot.JOINT_MIRROR_PERM[names.index("Left_Knee_Pitch")]] == "Right_Knee_Pitch"
  assert names[robot.JOINT_MIRROR_PERM[names.index("Waist")]] == "Waist"
  bodies = robot.BODY_NAMES
  assert bodies[robot.BODY_MIRROR_PERM[bodies.index("AL3")]] == "AR3"
  contacts = robot.CONTACT_BODIES
  assert contacts[robot.CONTACT_MIRROR_PERM[contacts.index("Hip_Yaw_Left")]] == "Hip_Yaw_Right"


def test_left_right_ranges_mirror(model):
  arrays = robot.joint_arrays(model)
  perm, sign = robot.JOINT_MIRROR_PERM, robot.JOINT_MIRROR_SIGN
  low = np.where(sign > 0, arrays.range_low[perm], -arrays.range_high[perm])
  high = np.where(sign > 0, arrays.range_high[perm], -arrays.range_low[perm])
  np.testing.assert_allclose(low, arrays.range_low)
  np.testing.assert_allclose(high, arrays.range_high)
  np.testing.assert_allclose(arrays.torque_limit[perm], arrays.torque_limit)
  np.testing.assert_allclose(arrays.kp[perm], arrays.kp)


def test_kinematics_mirror_consistent(model):
  rng = np.random.default_rng(1)
  arrays = robot.joint_arrays(model)
  ids = robot.body_ids(model)
  data, mirrored = mujoco.MjData(model), mujoco.MjData(model)
  for _ in range(5):
    qpos = np.zeros(model.nq)
    qpos[:3] = rng.normal(size=3)
    quat = rng.normal(size=4)
    qpos[3:7] = quat / np.linalg.norm(quat)
    qpos[7:] = rng.uniform(arrays.range_low, arrays.range_high)
    data.qpos[:] = qpos
    mirrored.qpos[:] = robot.mirror_qpos(qpos)
    # The mirrored configuration is legal: mirrored ranges are the ranges.
    assert np.all(mirrored.qpos[7:] >= arrays.range_low - 1e-9)
    assert np.all(mirrored.qpos[7:] <= arrays.range_high + 1e-9)
    mujoco.mj_kinematics(model, data)
    mujoco.mj_kinematics(model, mirrored)
    pos, pos_m = data.xpos[ids], mirrored.xpos[ids]
    np.testing.assert_allclose(pos_m[robot.BODY_MIRROR_PERM], robot.mirror_vec3(pos), atol=2e-3)
    quat, quat_m = data.xquat[ids], mirrored.xquat[ids]
    expected = robot.mirror_quat(quat)
    got = quat_m[robot.BODY_MIRROR_PERM]
    # q and -q are the same rotation.
    err = np.minimum(np.abs(got - expected).max(-1), np.abs(got + expected).max(-1))
    assert err.max() < 2e-3
    # Collision geoms mirror too (what the floor sees).
    gpos = data.geom_xpos
    for g in range(model.ngeom):
      name = model.geom(g).name
      other = name.replace("left", "@").replace("right", "left").replace("@", "right")
      if name in ("floor", "obstacle"):
        continue
      np.testing.assert_allclose(mirrored.geom_xpos[model.geom(other).id],
                                 robot.mirror_vec3(gpos[g]), atol=2e-3)


# --- keyframes --------------------------------------------------------------------------


def test_keyframes_exist_and_are_consistent(model):
  assert tuple(model.key(i).name for i in range(model.nkey)) == robot.KEYFRAME_NAMES
  for name in robot.KEYFRAME_NAMES:
    qpos, qvel = robot.keyframe(model, name)
    np.testing.assert_allclose(np.linalg.norm(qpos[3:7]), 1.0, atol=1e-5)
    np.testing.assert_array_equal(qvel, 0.0)
    np.testing.assert_allclose(model.key(name).ctrl, qpos[7:])
    arrays = robot.joint_arrays(model)
    assert np.all(qpos[7:] >= arrays.range_low) and np.all(qpos[7:] <= arrays.range_high)
  with pytest.raises(ValueError, match="ksi_prone_7.*stand"):
    robot.keyframe(model, "ksi_prone_7")


def test_keyframes_are_left_right_symmetric(model):
  """Every key state is its own mirror image, so KSI draws no side preference."""
  for name in robot.KEYFRAME_NAMES:
    qpos, qvel = robot.keyframe(model, name)
    np.testing.assert_allclose(robot.mirror_qpos(qpos), qpos, atol=1e-5, err_msg=name)
    np.testing.assert_allclose(robot.mirror_qvel(qvel), qvel, atol=1e-9)


def test_stand_pose_is_home(model):
  pose = robot.stand_pose(model)
  leg = [-0.2, 0.0, 0.0, 0.4, -0.2, 0.0]
  np.testing.assert_allclose(pose[11:17], leg)
  np.testing.assert_allclose(pose[17:23], leg)
  np.testing.assert_allclose(pose[2:6], [0.0, -1.4, 0.0, -0.4])
  np.testing.assert_allclose(robot.mirror_joint_vector(pose), pose)
  qpos, _ = robot.keyframe(model, "stand")
  assert abs(qpos[2] - 0.666) < 0.002


@pytest.mark.parametrize("name", robot.KEYFRAME_NAMES)
def test_keyframe_valid_and_settles(model, name):
  data = _data_at_key(model, name)
  depth = min((data.contact.dist[i] for i in range(data.ncon)), default=0.0)
  assert depth >= -1e-3, f"{name}: penetration {depth * 1e3:.2f} mm"
  base, data = _hold(model, name, 1.0)
  drift = np.linalg.norm(base - base[0], axis=1).max()
  assert drift < 0.05, f"{name}: base moved {drift * 100:.1f} cm"
  assert np.all(np.isfinite(data.qpos))


def test_stand_stands(model):
  base, data = _hold(model, "stand", 2.0)
  assert np.abs(base[:, 2] - base[0, 2]).max() < 0.02
  up = data.xmat[model.body("Trunk").id].reshape(3, 3)[:, 2]
  assert up[2] > 0.99
  touching = {b for b, n in zip(robot.CONTACT_BODIES, robot.CONTACT_SENSOR_NAMES)
              if _sensor(model, data, n)[0] > 0}
  assert touching == {"left_foot_link", "right_foot_link"}


def test_contact_sensors_on_lying_keys(model):
  def touching(name):
    _, data = _hold(model, name, 0.2)
    return {b for b, n in zip(robot.CONTACT_BODIES, robot.CONTACT_SENSOR_NAMES)
            if _sensor(model, data, n)[0] > 0}

  supine = touching("ksi_supine_1")
  assert {"Trunk", "H2", "left_foot_link", "right_foot_link"} <= supine
  prone = touching("ksi_prone_2")
  assert {"left_hand_link", "right_hand_link", "Shank_Left", "Shank_Right"} <= prone
  assert "Trunk" not in prone and "H2" not in prone


def test_imu_sensors_read_physics(model):
  _, data = _hold(model, "stand", 0.5)
  acc = _sensor(model, data, "accelerometer")
  assert abs(np.linalg.norm(acc) - 9.81) < 0.5  # standing still: the specific force is g
  quat = _sensor(model, data, "orientation")
  np.testing.assert_allclose(np.abs(quat), np.abs(data.xquat[model.body("Trunk").id]), atol=1e-6)
  assert np.linalg.norm(_sensor(model, data, "gyro")) < 0.5


# --- MJX ----------------------------------------------------------------------------------


def test_mjx_accepts_and_steps_model(model):
  """mjx.put_model accepts the model and a jitted mjx.step matches C MuJoCo."""
  import jax  # pylint: disable=import-outside-toplevel
  from mujoco import mjx  # pylint: disable=import-outside-toplevel

  mx = mjx.put_model(model)
  data = _data_at_key(model, "ksi_supine_1")
  dx = mjx.put_data(model, data)
  step = jax.jit(mjx.step)
  for _ in range(3):
    dx = step(mx, dx)
    mujoco.mj_step(model, data)
  # Both report the sensors of the state before the last integration step.
  np.testing.assert_allclose(np.asarray(dx.qpos), data.qpos, atol=1e-3)
  sensordata = np.asarray(dx.sensordata)
  for name in robot.CONTACT_SENSOR_NAMES:
    sl = robot.sensor_slice(model, name)
    assert (sensordata[sl] > 0) == (data.sensordata[sl] > 0), name
  for name in ("gyro", "orientation", "local_linvel"):
    sl = robot.sensor_slice(model, name)
    np.testing.assert_allclose(sensordata[sl], data.sensordata[sl], atol=2e-2)


def test_model_params_round_trip_through_the_model_fields(model):
  """The one ModelParams <-> model-field mapping both physics backends use gives back the model's
  own fields (as float32) for its own parameters, batched or not."""
  from jax_env.physics.view import MODEL_FIELDS, model_fields, model_params, param_shapes

  params = model_params(model)
  assert {k: v.shape for k, v in vars(params).items()} == param_shapes(model)
  fields = model_fields(params, model.actuator_gainprm, model.actuator_biasprm)
  assert tuple(fields) == MODEL_FIELDS
  own = lambda name: model.opt.gravity if name == "opt.gravity" else getattr(model, name)
  for name, value in fields.items():
    np.testing.assert_allclose(value, np.float32(own(name)), rtol=1e-6, err_msg=name)
  batched = model_fields(type(params)(**{k: np.stack([v, v]) for k, v in vars(params).items()}),
                         model.actuator_gainprm, model.actuator_biasprm)
  assert batched["actuator_biasprm"].shape == (2,) + model.actuator_biasprm.shape
