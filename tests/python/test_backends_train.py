"""The same short training on both physics backends lands in the same band of metrics.

Same stage, seed and budget: the networks start identical and the environments draw identical
initial states, so the runs differ only through the physics engines (C MuJoCo and MJX agree to
the tolerance of tests/python/test_native_backend.py) and what that difference does to the
updates. A backend that diverged (a wrong sign, a missing force, a broken auto-reset) would move
the per-term rewards far outside this band.
"""

import copy

import numpy as np

from jax_env import defaults
from jax_env import facade

# Per-iteration mean rewards (per step, per term) may differ by this much between backends.
REWARD_BAND = 0.15  # relative to the magnitude of the term, plus an absolute floor
REWARD_FLOOR = 0.02


def _stage():
  s = copy.deepcopy(defaults.default_stage_dict("planar"))
  s["sim"]["episode_s"] = 0.4
  s["scenario_params"]["settle_s"] = 0.04
  s["ppo"].update(num_envs=8, unroll_length=5, num_minibatches=2, update_epochs=1,
                  policy_hidden=[16, 16], value_hidden=[16, 16], checkpoint_every=100)
  s["rma"].update(enabled=False)
  s["advance"]["env_steps"] = 120  # three PPO iterations of 8 envs × 5 steps
  return s


def _train(tmp_path, backend):
  reports = []

  def callback(progress):
    reports.append(progress)
    return "continue"

  result = facade.train_stage({
      "stage": _stage(), "stage_name": "planar", "stage_dir": str(tmp_path / backend),
      "seed": 11, "backend": backend}, callback)
  return result, reports


def test_native_and_mjx_training_reach_the_same_band(tmp_path):
  native, native_reports = _train(tmp_path, "native")
  mjx, mjx_reports = _train(tmp_path, "mjx")
  assert native["status"] == mjx["status"] == "completed"
  assert native["env_steps"] == mjx["env_steps"] == 120
  assert len(native_reports) == len(mjx_reports) == 3
  for a, b in zip(native_reports, mjx_reports):
    assert a["rewards"].keys() == b["rewards"].keys()
    for term in a["rewards"]:
      x, y = a["rewards"][term], b["rewards"][term]
      tolerance = REWARD_FLOOR + REWARD_BAND * max(abs(x), abs(y))
      assert abs(x - y) <= tolerance, (a["iteration"], term, x, y)
  # The policies after the same updates on nearly the same data act alike.
  obs = np.random.default_rng(0).normal(size=(16, len(facade.feature_names(_stage())
                                                         ["obs_names"]))).tolist()
  a = np.asarray(facade.act({"checkpoint": native["checkpoint"], "obs": obs}))
  b = np.asarray(facade.act({"checkpoint": mjx["checkpoint"], "obs": obs}))
  assert np.max(np.abs(a - b)) < 0.05, np.max(np.abs(a - b))
