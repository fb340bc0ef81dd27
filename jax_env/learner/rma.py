"""Rapid Motor Adaptation (Kumar et al. 2021/2022), as the paper's training section cites it.

Phase 1 (PPO): the environment-factor encoder maps the privileged features (friction, masses,
gains, delay, contacts, pushes, terrain, ...) to a latent z; the base policy reads the normalized
proprioceptive observation (which includes the previous action) together with z. Encoder and
policy are trained end to end by PPO (see ppo.py).

Phase 2 (adaptation): the adaptation module (networks.AdaptationModule, a 1-D convolution over
the last `history_len` observations) regresses z. The data are collected while acting with the
module's OWN estimate z_hat (deterministic mean actions, as deployed), so the module learns on
the state distribution it will itself induce, which is what makes RMA robust to estimation
errors. The regression target z = encoder(privileged) is frozen, as are the base policy and
the observation statistics. The deployable actor is then adaptation module + base policy; it
reads only obs and the observation history (networks.deployable_mean).

Regularized online adaptation (ROA; Fu, Cheng and Pathak, "Deep Whole-Body Control", CoRL
2022), `[stage.rma] latent_regularization` > 0: the module also learns during PPO, on the PPO
rollout's windows (`adaptation_update` after every PPO update), and PPO's loss pulls the
encoder's latent toward the module's estimate with that weight. Kumar et al.'s encoder may put
into z what no observation history reveals (a push, a contact, the height); the policy then
leans on a latent the deployable actor cannot reproduce, and the deployable actor loses what
the privileged one has. The regularization keeps z estimable while PPO still shapes it.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import optax
from flax import struct

from jax_env.learner import networks as nets_lib
from jax_env.learner import ppo as ppo_lib


@struct.dataclass
class AdaptationBatch:
  """[T, B, ...] collected while acting with the adaptation module's estimate."""

  window: jax.Array  # [T, B, H, n_obs] raw observation windows (the module's input)
  privileged: jax.Array  # [T, B, n_priv]


def latent_targets(nets: nets_lib.Networks, params: dict, normalizer,
                   privileged: jax.Array) -> jax.Array:
  """z = encoder(normalized privileged): the regression target (no gradient)."""
  priv_n = nets_lib.normalize_privileged(normalizer, privileged)
  return jax.lax.stop_gradient(nets.encode(params["encoder"], priv_n))


def adaptation_loss(adaptation_params: dict, normalizer, window: jax.Array, target: jax.Array,
                    nets: nets_lib.Networks) -> jax.Array:
  """Mean squared latent error of the adaptation module on a batch of windows."""
  z_hat = nets_lib.estimate_latent(nets, adaptation_params["adaptation"], normalizer, window)
  return jnp.mean(jnp.square(z_hat - target))


def adaptation_update(state: ppo_lib.LearnerState, batch: AdaptationBatch, key: jax.Array, *,
                      nets: nets_lib.Networks, cfg, learning_rate: float,
                      axis_name: str | None = None):
  """`cfg.update_epochs` passes of minibatch Adam steps on the latent regression.

  Returns (state, metrics) with metrics["adaptation"] the mean error over the steps and
  metrics["adaptation_before"] the error of the module that collected the batch.
  """
  params = state.params
  targets = latent_targets(nets, params, state.normalizer, batch.privileged)
  samples = {"window": batch.window, "target": targets}
  samples = jax.tree_util.tree_map(lambda x: x.reshape((-1,) + x.shape[2:]), samples)
  n = samples["window"].shape[0]
  optimizer = ppo_lib.make_optimizer(cfg.max_grad_norm)
  grad_fn = jax.value_and_grad(adaptation_loss)

  def pmean(x):
    return x if axis_name is None else jax.lax.pmean(x, axis_name)

  def minibatch_step(carry, mb):
    ada_params, opt_state = carry
    loss, grads = grad_fn(ada_params, state.normalizer, mb["window"], mb["target"], nets)
    updates, opt_state = optimizer.update(pmean(grads), opt_state)
    ada_params = optax.apply_updates(
        ada_params, jax.tree_util.tree_map(lambda u: -learning_rate * u, updates))
    return (ada_params, opt_state), loss

  def epoch(carry, key_perm):
    perm = jax.random.permutation(key_perm, n)
    shuffled = jax.tree_util.tree_map(
        lambda x: x[perm].reshape((cfg.num_minibatches, -1) + x.shape[1:]), samples)
    return jax.lax.scan(minibatch_step, carry, shuffled)

  before = adaptation_loss(ppo_lib.adaptation_params(params), state.normalizer,
                           samples["window"], samples["target"], nets)
  (ada_params, opt_state), losses = jax.lax.scan(
      epoch, (ppo_lib.adaptation_params(params), state.adapt_opt_state),
      jax.random.split(key, cfg.update_epochs))
  new_params = dict(params)
  new_params.update(ada_params)
  metrics = {"adaptation": pmean(jnp.mean(losses)), "adaptation_before": pmean(before)}
  return state.replace(params=new_params, adapt_opt_state=opt_state), metrics
