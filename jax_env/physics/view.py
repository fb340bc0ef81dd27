"""The small window through which the environment reads and drives physics.

Both backends (MJX and C MuJoCo through `mujoco.batch`) implement `Backend`, so rewards,
observations and randomization are written once against `PhysicsView` and `ModelParams`.
Every array carries a leading batch axis B.
"""

from __future__ import annotations

from typing import Any, Protocol

import jax
from flax import struct


@struct.dataclass
class ModelParams:
  """Per-environment physical parameters, drawn fresh at every episode reset."""

  geom_friction: jax.Array  # [B, ngeom, 3]
  geom_solref: jax.Array  # [B, ngeom, 2]
  body_mass: jax.Array  # [B, nbody]
  body_ipos: jax.Array  # [B, nbody, 3]
  body_inertia: jax.Array  # [B, nbody, 3]
  actuator_kp: jax.Array  # [B, nu]   -> gainprm[0] = kp, biasprm[1] = -kp
  actuator_kd: jax.Array  # [B, nu]   -> biasprm[2] = -kd
  actuator_forcerange: jax.Array  # [B, nu, 2]
  gravity: jax.Array  # [B, 3]


@struct.dataclass
class PhysicsView:
  """What the environment may read after a step."""

  time: jax.Array  # [B]
  qpos: jax.Array  # [B, nq]
  qvel: jax.Array  # [B, nv]
  qacc: jax.Array  # [B, nv]
  actuator_force: jax.Array  # [B, nu]
  sensordata: jax.Array  # [B, nsensordata]
  xpos: jax.Array  # [B, nbody, 3]
  xquat: jax.Array  # [B, nbody, 4]  (w, x, y, z)


class Backend(Protocol):
  """A batched physics engine over one compiled `mujoco.MjModel`."""

  name: str

  def init(self, qpos: jax.Array, qvel: jax.Array, params: ModelParams,
           mocap_pos: jax.Array) -> Any:
    """Physics state [B] at the given configuration, derived quantities computed."""

  def step(self, state: Any, params: ModelParams, ctrl: jax.Array,
           xfrc_applied: jax.Array) -> Any:
    """Advance ctrl.shape[1] physics substeps; ctrl is [B, n_substeps, nu]."""

  def view(self, state: Any) -> PhysicsView:
    """The readable quantities of a physics state."""
