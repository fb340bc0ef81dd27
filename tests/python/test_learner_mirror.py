"""The mirror loss: zero for a mirror-equivariant policy, positive otherwise, reduced by its
own gradient; computed on raw features through the real networks and normalizer."""

import jax
import numpy as np
import optax
import pytest

from jax_env.learner import mirror as mirror_lib
from jax_env.learner import networks as nets_lib
from toy_env import ToyStandUpEnv

ENV = ToyStandUpEnv()
MAPS = ENV.mirror


def _config(**kw):
  c = dict(obs_size=ENV.obs_size, privileged_size=ENV.privileged_size,
           action_size=ENV.action_size, policy_hidden=(16, 16), value_hidden=(16,),
           activation="elu", rma=True, latent_dim=2, encoder_hidden=(8,), history_len=4,
           initial_action_std=0.5)
  c.update(kw)
  return nets_lib.NetworkConfig(**c)


def _batch(n=256, seed=0):
  state = ENV.reset(jax.random.split(jax.random.PRNGKey(seed), n))
  k1, k2 = jax.random.split(jax.random.PRNGKey(seed + 1))
  # Spread the inputs beyond the reset distribution so every feature matters.
  obs = state.obs + jax.random.normal(k1, state.obs.shape)
  priv = state.privileged + 0.3 * jax.random.normal(k2, state.privileged.shape)
  return obs, priv


def test_maps_are_involutions_and_checked():
  mirror_lib.check_maps(MAPS, ENV.obs_size, ENV.privileged_size, ENV.action_size)
  x = np.arange(ENV.obs_size, dtype=np.float32)[None]
  twice = mirror_lib.apply_map(mirror_lib.apply_map(x, MAPS.obs_perm, MAPS.obs_sign),
                               MAPS.obs_perm, MAPS.obs_sign)
  np.testing.assert_array_equal(twice, x)
  bad = MAPS.__class__(**{**MAPS.__dict__, "action_perm": np.array([0, 0], np.int32)})
  with pytest.raises(ValueError, match="action is not an involution"):
    mirror_lib.check_maps(bad, ENV.obs_size, ENV.privileged_size, ENV.action_size)


def test_zero_for_equivariant_policy_positive_otherwise():
  nets = nets_lib.Networks(_config())
  params = nets.init(jax.random.PRNGKey(1))
  normalizer = nets_lib.init_normalizer(nets.config)
  obs, priv = _batch()

  def mean_fn(o, p):
    return nets_lib.privileged_mean(nets, params, normalizer, o, p)

  def symmetrized(o, p):  # μ_sym(s) = ½(μ(s) + M_a μ(M_s s)) is equivariant by construction
    mo = mirror_lib.apply_map(o, MAPS.obs_perm, MAPS.obs_sign)
    mp = mirror_lib.apply_map(p, MAPS.privileged_perm, MAPS.privileged_sign)
    return 0.5 * (mean_fn(o, p) + mirror_lib.apply_map(mean_fn(mo, mp), MAPS.action_perm,
                                                       MAPS.action_sign))

  raw = float(mirror_lib.mirror_error(mean_fn, obs, priv, MAPS))
  sym = float(mirror_lib.mirror_error(symmetrized, obs, priv, MAPS))
  assert raw > 1e-4, raw
  assert sym < 1e-10, sym


def test_gradient_reduces_mirror_loss():
  nets = nets_lib.Networks(_config())
  params = nets.init(jax.random.PRNGKey(2))
  normalizer = nets_lib.init_normalizer(nets.config)
  obs, priv = _batch(seed=3)

  def loss(p):
    return mirror_lib.mirror_error(
        lambda o, q: nets_lib.privileged_mean(nets, p, normalizer, o, q), obs, priv, MAPS)

  opt = optax.adam(3e-3)
  state = opt.init(params)
  start = float(loss(params))

  @jax.jit
  def step(p, s):
    g = jax.grad(loss)(p)
    u, s = opt.update(g, s)
    return optax.apply_updates(p, u), s

  for _ in range(100):
    params, state = step(params, state)
  end = float(loss(params))
  assert end < 0.2 * start, (start, end)

