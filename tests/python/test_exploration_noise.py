"""Correlated exploration noise (`[stage.ppo] action_noise_correlation`, ours): the AR(1)
noise is standard normal at every step, correlated as configured, white (brax's sampling, the
very same numbers) at ρ = 0, restarted where an episode ends, validated, and trains."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jax_env import config
from jax_env.defaults import default_stage_dict
from jax_env.learner import train as train_lib


def test_zero_correlation_is_white_noise_drawn_as_before():
  key = jax.random.PRNGKey(3)
  previous = jnp.full((5, 4), 7.0)
  out = train_lib.correlated_noise(previous, key, 0.0)
  assert np.array_equal(np.asarray(out), np.asarray(jax.random.normal(key, (5, 4))))


def _chain(rho: float, steps: int, batch: int = 4096) -> np.ndarray:
  noise = jax.random.normal(jax.random.PRNGKey(0), (batch, 1))
  out = []
  for k in jax.random.split(jax.random.PRNGKey(1), steps):
    noise = train_lib.correlated_noise(noise, k, rho)
    out.append(np.asarray(noise[:, 0]))
  return np.stack(out)  # [steps, batch]


def test_correlated_noise_is_standard_normal_and_autocorrelated():
  rho = 0.9
  x = _chain(rho, 30)
  assert np.abs(x.mean()) < 0.03
  assert x.var(axis=1) == pytest.approx(np.ones(30), abs=0.07)  # stationary from the start
  for lag in (1, 5):
    corr = np.mean(x[lag:] * x[:-lag])
    assert corr == pytest.approx(rho ** lag, abs=0.03), lag
  white = _chain(0.0, 10)
  assert abs(np.mean(white[1:] * white[:-1])) < 0.03


def test_noise_restarts_where_an_episode_ended():
  noise = jnp.arange(12.0).reshape(4, 3)
  done = jnp.array([0.0, 1.0, 0.0, 1.0])
  out = np.asarray(train_lib.restart_noise(noise, jax.random.PRNGKey(2), done))
  assert np.array_equal(out[[0, 2]], np.asarray(noise)[[0, 2]])
  assert not np.any(np.isin(out[[1, 3]], np.asarray(noise)))
  assert np.all(np.abs(out[[1, 3]]) < 5.0)  # fresh N(0, 1) draws, not the old values


@pytest.mark.parametrize("value,message", [
    (1.0, "action_noise_correlation 1.0 must be below 1"),
    (-0.1, None), ("0.9", None)])
def test_correlation_is_validated(value, message):
  d = default_stage_dict("planar")
  d["ppo"]["action_noise_correlation"] = value
  errors = config.check_stage(d)
  assert [e["path"] for e in errors] == [["ppo", "action_noise_correlation"]]
  if message:
    assert errors[0]["message"] == message


def test_correlation_reaches_the_stage_config():
  d = default_stage_dict("planar")
  assert config.parse_stage(d).ppo.action_noise_correlation == 0.0
  d["ppo"]["action_noise_correlation"] = 0.95
  assert config.parse_stage(d).ppo.action_noise_correlation == 0.95


def test_training_with_correlated_noise_runs_and_repeats(tmp_path):
  from toy_env import ToyStandUpEnv, learner_config
  cfg = learner_config(env_steps=3 * 2048, ppo={"action_noise_correlation": 0.9},
                       rma={"adaptation_env_steps": 0})
  curves = []
  for name in ("a", "b"):
    curve = []

    def callback(progress, curve=curve):
      curve.append(progress["episode_return"] or progress["losses"]["total"])
      return "continue"

    result = train_lib.train_stage(ToyStandUpEnv(), cfg, stage_dir=tmp_path / name, seed=0,
                                   callback=callback)
    assert result["status"] == "completed"
    curves.append(curve)
  assert len(curves[0]) == 3 and np.all(np.isfinite(curves[0]))
  assert curves[0] == curves[1]  # one seed, one set of numbers
