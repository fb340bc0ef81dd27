"""ONNX export: parity with the deployable actor (`facade.act`) for RMA and non-RMA
checkpoints, the action mapping of `joint_target`, metadata, and refusals that write nothing.

Checkpoints are made directly with the learner's own code (network init, a normalizer updated
with data, weights perturbed as after training, `checkpoint.save`), so no environment is
compiled and nothing is trained.
"""

import copy
import json
import math
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import onnx
import onnxruntime as ort
import pytest
import safetensors.numpy

from jax_env import defaults, features
from jax_env import export as export_lib
from jax_env import facade
from jax_env import robot
from jax_env.learner import checkpoint as ckpt_lib
from jax_env.learner import networks as nets_lib
from jax_env.learner import ppo as ppo_lib


def _stage(kind, *, rma, history_len, hidden, activation, mapping):
  s = copy.deepcopy(defaults.default_stage_dict(kind))
  s["ppo"].update(policy_hidden=list(hidden), value_hidden=[16], activation=activation)
  s["rma"].update(enabled=rma, latent_dim=8, encoder_hidden=[16], history_len=history_len)
  s["action"]["mapping"] = mapping
  return s


def _checkpoint(path, stage, *, seed, with_stage_config=True, adaptation_env_steps=4096):
  """A checkpoint of `stage`'s layout with non-trivial weights and statistics, whose learner
  section records `adaptation_env_steps` of RMA adaptation (None: no learner section)."""
  obs_names, priv_names, act_names = features.feature_names(stage)
  p, r = stage["ppo"], stage["rma"]
  config = nets_lib.NetworkConfig(
      obs_size=len(obs_names), privileged_size=len(priv_names), action_size=len(act_names),
      policy_hidden=tuple(p["policy_hidden"]), value_hidden=tuple(p["value_hidden"]),
      activation=p["activation"], rma=r["enabled"], latent_dim=r["latent_dim"],
      encoder_hidden=tuple(r["encoder_hidden"]), history_len=r["history_len"],
      initial_action_std=1.0)
  nets = nets_lib.Networks(config)
  state = ppo_lib.init_learner_state(nets, nets.init(jax.random.PRNGKey(seed)), 1.0, 3e-4)
  keys = iter(jax.random.split(jax.random.PRNGKey(seed + 1), 100))

  def trained_like(x):  # O(1) actions in distribution, as after training (not the tiny head)
    fan_in = x.shape[-2] * (x.shape[0] if x.ndim == 3 else 1) if x.ndim > 1 else 100
    return x + 0.5 / math.sqrt(fan_in) * jax.random.normal(next(keys), x.shape)

  params = jax.tree_util.tree_map(trained_like, state.params)
  rng = np.random.default_rng(seed)
  obs = rng.normal(rng.normal(0, 1, config.obs_size), rng.uniform(0.05, 2.0, config.obs_size),
                   (400, config.obs_size))
  priv = rng.normal(0.0, 1.0, (400, config.privileged_size))
  normalizer = nets_lib.update_normalizer(state.normalizer, jnp.asarray(obs, jnp.float32),
                                          jnp.asarray(priv, jnp.float32))
  state = state.replace(params=params, normalizer=normalizer)
  extra = {ckpt_lib.STAGE_CONFIG_KEY: stage} if with_stage_config else {}
  if adaptation_env_steps is not None:
    extra["learner"] = {"phase": "done", "ppo_env_steps": 4096,
                        "adaptation_env_steps": adaptation_env_steps}
  return str(ckpt_lib.save(path, state=state, config=config, stage=stage["name"],
                           env_steps=4096, iteration=2, seed=seed, key=jax.random.PRNGKey(3),
                           obs_names=obs_names, privileged_names=priv_names,
                           action_names=act_names, action=stage["action"], extra=extra))


@pytest.fixture(scope="module")
def rma_checkpoint(tmp_path_factory):
  """Paper-sized actor (policy 512-256-128, 50-step history) of the full stage, elu."""
  stage = _stage("full", rma=True, history_len=50, hidden=(512, 256, 128), activation="elu",
                 mapping="current")
  return _checkpoint(tmp_path_factory.mktemp("rma") / "ck", stage, seed=1), stage


@pytest.fixture(scope="module")
def plain_checkpoint(tmp_path_factory):
  """No adaptation module, swish, the "default" mapping, and no stage_config."""
  stage = _stage("planar", rma=False, history_len=6, hidden=(32, 16), activation="swish",
                 mapping="default")
  return (_checkpoint(tmp_path_factory.mktemp("plain") / "ck", stage, seed=2,
                      with_stage_config=False), stage)


def _session(path):
  return ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])


def _rows(ckpt, n, seed, history=True):
  """In-distribution rows: drawn from the checkpoint's observation statistics."""
  t = safetensors.numpy.load_file(str(pathlib.Path(ckpt) / ckpt_lib.PARAMS_FILE))
  mean, std = t["normalizer/obs/mean"], t["normalizer/obs/std"]
  h = ckpt_lib.read_meta(ckpt)["network"]["history_len"]
  rng = np.random.default_rng(seed)
  obs = rng.normal(mean, std, (n, len(mean))).astype(np.float32)
  hist = rng.normal(mean, std, (n, h, len(mean))) if history else np.zeros((n, h, len(mean)))
  return obs, hist.astype(np.float32)


def _props(path):
  return {p.key: p.value for p in onnx.load(str(path)).metadata_props}


def test_rma_export_matches_act_and_documents_itself(rma_checkpoint, tmp_path):
  ckpt, stage = rma_checkpoint
  out = tmp_path / "actor.onnx"
  result = facade.export_onnx({"checkpoint": ckpt, "out": str(out), "tolerance": 1e-5})
  meta = ckpt_lib.read_meta(ckpt)
  n_obs, n_act = len(meta["obs_names"]), len(meta["action_names"])
  assert result["path"] == str(out) and out.is_file()
  assert result["opset"] == export_lib.OPSET
  assert result["inputs"] == [{"name": "obs", "shape": ["N", n_obs]},
                              {"name": "history", "shape": ["N", 50, n_obs]}]
  assert result["outputs"] == [{"name": "action", "shape": ["N", n_act]},
                               {"name": "joint_target", "shape": ["N", n_act]}]
  assert result["parity_rows"] >= 200
  assert 0.0 <= result["parity_max_scaled_diff"] <= 1e-5
  assert result["parity_max_abs_diff"] >= result["parity_max_scaled_diff"]
  assert result["history_input"] == "used"
  print(f"paper-sized RMA actor: max abs diff {result['parity_max_abs_diff']:.3g}, scaled "
        f"{result['parity_max_scaled_diff']:.3g} over {result['parity_rows']} rows")

  # Independently of the built-in check: onnxruntime on fresh rows vs facade.act.
  session = _session(out)
  for seed, with_history in ((10, True), (11, False)):
    obs, hist = _rows(ckpt, 8, seed, with_history)
    action, _ = session.run(None, {"obs": obs, "history": hist})
    expected = np.asarray(facade.act({"checkpoint": ckpt, "obs": obs.tolist(),
                                      "history": hist.tolist() if with_history else None}))
    np.testing.assert_allclose(action, expected, rtol=0, atol=1e-5)
  # The history matters (the adaptation module is in the graph).
  obs, hist = _rows(ckpt, 4, 12)
  a_hist, _ = session.run(None, {"obs": obs, "history": hist})
  a_zero, _ = session.run(None, {"obs": obs, "history": np.zeros_like(hist)})
  assert np.abs(a_hist - a_zero).max() > 1e-3

  props = _props(out)
  assert json.loads(props["obs_names"]) == meta["obs_names"]
  assert json.loads(props["action_names"]) == meta["action_names"]
  assert json.loads(props["history_len"]) == 50
  assert json.loads(props["ctrl_dt"]) == stage["sim"]["ctrl_dt"]
  assert props["mapping"] == "current"
  assert json.loads(props["scale"]) == stage["action"]["scale"]
  assert json.loads(props["clip"]) == stage["action"]["clip"]
  stand = robot.stand_pose()
  q_stand = [stand[robot.JOINT_NAMES.index(j)] for j in meta["action_names"]]
  np.testing.assert_allclose(json.loads(props["q_stand"]), q_stand, atol=1e-7)
  assert props["checkpoint"] == str(pathlib.Path(ckpt).resolve())
  assert json.loads(props["checkpoint_env_steps"]) == 4096
  assert props["checkpoint_stage"] == "full"
  assert len(props["checkpoint_params_sha256"]) == 64
  assert json.loads(props["hifar"])["onnxruntime"] == ort.__version__
  assert "history" in props["description"] and props["history_input"] == "used"


def test_joint_target_applies_the_current_mapping(rma_checkpoint, tmp_path):
  ckpt, _ = rma_checkpoint
  out = tmp_path / "actor.onnx"
  facade.export_onnx({"checkpoint": ckpt, "out": str(out)})
  meta = ckpt_lib.read_meta(ckpt)
  obs, hist = _rows(ckpt, 16, 20)
  obs *= 4.0  # large enough that some actions exceed the clip
  action, target = _session(out).run(None, {"obs": obs, "history": hist})
  assert np.abs(action).max() > 1.0, "the check needs clipped actions"
  index = [meta["obs_names"].index(f"joint_pos/{j}") for j in meta["action_names"]]
  stand = robot.stand_pose()
  q_stand = np.asarray([stand[robot.JOINT_NAMES.index(j)] for j in meta["action_names"]])
  expected = obs[:, index] + q_stand + 0.5 * np.clip(action, -1.0, 1.0)
  np.testing.assert_allclose(target, expected, rtol=0, atol=2e-6)


def test_non_rma_export_with_default_mapping(plain_checkpoint, tmp_path):
  ckpt, stage = plain_checkpoint
  out = tmp_path / "plain.onnx"
  result = facade.export_onnx({"checkpoint": ckpt, "out": str(out)})
  assert result["parity_max_scaled_diff"] <= 1e-5 and result["history_input"] == "ignored"
  meta = ckpt_lib.read_meta(ckpt)
  session = _session(out)
  obs, hist = _rows(ckpt, 8, 30)
  action, target = session.run(None, {"obs": obs, "history": hist})
  np.testing.assert_allclose(action, facade.act({"checkpoint": ckpt, "obs": obs.tolist()}),
                             rtol=0, atol=1e-5)
  # The history is accepted and ignored.
  action0, _ = session.run(None, {"obs": obs, "history": np.zeros_like(hist)})
  np.testing.assert_array_equal(action, action0)
  # "default": q_stand + scale·clip(a), whatever the measured joint positions.
  stand = robot.stand_pose()
  q_stand = np.asarray([stand[robot.JOINT_NAMES.index(j)] for j in meta["action_names"]])
  np.testing.assert_allclose(target, q_stand + 0.5 * np.clip(action, -1, 1), rtol=0, atol=1e-6)
  props = _props(out)
  assert props["mapping"] == "default" and props["history_input"] == "ignored"
  assert props["rma"] == "false" and "IGNORED" in props["description"]
  # No stage_config in the checkpoint and no stage given: ctrl_dt is left out, not guessed...
  assert "ctrl_dt" not in props
  # ...and a given stage table supplies it.
  facade.export_onnx({"checkpoint": ckpt, "out": str(out), "stage": stage})
  assert json.loads(_props(out)["ctrl_dt"]) == stage["sim"]["ctrl_dt"]


def test_refusals_write_nothing(plain_checkpoint, rma_checkpoint, tmp_path):
  ckpt, _ = plain_checkpoint
  out = tmp_path / "x.onnx"
  # A tolerance no float32 computation meets: the parity check fails with its number.
  with pytest.raises(ValueError, match=r"ONNX parity check failed: \|onnx - jax\| / max\(1, "
                                       r"\|jax\|\) of `action` reaches [0-9.e-]+ \(row \d+, "
                                       r"\w+; max abs diff .* above the tolerance 1e-30"):
    facade.export_onnx({"checkpoint": rma_checkpoint[0], "out": str(out), "tolerance": 1e-30})
  with pytest.raises(ValueError, match="no such directory"):
    facade.export_onnx({"checkpoint": ckpt, "out": str(tmp_path / "missing" / "x.onnx")})
  with pytest.raises(ValueError, match="is a directory"):
    facade.export_onnx({"checkpoint": ckpt, "out": str(tmp_path)})
  with pytest.raises(ValueError, match="unknown request key.*valid: checkpoint, out"):
    facade.export_onnx({"checkpoint": ckpt, "out": str(out), "force": True})
  with pytest.raises(ValueError, match="tolerance must be a positive number"):
    facade.export_onnx({"checkpoint": ckpt, "out": str(out), "tolerance": -1})
  with pytest.raises(ValueError, match="is not the stage this checkpoint acts in"):
    full = _stage("full", rma=False, history_len=6, hidden=(32, 16), activation="swish",
                  mapping="default")
    facade.export_onnx({"checkpoint": ckpt, "out": str(out), "stage": full})
  with pytest.raises(ckpt_lib.CheckpointError, match="no such checkpoint directory"):
    facade.export_onnx({"checkpoint": str(tmp_path / "nope"), "out": str(out)})
  assert list(tmp_path.iterdir()) == [], "nothing written, no temporary files left"

  # An RMA checkpoint whose adaptation module was never trained (a checkpoint of the PPO phase,
  # or one without the learner's section) is refused before anything is built.
  stage = _stage("full", rma=True, history_len=4, hidden=(16,), activation="elu",
                 mapping="current")
  for steps, name in ((0, "ppo_phase"), (None, "no_learner")):
    untrained = _checkpoint(tmp_path.parent / f"{tmp_path.name}_{name}", stage, seed=4,
                            adaptation_env_steps=steps)
    with pytest.raises(ckpt_lib.CheckpointError) as e:
      facade.export_onnx({"checkpoint": untrained, "out": str(out)})
    assert str(e.value) == (
        f"{pathlib.Path(untrained).resolve()}: its RMA adaptation module was never trained "
        "(stage full ended before its adaptation phase); train with "
        "rma.adaptation_env_steps > 0 or evaluate a later checkpoint")
  assert list(tmp_path.iterdir()) == [], "nothing written, no temporary files left"

  # An existing file is replaced atomically (no temporary sibling left behind).
  out.write_bytes(b"old")
  facade.export_onnx({"checkpoint": ckpt, "out": str(out)})
  assert onnx.load(str(out)).graph.output[0].name == "action"
  assert sorted(p.name for p in tmp_path.iterdir()) == ["x.onnx"]
