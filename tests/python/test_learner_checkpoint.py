"""Checkpoints: round trip, annotations sufficient for expansion by name, refusal of bad
checkpoints with clear messages, atomic writes, and act() on the deployable actor."""

import dataclasses
import json
import math
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import safetensors.numpy

from jax_env import facade
from jax_env import files as files_lib
from jax_env.learner import checkpoint as ckpt_lib
from jax_env.learner import networks as nets_lib
from jax_env.learner import ppo as ppo_lib
from toy_env import ToyStandUpEnv

ENV = ToyStandUpEnv()
NAMES = {"obs": list(ENV.obs_names), "privileged": list(ENV.privileged_names),
         "action": list(ENV.action_names)}
ACTION = {"mapping": "current", "scale": 1.0, "clip": 1.0}


def _config(names=NAMES, rma=True, std=0.5):
  return nets_lib.NetworkConfig(
      obs_size=len(names["obs"]), privileged_size=len(names["privileged"]),
      action_size=len(names["action"]), policy_hidden=(16, 8), value_hidden=(16,),
      activation="elu", rma=rma, latent_dim=3, encoder_hidden=(8,), history_len=6,
      initial_action_std=std)


def _trained_like_state(config, seed=0):
  """A learner state with non-trivial values everywhere (as after some training)."""
  nets = nets_lib.Networks(config)
  state = ppo_lib.init_learner_state(nets, nets.init(jax.random.PRNGKey(seed)), 1.0, 3e-4)
  keys = iter(jax.random.split(jax.random.PRNGKey(seed + 100), 1000))

  def noisy(x):
    if jnp.issubdtype(x.dtype, jnp.floating) and x.ndim > 0:
      return x + 0.1 * jax.random.normal(next(keys), x.shape)
    return x

  params = jax.tree_util.tree_map(noisy, state.params)
  opt = (state.opt_state[0], state.opt_state[1]._replace(
      count=jnp.asarray(7, jnp.int32), mu=jax.tree_util.tree_map(noisy, state.opt_state[1].mu),
      nu=jax.tree_util.tree_map(lambda x: jnp.abs(noisy(x)), state.opt_state[1].nu)))
  rng = np.random.default_rng(seed)
  obs = jnp.asarray(rng.normal(2.0, 3.0, (500, config.obs_size)), jnp.float32)
  priv = jnp.asarray(rng.normal(-1.0, 0.5, (500, config.privileged_size)), jnp.float32)
  normalizer = nets_lib.update_normalizer(state.normalizer, obs, priv)
  return nets, state.replace(params=params, opt_state=opt, normalizer=normalizer,
                             learning_rate=jnp.asarray(1.7e-3, jnp.float32))


def _save(path, state, config, names=NAMES, **extra):
  return ckpt_lib.save(path, state=state, config=config, stage="toy", env_steps=4096,
                       iteration=2, seed=7, key=jax.random.PRNGKey(3), obs_names=names["obs"],
                       privileged_names=names["privileged"], action_names=names["action"],
                       action=ACTION, extra=extra or None)


def _leaves_equal(a, b):
  la, lb = jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)
  assert len(la) == len(lb)
  for x, y in zip(la, lb):
    np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_round_trip_is_exact(tmp_path):
  config = _config()
  nets, state = _trained_like_state(config)
  d = _save(tmp_path / "ck", state, config)
  assert sorted(os.listdir(tmp_path)) == ["ck"], "no temporary directory left behind"
  ck = ckpt_lib.load(d)
  template = ppo_lib.init_learner_state(nets, nets.init(jax.random.PRNGKey(9)), 1.0, 3e-4)
  restored = ckpt_lib.restore_learner(template, ck.tensors, fresh_optimizer=False)
  _leaves_equal(restored, state)
  assert int(restored.normalizer.count.to_numpy()) == 500
  assert ck.meta["prng_key"] == [0, 3]
  assert ck.tensors["normalizer/count"].dtype == np.int64
  assert ck.tensors["opt/count"].dtype == np.int32


def test_every_tensor_is_annotated_consistently(tmp_path):
  config = _config()
  _, state = _trained_like_state(config)
  ck = ckpt_lib.load(_save(tmp_path / "ck", state, config))
  sizes = {k: len(v) for k, v in NAMES.items()}
  assert set(ck.meta["tensors"]) == set(ck.tensors)
  for name, ann in ck.meta["tensors"].items():
    shape = ann["shape"]
    assert list(ck.tensors[name].shape) == shape
    assert len(ann["axes"]) == len(shape), name
    for axis, segs in enumerate(ann["axes"]):
      if segs is not None:
        covered = sum(s["fixed"] if "fixed" in s else sizes[s["features"]] for s in segs)
        assert covered == shape[axis], name
  t = ck.meta["tensors"]
  assert t["policy/hidden_0/kernel"]["axes"] == [[{"features": "obs"}, {"fixed": 3}], None]
  assert t["policy/hidden_2/kernel"]["axes"] == [None, [{"features": "action"}]]
  assert t["policy/hidden_2/bias"]["axes"] == [[{"features": "action"}]]
  assert t["policy/log_std"] == {"shape": [2], "axes": [[{"features": "action"}]],
                                 "fill": "log_initial_action_std"}
  assert t["value/hidden_0/kernel"]["axes"][0] == [{"features": "obs"},
                                                   {"features": "privileged"}]
  assert t["encoder/hidden_0/kernel"]["axes"][0] == [{"features": "privileged"}]
  assert t["adaptation/conv_0/kernel"]["axes"] == [None, [{"features": "obs"}], None]
  assert t["normalizer/obs/std"]["fill"] == 1.0 and t["normalizer/obs/mean"]["fill"] == 0.0
  assert t["opt/policy/mu/hidden_0/kernel"]["axes"] == t["policy/hidden_0/kernel"]["axes"]
  assert t["opt/policy/nu/log_std"]["fill"] == 0.0
  assert t["opt/adaptation/mu/conv_0/kernel"]["axes"][1] == [{"features": "obs"}]


# ---------------------------------------------------------------------------------------------
# Expansion by annotation, as the Rust CLI does it (docs/contracts.md): the actor must give the
# same actions for the old action names whatever the new features are, and 0 for new actions.


def _expand(meta, tensors, target, log_std0):
  out = {}
  for name, x in tensors.items():
    ann = meta["tensors"][name]
    for axis, segs in enumerate(ann["axes"]):
      if segs is None:
        continue
      old, new = [], []
      for s, seg in enumerate(segs):
        if "fixed" in seg:
          old += [("fixed", s, i) for i in range(seg["fixed"])]
          new += [("fixed", s, i) for i in range(seg["fixed"])]
        else:
          kind = seg["features"]
          old += [(kind, n) for n in meta[f"{kind}_names"]]
          new += [(kind, n) for n in target[kind]]
      fill = log_std0 if ann["fill"] == "log_initial_action_std" else ann["fill"]
      shape = list(x.shape)
      shape[axis] = len(new)
      y = np.full(shape, fill, x.dtype)
      index = {e: i for i, e in enumerate(old)}
      for j, e in enumerate(new):
        if e in index:
          src = [slice(None)] * x.ndim
          dst = [slice(None)] * x.ndim
          src[axis], dst[axis] = index[e], j
          y[tuple(dst)] = x[tuple(src)]
      x = y
    out[name] = x
  return out


def test_zero_filled_expansion_keeps_old_actions_and_zero_new_ones(tmp_path):
  config = _config()
  nets, state = _trained_like_state(config)
  ck = ckpt_lib.load(_save(tmp_path / "ck", state, config))
  target = {"obs": NAMES["obs"][:3] + ["extra/a"] + NAMES["obs"][3:] + ["extra/b"],
            "privileged": ["friction"] + NAMES["privileged"],
            "action": ["left", "middle", "right"]}
  big_cfg = _config(target, std=0.3)
  tensors = _expand(ck.meta, ck.tensors, target, math.log(0.3))
  big = nets_lib.Networks(big_cfg)
  # The whole learner state (optimizer moments included) restores into the new layout.
  template = ppo_lib.init_learner_state(big, big.init(jax.random.PRNGKey(1)), 1.0, 3e-4)
  grown = ckpt_lib.restore_learner(template, tensors, fresh_optimizer=True, learning_rate=3e-4,
                                   stage_start=big_cfg)
  assert int(grown.opt_state[1].count) == 0
  np.testing.assert_allclose(grown.params["policy"]["log_std"][1], math.log(0.3), rtol=1e-6)

  rng = np.random.default_rng(0)
  n = 64
  old_obs = rng.normal(size=(n, config.obs_size)).astype(np.float32)
  old_hist = rng.normal(size=(n, config.history_len, config.obs_size)).astype(np.float32)
  old_priv = rng.normal(size=(n, config.privileged_size)).astype(np.float32)
  obs_idx = [target["obs"].index(x) for x in NAMES["obs"]]
  priv_idx = [target["privileged"].index(x) for x in NAMES["privileged"]]
  act_idx = [target["action"].index(x) for x in NAMES["action"]]
  # New features take arbitrary (large) values.
  new_obs = (100 * rng.normal(size=(n, big_cfg.obs_size))).astype(np.float32)
  new_hist = (100 * rng.normal(size=(n, big_cfg.history_len, big_cfg.obs_size))
              ).astype(np.float32)
  new_priv = (100 * rng.normal(size=(n, big_cfg.privileged_size))).astype(np.float32)
  new_obs[:, obs_idx] = old_obs
  new_hist[:, :, obs_idx] = old_hist
  new_priv[:, priv_idx] = old_priv

  before = nets_lib.deployable_mean(nets, state.params, state.normalizer, old_obs, old_hist)
  after = nets_lib.deployable_mean(big, grown.params, grown.normalizer, new_obs, new_hist)
  np.testing.assert_allclose(np.asarray(after)[:, act_idx], before, rtol=1e-5, atol=1e-6)
  assert np.all(np.asarray(after)[:, 1] == 0.0), "a new action's mean is exactly zero"

  before = nets_lib.privileged_mean(nets, state.params, state.normalizer, old_obs, old_priv)
  after = nets_lib.privileged_mean(big, grown.params, grown.normalizer, new_obs, new_priv)
  np.testing.assert_allclose(np.asarray(after)[:, act_idx], before, rtol=1e-5, atol=1e-6)
  assert np.all(np.asarray(after)[:, 1] == 0.0)

  v0 = nets.value(state.params["value"], *nets_lib.normalize(state.normalizer, old_obs,
                                                             old_priv))
  v1 = big.value(grown.params["value"], *nets_lib.normalize(grown.normalizer, new_obs,
                                                            new_priv))
  np.testing.assert_allclose(v1, v0, rtol=1e-5, atol=1e-6)
  # At a stage start the statistics are kept as they were, count included; the new features
  # (fill: std 1, summed_variance 0) are the unseen ones.
  assert int(grown.normalizer.count.to_numpy()) == int(state.normalizer.count.to_numpy())
  np.testing.assert_array_equal(np.asarray(grown.normalizer.mean["obs"])[obs_idx],
                                np.asarray(state.normalizer.mean["obs"]))
  np.testing.assert_array_equal(np.asarray(grown.normalizer.std["obs"])[obs_idx],
                                np.asarray(state.normalizer.std["obs"]))
  unseen = ckpt_lib.unseen_features(grown.normalizer)
  new_idx = [target["obs"].index("extra/a"), target["obs"].index("extra/b")]
  assert sorted(np.flatnonzero(unseen["obs"])) == sorted(new_idx)
  assert list(np.flatnonzero(unseen["privileged"])) == [target["privileged"].index("friction")]


def test_stage_start_zeroes_the_weights_of_features_that_never_varied(tmp_path):
  # A privileged and an observed feature that were constant in the previous stage: their
  # statistics say std 1e-6 (brax's floor), and the weights reading them were never trained.
  config = _config()
  nets, state = _trained_like_state(config)
  rng = np.random.default_rng(1)
  obs = rng.normal(2.0, 3.0, (500, config.obs_size)).astype(np.float32)
  priv = rng.normal(-1.0, 0.5, (500, config.privileged_size)).astype(np.float32)
  obs[:, 1] = 0.25
  priv[:, 0] = 1.0
  fresh = ppo_lib.init_learner_state(nets, nets.init(jax.random.PRNGKey(0)), 1.0, 3e-4)
  state = state.replace(normalizer=nets_lib.update_normalizer(fresh.normalizer, obs, priv))
  ck = ckpt_lib.load(_save(tmp_path / "ck", state, config))
  template = ppo_lib.init_learner_state(nets, nets.init(jax.random.PRNGKey(1)), 1.0, 3e-4)
  kept = ckpt_lib.restore_learner(template, ck.tensors, fresh_optimizer=True,
                                  learning_rate=3e-4)
  started = ckpt_lib.restore_learner(template, ck.tensors, fresh_optimizer=True,
                                     learning_rate=3e-4, stage_start=config)
  unseen = ckpt_lib.unseen_features(started.normalizer)
  assert list(np.flatnonzero(unseen["obs"])) == [1]
  assert list(np.flatnonzero(unseen["privileged"])) == [0]
  p, q = kept.params, started.params
  # policy: [obs, latent] -> hidden; value: [obs, privileged]; encoder: privileged;
  # adaptation: a convolution over observation channels.
  assert np.any(np.asarray(p["policy"]["hidden_0"]["kernel"])[1] != 0)
  np.testing.assert_array_equal(np.asarray(q["policy"]["hidden_0"]["kernel"])[1], 0.0)
  np.testing.assert_array_equal(np.asarray(q["value"]["hidden_0"]["kernel"])[1], 0.0)
  np.testing.assert_array_equal(
      np.asarray(q["value"]["hidden_0"]["kernel"])[config.obs_size + 0], 0.0)
  np.testing.assert_array_equal(np.asarray(q["encoder"]["hidden_0"]["kernel"])[0], 0.0)
  np.testing.assert_array_equal(np.asarray(q["adaptation"]["conv_0"]["kernel"])[:, 1], 0.0)
  # Everything else is untouched, and on the previous stage's data (the constants at their
  # values) every output is the same: only the newly varying inputs lose their weights.
  changed = {"policy/hidden_0/kernel", "value/hidden_0/kernel", "encoder/hidden_0/kernel",
             "adaptation/conv_0/kernel"}
  for name, x in ckpt_lib._flatten(p, "").items():
    y = ckpt_lib._flatten(q, "")[name]
    if name not in changed:
      np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
  hist = np.broadcast_to(obs[:64, None, :], (64, config.history_len, config.obs_size))
  np.testing.assert_allclose(
      nets_lib.deployable_mean(nets, q, started.normalizer, obs[:64], hist),
      nets_lib.deployable_mean(nets, p, kept.normalizer, obs[:64], hist), rtol=1e-4, atol=1e-4)
  np.testing.assert_allclose(
      nets_lib.privileged_mean(nets, q, started.normalizer, obs[:64], priv[:64]),
      nets_lib.privileged_mean(nets, p, kept.normalizer, obs[:64], priv[:64]),
      rtol=1e-4, atol=1e-4)


def test_calibration_sets_unseen_features_from_the_batch_and_keeps_the_rest():
  config = _config()
  _, state = _trained_like_state(config)
  norm = state.normalizer
  rng = np.random.default_rng(2)
  obs = rng.normal(5.0, 2.0, (4, 256, config.obs_size)).astype(np.float32)
  priv = rng.normal(-3.0, 0.25, (4, 256, config.privileged_size)).astype(np.float32)
  mask = {"obs": np.zeros(config.obs_size, np.float32),
          "privileged": np.zeros(config.privileged_size, np.float32)}
  same = nets_lib.calibrate_normalizer(norm, obs, priv, mask)
  _leaves_equal(same, norm)
  mask["obs"][2] = 1.0
  mask["privileged"][0] = 1.0
  out = nets_lib.calibrate_normalizer(norm, obs, priv, mask)
  count = int(norm.count.to_numpy())
  for kind, x, i in (("obs", obs, 2), ("privileged", priv, 0)):
    rows = x.reshape(-1, x.shape[-1])
    np.testing.assert_allclose(out.mean[kind][i], rows[:, i].mean(), rtol=1e-4)
    np.testing.assert_allclose(out.std[kind][i], rows[:, i].std(), rtol=1e-3)
    np.testing.assert_allclose(out.summed_variance[kind][i], rows[:, i].var() * count,
                               rtol=1e-3)
    others = np.arange(x.shape[-1]) != i
    for field in ("mean", "std", "summed_variance"):
      np.testing.assert_array_equal(np.asarray(getattr(out, field)[kind])[others],
                                    np.asarray(getattr(norm, field)[kind])[others])
  assert int(out.count.to_numpy()) == count


# ---------------------------------------------------------------------------------------------
# Refusals.


def test_newer_format_version_is_refused(tmp_path):
  config = _config()
  _, state = _trained_like_state(config)
  d = _save(tmp_path / "ck", state, config)
  meta = json.loads((d / "checkpoint.json").read_text())
  meta["format_version"] = 2
  (d / "checkpoint.json").write_text(json.dumps(meta))
  with pytest.raises(ckpt_lib.CheckpointError,
                     match="format_version 2 is newer than this hifar supports"):
    ckpt_lib.load(d)
  del meta["format_version"]
  (d / "checkpoint.json").write_text(json.dumps(meta))
  with pytest.raises(ckpt_lib.CheckpointError, match="missing or invalid format_version"):
    ckpt_lib.load(d)
  (d / "checkpoint.json").write_text("{not json")
  with pytest.raises(ckpt_lib.CheckpointError, match="corrupt checkpoint metadata"):
    ckpt_lib.load(d)


def test_missing_or_corrupt_files_are_refused(tmp_path):
  with pytest.raises(ckpt_lib.CheckpointError, match="no such checkpoint directory"):
    ckpt_lib.load(tmp_path / "nope")
  config = _config()
  _, state = _trained_like_state(config)
  d = _save(tmp_path / "ck", state, config)
  (d / "params.safetensors").write_bytes(b"garbage")
  with pytest.raises(ckpt_lib.CheckpointError, match="corrupt safetensors file"):
    ckpt_lib.load(d)
  d = _save(tmp_path / "ck2", state, config)
  tensors = safetensors.numpy.load((d / "params.safetensors").read_bytes())
  tensors["stray"] = np.zeros(3, np.float32)
  (d / "params.safetensors").write_bytes(safetensors.numpy.save(tensors))
  with pytest.raises(ckpt_lib.CheckpointError, match="tensor stray has no entry"):
    ckpt_lib.load(d)
  with pytest.raises(ckpt_lib.CheckpointError, match="no rollout_state.safetensors"):
    ckpt_lib.load_rollout(d)


def test_mismatched_layout_is_refused_with_the_differences(tmp_path):
  config = _config()
  nets, state = _trained_like_state(config)
  ck = ckpt_lib.load(_save(tmp_path / "ck", state, config))
  obs = NAMES["obs"] + ["extra/a"]
  with pytest.raises(ckpt_lib.CheckpointError) as e:
    ckpt_lib.check_layout(ck.meta, obs, NAMES["privileged"], NAMES["action"],
                          {**config.meta(), "policy_hidden": [32, 8]}, "stage full")
  msg = str(e.value)
  assert "obs_names differ" in msg and "new in the stage: extra/a" in msg
  assert "network.policy_hidden is [16, 8] in the checkpoint, [32, 8] in the stage" in msg
  assert "hifar expand-checkpoint" in msg
  # The tensors themselves are checked too (shape names the tensor).
  wide = nets_lib.Networks(dataclasses.replace(config, policy_hidden=(32, 8)))
  template = ppo_lib.init_learner_state(wide, wide.init(jax.random.PRNGKey(0)), 1.0, 3e-4)
  with pytest.raises(ckpt_lib.CheckpointError,
                     match=r"tensor policy/hidden_0/(bias|kernel) has shape .* needs"):
    ckpt_lib.restore_learner(template, ck.tensors, fresh_optimizer=False)
  # A checkpoint with modules this stage lacks (RMA on -> off) is refused by name.
  flat = nets_lib.Networks(_config(rma=False))
  template = ppo_lib.init_learner_state(flat, flat.init(jax.random.PRNGKey(0)), 1.0, 3e-4)
  with pytest.raises(ckpt_lib.CheckpointError):
    ckpt_lib.restore_learner(template, ck.tensors, fresh_optimizer=False)


def test_atomic_replace_and_latest(tmp_path):
  config = _config()
  _, state = _trained_like_state(config)
  d = tmp_path / "checkpoints" / "000000004096"
  _save(d, state, config)
  _save(d, state.replace(learning_rate=jnp.asarray(5e-4, jnp.float32)), config)
  ck = ckpt_lib.load(d)
  assert float(ck.tensors["opt/learning_rate"]) == pytest.approx(5e-4)
  ckpt_lib.write_latest(tmp_path / "checkpoints", d.name)
  assert ckpt_lib.read_latest(tmp_path / "checkpoints") == d
  assert sorted(os.listdir(tmp_path / "checkpoints")) == ["000000004096", "LATEST"]

  class Boom(Exception):
    pass

  def explode(*a, **k):
    raise Boom

  # A failure while writing leaves the old checkpoint intact and no temporary directory.
  orig = files_lib._write_synced
  files_lib._write_synced = explode
  try:
    with pytest.raises(Boom):
      _save(d, state, config)
  finally:
    files_lib._write_synced = orig
  assert sorted(os.listdir(tmp_path / "checkpoints")) == ["000000004096", "LATEST"]
  assert float(ckpt_lib.load(d).tensors["opt/learning_rate"]) == pytest.approx(5e-4)


# ---------------------------------------------------------------------------------------------
# act().


def _elu(x):
  return np.where(x > 0, x, np.expm1(np.minimum(x, 0)))


def test_act_matches_policy_mean_without_rma(tmp_path):
  """act() = the Gaussian's mean, recomputed here in numpy from the saved tensors."""
  config = _config(rma=False)
  _, state = _trained_like_state(config, seed=4)
  d = str(_save(tmp_path / "ck", state, config))
  obs = np.random.default_rng(1).normal(size=(5, config.obs_size)).astype(np.float32)
  actions = np.asarray(facade.act({"checkpoint": d, "obs": obs.tolist()}))
  t = safetensors.numpy.load_file(os.path.join(d, "params.safetensors"))
  x = np.clip((obs - t["normalizer/obs/mean"]) / t["normalizer/obs/std"], -10, 10)
  for i in range(3):
    x = x @ t[f"policy/hidden_{i}/kernel"] + t[f"policy/hidden_{i}/bias"]
    if i < 2:
      x = _elu(x)
  np.testing.assert_allclose(actions, x, rtol=1e-4, atol=1e-5)
  assert facade.act({"checkpoint": d, "obs": obs.tolist()}) == actions.tolist(), "deterministic"


def test_act_uses_adaptation_module_and_history(tmp_path):
  config = _config(rma=True)
  nets, state = _trained_like_state(config, seed=5)
  # As after the stage's adaptation phase: act refuses an untrained adaptation module.
  d = str(_save(tmp_path / "ck", state, config, learner={"adaptation_env_steps": 64}))
  rng = np.random.default_rng(2)
  obs = rng.normal(size=(3, config.obs_size)).astype(np.float32)
  hist = rng.normal(size=(3, config.history_len, config.obs_size)).astype(np.float32)
  expected = nets_lib.deployable_mean(nets, state.params, state.normalizer, obs, hist)
  with_history = {"checkpoint": d, "obs": obs.tolist(), "history": hist.tolist()}
  np.testing.assert_allclose(facade.act(with_history), expected, rtol=1e-5, atol=1e-6)
  zeros = nets_lib.deployable_mean(nets, state.params, state.normalizer, obs,
                                   np.zeros_like(hist))
  np.testing.assert_allclose(facade.act({"checkpoint": d, "obs": obs.tolist()}), zeros,
                             rtol=1e-5, atol=1e-6)
  # The module really reads the history.
  assert not np.allclose(expected, zeros)
  with pytest.raises(ValueError, match=r"obs must be N × 5"):
    facade.act({"checkpoint": d, "obs": [[0.0] * 4]})
  with pytest.raises(ValueError, match=r"history must be N × history_len × n_obs = \[3, 6, 5\]"):
    facade.act({**with_history, "history": hist[:, :2].tolist()})
