"""The feature layout: what every observation, privileged-observation and action index means
(docs/contracts.md, "Feature names").

A layout is an ordered tuple of segments `(prefix, labels)`: the features `prefix/label` for
each label, a bare `prefix` when labels is None, or `prefix/<J>` for the joints of a stage's
`observed_joints` / `controlled_joints` (canonical order) when labels names that list. The
environment assembles its observation vectors segment by segment from these layouts
(`assemble`), the feature names are expanded from them (`feature_names`), and
`jax_env/names.json` exports them for the Rust CLI, which expands the same layout for checkpoint
expansion. Checkpoint expansion matches tensor rows and columns by these names, so the layout
is the one place that fixes the order.
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

from jax_env import robot
from jax_env.stage_config import StageConfig

AXES: tuple[str, ...] = ("x", "y", "z")
OBSERVED_JOINTS = "observed_joints"
CONTROLLED_JOINTS = "controlled_joints"

# (prefix, labels) segments; see the module docstring.
Layout = tuple[tuple[str, tuple[str, ...] | str | None], ...]

OBS_LAYOUT: Layout = (
    ("gravity", AXES),  # gravity direction in the IMU (Trunk) frame
    ("ang_vel", AXES),  # gyro, IMU frame
    ("joint_pos", OBSERVED_JOINTS),  # relative to the `stand` keyframe
    ("joint_vel", OBSERVED_JOINTS),
    ("prev_action", CONTROLLED_JOINTS),
)

# The same in every stage, so the critic and encoder inputs never change size for a reason
# other than the observed/controlled joints.
PRIVILEGED_LAYOUT: Layout = (
    ("friction", None),
    ("compliance", None),
    ("restitution", None),
    ("mass_scale", robot.BODY_NAMES),
    ("com_offset", tuple(f"{b}/{a}" for b in robot.BODY_NAMES for a in AXES)),
    ("kp_scale", robot.JOINT_NAMES),
    ("kd_scale", robot.JOINT_NAMES),
    ("torque_limit_scale", None),
    ("delay", None),
    ("base_height", None),
    ("base_lin_vel", AXES),  # world frame
    ("contact", robot.CONTACT_BODIES),
    ("push_force", AXES),  # world frame
    ("push_torque", AXES),
    ("terrain", ("slope_x", "slope_y", "obstacle")),  # ground tilt (rad), obstacle (0/1)
)

# The action vector: one entry per controlled joint, named by the bare joint name.
ACTION_LAYOUT = CONTROLLED_JOINTS


def _labels(labels, stage: StageConfig | None) -> tuple[str, ...] | None:
  if isinstance(labels, str):
    return tuple(getattr(stage, labels))
  return labels


def expand(layout: Layout, stage: StageConfig | None = None) -> tuple[str, ...]:
  """The feature names of a layout (`stage` supplies the joint lists it refers to)."""
  names = []
  for prefix, labels in layout:
    labels = _labels(labels, stage)
    names += [prefix] if labels is None else [f"{prefix}/{label}" for label in labels]
  return tuple(names)


def assemble(layout: Layout, parts: Mapping[str, Any], stage: StageConfig | None = None):
  """The feature vectors [B, n] of a layout from one array [B, width] per segment prefix."""
  import jax.numpy as jnp
  if set(parts) != {prefix for prefix, _ in layout}:
    raise ValueError(f"segments {sorted(parts)} do not match the layout's "
                     f"{[prefix for prefix, _ in layout]}")
  columns = []
  for prefix, labels in layout:
    labels = _labels(labels, stage)
    width = 1 if labels is None else len(labels)
    if parts[prefix].shape[-1] != width:
      raise ValueError(f"segment {prefix!r} has {parts[prefix].shape[-1]} columns, the layout "
                       f"{width}")
    columns.append(parts[prefix])
  return jnp.concatenate(columns, axis=-1)


def privileged_names() -> tuple[str, ...]:
  return expand(PRIVILEGED_LAYOUT)


def feature_names(stage) -> tuple[tuple[str, ...], tuple[str, ...], tuple[str, ...]]:
  """(obs_names, privileged_names, action_names) of a stage (StageConfig or stage dict)."""
  s = stage if isinstance(stage, StageConfig) else StageConfig.from_dict(stage)
  return expand(OBS_LAYOUT, s), privileged_names(), _labels(ACTION_LAYOUT, s)


def export() -> dict:
  """The layouts as JSON data for the Rust CLI (privileged names expanded: they are static)."""
  return {
      "obs": [{"prefix": prefix, "labels": list(labels) if isinstance(labels, tuple) else labels}
              for prefix, labels in OBS_LAYOUT],
      "privileged": list(privileged_names()),
      "action": ACTION_LAYOUT,
  }


# ---------------------------------------------------------------------------------------------
# Mirror maps over feature lists.


def mirror_joint_name(joint: str) -> str:
  """The left/right partner of a joint (itself for centre-line joints)."""
  return robot.JOINT_NAMES[int(robot.JOINT_MIRROR_PERM[robot.JOINT_NAMES.index(joint)])]


def _mirror_body(body: str) -> str:
  return robot.BODY_NAMES[int(robot.BODY_MIRROR_PERM[robot.BODY_NAMES.index(body)])]


_VEC_SIGN = {"x": 1.0, "y": -1.0, "z": 1.0}  # true vectors under the y -> -y reflection
_PSEUDO_SIGN = {"x": -1.0, "y": 1.0, "z": -1.0}  # angular velocities, torques


def mirror_feature(name: str, kind: str = "obs") -> tuple[str, float]:
  """The left/right mirror of a feature: (mirrored feature's name, sign).

  mirror(x)[i] = sign_i · x[index of name_i's mirror]. Joints swap sides and flip sign for roll
  and yaw axes (robot.JOINT_MIRROR_SIGN); bodies swap sides; lateral components of vectors
  (gravity y, base velocity y, CoM offset y, push force y, slope_y) and the x/z components of
  pseudo-vectors (angular velocity, push torque) flip sign. `kind="action"` reads bare joint
  names.
  """
  if kind == "action":
    j = robot.JOINT_NAMES.index(name)
    return mirror_joint_name(name), float(robot.JOINT_MIRROR_SIGN[j])
  parts = name.split("/")
  head = parts[0]
  if head in ("joint_pos", "joint_vel", "prev_action"):
    j = robot.JOINT_NAMES.index(parts[1])
    return f"{head}/{mirror_joint_name(parts[1])}", float(robot.JOINT_MIRROR_SIGN[j])
  if head in ("kp_scale", "kd_scale"):
    return f"{head}/{mirror_joint_name(parts[1])}", 1.0
  if head in ("gravity", "base_lin_vel", "push_force"):
    return name, _VEC_SIGN[parts[1]]
  if head in ("ang_vel", "push_torque"):
    return name, _PSEUDO_SIGN[parts[1]]
  if head in ("mass_scale", "contact"):
    return f"{head}/{_mirror_body(parts[1])}", 1.0
  if head == "com_offset":
    return f"com_offset/{_mirror_body(parts[1])}/{parts[2]}", _VEC_SIGN[parts[2]]
  if name == "terrain/slope_y":
    return name, -1.0
  return name, 1.0  # scalars unchanged by the reflection


def mirror_map(names: Sequence[str], kind: str = "obs"):
  """(perm int32, sign float32) with mirror(x) = x[..., perm] * sign over a feature list."""
  import numpy as np
  index = {n: i for i, n in enumerate(names)}
  perm, sign = [], []
  for n in names:
    m, s = mirror_feature(n, kind)
    if m not in index:
      raise ValueError(f"feature {n!r} mirrors to {m!r}, which is not in the list")
    perm.append(index[m])
    sign.append(s)
  return np.array(perm, np.int32), np.array(sign, np.float32)
