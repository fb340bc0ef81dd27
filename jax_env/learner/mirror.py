"""Mirror (left/right symmetry) loss.

The paper adds "a mirror loss term to encourage symmetric strategies while allowing asymmetry":

    L_mirror = w · mean_batch ‖μ(s) − M_a(μ(M_s(s)))‖²

where M_s mirrors a state (observations AND the privileged features the RMA latent is computed
from) and M_a mirrors an action. Every map is `x[..., perm] * sign` (the environment's
`MirrorMaps`); they are applied to RAW features, before normalization, because the running
statistics themselves need not be symmetric (a mirror-equivariant policy is one that commutes
with the reflection of the robot, not of its normalized inputs). It is a soft penalty, so the
policy may still break symmetry where that pays (the paper's "allowing asymmetry").
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp


def apply_map(x: jax.Array, perm, sign) -> jax.Array:
  """mirror(x) = x[..., perm] * sign."""
  return jnp.take(x, jnp.asarray(perm), axis=-1) * jnp.asarray(sign, x.dtype)


def mirror_error(mean_fn: Callable[[jax.Array, jax.Array], jax.Array], obs: jax.Array,
                 privileged: jax.Array, maps) -> jax.Array:
  """mean over the batch of ‖μ(s) − M_a(μ(M_s(s)))‖² (unweighted).

  `mean_fn(obs, privileged)` is the policy mean on raw features (it normalizes and encodes
  internally); gradients flow through both evaluations.
  """
  mu = mean_fn(obs, privileged)
  mu_of_mirror = mean_fn(apply_map(obs, maps.obs_perm, maps.obs_sign),
                         apply_map(privileged, maps.privileged_perm, maps.privileged_sign))
  diff = mu - apply_map(mu_of_mirror, maps.action_perm, maps.action_sign)
  return jnp.mean(jnp.sum(jnp.square(diff), axis=-1))


def check_maps(maps, obs_size: int, privileged_size: int, action_size: int) -> None:
  """Raises ValueError unless every map has the right size and is an involution."""
  import numpy as np
  for kind, n in (("obs", obs_size), ("privileged", privileged_size), ("action", action_size)):
    perm = np.asarray(getattr(maps, f"{kind}_perm"))
    sign = np.asarray(getattr(maps, f"{kind}_sign"))
    if perm.shape != (n,) or sign.shape != (n,):
      raise ValueError(f"mirror map for {kind} has shape {perm.shape}/{sign.shape}, "
                       f"expected ({n},)")
    if not np.array_equal(perm[perm], np.arange(n)) or not np.all(sign[perm] * sign == 1):
      raise ValueError(f"mirror map for {kind} is not an involution")
