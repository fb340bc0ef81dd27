"""Physics backends behind one `Backend` protocol (see view.py).

`make_backend` picks one by name so the environment never imports an engine directly:
"mjx" (MuJoCo MJX, JAX implementation; the accelerator path) or "native" (C MuJoCo through
`mujoco.batch`, imported lazily so a missing or broken native module never breaks MJX users).
"""

from __future__ import annotations

import mujoco

from jax_env.physics.view import Backend, ModelParams, PhysicsView, model_params

BACKENDS = ("mjx", "native")


def make_backend(name: str, mj_model: mujoco.MjModel, **kwargs) -> Backend:
  """A backend stepping `mj_model`; kwargs go to the backend's constructor."""
  if name == "mjx":
    from jax_env.physics.mjx_backend import MjxBackend
    return MjxBackend(mj_model, **kwargs)
  if name == "native":
    from jax_env.physics.native_backend import NativeBackend
    return NativeBackend(mj_model, **kwargs)
  raise ValueError(f"unknown physics backend {name!r}; valid: {', '.join(BACKENDS)}")


def nominal_params(mj_model: mujoco.MjModel, batch: int) -> ModelParams:
  """The model's own parameters broadcast to a batch (no randomization)."""
  import jax
  import jax.numpy as jnp

  return jax.tree_util.tree_map(lambda x: jnp.broadcast_to(jnp.asarray(x), (batch,) + x.shape),
                                model_params(mj_model))


__all__ = ["BACKENDS", "Backend", "ModelParams", "PhysicsView", "make_backend",
           "nominal_params"]
