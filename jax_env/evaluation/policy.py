"""A checkpoint's deployable actor, and the stage its environment is rebuilt from.

Evaluation, recordings and export act exactly as the robot would: observations and their
history in, the adaptation module's latent and the base policy's mean out (no privileged
inputs, no sampling). The history is updated the way the learner updates it in training.

Evaluation can instead act with the `privileged` actor: the same base policy with the latent of
the environment-factor encoder, read from the simulator's privileged state — the actor PPO
trains and the training monitor measures (learner/monitor.py). It cannot be deployed; it tells
how much of a policy's stand rate the adaptation module loses, and it can evaluate a checkpoint
of a stage's PPO phase, whose adaptation module is not trained yet.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jnp

from jax_env.learner import checkpoint as ckpt_lib
from jax_env.learner import networks as nets_lib

# The actors an evaluation can act with (names.json "actors"; `hifar eval --actor`); the first
# is the default and the only one `act`, `rollout` and `export` use.
DEPLOYABLE = "deployable"
PRIVILEGED = "privileged"
ACTORS = (DEPLOYABLE, PRIVILEGED)


@dataclasses.dataclass(frozen=True)
class Policy:
  """A loaded checkpoint: its metadata, networks, parameters and the deterministic actor."""

  directory: Path
  meta: dict
  nets: nets_lib.Networks
  params: Any
  normalizer: Any

  @property
  def history_len(self) -> int:
    return self.nets.config.history_len

  @property
  def obs_size(self) -> int:
    return self.nets.config.obs_size

  def act(self, obs: jax.Array, history: jax.Array) -> jax.Array:
    """Deterministic actions [B, n_act] (unclipped mean; the env clips). Pure, jit-able."""
    return nets_lib.deployable_mean(self.nets, self.params, self.normalizer, obs, history)

  def initial_history(self, batch: int) -> jax.Array:
    """The history an episode starts with in training: zeros [B, H, n_obs]."""
    return jnp.zeros((batch, self.history_len, self.obs_size), jnp.float32)


def check_adaptation_trained(meta: dict, checkpoint_dir: str | Path) -> None:
  """Refuses an RMA checkpoint whose adaptation module was never trained.

  The deployable actor acts through the adaptation module; until a stage's adaptation phase has
  run, that module is its random initialisation (or whatever the stage started from), so acting,
  evaluating, recording or exporting it would measure noise. The learner counts the phase's env
  steps in checkpoint.json's "learner" section (`adaptation_env_steps`); a checkpoint with
  `network.rma` true whose count is 0, or that has no such section, is refused — unless its
  stage trains the module beside PPO (`rma.latent_regularization` > 0 in its `stage_config`)
  and PPO has run (`ppo_env_steps` > 0). The one rule `hifar act`, `eval`, `rollout` and
  `export` share (Rust applies it before Python starts: checkpoint::check_deployable).
  """
  network = meta.get("network")
  if not (isinstance(network, dict) and network.get("rma") is True):
    return
  learner = meta.get("learner")

  def positive(table, key) -> bool:
    value = table.get(key) if isinstance(table, dict) else None
    return isinstance(value, (int, float)) and not isinstance(value, bool) and value > 0

  stage = meta.get(ckpt_lib.STAGE_CONFIG_KEY)
  online = positive(stage.get("rma") if isinstance(stage, dict) else None,
                    "latent_regularization")
  if positive(learner, "adaptation_env_steps") or (online and positive(learner, "ppo_env_steps")):
    return
  raise ckpt_lib.CheckpointError(
      f"{checkpoint_dir}: its RMA adaptation module was never trained (stage "
      f"{meta.get('stage', '?')} ended before its adaptation phase); train with "
      "rma.adaptation_env_steps > 0 or evaluate a later checkpoint")


def load(checkpoint_dir: str | Path, actor: str = DEPLOYABLE) -> Policy:
  """A checkpoint's policy for `actor` (the deployable one is refused while its adaptation
  module is untrained; the privileged one does not read that module)."""
  if actor not in ACTORS:
    raise ValueError(f"actor {actor!r} is not one of {', '.join(ACTORS)}")
  d = Path(checkpoint_dir)
  ck = ckpt_lib.load(d)
  if actor == DEPLOYABLE:
    check_adaptation_trained(ck.meta, d)
  nets = nets_lib.Networks(ck.network_config())
  params, normalizer = ckpt_lib.restore_params(nets, ck.tensors)
  return Policy(directory=d, meta=ckpt_lib.read_meta(d), nets=nets, params=params,
                normalizer=normalizer)


def stage_of(policy: Policy, stage: dict | None) -> dict:
  """The stage table to rebuild the environment from: the given one, else the checkpoint's."""
  if stage is None:
    stage = policy.meta.get(ckpt_lib.STAGE_CONFIG_KEY)
  if stage is None:
    raise ValueError(f"{policy.directory}: checkpoint.json has no {ckpt_lib.STAGE_CONFIG_KEY!r}; "
                     "pass the run directory instead (its curriculum names the stage)")
  return stage


def check_features(policy: Policy, env) -> None:
  """The environment must produce exactly the observations the policy was trained on."""
  names = tuple(policy.meta["obs_names"])
  if names != tuple(env.obs_names):
    raise ValueError(f"{policy.directory}: the checkpoint's obs_names ({len(names)}) differ from "
                     f"the stage's ({len(env.obs_names)}); evaluate it with the stage it was "
                     "trained in")
  if tuple(policy.meta["action_names"]) != tuple(env.action_names):
    raise ValueError(f"{policy.directory}: the checkpoint's action_names differ from the stage's")


def episode_step(policy: Policy, env, actor: str = DEPLOYABLE) -> Callable:
  """(env_state, history) -> (env_state, history): one control step of `actor`.

  Compose it with `jax.lax.scan`; the history resets where an episode ended, as in training.
  """

  def act(state, history):
    if actor == PRIVILEGED:
      return nets_lib.privileged_mean(policy.nets, policy.params, policy.normalizer, state.obs,
                                      state.privileged)
    return policy.act(state.obs, history)

  def step(carry):
    state, history = carry
    action = act(state, history)
    nxt = env.step(state, action)
    return nxt, nets_lib.push_history(history, state.obs, nxt.done)

  return step
