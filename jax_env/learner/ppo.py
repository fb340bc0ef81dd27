"""PPO: losses, the minibatch-epoch update, gradient clipping and the learning-rate schedule.

Brax's parts where they fit (`losses.compute_gae`, `distribution.NormalDistribution`,
`running_statistics`, the adaptive-KL rule of `ppo.optimizer`), with what brax's `ppo.train`
cannot do: an asymmetric critic on privileged features, the RMA encoder trained end to end
with the policy, the mirror loss, masking of transitions whose action had no effect, and an
optimizer state that is plain arrays (so checkpoints can be expanded and resumed exactly).

One update (called once per iteration, inside the device-parallel step):
  1. GAE with the value function before the update (brax's `compute_gae`: the step where an
     episode was truncated by the time limit is masked, an episode ended by a blow-up is a
     termination).
  2. `update_epochs` passes over the batch in `num_minibatches` shuffled minibatches of single
     transitions; each minibatch: loss, gradients averaged over devices, global-norm clipping,
     Adam, learning rate fixed or adapted from the KL between the collecting policy and the
     current one (brax / rsl_rl rule: ÷1.5 above 2·desired_kl, ×1.5 below desired_kl/2).
  3. The running observation statistics absorb the batch AFTER the epochs, so the importance
     ratios and KL of the epochs compare policies under the same normalization (and on a
     stage's first iteration, features never seen varying take this batch's statistics).
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import optax
from brax.training.agents.ppo import losses as brax_losses
from flax import struct

from jax_env.learner import mirror as mirror_lib
from jax_env.learner import networks as nets_lib

# Bounds of the adaptive-KL learning rate (brax's defaults).
MIN_LEARNING_RATE = 1e-5
MAX_LEARNING_RATE = 1e-2

# The modules PPO trains; the adaptation module has its own optimizer (RMA phase 2).
PPO_MODULES = ("policy", "value", "encoder")


@struct.dataclass
class Transition:
  """One control step of the rollout, [T, B, ...] after the scan."""

  obs: jax.Array
  privileged: jax.Array
  action: jax.Array  # the raw Gaussian sample (the env clips it)
  loc: jax.Array  # mean of the collecting policy
  log_prob: jax.Array
  reward: jax.Array
  done: jax.Array
  truncation: jax.Array
  active: jax.Array  # 1 where the action took effect (not settling)
  # The stored get-up path's action for this state (env.teacher_action) and 1 where there is
  # one (an episode started on a path, still within it); None without [stage.imitation].
  teacher: jax.Array | None = None
  teacher_mask: jax.Array | None = None
  forced: jax.Array | None = None  # 1 where the plan's action was taken instead of the policy's
  # The adaptation module's input at this step (networks.history_window); None unless
  # [stage.rma] latent_regularization is on.
  window: jax.Array | None = None


@struct.dataclass
class LearnerState:
  """Everything the learner updates (replicated over devices)."""

  params: dict
  opt_state: Any  # (clip state, ScaleByAdamState) over the PPO modules
  adapt_opt_state: Any  # the same over the adaptation module (or over {} without RMA)
  learning_rate: jax.Array  # scalar: the current PPO learning rate (adaptive KL changes it)
  normalizer: Any  # running_statistics.RunningStatisticsState over {"obs", "privileged"}


def make_optimizer(max_grad_norm: float) -> optax.GradientTransformation:
  """Global-norm clipping then Adam without a learning rate (applied by `apply_updates`).

  The learning rate lives in `LearnerState` as an array, so the adaptive schedule, exact
  resume and checkpoints treat it like any other state. max_grad_norm = 0 disables clipping.
  """
  limit = max_grad_norm if max_grad_norm > 0 else float("inf")
  return optax.chain(optax.clip_by_global_norm(limit), optax.scale_by_adam())


def ppo_params(params: dict) -> dict:
  return {k: params[k] for k in PPO_MODULES if k in params}


def adaptation_params(params: dict) -> dict:
  return {"adaptation": params["adaptation"]} if "adaptation" in params else {}


def init_learner_state(nets: nets_lib.Networks, params: dict, max_grad_norm: float,
                       learning_rate: float) -> LearnerState:
  opt = make_optimizer(max_grad_norm)
  return LearnerState(
      params=params, opt_state=opt.init(ppo_params(params)),
      adapt_opt_state=opt.init(adaptation_params(params)),
      learning_rate=jnp.asarray(learning_rate, jnp.float32),
      normalizer=nets_lib.init_normalizer(nets.config))


def adaptive_kl_learning_rate(lr: jax.Array, kl: jax.Array, desired_kl: float) -> jax.Array:
  """Brax's / rsl_rl's rule (`brax.training.agents.ppo.optimizer.adaptive_kl_learning_rate`)."""
  lr = jnp.where(kl > desired_kl * 2.0, jnp.maximum(MIN_LEARNING_RATE, lr / 1.5), lr)
  lr = jnp.where((kl < desired_kl / 2.0) & (kl > 0.0),
                 jnp.minimum(MAX_LEARNING_RATE, lr * 1.5), lr)
  return lr


def gaussian_kl(old_loc, old_log_std, new_loc, new_log_std) -> jax.Array:
  """KL(old ‖ new) of diagonal Gaussians, summed over action dimensions."""
  old_var = jnp.exp(2 * old_log_std)
  new_var = jnp.exp(2 * new_log_std)
  return jnp.sum(new_log_std - old_log_std + (old_var + jnp.square(old_loc - new_loc))
                 / (2.0 * new_var) - 0.5, axis=-1)


def _weighted_mean(x, w):
  return jnp.sum(x * w) / jnp.maximum(jnp.sum(w), 1.0)


def compute_targets(nets: nets_lib.Networks, params: dict, normalizer, data: Transition,
                    final_obs: jax.Array, final_privileged: jax.Array, discount: float,
                    gae_lambda: float, reward_scaling: float):
  """(value targets, advantages), both [T, B], from brax's GAE with the current critic."""
  obs_n, priv_n = nets_lib.normalize(normalizer, data.obs, data.privileged)
  values = nets.value(params["value"], obs_n, priv_n)
  fin_obs_n, fin_priv_n = nets_lib.normalize(normalizer, final_obs, final_privileged)
  bootstrap = nets.value(params["value"], fin_obs_n, fin_priv_n)
  termination = data.done * (1.0 - data.truncation)
  return brax_losses.compute_gae(
      truncation=data.truncation, termination=termination,
      rewards=data.reward * reward_scaling, values=values, bootstrap_value=bootstrap,
      lambda_=gae_lambda, discount=discount)


def ppo_loss(train_params: dict, normalizer, mb: dict, nets: nets_lib.Networks, cfg,
             mirror_weight: float, maps, old_log_std: jax.Array, imitation_weight=None,
             latent_regularization: float = 0.0):
  """PPO loss on one minibatch of single transitions; returns (loss, metrics).

  mb: obs, privileged, action, loc, log_prob, target, advantage, weight (1 where the
  transition trains the policy: the action took effect and the step was not a truncation),
  teacher and teacher_weight (the path's action, and 1 where it applies and the action took
  effect). imitation_weight: [stage.imitation]'s weight × its schedule's scale (traced), or
  None without [stage.imitation] (then the loss is computed exactly as before it existed).
  latent_regularization > 0: mb also holds z_hat, the adaptation module's estimate, and the
  loss pulls the encoder's latent toward it (regularized online adaptation, rma.py).
  """
  pol = train_params["policy"]
  obs_n, priv_n = nets_lib.normalize(normalizer, mb["obs"], mb["privileged"])
  z = nets.encode(train_params["encoder"], priv_n) if nets.config.rma else None
  loc = nets.policy_mean(pol, obs_n, z)
  log_std = pol["log_std"]
  std = jnp.exp(log_std)
  dist = nets.action_distribution
  log_prob = dist.log_prob((loc, jnp.broadcast_to(std, loc.shape)), mb["action"])
  w = mb["weight"]

  adv = mb["advantage"]
  adv_mean = _weighted_mean(adv, w)
  adv_std = jnp.sqrt(_weighted_mean(jnp.square(adv - adv_mean), w))
  adv = (adv - adv_mean) / (adv_std + 1e-8)
  # A sample out of the loss (weight 0: a truncated step, or a step forced to act with a path's
  # plan, whose action can lie hundreds of nats off the policy) must not overflow the ratio:
  # inf × 0 is NaN, and one NaN ends the stage.
  ratio = jnp.exp(jnp.where(w > 0, log_prob - mb["log_prob"], 0.0))
  surrogate = jnp.minimum(ratio * adv, jnp.clip(ratio, 1 - cfg.clip_epsilon,
                                                1 + cfg.clip_epsilon) * adv)
  policy_loss = -_weighted_mean(surrogate, w)

  value = nets.value(train_params["value"], obs_n, priv_n)
  value_loss = 0.5 * cfg.value_loss_coef * jnp.mean(jnp.square(mb["target"] - value))

  # State-independent std: the entropy is the same for every sample.
  entropy = jnp.sum(0.5 + 0.5 * jnp.log(2 * jnp.pi) + log_std)
  entropy_loss = -cfg.entropy_cost * entropy

  def mean_fn(obs, privileged):
    return nets_lib.privileged_mean(nets, train_params, normalizer, obs, privileged)

  sym = mirror_lib.mirror_error(mean_fn, mb["obs"], mb["privileged"], maps)
  if mirror_weight > 0:
    mirror_loss = mirror_weight * sym
  else:
    sym = jax.lax.stop_gradient(sym)
    mirror_loss = jnp.zeros(())

  total = policy_loss + value_loss + entropy_loss + mirror_loss
  if imitation_weight is None:
    imitation_error = imitation_loss = jnp.zeros(())
  else:
    # Kickstarting from the stored paths: the policy's mean toward the plan's action.
    imitation_error = _weighted_mean(jnp.mean(jnp.square(loc - mb["teacher"]), axis=-1),
                                     mb["teacher_weight"])
    imitation_loss = imitation_weight * imitation_error
    total = total + imitation_loss
  if latent_regularization > 0:
    latent_error = jnp.mean(jnp.square(z - mb["z_hat"]))
    total = total + latent_regularization * latent_error
  kl = _weighted_mean(gaussian_kl(mb["loc"], old_log_std, jax.lax.stop_gradient(loc),
                                  jax.lax.stop_gradient(log_std)), w)
  metrics = {"total": total, "policy": policy_loss, "value": value_loss,
             "entropy": entropy_loss, "mirror": mirror_loss, "symmetry_error": sym,
             "imitation": imitation_loss, "imitation_error": imitation_error,
             "kl": kl, "clip_fraction": _weighted_mean(
                 (jnp.abs(ratio - 1) > cfg.clip_epsilon).astype(jnp.float32), w),
             "action_std": jnp.mean(std)}
  if latent_regularization > 0:
    metrics["latent_error"] = latent_error
  return total, metrics


def _pmean(x, axis_name):
  return x if axis_name is None else jax.lax.pmean(x, axis_name)


def bound_action_std(train_params: dict, max_action_std: float | None) -> dict:
  """Projects the policy's log-std back to at most log(max_action_std) after a step.

  The env clips actions, so beyond the clip a larger std costs the policy nothing while the
  entropy bonus keeps paying for it: without a bound the std runs away (hifar's run B went
  from 0.5 to 2.8). A projection, not a squashing, so the reported std is the one sampled.
  """
  if max_action_std is None:
    return train_params
  policy = dict(train_params["policy"])
  policy["log_std"] = jnp.minimum(policy["log_std"], jnp.log(max_action_std))
  return {**train_params, "policy": policy}


def ppo_update(state: LearnerState, data: Transition, final_obs, final_privileged,
               key: jax.Array, *, nets: nets_lib.Networks, cfg, mirror_weight: float, maps,
               calibrate=None, axis_name: str | None = None, imitation_weight=None,
               max_action_std=None, latent_regularization: float = 0.0):
  """One PPO update on a rollout [T, B_local]; returns (state, metrics averaged).
  calibrate: per-feature masks for `networks.calibrate_normalizer` (the first iteration of a
  stage started from a checkpoint), or None. max_action_std: this iteration's bound on the
  std (a traced scalar where a schedule moves it); None: cfg.max_action_std.
  latent_regularization: [stage.rma]'s weight; > 0 needs `data.window` (the module's
  estimates are computed once, before the epochs, and held fixed like the PPO targets)."""
  if max_action_std is None:
    max_action_std = cfg.max_action_std
  params = state.params
  normalizer = state.normalizer
  targets, advantages = compute_targets(nets, params, normalizer, data, final_obs,
                                        final_privileged, cfg.discount, cfg.gae_lambda,
                                        cfg.reward_scaling)
  samples = {
      "obs": data.obs, "privileged": data.privileged, "action": data.action, "loc": data.loc,
      "log_prob": data.log_prob, "target": targets, "advantage": advantages,
      "weight": data.active * (1.0 - data.truncation),
  }
  if imitation_weight is not None:
    # A forced step's action is not the policy's sample: it trains only the imitation term.
    samples["weight"] = samples["weight"] * (1.0 - data.forced)
    samples["teacher"] = data.teacher
    samples["teacher_weight"] = data.teacher_mask * data.active
  if latent_regularization > 0:
    samples["z_hat"] = jax.lax.stop_gradient(
        nets_lib.estimate_latent(nets, params["adaptation"], normalizer, data.window))
  samples = jax.tree_util.tree_map(lambda x: x.reshape((-1,) + x.shape[2:]), samples)
  n = samples["obs"].shape[0]
  if n % cfg.num_minibatches:
    raise ValueError(f"{n} transitions per device do not split into "
                     f"{cfg.num_minibatches} minibatches")
  old_log_std = params["policy"]["log_std"]
  optimizer = make_optimizer(cfg.max_grad_norm)
  grad_fn = jax.value_and_grad(
      functools.partial(ppo_loss, nets=nets, cfg=cfg, mirror_weight=mirror_weight, maps=maps,
                        old_log_std=old_log_std, imitation_weight=imitation_weight,
                        latent_regularization=latent_regularization),
      has_aux=True)

  def minibatch_step(carry, mb):
    train_params, opt_state, lr = carry
    (_, metrics), grads = grad_fn(train_params, normalizer, mb)
    grads = _pmean(grads, axis_name)
    if cfg.lr_schedule == "adaptive_kl":
      lr = adaptive_kl_learning_rate(lr, _pmean(metrics["kl"], axis_name), cfg.desired_kl)
    updates, opt_state = optimizer.update(grads, opt_state)
    train_params = optax.apply_updates(
        train_params, jax.tree_util.tree_map(lambda u: -lr * u, updates))
    train_params = bound_action_std(train_params, max_action_std)
    metrics["learning_rate"] = lr
    return (train_params, opt_state, lr), metrics

  def epoch(carry, key_perm):
    perm = jax.random.permutation(key_perm, n)
    shuffled = jax.tree_util.tree_map(
        lambda x: x[perm].reshape((cfg.num_minibatches, -1) + x.shape[1:]), samples)
    return jax.lax.scan(minibatch_step, carry, shuffled)

  keys = jax.random.split(key, cfg.update_epochs)
  (train_params, opt_state, lr), metrics = jax.lax.scan(
      epoch, (ppo_params(params), state.opt_state, state.learning_rate), keys)
  metrics = jax.tree_util.tree_map(lambda x: _pmean(jnp.mean(x), axis_name), metrics)

  if cfg.normalize_observations:
    normalizer = nets_lib.update_normalizer(normalizer, data.obs, data.privileged, axis_name)
    if calibrate is not None:
      # Only a stage's first iteration calibrates; every other one skips the batch moments.
      # The mask is replicated, so every device takes the same branch.
      wanted = jnp.any(calibrate["obs"] > 0) | jnp.any(calibrate["privileged"] > 0)
      normalizer = jax.lax.cond(
          wanted,
          lambda n: nets_lib.calibrate_normalizer(n, data.obs, data.privileged, calibrate,
                                                  axis_name),
          lambda n: n, normalizer)
  new_params = dict(params)
  new_params.update(train_params)
  return state.replace(params=new_params, opt_state=opt_state, learning_rate=lr,
                       normalizer=normalizer), metrics
