"""The deterministic stand-rate monitor: how the noise-free policy does from each start state.

PPO's own stand rate counts the episodes of the *stochastic* policy under domain randomization,
and it can hold steady while the deterministic policy loses a get-up it had (hifar's run E in
shared/reference/GETUP-RECIPES.md §4). Every `monitor.every` iterations the learner therefore
runs `monitor.episodes` episodes from each monitored start scenario under nominal conditions
(evaluation.conditions.evaluation_stage: no randomization, pushes or delay, flat ground; the
stage's terminations apply, as in `hifar eval`, so that a get-up through a terminated posture —
head down past `termination.upside_down` — counts as the failure the evaluation will call it)
with a noise-free actor — during PPO the training-time policy (the privileged actor: the
encoder's latent of the simulator's state, as `hifar eval --actor privileged` acts), during
the adaptation phase the deployable one (the adaptation module's latent of the observation
history, as `hifar eval` acts), each the actor whose parameters that phase trains — and reports per
scenario: the stand rate (stable standing held for success.hold_s, the paper's criterion), the
mean recovery time of the successes, the mean highest Trunk height, and the share of episodes a
termination rule ended (a get-up that a rule cuts short reads here, not as a failure to rise).

The episodes' keys come from the stage seed alone (`MONITOR_SEED_SALT`), the same at every
monitor call, so successive numbers differ only by the policy.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Mapping

import jax
import jax.numpy as jnp
import numpy as np

from jax_env import stage_config
from jax_env.evaluation.policy import DEPLOYABLE, PRIVILEGED
from jax_env.learner import networks as nets_lib
from jax_env.scenarios import SCENARIOS

MONITOR_SEED_SALT = 0x6D6F6E  # "mon"


@dataclasses.dataclass(frozen=True)
class Monitor:
  """Runs the monitor episodes; `__call__(params, normalizer[, actor]) -> progress["monitor"]`."""

  scenarios: tuple[str, ...]
  episodes: int
  runs: Mapping[str, Callable[[Any, Any], dict]]  # by actor; each jit-compiled on first use

  def __call__(self, params, normalizer, actor: str = PRIVILEGED) -> dict:
    out = jax.device_get(self.runs[actor](params, normalizer))
    per = {k: np.asarray(v).reshape(len(self.scenarios), self.episodes) for k, v in out.items()}
    result: dict[str, Any] = {"stand_rate": {}, "recovery_time": {}, "max_height": {},
                              "terminated": {}}
    rules = [stage_config.EPISODE_ENDS.index(r) for r in stage_config.TERMINATION_RULES]
    for i, name in enumerate(self.scenarios):
      success = per["success"][i] > 0
      result["stand_rate"][name] = float(np.mean(success))
      times = per["recovery_time"][i][success]
      result["recovery_time"][name] = float(np.mean(times)) if times.size else None
      result["max_height"][name] = float(np.mean(per["max_height"][i]))
      result["terminated"][name] = float(np.mean(np.isin(per["end"][i], rules)))
    result["mean_stand_rate"] = float(np.mean(list(result["stand_rate"].values())))
    result["actor"] = actor
    return result


def make_monitor(config: stage_config.MonitorConfig | None,
                 stage_table: Mapping[str, Any] | None, nets: nets_lib.Networks,
                 backend: str | None, seed_key: jax.Array) -> Monitor | None:
  """The stage's monitor (`config.scenarios` resolved, see LearnerConfig.from_stage), or None
  when it is off or the environment cannot be rebuilt (no stage table or backend name)."""
  if config is None or config.every <= 0 or stage_table is None or backend is None:
    return None
  from jax_env.env import FallRecoveryEnv
  from jax_env.evaluation.conditions import evaluation_stage

  env = FallRecoveryEnv(evaluation_stage(stage_table), backend=backend)
  scenarios = tuple(config.scenarios)
  n = config.episodes
  forced = jnp.asarray(np.repeat([SCENARIOS.index(s) for s in scenarios], n),
                       jnp.int32)
  keys = jax.random.split(jax.random.fold_in(seed_key, MONITOR_SEED_SALT), forced.shape[0])
  steps = env.episode_steps
  names = ("success", "recovery_time", "max_height", "end")

  def make_run(actor: str):
    deployable = actor == DEPLOYABLE
    history_shape = (forced.shape[0], nets.config.history_len, nets.config.obs_size)

    @jax.jit
    def run(params, normalizer):
      state = env.reset(keys, scenario=forced)

      def step(carry, _):
        es, hist, ended, record = carry
        if deployable:  # as `hifar eval` acts: the observation history, no privileged input
          action = nets_lib.deployable_mean(nets, params, normalizer, es.obs, hist)
        else:
          action = nets_lib.privileged_mean(nets, params, normalizer, es.obs, es.privileged)
        nxt = env.step(es, action)
        hist = nets_lib.push_history(hist, es.obs, nxt.done) if deployable else hist
        first = (nxt.done > 0) & ~ended
        record = {k: jnp.where(first, nxt.episode_metrics[k], record[k]) for k in names}
        return (nxt, hist, ended | first, record), None

      record = {k: jnp.zeros(forced.shape, jnp.float32) for k in names}
      hist = jnp.zeros(history_shape, jnp.float32) if deployable else None
      carry = (state, hist, jnp.zeros(forced.shape, bool), record)
      (_, _, _, record), _ = jax.lax.scan(step, carry, None, length=steps)
      return record

    return run

  return Monitor(scenarios=scenarios, episodes=n,
                 runs={actor: make_run(actor) for actor in (PRIVILEGED, DEPLOYABLE)})


def is_due(iteration: int, every: int, last: bool) -> bool:
  """Whether the monitor runs after `iteration` (1-based): every `every`, and at the end."""
  return every > 0 and (iteration % every == 0 or last)

