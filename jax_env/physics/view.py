"""The small window through which the environment reads and drives physics.

Both backends (MJX and C MuJoCo through `mujoco.batch`) implement `Backend`, so rewards,
observations and randomization are written once against `PhysicsView` and `ModelParams`.
Every array carries a leading batch axis B.
"""

from __future__ import annotations

from typing import Any, Protocol

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
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


# The model fields that realise a `ModelParams`, by their `mjx.Model.tree_replace` path (which is
# also the `mujoco.batch` field name): what both backends carry per environment.
MODEL_FIELDS = ("geom_friction", "geom_solref", "body_mass", "body_ipos", "body_inertia",
                "actuator_gainprm", "actuator_biasprm", "actuator_forcerange", "opt.gravity")


def param_shapes(m: mujoco.MjModel) -> dict[str, tuple[int, ...]]:
  """The shape of one environment's value of every `ModelParams` field."""
  return {"geom_friction": (m.ngeom, 3), "geom_solref": (m.ngeom, 2), "body_mass": (m.nbody,),
          "body_ipos": (m.nbody, 3), "body_inertia": (m.nbody, 3), "actuator_kp": (m.nu,),
          "actuator_kd": (m.nu,), "actuator_forcerange": (m.nu, 2), "gravity": (3,)}


def model_params(m: mujoco.MjModel) -> ModelParams:
  """The model's own parameters (float32, no batch axis): what `model_fields` writes back."""
  f32 = lambda x: np.asarray(x, np.float32)
  return ModelParams(
      geom_friction=f32(m.geom_friction), geom_solref=f32(m.geom_solref),
      body_mass=f32(m.body_mass), body_ipos=f32(m.body_ipos), body_inertia=f32(m.body_inertia),
      actuator_kp=f32(m.actuator_gainprm[:, 0]), actuator_kd=f32(-m.actuator_biasprm[:, 2]),
      actuator_forcerange=f32(m.actuator_forcerange), gravity=f32(m.opt.gravity))


def model_fields(params: ModelParams, gainprm, biasprm) -> dict[str, Any]:
  """The values of MODEL_FIELDS that realise `params` (NumPy or JAX arrays, batched or not).

  The actuators are position servos, force = kp·ctrl − kp·q − kd·q̇: kp sets gainprm[0] and
  biasprm[1], kd biasprm[2]; the other columns keep the model's own `gainprm` / `biasprm`
  ([nu, 10]).
  """
  xp = jnp if isinstance(params.actuator_kp, jax.Array) else np
  kp, kd = params.actuator_kp[..., None], params.actuator_kd[..., None]
  keep = lambda rows: xp.broadcast_to(rows, kp.shape[:-2] + rows.shape)
  return {
      "geom_friction": params.geom_friction,
      "geom_solref": params.geom_solref,
      "body_mass": params.body_mass,
      "body_ipos": params.body_ipos,
      "body_inertia": params.body_inertia,
      "actuator_gainprm": xp.concatenate([kp, keep(gainprm[:, 1:])], axis=-1),
      "actuator_biasprm": xp.concatenate([keep(biasprm[:, :1]), -kp, -kd, keep(biasprm[:, 3:])],
                                         axis=-1),
      "actuator_forcerange": params.actuator_forcerange,
      "opt.gravity": params.gravity,
  }


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
           mocap_pos: jax.Array, only: jax.Array | None = None) -> Any:
    """Physics state [B] at the given configuration, derived quantities computed.

    `only` [B] bool: the rows the caller keeps (an auto-reset keeps the episodes that ended);
    a backend may leave the other rows' state unspecified and skip their work."""

  def step(self, state: Any, params: ModelParams, ctrl: jax.Array,
           xfrc_applied: jax.Array) -> Any:
    """Advance ctrl.shape[1] physics substeps; ctrl is [B, n_substeps, nu]."""

  def view(self, state: Any) -> PhysicsView:
    """The readable quantities of a physics state."""
