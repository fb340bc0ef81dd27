"""Data parallelism: the learner splits the batch over two (simulated CPU) devices, averages
gradients and normalizer statistics across them, and learns as well as on one device.

Two CPU devices exist only if XLA is told so before JAX starts, hence the subprocess."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import safetensors.numpy

from jax_env.learner import checkpoint as ckpt_lib
from jax_env.learner import train
from toy_env import ToyStandUpEnv, learner_config

HERE = Path(__file__).resolve().parent
ITER_STEPS = 64 * 32
PPO_ITERS = 80

_SCRIPT = """
import json, sys
import jax
from jax_env.learner import train
from toy_env import ToyStandUpEnv, learner_config
assert len(jax.local_devices()) == 2, jax.local_devices()
reports = []
def callback(p):
  reports.append(p)
  return "continue"
cfg = learner_config(env_steps={ppo}, rma={{"adaptation_env_steps": {adapt}}})
result = train.train_stage(ToyStandUpEnv(), cfg, stage_dir=sys.argv[1], seed=0,
                           callback=callback)
print("RESULT " + json.dumps({{"result": result, "reports": reports}}))
"""


def _tail(reports, key, n=10):
  vals = [r[key] for r in reports[-n:] if r[key] is not None]
  return float(np.mean(vals))


@pytest.fixture(scope="module")
def two_devices(tmp_path_factory):
  stage_dir = tmp_path_factory.mktemp("two")
  env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2",
             JAX_PLATFORMS="cpu", PYTHONPATH=f"{HERE}{os.pathsep}"
             f"{os.environ.get('PYTHONPATH', '')}")
  script = _SCRIPT.format(ppo=PPO_ITERS * ITER_STEPS, adapt=2 * ITER_STEPS)
  out = subprocess.run([sys.executable, "-c", script, str(stage_dir)], env=env,
                       capture_output=True, text=True, timeout=1200)
  assert out.returncode == 0, out.stderr[-4000:]
  line = next(l for l in out.stdout.splitlines() if l.startswith("RESULT "))
  return json.loads(line[len("RESULT "):])


def test_two_devices_learn_like_one(tmp_path, two_devices):
  reports = []
  cfg = learner_config(env_steps=PPO_ITERS * ITER_STEPS, rma={"adaptation_env_steps": 0})
  train.train_stage(ToyStandUpEnv(), cfg, stage_dir=tmp_path, seed=0,
                    callback=lambda p: reports.append(p) or "continue")
  two = [r for r in two_devices["reports"] if r["phase"] == "ppo"]
  assert len(two) == len(reports) == PPO_ITERS
  assert [r["env_steps"] for r in two] == [r["env_steps"] for r in reports]
  # Different sampling keys per device: not the same numbers, the same outcome.
  assert two[-1]["losses"] != reports[-1]["losses"]
  assert _tail(two, "stand_rate") >= 0.8
  assert _tail(reports, "stand_rate") >= 0.8
  assert abs(_tail(two, "episode_return") - _tail(reports, "episode_return")) < 4.0


def test_two_device_checkpoint_is_consistent(two_devices):
  result = two_devices["result"]
  assert result["status"] == "completed"
  assert result["env_steps"] == (PPO_ITERS + 2) * ITER_STEPS
  ck = ckpt_lib.load(result["checkpoint"])
  assert ck.meta["learner"]["devices"] == 2
  # The normalizer absorbed every device's samples (psum), once per PPO iteration.
  assert int(ck.tensors["normalizer/count"]) == PPO_ITERS * ITER_STEPS
  rollout = safetensors.numpy.load_file(f"{result['checkpoint']}/rollout_state.safetensors")
  assert rollout["history"].shape == (64, 8, len(ToyStandUpEnv.obs_names))
  adapt = [r for r in two_devices["reports"] if r["phase"] == "adaptation"]
  assert len(adapt) == 2 and all(np.isfinite(r["losses"]["adaptation"]) for r in adapt)
