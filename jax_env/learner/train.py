"""`train_stage`: one curriculum stage of PPO (+ RMA adaptation), data-parallel, resumable.

The loop, per iteration (one jitted, `jax.pmap`ped call over all local devices):
  rollout   `unroll_length` control steps of every environment (jax.lax.scan), actions sampled
            from the Gaussian policy whose latent comes from the privileged encoder;
  update    PPO epochs (ppo.ppo_update), gradients averaged over devices.
Then the deterministic monitor where it is due (monitor.py: the noise-free policy's stand rate
per start state), the progress callback, and a checkpoint every `checkpoint_every` iterations.
Between iterations the host sets the schedules' values for the next rollout (`ScheduleScale`:
the penalty scale and the assisting force), and a fresh environment batch has its episode
clocks staggered once. When the PPO budget (`advance.env_steps`) is spent or the callback
answers "finish", the RMA adaptation phase runs for `rma.adaptation_env_steps` (rollouts acting
with the adaptation module's own estimate, then latent regression, rma.adaptation_update), and
a final checkpoint is written. With `[stage.monitor] keep_best` the monitor judges the
deployable actor during that phase, and the stage ends with the adaptation module that stood
best — the module the phase started from included, where PPO trained it online (ROA).

Randomness comes only from the stage seed: key → (init, env reset, training); every iteration
splits the training key into one key per device. The learner state is replicated on the
devices, the environment batch is split across them, so the environments and their initial
states do not depend on the device count (the sampled actions and minibatches do).

Exact resume: a checkpoint holds the learner state (params.safetensors), the environment state,
observation history and training key (rollout_state.safetensors), and the counters and phase
(checkpoint.json, "learner"). Resuming from it runs the very same jitted computations on the
same inputs, so on one CPU device a resumed run is bit-identical to an uninterrupted one
(tests/python/test_learner_resume.py checks it).
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path
from typing import Any, Callable, Mapping

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from jax_env.learner import checkpoint as ckpt_lib
from jax_env.learner import mirror as mirror_lib
from jax_env.learner import monitor as monitor_lib
from jax_env.learner import networks as nets_lib
from jax_env.learner import ppo as ppo_lib
from jax_env.learner import rma as rma_lib
from jax_env.stage_config import EPISODE_ENDS

AXIS = "i"
ANSWERS = ("continue", "finish", "interrupt")
# Episode metrics reported as means over the episodes that ended in an iteration: the highest
# Trunk height (m) and the time spent standing (s).
EPISODE_MEANS = ("max_height", "time_standing")


@dataclasses.dataclass(frozen=True)
class LearnerConfig:
  """What the learner reads from a stage (the ppo, rma, mirror and advance sections)."""

  stage_name: str
  ppo: Any  # config.PPOConfig
  rma: Any  # config.RMAConfig
  mirror_weight: float
  env_steps: int  # the PPO budget: advance.env_steps
  action: Mapping[str, Any]  # {"mapping", "scale", "clip"}, recorded in checkpoints
  penalty_schedule: Any = None  # config.Schedule, or None: penalties at full weight
  assist: Any = None  # config.AssistConfig, or None: no assisting force
  imitation: Any = None  # config.ImitationConfig, or None: no learning from the paths' plans
  monitor: Any = None  # config.MonitorConfig with its scenarios resolved, or None: off

  @classmethod
  def from_stage(cls, stage) -> "LearnerConfig":
    monitor = dataclasses.replace(stage.monitor, scenarios=stage.monitor_scenarios)
    return cls(stage_name=stage.name, ppo=stage.ppo, rma=stage.rma,
               mirror_weight=stage.mirror.weight, env_steps=stage.advance.env_steps,
               action=dataclasses.asdict(stage.action),
               penalty_schedule=stage.reward_shaping.penalty_schedule,
               assist=stage.assist if stage.assist.force > 0 else None,
               imitation=stage.imitation if stage.imitation.weight > 0 else None,
               monitor=monitor if monitor.every > 0 else None)

  @property
  def online_adaptation(self) -> bool:
    """[stage.rma] latent_regularization: the adaptation module also learns during PPO (ROA)."""
    return bool(self.rma.enabled) and self.rma.latent_regularization > 0

  def network_config(self, env) -> nets_lib.NetworkConfig:
    p, r = self.ppo, self.rma
    return nets_lib.NetworkConfig(
        obs_size=env.obs_size, privileged_size=env.privileged_size,
        action_size=env.action_size, policy_hidden=tuple(p.policy_hidden),
        value_hidden=tuple(p.value_hidden), activation=p.activation, rma=bool(r.enabled),
        latent_dim=r.latent_dim, encoder_hidden=tuple(r.encoder_hidden),
        history_len=r.history_len, initial_action_std=p.initial_action_std)


@dataclasses.dataclass(frozen=True)
class ScheduleScale:
  """A stage schedule (config.Schedule) as the learner applies it, one value per
  iteration. By stand rate the value moves one way only (`ratchet`): `max` for penalties, which
  do not ease off when the stand rate dips, `min` for the assist, the imitation weight and the
  bound on the action std, which do not come back."""

  schedule: Any  # config.Schedule or None (the value is then 1 throughout)
  ratchet: Callable[[float, float], float] = max

  @property
  def initial(self) -> float:
    return 1.0 if self.schedule is None else float(self.schedule.scale(0.0))

  def after(self, current: float, env_steps: int, stand_rate: float | None) -> float:
    """The value for the next iteration, given this one's env steps and stand rate."""
    if self.schedule is None:
      return 1.0
    if self.schedule.by == "env_steps":
      return float(self.schedule.scale(env_steps))
    if stand_rate is None:
      return current
    return self.ratchet(current, float(self.schedule.scale(stand_rate)))


def seed_key(seed: int) -> jax.Array:
  """The PRNG key of a u64 seed, both halves kept (what `jax.random.PRNGKey` does only with
  x64 enabled; without it, seeds that differ above bit 32 would collide). Equals
  PRNGKey(seed) for seeds below 2**32."""
  seed = int(seed)
  if not 0 <= seed < 2**64:
    raise ValueError(f"seed {seed} is not a u64")
  return jnp.asarray([seed >> 32, seed & 0xFFFFFFFF], dtype=jnp.uint32)


class _Log:
  """Appends timestamped lines to the run's log file (no-op without one)."""

  def __init__(self, path):
    self.path = Path(path) if path else None

  def __call__(self, message: str) -> None:
    if self.path is None:
      return
    stamp = time.strftime("%Y-%m-%dT%H:%M:%S")
    with open(self.path, "a") as f:
      f.write(f"{stamp} [learner] {message}\n")


# ---------------------------------------------------------------------------------------------
# Pytree <-> named arrays (rollout state).


def _path_name(path) -> str:
  parts = []
  for p in path:
    if isinstance(p, jax.tree_util.DictKey):
      parts.append(str(p.key))
    elif isinstance(p, jax.tree_util.GetAttrKey):
      parts.append(p.name)
    elif isinstance(p, jax.tree_util.SequenceKey):
      parts.append(str(p.idx))
    else:
      parts.append(str(p))
  return "/".join(parts)


def _named_leaves(tree, prefix: str) -> dict[str, Any]:
  leaves = jax.tree_util.tree_flatten_with_path(tree)[0]
  return {f"{prefix}/{_path_name(path)}": leaf for path, leaf in leaves}


def _restore_tree(template, prefix: str, arrays: Mapping[str, np.ndarray], where: str):
  leaves, treedef = jax.tree_util.tree_flatten_with_path(template)
  out = []
  for path, leaf in leaves:
    name = f"{prefix}/{_path_name(path)}"
    if name not in arrays:
      raise ckpt_lib.CheckpointError(f"{where}: rollout state has no {name}; it was written "
                                     "for a different environment")
    x = arrays[name]
    if x.shape != leaf.shape or x.dtype != np.dtype(leaf.dtype):
      raise ckpt_lib.CheckpointError(
          f"{where}: rollout state {name} is {x.dtype}{list(x.shape)}, the environment "
          f"needs {np.dtype(leaf.dtype)}{list(leaf.shape)}")
    out.append(jnp.asarray(x))
  return jax.tree_util.tree_unflatten(treedef, out)


def _restore_history(arrays: Mapping[str, np.ndarray], shape, where: str) -> jax.Array:
  x = arrays.get("history")
  if x is None or x.shape != tuple(shape) or x.dtype != np.float32:
    found = "nothing" if x is None else f"{x.dtype}{list(x.shape)}"
    raise ckpt_lib.CheckpointError(f"{where}: rollout state history is {found}, the stage "
                                   f"needs float32{list(shape)}")
  return jnp.asarray(x)


# ---------------------------------------------------------------------------------------------
# Device placement.


def _device_sharding(devices) -> NamedSharding:
  """The sharding `jax.pmap` gives its outputs; inputs placed with it avoid a second compile
  (pmap, now built on shard_map, keys its cache on the input shardings)."""
  return NamedSharding(Mesh(np.array(devices), (AXIS,)), PartitionSpec(AXIS))


def _put(tree, sharding):
  return jax.device_put(tree, sharding)


def _replicate(tree, n: int):
  return jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (n,) + jnp.shape(x)), tree)


def _unreplicate(tree):
  return jax.tree_util.tree_map(lambda x: x[0], tree)


def _shard(tree, n: int):
  return jax.tree_util.tree_map(lambda x: x.reshape((n, x.shape[0] // n) + x.shape[1:]), tree)


def _unshard(tree):
  # Explicit sizes: a -1 cannot be inferred for empty arrays (the history without RMA).
  return jax.tree_util.tree_map(lambda x: x.reshape((x.shape[0] * x.shape[1],) + x.shape[2:]),
                                tree)


# ---------------------------------------------------------------------------------------------
# Episode statistics of a rollout.


def _step_stats(nxt) -> dict[str, jax.Array]:
  """Sums over the local batch of one step's episode ends and per-term rewards."""
  done = nxt.done
  em = nxt.episode_metrics
  success = done * em["success"]
  stats = {
      "episodes": jnp.sum(done),
      "successes": jnp.sum(success),
      "recovery_time": jnp.sum(jnp.where(success > 0, jnp.nan_to_num(em["recovery_time"]), 0.0)),
      "return": jnp.sum(done * em["return"]),
      "steps": jnp.asarray(done.shape[0], jnp.float32),
  }
  for k in EPISODE_MEANS:
    if k in em:  # optional episode metrics of the environment API
      stats[k] = jnp.sum(done * em[k])
  if "end" in em:  # optional: how episodes ended, an index into EPISODE_ENDS
    for i, name in enumerate(EPISODE_ENDS):
      stats[f"end/{name}"] = jnp.sum(done * (em["end"] == i))
  for k, v in nxt.metrics.items():
    if k.startswith("reward/"):
      stats[k] = jnp.sum(v)
  return stats


def _summarize(stats: Mapping[str, Any]) -> dict[str, Any]:
  """Host-side progress fields from the summed statistics."""
  s = {k: float(v) for k, v in stats.items()}
  episodes, successes = s["episodes"], s["successes"]
  rewards = {k[len("reward/"):]: s[k] / max(s["steps"], 1.0)
             for k in s if k.startswith("reward/")}
  per_episode = lambda k: s[k] / episodes if episodes > 0 and k in s else None
  return {
      "rewards": rewards,
      "stand_rate": per_episode("successes"),
      "recovery_time": s["recovery_time"] / successes if successes > 0 else None,
      "episode_return": per_episode("return"),
      **{k: per_episode(k) for k in EPISODE_MEANS if k in s},
      # The share of the ended episodes that ended each way (time limit, a termination rule).
      **({"episode_ends": {n: per_episode(f"end/{n}") for n in EPISODE_ENDS}}
         if f"end/{EPISODE_ENDS[0]}" in s else {}),
  }


# ---------------------------------------------------------------------------------------------
# The jitted iteration functions.


def _with_schedules(env, env_state, schedules):
  """The env state with this iteration's schedule values, [penalty scale, assist force (N),
  imitation weight, bound on the action std] (the last two are the learner's; an env without
  penalties or an assist ignores them)."""
  if hasattr(env, "with_penalty_scale"):
    env_state = env.with_penalty_scale(env_state, schedules[0])
  if hasattr(env, "with_assist_force"):
    env_state = env.with_assist_force(env_state, schedules[1])
  return env_state


def correlated_noise(previous: jax.Array, key: jax.Array, rho: float) -> jax.Array:
  """This step's standard-normal exploration noise: AR(1), ρ·ε + √(1−ρ²)·ξ with ξ drawn from
  `key`, so that every step's noise is still N(0, 1) (the PPO ratio reads the same Gaussian)
  while it stays correlated for about 1/(1−ρ) control steps. ρ = 0 is brax's white noise, ξ
  itself. Correlated action noise explores the slow whole-body moves of a get-up, which white
  noise at 50 Hz averages away in the PD loop (Hollenstein et al., "Colored Noise in PPO",
  AAAI 2024; Raffin et al.'s gSDE). The noise starts afresh at every iteration, so the rollout
  state (and exact resume) carries none of it. On the T1 get-up (docs/experiments.md) it kept the
  policy from holding the standing tolerance, so no shipped curriculum uses it."""
  xi = jax.random.normal(key, previous.shape)
  if rho == 0.0:
    return xi
  return rho * previous + math.sqrt(1.0 - rho * rho) * xi


def restart_noise(noise: jax.Array, key: jax.Array, done: jax.Array) -> jax.Array:
  """The noise with a stationary fresh draw where an episode ended: a new episode does not
  inherit the last one's direction of exploration."""
  fresh = jax.random.normal(jax.random.fold_in(key, 1), noise.shape)
  return jnp.where(done[:, None] > 0, fresh, noise)


def _make_steps(env, nets: nets_lib.Networks, config: LearnerConfig, maps, devices):
  ppo_cfg = config.ppo
  unroll = ppo_cfg.unroll_length

  def scan_stats(stats):
    return jax.tree_util.tree_map(lambda x: jax.lax.psum(jnp.sum(x), AXIS), stats)

  # [stage.rma] latent_regularization: the PPO rollout also keeps the module's windows.
  online = config.online_adaptation

  def ppo_iteration(learner: ppo_lib.LearnerState, env_state, history, key, schedules,
                    calibrate):
    k_roll, k_update = jax.random.split(key)
    env_state = _with_schedules(env, env_state, schedules)
    params, normalizer = learner.params, learner.normalizer
    log_std = params["policy"]["log_std"]
    dist = nets.action_distribution
    rho = ppo_cfg.action_noise_correlation
    # The noise before the first step: stationary, from a key of its own (fold_in leaves the
    # steps' keys, and with ρ = 0 every sampled action, as they were).
    noise = jax.random.normal(jax.random.fold_in(k_roll, 1),
                              (env_state.obs.shape[0], nets.config.action_size))

    def step(carry, k):
      es, hist, noise = carry
      loc = nets_lib.privileged_mean(nets, params, normalizer, es.obs, es.privileged)
      std = jnp.broadcast_to(jnp.exp(log_std), loc.shape)
      noise = correlated_noise(noise, k, rho)
      action = loc + std * noise
      if config.imitation is not None:
        teacher, teacher_mask = env.teacher_action(es)
        # Forced path episodes act with the plan (and the policy's noise) while imitation is on.
        forced = teacher_mask * es.teacher_forced * (schedules[2] > 0)
        action = jnp.where(forced[:, None] > 0, teacher + std * noise, action)
      else:
        teacher = teacher_mask = forced = None  # empty pytree leaves: the update is as before
      log_prob = dist.log_prob((loc, std), action)
      nxt = env.step(es, action)
      tr = ppo_lib.Transition(obs=es.obs, privileged=es.privileged, action=action, loc=loc,
                              log_prob=log_prob, reward=nxt.reward, done=nxt.done,
                              truncation=nxt.truncation, active=es.control_active,
                              teacher=teacher, teacher_mask=teacher_mask, forced=forced,
                              window=nets_lib.history_window(hist, es.obs) if online else None)
      if rho:
        noise = restart_noise(noise, k, nxt.done)
      return ((nxt, nets_lib.push_history(hist, es.obs, nxt.done), noise),
              (tr, _step_stats(nxt)))

    (env_state, history, _), (data, stats) = jax.lax.scan(
        step, (env_state, history, noise), jax.random.split(k_roll, unroll))
    if online:  # a key of its own; without it every key is as before the option existed
      k_update, k_adapt = jax.random.split(k_update)
    learner, metrics = ppo_lib.ppo_update(
        learner, data, env_state.obs, env_state.privileged, k_update, nets=nets, cfg=ppo_cfg,
        mirror_weight=config.mirror_weight, maps=maps, calibrate=calibrate, axis_name=AXIS,
        imitation_weight=schedules[2] if config.imitation is not None else None,
        # Without a schedule the bound is cfg's, a compile-time constant.
        max_action_std=schedules[3] if ppo_cfg.action_std_schedule is not None else None,
        latent_regularization=config.rma.latent_regularization if online else 0.0)
    if online:
      # Regularized online adaptation: the module learns beside PPO, on the PPO rollout's
      # windows, toward the encoder's updated latent.
      learner, adapt_metrics = rma_lib.adaptation_update(
          learner, rma_lib.AdaptationBatch(window=data.window, privileged=data.privileged),
          k_adapt, nets=nets, cfg=ppo_cfg, learning_rate=config.rma.adaptation_learning_rate,
          axis_name=AXIS)
      metrics = {**metrics, **adapt_metrics}
    return learner, env_state, history, metrics, scan_stats(stats)

  def adaptation_iteration(learner: ppo_lib.LearnerState, env_state, history, key,
                           schedules, calibrate):
    del calibrate  # the adaptation phase leaves the statistics alone
    params, normalizer = learner.params, learner.normalizer
    env_state = _with_schedules(env, env_state, schedules)

    def step(carry, _):
      es, hist = carry
      window = nets_lib.history_window(hist, es.obs)
      action = nets_lib.deployable_mean(nets, params, normalizer, es.obs, hist)
      nxt = env.step(es, action)
      batch = rma_lib.AdaptationBatch(window=window, privileged=es.privileged)
      return (nxt, nets_lib.push_history(hist, es.obs, nxt.done)), (batch, _step_stats(nxt))

    (env_state, history), (batch, stats) = jax.lax.scan(
        step, (env_state, history), None, length=unroll)
    learner, metrics = rma_lib.adaptation_update(
        learner, batch, key, nets=nets, cfg=ppo_cfg,
        learning_rate=config.rma.adaptation_learning_rate, axis_name=AXIS)
    return learner, env_state, history, metrics, scan_stats(stats)

  return (jax.pmap(ppo_iteration, axis_name=AXIS, devices=devices),
          jax.pmap(adaptation_iteration, axis_name=AXIS, devices=devices))


# ---------------------------------------------------------------------------------------------
# The entry point.


def train_stage(env, config: LearnerConfig, *, stage_dir: str | Path, seed: int,
                num_envs: int | None = None, init_checkpoint: str | Path | None = None,
                resume_checkpoint: str | Path | None = None,
                callback: Callable[[dict], str] | None = None, log_file: str | Path | None = None,
                devices: list | None = None, stage_config: Mapping[str, Any] | None = None
                ) -> dict:
  """Trains one stage; returns {"status", "checkpoint", "env_steps"}.

  Args:
    env: a batched environment with the API of docs/contracts.md ("Environment API").
    config: the stage's learner settings (LearnerConfig.from_stage).
    stage_dir: checkpoints go to `<stage_dir>/checkpoints/<env_steps:012d>/` plus `LATEST`.
    seed: the stage seed; all randomness derives from it.
    num_envs: overrides ppo.num_envs; must divide by num_minibatches × devices.
    init_checkpoint: start from these weights (same feature layout: expand it first), with
      fresh optimizer step counters, the stage's learning rate, and observation statistics
      kept; the input weights of features that never varied are zeroed and those features'
      statistics are taken from the stage's first batch (checkpoint.py explains why).
    resume_checkpoint: continue exactly where this checkpoint stopped (needs its rollout
      state); wins over init_checkpoint.
    callback: called after every iteration with the progress dict of the facade contract;
      answers "continue", "finish" (end the PPO phase now: the adaptation phase still runs,
      since the deployable actor needs it) or "interrupt" (checkpoint and return now).
    log_file: the run's log, to which the learner appends what it did.
    devices: local devices to split the batch over (default: all).
    stage_config: the stage table the env was built from, recorded in every checkpoint
      (`stage_config`) so that evaluation, rollouts and export can rebuild the environment.

  Status: "completed" (budget spent), "finished_early" (the callback said "finish"),
  "interrupted".
  """
  log = _Log(log_file)
  devices = list(devices or jax.local_devices())
  n_dev = len(devices)
  p = config.ppo
  batch = int(num_envs or p.num_envs)
  if batch <= 0 or batch % (p.num_minibatches * n_dev):
    raise ValueError(f"num_envs {batch} must be a positive multiple of num_minibatches "
                     f"({p.num_minibatches}) × devices ({n_dev}) = {p.num_minibatches * n_dev}")
  net_cfg = config.network_config(env)
  nets = nets_lib.Networks(net_cfg)
  maps = env.mirror
  mirror_lib.check_maps(maps, env.obs_size, env.privileged_size, env.action_size)
  if net_cfg.rma and config.rma.history_len < 1:
    raise ValueError(f"rma.history_len must be >= 1, got {config.rma.history_len}")

  steps_per_iter = batch * p.unroll_length
  ppo_budget = int(config.env_steps)
  adapt_budget = int(config.rma.adaptation_env_steps) if net_cfg.rma else 0
  names = (tuple(env.obs_names), tuple(env.privileged_names), tuple(env.action_names))

  # -- state: fresh, initialised from weights, or resumed --------------------------------------
  k_init, k_env, key = jax.random.split(seed_key(seed), 3)
  # One compiled function for the whole initialisation (op by op, every layer's initializer
  # would be compiled on its own).
  template = jax.jit(lambda k: ppo_lib.init_learner_state(nets, nets.init(k), p.max_grad_norm,
                                                          p.learning_rate))(k_init)
  learner = template
  # Features whose statistics the first PPO iteration sets from its batch (none unless the
  # stage starts from another stage's checkpoint).
  calibrate = {kind: np.zeros(np.shape(template.normalizer.mean[kind]), np.float32)
               for kind in ("obs", "privileged")}
  penalty = ScheduleScale(config.penalty_schedule)
  assist = ScheduleScale(config.assist.schedule if config.assist else None, ratchet=min)
  imitation = ScheduleScale(config.imitation.schedule if config.imitation else None,
                            ratchet=min)
  std_bound = ScheduleScale(p.action_std_schedule, ratchet=min)
  progress = Progress(penalty_scale=penalty.initial, assist_scale=assist.initial,
                      imitation_scale=imitation.initial, std_scale=std_bound.initial)
  reset = jax.jit(env.reset)
  env_state = None
  history = None
  if resume_checkpoint is not None:
    ck = ckpt_lib.load(resume_checkpoint)
    ckpt_lib.check_layout(ck.meta, *names, net_cfg.meta(), str(resume_checkpoint))
    info = ck.meta.get("learner")
    if not isinstance(info, dict):
      raise ckpt_lib.CheckpointError(f"{resume_checkpoint}: checkpoint.json has no learner "
                                     "section; it cannot be resumed exactly")
    if int(info.get("num_envs", -1)) != batch:
      raise ckpt_lib.CheckpointError(
          f"{resume_checkpoint}: written with {info.get('num_envs')} environments, resuming "
          f"with {batch}; resume with num_envs = {info.get('num_envs')}")
    learner = ckpt_lib.restore_learner(template, ck.tensors, fresh_optimizer=False)
    rollout = ckpt_lib.load_rollout(resume_checkpoint)
    env_template = jax.eval_shape(reset, jax.random.split(k_env, batch))
    env_state = _restore_tree(env_template, "env", rollout, str(resume_checkpoint))
    history = _restore_history(rollout, (batch, net_cfg.history_len, env.obs_size),
                               str(resume_checkpoint))
    key = jnp.asarray(np.asarray(ck.meta["prng_key"], np.uint32))
    progress = progress.resumed(info)
    if progress.phase not in PHASES:
      raise ckpt_lib.CheckpointError(f"{resume_checkpoint}: unknown learner phase "
                                     f"{progress.phase!r}")
    if int(info.get("devices", n_dev)) != n_dev:
      log(f"resuming a run written on {info.get('devices')} devices on {n_dev}: it continues "
          "correctly but is no longer bit-identical to an uninterrupted run")
    log(f"stage {config.stage_name}: resuming from {resume_checkpoint} "
        f"(iteration {progress.iteration}, phase {progress.phase})")
    if progress.phase == "done":
      return {"status": progress.status, "checkpoint": str(Path(resume_checkpoint)),
              "env_steps": progress.env_steps}
  elif init_checkpoint is not None:
    ck = ckpt_lib.load(init_checkpoint)
    ckpt_lib.check_layout(ck.meta, *names, net_cfg.meta(), str(init_checkpoint))
    learner = ckpt_lib.restore_learner(template, ck.tensors, fresh_optimizer=True,
                                       learning_rate=p.learning_rate, stage_start=net_cfg)
    unseen = ckpt_lib.unseen_features(learner.normalizer)
    calibrate = {k: v.astype(np.float32) for k, v in unseen.items()}
    log(f"stage {config.stage_name}: initialised from {init_checkpoint}; features never seen "
        f"varying (input weights zeroed, statistics from the first batch): "
        f"{int(unseen['obs'].sum())} of {len(unseen['obs'])} observed, "
        f"{int(unseen['privileged'].sum())} of {len(unseen['privileged'])} privileged")
  if env_state is None:
    env_state = reset(jax.random.split(k_env, batch))
    if hasattr(env, "stagger"):
      env_state = jax.jit(env.stagger)(env_state, jax.random.fold_in(k_env, 1))
    history = jnp.zeros((batch, net_cfg.history_len, env.obs_size), jnp.float32)

  ppo_iter, adapt_iter = _make_steps(env, nets, config, maps, devices)
  monitor = monitor_lib.make_monitor(config.monitor, stage_config, nets,
                                     getattr(env, "backend_name", None),
                                     jax.random.fold_in(seed_key(seed), 2))
  stage = _StageRun(
      config=config, net_cfg=net_cfg, names=names, devices=devices, batch=batch, seed=seed,
      checkpoints_dir=Path(stage_dir) / "checkpoints", stage_config=stage_config,
      budgets=_Budgets(steps_per_iter=steps_per_iter, ppo=ppo_budget, adaptation=adapt_budget),
      steps={"ppo": ppo_iter, "adaptation": adapt_iter}, monitor=monitor, penalty=penalty,
      assist=assist, imitation=imitation, std_bound=std_bound, callback=callback, log=log,
      progress=progress, learner=learner, env_state=env_state, history=history, key=key,
      calibrate=calibrate)
  log(f"stage {config.stage_name}: {batch} envs on {n_dev} device(s), {steps_per_iter} env "
      f"steps per iteration, PPO budget {ppo_budget}, adaptation {adapt_budget}")
  return stage.run()


PHASES = ("ppo", "adaptation", "done")
# The actor the monitor judges in each training phase: the one whose parameters it trains.
MONITOR_ACTOR = {"ppo": monitor_lib.PRIVILEGED, "adaptation": monitor_lib.DEPLOYABLE}


def is_new_best(best: float | None, rate: float) -> bool:
  """Whether a monitor point with mean stand rate `rate` replaces the best so far: the first
  does, and a later one that is at least as good (of equals, the more trained policy)."""
  return best is None or rate >= best


@dataclasses.dataclass
class Progress:
  """Where a stage's training stands: the `learner` section of every checkpoint.json (with the
  run's sizes), and what an exact resume continues from."""

  iteration: int = 0
  ppo_env_steps: int = 0
  adaptation_env_steps: int = 0
  phase: str = "ppo"  # PHASES, in order; "adaptation" only with RMA
  finished_early: bool = False  # the callback answered "finish" during PPO
  penalty_scale: float = 1.0  # the penalty schedule's scale for the next PPO rollout
  assist_scale: float = 1.0  # the assist schedule's scale for the next PPO rollout
  imitation_scale: float = 1.0  # the imitation schedule's scale for the next PPO update
  std_scale: float = 1.0  # the action-std schedule's scale of max_action_std, next PPO update
  # The best monitor point so far ([stage.monitor] keep_best): its mean stand rate and the env
  # steps of the checkpoint written there.
  best_monitor_rate: float | None = None
  best_monitor_env_steps: int | None = None

  @property
  def env_steps(self) -> int:
    return self.ppo_env_steps + self.adaptation_env_steps

  @property
  def status(self) -> str:
    """The status of a stage that ends here (but for an interruption)."""
    return "finished_early" if self.finished_early else "completed"

  def resumed(self, info: Mapping[str, Any]) -> "Progress":
    """This progress with the values a checkpoint's `learner` section records."""
    return dataclasses.replace(self, **{f.name: info[f.name] for f in dataclasses.fields(self)
                                        if f.name in info})


@dataclasses.dataclass(frozen=True)
class _Budgets:
  steps_per_iter: int  # env steps of one iteration (all envs, all devices)
  ppo: int
  adaptation: int  # 0 without RMA

  @property
  def adaptation_target(self) -> int:
    """Where the adaptation phase ends: its budget rounded up to whole iterations."""
    return math.ceil(self.adaptation / self.steps_per_iter) * self.steps_per_iter


class _StageRun:
  """The host loop of one stage, its state explicit: the learner replicated on the devices,
  the environments and observation histories split across them, the training key, and
  `progress`; `run` drives the phases, `save` checkpoints all of it."""

  def __init__(self, *, config: LearnerConfig, net_cfg, names, devices, batch: int, seed: int,
               checkpoints_dir: Path, stage_config, budgets: _Budgets, steps, monitor,
               penalty: ScheduleScale, assist: ScheduleScale, imitation: ScheduleScale,
               std_bound: ScheduleScale,
               callback, log, progress: Progress, learner, env_state, history, key, calibrate):
    self.config, self.net_cfg, self.names, self.seed = config, net_cfg, names, seed
    self.checkpoints_dir, self.stage_config = checkpoints_dir, stage_config
    self.budgets, self.steps, self.monitor, self.penalty = budgets, steps, monitor, penalty
    self.assist = assist
    self.assist_newtons = float(config.assist.force) if config.assist else 0.0
    self.imitation = imitation
    self.std_bound = std_bound
    self.imitation_weight = float(config.imitation.weight) if config.imitation else 0.0
    self.callback, self.log, self.progress = callback, log, progress
    self.n_dev = len(devices)
    self.sharding = _device_sharding(devices)
    self.batch = batch
    self.learner = _put(_replicate(learner, self.n_dev), self.sharding)
    self.env_state = _put(_shard(env_state, self.n_dev), self.sharding)
    self.history = _put(_shard(history, self.n_dev), self.sharding)
    self.key = key
    # The masks live on the devices: the stage's first PPO iteration gets `calibrate`, every
    # later one the zero mask (ppo_update then skips the calibration).
    self.calibrate = _put(_replicate(calibrate, self.n_dev), self.sharding)
    self.no_calibration = jax.tree_util.tree_map(jnp.zeros_like, self.calibrate)
    # A new best monitor point is checkpointed at once (keep_best returns to it).
    self.best_unsaved = False

  def run(self) -> dict:
    progress, budgets = self.progress, self.budgets
    every = max(int(self.config.ppo.checkpoint_every), 1)
    if progress.phase == "ppo":
      while progress.ppo_env_steps < budgets.ppo:
        answer = self.iterate("ppo", budgets.ppo)
        if answer == "interrupt":
          return self.interrupted()
        if answer == "finish":
          progress.finished_early = True
          self.log(f"stage {self.config.stage_name}: finish requested at {progress.env_steps} "
                   "env steps")
          break
        if progress.iteration % every == 0 or self.best_unsaved:
          self.save()
      self.keep_best()
      progress.phase = "adaptation" if budgets.adaptation > 0 else "done"
      if progress.phase == "adaptation":
        self.enter_adaptation()
        self.save()  # the phase boundary: a resume must not re-enter PPO

    if progress.phase == "adaptation":
      total = progress.ppo_env_steps + budgets.adaptation_target
      while progress.adaptation_env_steps < budgets.adaptation:
        answer = self.iterate("adaptation", total)
        if answer == "interrupt":
          return self.interrupted()
        # "finish" judges the PPO policy; the adaptation phase always completes its budget.
        if progress.adaptation_env_steps < budgets.adaptation and (
            progress.iteration % every == 0 or self.best_unsaved):
          self.save()
      self.keep_best()
      progress.phase = "done"

    directory = self.save()
    self.log(f"stage {self.config.stage_name}: {progress.status} at {progress.env_steps} env "
             "steps")
    return {"status": progress.status, "checkpoint": str(directory),
            "env_steps": progress.env_steps}

  def iterate(self, phase: str, total: int) -> str:
    """One iteration of `phase`; returns the callback's answer."""
    progress, config = self.progress, self.config
    self.key, k_iter = jax.random.split(self.key)
    t0 = time.perf_counter()
    scale = progress.penalty_scale
    # The adaptation module learns under deployment's conditions: no assist.
    force = self.assist_newtons * progress.assist_scale if phase == "ppo" else 0.0
    imitation = self.imitation_weight * progress.imitation_scale
    max_std = config.ppo.max_action_std
    bound = max_std * progress.std_scale if max_std is not None else 0.0  # 0: unused
    schedules = jnp.tile(jnp.asarray([scale, force, imitation, bound], jnp.float32),
                         (self.n_dev, 1))
    self.learner, self.env_state, self.history, metrics, stats = self.steps[phase](
        self.learner, self.env_state, self.history,
        _put(jax.random.split(k_iter, self.n_dev), self.sharding), _put(schedules, self.sharding),
        self.calibrate)
    if phase == "ppo":  # calibration is once, on the stage's first batch
      self.calibrate = self.no_calibration
    metrics, stats = jax.device_get((_unreplicate(metrics), _unreplicate(stats)))
    dt = time.perf_counter() - t0
    steps = self.budgets.steps_per_iter
    progress.iteration += 1
    setattr(progress, f"{phase}_env_steps", getattr(progress, f"{phase}_env_steps") + steps)
    report = {"iteration": progress.iteration, "env_steps": progress.env_steps,
              "steps_per_s": steps / max(dt, 1e-9), "total_env_steps": total,
              "phase": phase, "losses": {k: float(v) for k, v in metrics.items()},
              "penalty_scale": scale, "assist_force": force}
    if self.imitation_weight > 0 and phase == "ppo":
      report["imitation_weight"] = imitation
    if max_std is not None and phase == "ppo":
      report["max_action_std"] = bound
    report.update(_summarize(stats))
    if phase == "ppo":
      progress.penalty_scale = self.penalty.after(scale, progress.ppo_env_steps,
                                                  report["stand_rate"])
      progress.assist_scale = self.assist.after(progress.assist_scale, progress.ppo_env_steps,
                                                report["stand_rate"])
      progress.imitation_scale = self.imitation.after(progress.imitation_scale,
                                                      progress.ppo_env_steps,
                                                      report["stand_rate"])
      std_scale = self.std_bound.after(progress.std_scale, progress.ppo_env_steps,
                                       report["stand_rate"])
      tightened, progress.std_scale = std_scale < progress.std_scale, std_scale
    last = (progress.ppo_env_steps >= self.budgets.ppo if phase == "ppo"
            else progress.adaptation_env_steps >= self.budgets.adaptation)
    if self.monitor is not None and monitor_lib.is_due(progress.iteration,
                                                       config.monitor.every, last):
      # PPO trains the base policy, which the privileged actor judges; the adaptation phase
      # trains the module, which only the deployable actor reads.
      report["monitor"] = self.run_monitor(MONITOR_ACTOR[phase])
    if phase == "ppo":
      if tightened and progress.best_monitor_env_steps is not None:
        # The std bound tightens from the next iteration on: keep_best compares only policies
        # trained under the tightest bound, or a monitor point from before (a few episodes per
        # start cannot tell 94% from 100%) would undo what the low-noise training is for.
        self.log(f"stage {config.stage_name}: the action std bound tightens to "
                 f"{max_std * std_scale:.3g}; keep_best forgets the monitor "
                 f"points before {progress.ppo_env_steps} env steps")
        progress.best_monitor_rate = progress.best_monitor_env_steps = None
    bad = sorted(k for k, v in report["losses"].items() if not math.isfinite(v))
    if bad:
      # The parameters are poisoned from here on: stop rather than checkpoint garbage.
      message = (f"stage {config.stage_name}: non-finite {', '.join(bad)} at iteration "
                 f"{progress.iteration} ({phase}); the last good checkpoint is "
                 f"{ckpt_lib.read_latest(self.checkpoints_dir) or 'none'}")
      self.log(message)
      raise FloatingPointError(message)
    answer = self.callback(report) if self.callback is not None else "continue"
    if answer not in ANSWERS:
      raise ValueError(f"progress callback answered {answer!r}; valid: {', '.join(ANSWERS)}")
    return answer

  def run_monitor(self, actor: str) -> dict:
    """The monitor of the current parameters with `actor`; a new best monitor point of
    [stage.monitor] keep_best is checkpointed right after (`best_unsaved`)."""
    progress = self.progress
    host = _unreplicate(self.learner)
    result = self.monitor(host.params, host.normalizer, actor)
    if self.config.monitor.keep_best and is_new_best(progress.best_monitor_rate,
                                                     result["mean_stand_rate"]):
      progress.best_monitor_rate = result["mean_stand_rate"]
      progress.best_monitor_env_steps = progress.env_steps
      self.best_unsaved = True
    return result

  def enter_adaptation(self) -> None:
    """The PPO phase is over: keep_best starts over for the adaptation module. Where PPO trained
    the module online (ROA) the deployable actor as PPO left it is the first candidate, so that
    the phase keeps it unless the module the phase trains stands better; its checkpoint is the
    phase boundary's, written next."""
    progress = self.progress
    progress.best_monitor_rate = progress.best_monitor_env_steps = None
    if (self.monitor is None or not self.config.monitor.keep_best
        or not self.config.online_adaptation):
      return
    result = self.run_monitor(monitor_lib.DEPLOYABLE)
    self.log(f"stage {self.config.stage_name}: the deployable actor with the module PPO trained "
             f"online: mean monitor stand rate {result['mean_stand_rate']:.3f}")

  def keep_best(self) -> None:
    """At the end of a phase with [stage.monitor] keep_best: the learner goes back to the state
    checkpointed at the phase's best monitor point — at the end of PPO, so that the adaptation
    phase and the final checkpoint build on the policy that stood best rather than on the last
    iteration's; at the end of the adaptation phase, the adaptation module that stood best (the
    base policy is the same at every point of that phase)."""
    progress = self.progress
    if progress.best_monitor_env_steps is None:  # keep_best off, or no monitor point yet
      return
    phase, what = (("PPO", "PPO parameters") if progress.phase == "ppo"
                   else ("adaptation", "adaptation module"))
    if progress.best_monitor_env_steps == progress.env_steps:
      self.log(f"stage {self.config.stage_name}: the last {phase} iteration is the best monitor "
               f"point (mean stand rate {progress.best_monitor_rate:.3f}); kept")
      return
    directory = self.checkpoints_dir / f"{progress.best_monitor_env_steps:012d}"
    best = ckpt_lib.load(directory)
    host = jax.device_get(_unreplicate(self.learner))
    restored = ckpt_lib.restore_learner(host, best.tensors, fresh_optimizer=False)
    self.learner = _put(_replicate(restored, self.n_dev), self.sharding)
    self.log(f"stage {self.config.stage_name}: keeping the {what} of {directory} (mean "
             f"monitor stand rate {progress.best_monitor_rate:.3f}, the best of the {phase} "
             f"phase) instead of those at {progress.env_steps} env steps")

  def save(self) -> Path:
    """A checkpoint of everything an exact resume needs; returns its directory."""
    self.best_unsaved = False
    progress, config, p = self.progress, self.config, self.config.ppo
    steps = progress.env_steps
    host_learner = jax.device_get(_unreplicate(self.learner))
    rollout = {k: np.asarray(v) for k, v in _named_leaves(
        jax.device_get(_unshard(self.env_state)), "env").items()}
    rollout["history"] = np.asarray(jax.device_get(_unshard(self.history)))
    directory = self.checkpoints_dir / f"{steps:012d}"
    extra = {"learner": dict(dataclasses.asdict(progress), num_envs=self.batch,
                             devices=self.n_dev, initial_action_std=p.initial_action_std,
                             ppo_budget=self.budgets.ppo,
                             adaptation_budget=self.budgets.adaptation)}
    if self.stage_config is not None:
      extra[ckpt_lib.STAGE_CONFIG_KEY] = dict(self.stage_config)
    obs_names, privileged_names, action_names = self.names
    ckpt_lib.save(directory, state=host_learner, config=self.net_cfg, stage=config.stage_name,
                  env_steps=steps, iteration=progress.iteration, seed=self.seed, key=self.key,
                  obs_names=obs_names, privileged_names=privileged_names,
                  action_names=action_names, action=config.action, extra=extra,
                  rollout=rollout)
    ckpt_lib.write_latest(self.checkpoints_dir, directory.name)
    _prune_rollouts(self.checkpoints_dir, keep=directory)
    self.log(f"stage {config.stage_name}: checkpoint {directory} (iteration "
             f"{progress.iteration}, phase {progress.phase})")
    return directory

  def interrupted(self) -> dict:
    directory = self.save()
    self.log(f"stage {self.config.stage_name}: interrupted at {self.progress.env_steps} env "
             "steps")
    return {"status": "interrupted", "checkpoint": str(directory),
            "env_steps": self.progress.env_steps}


def _prune_rollouts(checkpoints_dir: Path, keep: Path) -> None:
  """Drops the rollout state of older checkpoints: only the newest is resumed from, and at
  scale a rollout state (every environment's full simulator state) dwarfs the parameters."""
  for d in checkpoints_dir.iterdir():
    if d.is_dir() and not d.name.startswith(".") and d != keep:
      f = d / ckpt_lib.ROLLOUT_FILE
      if f.exists():
        f.unlink()
