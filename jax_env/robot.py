"""The Booster T1 as the rest of the code sees it: names, groups, limits, mirror maps.

Everything that crosses module or language boundaries (joint, body and contact-body names,
their order, keyframe names) is pinned in docs/contracts.md and repeated here as plain
tuples, so that importing this module never compiles MuJoCo. Numbers that live in the
model (gains, torque limits, ranges) are read from the compiled model by `joint_arrays`,
so that the XML stays the single source for them; the one limit MuJoCo has no field for
(joint velocity) is a URDF-A table here.

Mirror maps (left <-> right reflection through the robot's sagittal x-z plane):
  * joints: `x_mirrored = x[JOINT_MIRROR_PERM] * JOINT_MIRROR_SIGN`. A reflection turns a
    rotation by q about axis a into a rotation by -q about the reflected axis. Every T1
    joint axis is a body-frame x, y or z axis, and all body frames are parallel at zero
    pose, so pitch joints (axis y, which the reflection flips) keep their sign and roll /
    yaw joints (axes x, z) change it. `mirror_signs_from_model` re-derives the signs from
    the model's actual axes (the tests check both agree).
  * base-frame 3-vectors: positions, linear velocities, projected gravity, forces
    (true vectors) map (x, y, z) -> (x, -y, z) (`mirror_vec3`); angular velocities and
    torques (pseudo-vectors) map (x, y, z) -> (-x, y, -z) (`mirror_pseudovec3`).
  * quaternions (w, x, y, z) -> (w, -x, y, -z) (`mirror_quat`).
  * per-joint scalars that are not angles (gains, gain scales, limits, torque limits as
    magnitudes): permute only, `mirror_joint_scalars`.
  * bodies: `BODY_MIRROR_PERM` over BODY_NAMES, `CONTACT_MIRROR_PERM` over CONTACT_BODIES;
    a per-body vector (e.g. a CoM offset) is permuted AND mirrored with `mirror_vec3`.
All permutations are involutions, and every sign vector squares to one.

Examples for observation features (docs/contracts.md): `gravity/*` is a true vector,
`ang_vel/*` a pseudo-vector, `joint_pos|joint_vel|prev_action/<J>` are joint vectors;
`push_force/*` is a true vector, `push_torque/*` a pseudo-vector; `mass_scale/<B>`,
`kp_scale/<J>` permute only; `com_offset/<B>/*` permute and flip y; `contact/<B>` permute.

Contact sensors `contact/<body>` report the NUMBER of contacts between that body's single
collision geom and the floor (MuJoCo `data="found"`); treat > 0 as touching.
"""

from __future__ import annotations

import dataclasses
import functools

import mujoco
import numpy as np

from jax_env import paths

# Canonical joint order: qpos[7:], qvel[6:], actuator order (T1-FACTS §1).
JOINT_NAMES: tuple[str, ...] = (
    "AAHead_yaw", "Head_pitch",
    "Left_Shoulder_Pitch", "Left_Shoulder_Roll", "Left_Elbow_Pitch", "Left_Elbow_Yaw",
    "Right_Shoulder_Pitch", "Right_Shoulder_Roll", "Right_Elbow_Pitch", "Right_Elbow_Yaw",
    "Waist",
    "Left_Hip_Pitch", "Left_Hip_Roll", "Left_Hip_Yaw", "Left_Knee_Pitch",
    "Left_Ankle_Pitch", "Left_Ankle_Roll",
    "Right_Hip_Pitch", "Right_Hip_Roll", "Right_Hip_Yaw", "Right_Knee_Pitch",
    "Right_Ankle_Pitch", "Right_Ankle_Roll",
)
NUM_JOINTS = len(JOINT_NAMES)

# Robot bodies in model order; model body id = index + 1 (0 is the world).
BODY_NAMES: tuple[str, ...] = (
    "Trunk", "H1", "H2", "AL1", "AL2", "AL3", "left_hand_link", "AR1", "AR2", "AR3",
    "right_hand_link", "Waist", "Hip_Pitch_Left", "Hip_Roll_Left", "Hip_Yaw_Left",
    "Shank_Left", "Ankle_Cross_Left", "left_foot_link", "Hip_Pitch_Right",
    "Hip_Roll_Right", "Hip_Yaw_Right", "Shank_Right", "Ankle_Cross_Right",
    "right_foot_link",
)

# The feet (left, right): the support the centre of mass must come over to stand.
FOOT_BODIES: tuple[str, str] = ("left_foot_link", "right_foot_link")

# Bodies with floor-contact sensors `contact/<body>` (sensor order = this order).
CONTACT_BODIES: tuple[str, ...] = (
    "Trunk", "H2", "AL3", "left_hand_link", "AR3", "right_hand_link", "Waist",
    "Hip_Yaw_Left", "Shank_Left", "left_foot_link", "Hip_Yaw_Right", "Shank_Right",
    "right_foot_link",
)
CONTACT_SENSOR_NAMES: tuple[str, ...] = tuple(f"contact/{b}" for b in CONTACT_BODIES)

# IMU sensors at the `imu` site (Trunk origin).
IMU_SITE = "imu"
GYRO_SENSOR = "gyro"
ACCELEROMETER_SENSOR = "accelerometer"
ORIENTATION_SENSOR = "orientation"
LOCAL_LINVEL_SENSOR = "local_linvel"

FLOOR_GEOM = "floor"
OBSTACLE_BODY = "obstacle"

# Joints that move in the sagittal (x-z) plane; Elbow_Yaw is the elbow flexion of this
# robot (T1-FACTS §8), Elbow_Pitch is humeral rotation.
SAGITTAL_JOINTS: tuple[str, ...] = (
    "Left_Shoulder_Pitch", "Left_Elbow_Yaw", "Right_Shoulder_Pitch", "Right_Elbow_Yaw",
    "Left_Hip_Pitch", "Left_Knee_Pitch", "Left_Ankle_Pitch",
    "Right_Hip_Pitch", "Right_Knee_Pitch", "Right_Ankle_Pitch",
)
LATERAL_JOINTS: tuple[str, ...] = ("Left_Hip_Roll", "Right_Hip_Roll")
HELD_JOINTS: tuple[str, ...] = tuple(
    j for j in JOINT_NAMES if j not in SAGITTAL_JOINTS and j not in LATERAL_JOINTS)

KEYFRAME_NAMES: tuple[str, ...] = (
    "stand", "ksi_prone_1", "ksi_prone_2", "ksi_prone_3",
    "ksi_supine_1", "ksi_supine_2", "ksi_supine_3",
)

# Actuator group of every joint (the MJCF default class that sets its gains and limits).
JOINT_GROUP: dict[str, str] = {
    "AAHead_yaw": "head", "Head_pitch": "head",
    **{f"{s}_{j}": "arm" for s in ("Left", "Right")
       for j in ("Shoulder_Pitch", "Shoulder_Roll", "Elbow_Pitch", "Elbow_Yaw")},
    "Waist": "waist",
    **{f"{s}_Hip_Pitch": "hip_pitch" for s in ("Left", "Right")},
    **{f"{s}_Hip_Roll": "hip_roll" for s in ("Left", "Right")},
    **{f"{s}_Hip_Yaw": "hip_yaw" for s in ("Left", "Right")},
    **{f"{s}_Knee_Pitch": "knee" for s in ("Left", "Right")},
    **{f"{s}_Ankle_Pitch": "ankle_pitch" for s in ("Left", "Right")},
    **{f"{s}_Ankle_Roll": "ankle_roll" for s in ("Left", "Right")},
}

# Joint velocity limits in rad/s, URDF-A (T1-FACTS §4). MuJoCo has no field for them.
GROUP_VELOCITY_LIMIT: dict[str, float] = {
    "head": 12.56, "arm": 18.84, "waist": 10.88, "hip_pitch": 12.5, "hip_roll": 10.9,
    "hip_yaw": 10.9, "knee": 11.7, "ankle_pitch": 18.8, "ankle_roll": 12.4,
}
VELOCITY_LIMITS = np.array(
    [GROUP_VELOCITY_LIMIT[JOINT_GROUP[j]] for j in JOINT_NAMES], dtype=np.float64)


# ---------------------------------------------------------------------------------------
# Mirror maps.


def _swap_side(name: str) -> str:
  """Left <-> right name of a joint or body (unchanged for centre-line ones)."""
  pairs = (("Left", "Right"), ("left", "right"), ("AL", "AR"))
  for a, b in pairs:
    if a in name:
      return name.replace(a, b)
    if b in name:
      return name.replace(b, a)
  return name


def _perm(names: tuple[str, ...]) -> np.ndarray:
  index = {n: i for i, n in enumerate(names)}
  return np.array([index[_swap_side(n)] for n in names], dtype=np.int32)


def _axis_sign(name: str) -> float:
  """+1 for pitch joints (body y axis), -1 for roll and yaw joints (body x or z axis)."""
  return 1.0 if name.endswith("pitch") or name.endswith("Pitch") else -1.0


JOINT_MIRROR_PERM: np.ndarray = _perm(JOINT_NAMES)
JOINT_MIRROR_SIGN: np.ndarray = np.array([_axis_sign(j) for j in JOINT_NAMES],
                                         dtype=np.float32)
BODY_MIRROR_PERM: np.ndarray = _perm(BODY_NAMES)
CONTACT_MIRROR_PERM: np.ndarray = _perm(CONTACT_BODIES)

# Sign vectors for base-frame (or world-frame) 3-vectors under y -> -y reflection.
VEC3_MIRROR_SIGN = np.array([1.0, -1.0, 1.0], dtype=np.float32)
PSEUDOVEC3_MIRROR_SIGN = np.array([-1.0, 1.0, -1.0], dtype=np.float32)
QUAT_MIRROR_SIGN = np.array([1.0, -1.0, 1.0, -1.0], dtype=np.float32)


def mirror_joint_vector(x):
  """Mirrors a [..., 23] joint-space vector (positions, velocities, targets, torques)."""
  return x[..., JOINT_MIRROR_PERM] * JOINT_MIRROR_SIGN.astype(x.dtype)


def mirror_joint_scalars(x):
  """Mirrors [..., 23] per-joint magnitudes (gains, scales, limits): permutation only."""
  return x[..., JOINT_MIRROR_PERM]


def mirror_vec3(v):
  """Mirrors [..., 3] true vectors (positions, linear velocity, gravity, force)."""
  return v * VEC3_MIRROR_SIGN.astype(v.dtype)


def mirror_pseudovec3(w):
  """Mirrors [..., 3] pseudo-vectors (angular velocity, torque): x and z flip."""
  return w * PSEUDOVEC3_MIRROR_SIGN.astype(w.dtype)


def mirror_quat(q):
  """Mirrors [..., 4] orientations (w, x, y, z): M R M is (w, -x, y, -z)."""
  return q * QUAT_MIRROR_SIGN.astype(q.dtype)


# Indices of the right side's joints in JOINT_NAMES.
RIGHT_JOINTS = [i for i, name in enumerate(JOINT_NAMES) if name.startswith("Right_")]


def mirror_left_to_right(joints: np.ndarray) -> np.ndarray:
  """[23] joints with the right side set to the mirror image of the left (roll and yaw joints
  change sign); centre-line joints unchanged."""
  q = np.array(joints, copy=True)
  q[RIGHT_JOINTS] = np.asarray(mirror_joint_vector(q))[RIGHT_JOINTS]
  return q


def mirror_qpos(qpos):
  """Mirrors a full [..., 30] qpos (free joint position + quaternion, then joints)."""
  return np.concatenate([
      mirror_vec3(qpos[..., 0:3]), mirror_quat(qpos[..., 3:7]),
      mirror_joint_vector(qpos[..., 7:])], axis=-1)


def mirror_qvel(qvel):
  """Mirrors a full [..., 29] qvel (world linear, local angular velocity, joints)."""
  return np.concatenate([
      mirror_vec3(qvel[..., 0:3]), mirror_pseudovec3(qvel[..., 3:6]),
      mirror_joint_vector(qvel[..., 6:])], axis=-1)


def mirror_signs_from_model(model: mujoco.MjModel) -> np.ndarray:
  """Joint mirror signs derived from the model's joint axes at zero pose.

  Reflection M = diag(1, -1, 1) maps a rotation by q about a to a rotation by -q about
  M a. With M a_i = s a_j (j the mirror joint of i), that is a rotation by -s q about
  a_j, so the sign is -(M a_i . a_j), both axes expressed in the Trunk frame.
  """
  data = mujoco.MjData(model)
  data.qpos[:] = 0.0
  data.qpos[3] = 1.0
  mujoco.mj_kinematics(model, data)
  m = np.array([1.0, -1.0, 1.0])
  signs = np.zeros(NUM_JOINTS)
  for i, name in enumerate(JOINT_NAMES):
    a_i = data.xaxis[model.joint(name).id]
    a_j = data.xaxis[model.joint(JOINT_NAMES[JOINT_MIRROR_PERM[i]]).id]
    signs[i] = -float(np.dot(m * a_i, a_j))
  return signs


# ---------------------------------------------------------------------------------------
# The compiled model.


class ModelMismatchError(ValueError):
  """The compiled MJCF does not have the names or order the contracts pin."""


def _check_model(model: mujoco.MjModel) -> None:
  """Fails loudly if the MJCF drifted from the contract's names and orders."""
  joints = tuple(model.joint(i).name for i in range(1, model.njnt))
  if model.jnt_type[0] != mujoco.mjtJoint.mjJNT_FREE or joints != JOINT_NAMES:
    raise ModelMismatchError(f"joint order {joints} is not the canonical {JOINT_NAMES}")
  actuators = tuple(model.actuator(i).name for i in range(model.nu))
  targets = tuple(model.joint(model.actuator_trnid[i, 0]).name for i in range(model.nu))
  if actuators != JOINT_NAMES or targets != JOINT_NAMES:
    raise ModelMismatchError(f"actuator order {targets} is not {JOINT_NAMES}")
  bodies = tuple(model.body(i).name for i in range(1, 1 + len(BODY_NAMES)))
  if bodies != BODY_NAMES:
    raise ModelMismatchError(f"body order {bodies} is not {BODY_NAMES}")
  keys = {model.key(i).name for i in range(model.nkey)}
  missing = [k for k in KEYFRAME_NAMES if k not in keys]
  if missing:
    raise ModelMismatchError(f"keyframes {missing} missing; the model has {sorted(keys)}")


def load_model(path=None) -> mujoco.MjModel:
  """Compiles assets/t1/scene.xml (robot + floor + obstacle + keyframes)."""
  model = mujoco.MjModel.from_xml_path(str(path or paths.SCENE_XML))
  _check_model(model)
  return model


@functools.cache
def _cached_model() -> mujoco.MjModel:
  return load_model()


def keyframe(model: mujoco.MjModel, name: str) -> tuple[np.ndarray, np.ndarray]:
  """(qpos, qvel) copies of the named keyframe."""
  names = [model.key(i).name for i in range(model.nkey)]
  if name not in names:
    raise ValueError(f"unknown keyframe {name!r}; valid keyframes: {', '.join(names)}")
  key = model.key(name)
  return np.array(key.qpos, dtype=np.float64), np.array(key.qvel, dtype=np.float64)


def stand_pose(model: mujoco.MjModel | None = None) -> np.ndarray:
  """[23] joint positions of the `stand` keyframe (the PD default of held joints)."""
  qpos, _ = keyframe(model if model is not None else _cached_model(), "stand")
  return qpos[7:].copy()


@dataclasses.dataclass(frozen=True)
class JointArrays:
  """Per-joint numbers in canonical order, as the compiled model holds them."""

  torque_limit: np.ndarray  # [23] N·m, actuator forcerange upper bound (URDF-A effort)
  velocity_limit: np.ndarray  # [23] rad/s, URDF-A
  kp: np.ndarray  # [23] N·m/rad, actuator gainprm[0]
  kd: np.ndarray  # [23] N·m·s/rad, -actuator biasprm[2]
  armature: np.ndarray  # [23] kg·m²
  frictionloss: np.ndarray  # [23] N·m
  range_low: np.ndarray  # [23] rad
  range_high: np.ndarray  # [23] rad


def joint_arrays(model: mujoco.MjModel | None = None) -> JointArrays:
  """Reads gains, limits and ranges of the 23 joints from the compiled model."""
  model = model if model is not None else _cached_model()
  jnt = np.array([model.joint(j).id for j in JOINT_NAMES])
  dof = model.jnt_dofadr[jnt]
  return JointArrays(
      torque_limit=model.actuator_forcerange[:, 1].copy(),
      velocity_limit=VELOCITY_LIMITS.copy(),
      kp=model.actuator_gainprm[:, 0].copy(),
      kd=-model.actuator_biasprm[:, 2].copy(),
      armature=model.dof_armature[dof].copy(),
      frictionloss=model.dof_frictionloss[dof].copy(),
      range_low=model.jnt_range[jnt, 0].copy(),
      range_high=model.jnt_range[jnt, 1].copy(),
  )


def body_ids(model: mujoco.MjModel, names=BODY_NAMES) -> np.ndarray:
  """Model body ids of the given bodies."""
  return np.array([model.body(b).id for b in names], dtype=np.int32)


def sensor_slice(model: mujoco.MjModel, name: str) -> slice:
  """Where the named sensor's values sit in `sensordata`."""
  sensor = model.sensor(name)
  adr = int(sensor.adr[0])
  return slice(adr, adr + int(sensor.dim[0]))
