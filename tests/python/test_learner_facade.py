"""The facade the Rust CLI calls, end to end on the real FallRecoveryEnv (tiny sizes, the
native C MuJoCo backend, which compiles in seconds on a CPU)."""

import copy
import json
import math

import numpy as np
import pytest

from jax_env import defaults
from jax_env import facade
from jax_env.learner import checkpoint as ckpt_lib


def _tiny_stage():
  s = copy.deepcopy(defaults.default_stage_dict("planar"))
  s["sim"]["episode_s"] = 0.4
  s["scenario_params"]["settle_s"] = 0.04
  s["success"]["hold_s"] = 0.2  # shorter than the episode, as `check_stage` asks
  s["ppo"].update(num_envs=8, unroll_length=4, num_minibatches=2, update_epochs=1,
                  policy_hidden=[16, 16], value_hidden=[16, 16], checkpoint_every=1)
  s["rma"].update(latent_dim=4, encoder_hidden=[16], history_len=4, adaptation_env_steps=32)
  s["advance"]["env_steps"] = 64  # two PPO iterations of 8 envs × 4 steps
  return s


def test_versions_doctor_names_and_checks():
  v = facade.versions()
  assert v["jax"] == "0.9.2" and v["brax"] == "0.14.2" and v["python"].startswith("3.11")
  d = facade.doctor()
  assert d["devices"] and d["default_backend"] in ("native", "mjx") and d["reason"]
  assert d["problems"] == []
  stage = _tiny_stage()
  names = facade.feature_names(stage)
  assert names["obs_names"][:3] == ["gravity/x", "gravity/y", "gravity/z"]
  assert len(names["action_names"]) == 10
  assert facade.check_stage(stage) == []
  bad = copy.deepcopy(stage)
  bad["controlled_joints"][3] = "Left_Elbow_Twist"
  problems = facade.check_stage(bad)
  assert problems and problems[0]["path"][0] == "controlled_joints"
  with pytest.raises(ValueError, match="unknown request key"):
    facade.train_stage({"stage": stage, "bogus": 1}, None)
  with pytest.raises(ValueError, match="unknown backend 'gpu'"):
    facade.train_stage({"stage": stage, "stage_dir": "x", "seed": 1, "backend": "gpu"}, None)


def test_train_stage_smoke_on_the_real_env(tmp_path):
  stage = _tiny_stage()
  reports = []

  def callback(progress):
    json.dumps(progress)  # JSON-like, as the Rust side needs
    reports.append(progress)
    return "continue"

  log = tmp_path / "run.log"
  result = facade.train_stage({
      "stage": stage, "stage_name": "planar", "stage_dir": str(tmp_path / "planar"),
      "seed": 7, "backend": "native", "num_envs": None, "init_checkpoint": None,
      "resume_checkpoint": None, "log_file": str(log)}, callback)
  assert result["status"] == "completed"
  assert result["env_steps"] == 96
  assert [r["phase"] for r in reports] == ["ppo", "ppo", "adaptation"]
  for r in reports:
    assert all(math.isfinite(v) for v in r["losses"].values()), r["losses"]
  assert set(reports[0]["rewards"]) >= {"survival", "base_height", "standing"}
  latest = ckpt_lib.read_latest(tmp_path / "planar" / "checkpoints")
  assert str(latest) == result["checkpoint"]
  meta = ckpt_lib.read_meta(latest)
  names = facade.feature_names(stage)
  assert meta["obs_names"] == names["obs_names"]
  assert meta["action"] == {"mapping": "current", "scale": 0.5, "clip": 1.0}
  assert meta["stage"] == "planar" and meta["seed"] == 7
  assert meta["stage_config"] == stage  # evaluation and export rebuild the env from it
  assert "[learner]" in log.read_text()

  n_obs = len(names["obs_names"])
  obs = np.random.default_rng(0).normal(size=(2, n_obs)).tolist()
  actions = facade.act({"checkpoint": result["checkpoint"], "obs": obs})
  assert np.asarray(actions).shape == (2, len(names["action_names"]))
  zeros = [[[0.0] * n_obs] * 4] * 2
  assert facade.act({"checkpoint": result["checkpoint"], "obs": obs, "history": zeros}) == actions

  # Resuming the finished stage restores the real environment's full rollout state (every
  # leaf by name, shape and dtype) and returns at once.
  again = facade.train_stage({
      "stage": stage, "stage_name": "planar", "stage_dir": str(tmp_path / "planar"),
      "seed": 7, "backend": "native", "resume_checkpoint": result["checkpoint"]},
      lambda p: pytest.fail("a finished stage runs no iteration"))
  assert again == result
