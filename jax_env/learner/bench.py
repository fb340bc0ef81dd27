"""Learner update throughput: `python -m jax_env.learner.bench [--envs N] [--json]`.

Times the PPO update alone (GAE, `update_epochs` × `num_minibatches` Adam steps with the
mirror loss, normalizer update) and the RMA adaptation update on synthetic rollouts with the
feature sizes of the paper's second stage (all 23 joints observed, 12 controlled) and the
curriculum's default network sizes (policy and value 512-256-128, encoder 256-128, latent 8,
history 50). Samples/s = transitions in the rollout / seconds per update, so every sample is
used `update_epochs` times within that second. No environment is stepped: this isolates the
learner from the physics (jax_env.bench measures whole iterations).
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp

from jax_env import defaults, features
from jax_env.stage_config import StageConfig
from jax_env.learner import networks as nets_lib
from jax_env.learner import ppo as ppo_lib
from jax_env.learner import rma as rma_lib


def measure(num_envs: int = 1024, unroll_length: int = 20, num_minibatches: int = 8,
            update_epochs: int = 4, repeats: int = 3, mirror_weight: float = 0.5) -> dict:
  stage = StageConfig.from_dict(defaults.default_stage_dict("full"))
  obs_names, priv_names, act_names = features.feature_names(stage)
  ppo = stage.ppo.__class__(**{**stage.ppo.__dict__, "num_envs": num_envs,
                               "unroll_length": unroll_length,
                               "num_minibatches": num_minibatches,
                               "update_epochs": update_epochs, "policy_hidden": (512, 256, 128),
                               "value_hidden": (512, 256, 128)})
  cfg = nets_lib.NetworkConfig(
      obs_size=len(obs_names), privileged_size=len(priv_names), action_size=len(act_names),
      policy_hidden=ppo.policy_hidden, value_hidden=ppo.value_hidden, activation="elu",
      rma=True, latent_dim=8, encoder_hidden=(256, 128), history_len=50, initial_action_std=1.0)
  nets = nets_lib.Networks(cfg)
  maps = stage_maps(obs_names, priv_names, act_names)
  key = jax.random.PRNGKey(0)
  state = jax.jit(lambda k: ppo_lib.init_learner_state(nets, nets.init(k), 1.0, 3e-4))(key)
  t, b = unroll_length, num_envs
  ks = jax.random.split(key, 8)
  data = ppo_lib.Transition(
      obs=jax.random.normal(ks[0], (t, b, cfg.obs_size)),
      privileged=jax.random.normal(ks[1], (t, b, cfg.privileged_size)),
      action=jax.random.normal(ks[2], (t, b, cfg.action_size)),
      loc=jnp.zeros((t, b, cfg.action_size)),
      log_prob=jnp.full((t, b), -cfg.action_size * 1.4189),
      reward=jax.random.normal(ks[3], (t, b)), done=jnp.zeros((t, b)),
      truncation=jnp.zeros((t, b)), active=jnp.ones((t, b)))
  final_obs, final_priv = data.obs[-1], data.privileged[-1]

  update = jax.jit(lambda s, k: ppo_lib.ppo_update(
      s, data, final_obs, final_priv, k, nets=nets, cfg=ppo, mirror_weight=mirror_weight,
      maps=maps))
  windows = jax.random.normal(ks[4], (t, b, cfg.history_len, cfg.obs_size))
  batch = rma_lib.AdaptationBatch(window=windows, privileged=data.privileged)
  adapt = jax.jit(lambda s, k: rma_lib.adaptation_update(s, batch, k, nets=nets, cfg=ppo,
                                                         learning_rate=1e-3))
  out = {"device": str(jax.devices()[0]), "num_envs": b, "unroll_length": t,
         "num_minibatches": num_minibatches, "update_epochs": update_epochs,
         "obs": cfg.obs_size, "privileged": cfg.privileged_size, "actions": cfg.action_size}
  for name, fn in (("ppo_update", update), ("adaptation_update", adapt)):
    t0 = time.perf_counter()
    jax.block_until_ready(fn(state, key))
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    for i in range(repeats):
      jax.block_until_ready(fn(state, jax.random.fold_in(key, i)))
    dt = (time.perf_counter() - t0) / repeats
    out[name] = {"seconds_per_update": dt, "samples_per_s": t * b / dt,
                 "first_call_s": compile_s}
  return out


def stage_maps(obs_names, priv_names, act_names):
  from jax_env.env import MirrorMaps
  return MirrorMaps(*features.mirror_map(obs_names), *features.mirror_map(priv_names),
                    *features.mirror_map(act_names, kind="action"))


def main() -> None:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--envs", type=int, default=1024)
  p.add_argument("--unroll", type=int, default=20)
  p.add_argument("--minibatches", type=int, default=8)
  p.add_argument("--epochs", type=int, default=4)
  p.add_argument("--repeats", type=int, default=3)
  p.add_argument("--json", action="store_true")
  a = p.parse_args()
  out = measure(a.envs, a.unroll, a.minibatches, a.epochs, a.repeats)
  if a.json:
    print(json.dumps(out))
    return
  print(f"{out['device']}: {out['num_envs']} envs × {out['unroll_length']} steps, "
        f"{out['num_minibatches']} minibatches × {out['update_epochs']} epochs")
  for name in ("ppo_update", "adaptation_update"):
    r = out[name]
    print(f"  {name:18s} {r['samples_per_s']:12,.0f} samples/s  "
          f"({r['seconds_per_update']:.3f} s per update, first call {r['first_call_s']:.1f} s)")


if __name__ == "__main__":
  main()
