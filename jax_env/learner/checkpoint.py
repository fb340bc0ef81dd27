"""Checkpoint directories (docs/contracts.md, "Checkpoint directory"). Never pickle.

A checkpoint is a directory with
  params.safetensors         every module's parameters, the normalizer statistics and the
                             optimizer state (float32 unless noted below);
  checkpoint.json            what the tensors mean: feature names, network sizes, and for EVERY
                             tensor its shape, per-axis annotation and fill value, so that the
                             Rust CLI can expand a checkpoint to a stage with more features
                             without Python;
  rollout_state.safetensors  (optional) the environment state, observation history and
                             training key of the learner, for exact resume only.

Tensor names: `<module>/<path>` for policy, value, encoder, adaptation (`policy/log_std`
included); `normalizer/{obs,privileged}/{mean,std,summed_variance}` and `normalizer/count`
(int64, samples seen); `opt/<module>/{mu,nu}/<path>` (Adam moments, annotated like their
parameter with fill 0), `opt/count` (int32, PPO Adam steps), `opt/learning_rate` (the current,
possibly KL-adapted, PPO learning rate) and `opt/adaptation/count` (int32, adaptation-module
Adam steps).

Normalizer fills: mean 0 and std 1, so a new feature enters unscaled (and meets zero weights).
`summed_variance` (Welford's running sum) has fill 0. When the learner STARTS a stage from a
checkpoint (`init_checkpoint`; `restore_learner(stage_start=...)`) it keeps the statistics,
count included, of every feature that varied in the previous stage, so the policy's inputs
mean what they meant when it was trained. (Rebasing them to a prior worth one iteration, as
hifar did before, let every mean and std follow the new stage's randomized, pushed data within
a few iterations; the inputs shifted under the policy and it lost every get-up it had.)
A feature that never varied (recorded std at most UNSEEN_STD: new in this stage, or constant
in the previous one, like the domain-randomization factors of a stage without randomization)
carried no information, so the weights that read it were never trained; they are set to zero
like a new feature's, and its statistics are calibrated on the stage's first batch (see
`networks.calibrate_normalizer`). Exact resume restores everything as stored.

Writes are atomic: every file goes to a temporary sibling directory, is fsynced, and the
directory is renamed into place (and the parent fsynced); `LATEST` is replaced the same way.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Any, Mapping

import jax
import jax.numpy as jnp
import numpy as np
import safetensors.numpy
from brax.training import types as brax_types
from brax.training.acme import running_statistics

from jax_env.files import write_atomic, write_dir_atomic
from jax_env.learner import networks as nets_lib
from jax_env.learner import ppo as ppo_lib

FORMAT_VERSION = 1
PARAMS_FILE = "params.safetensors"
META_FILE = "checkpoint.json"
# checkpoint.json key of the stage table (curriculum `[[stage]]`) the checkpoint was trained on.
STAGE_CONFIG_KEY = "stage_config"
ROLLOUT_FILE = "rollout_state.safetensors"
LATEST_FILE = "LATEST"
LOG_INITIAL_ACTION_STD = "log_initial_action_std"


class CheckpointError(ValueError):
  """A checkpoint that cannot be read or does not fit; the message says why."""


# ---------------------------------------------------------------------------------------------
# Axis annotations.

OBS = {"features": "obs"}
PRIV = {"features": "privileged"}
ACT = {"features": "action"}


def _annotation(name: str, shape: tuple[int, ...], config: nets_lib.NetworkConfig) -> dict:
  """The annotation of a parameter (or of its Adam moment: same axes, fill 0)."""
  axes: list[Any] = [None] * len(shape)
  fill: Any = 0.0
  parts = name.split("/")
  module, path = parts[0], "/".join(parts[1:])
  if module == "policy":
    last = f"hidden_{len(config.policy_hidden)}"
    if path == "hidden_0/kernel":
      axes[0] = [OBS] + ([{"fixed": config.latent_dim}] if config.rma else [])
    if path == f"{last}/kernel":
      axes[1] = [ACT]
    elif path == f"{last}/bias":
      axes[0] = [ACT]
    elif path == "log_std":
      axes[0] = [ACT]
      fill = LOG_INITIAL_ACTION_STD
  elif module == "value" and path == "hidden_0/kernel":
    axes[0] = [OBS, PRIV]
  elif module == "encoder" and path == "hidden_0/kernel":
    axes[0] = [PRIV]
  elif module == "adaptation" and path == "conv_0/kernel":
    axes[1] = [OBS]
  return {"shape": list(shape), "axes": axes, "fill": fill}


def _flatten(tree: Mapping[str, Any], prefix: str) -> dict[str, Any]:
  out = {}
  for k, v in tree.items():
    name = f"{prefix}/{k}" if prefix else k
    if isinstance(v, Mapping):
      out.update(_flatten(v, name))
    else:
      out[name] = v
  return out


def _unflatten_like(template: Mapping[str, Any], prefix: str, tensors: Mapping[str, Any],
                    used: set) -> dict:
  out = {}
  for k, v in template.items():
    name = f"{prefix}/{k}" if prefix else k
    if isinstance(v, Mapping):
      out[k] = _unflatten_like(v, name, tensors, used)
    else:
      out[k] = _take(tensors, name, v, used)
  return out


def _take(tensors, name, like, used):
  if name not in tensors:
    raise CheckpointError(f"checkpoint has no tensor {name}")
  x = np.asarray(tensors[name])
  shape, dtype = tuple(np.shape(like)), np.dtype(getattr(like, "dtype", np.float32))
  if x.shape != shape:
    raise CheckpointError(f"tensor {name} has shape {list(x.shape)}, this stage's network "
                          f"needs {list(shape)}")
  used.add(name)
  return jnp.asarray(x.astype(dtype))


def _adam(opt_state):
  """The ScaleByAdamState inside a (clip, adam) chain state."""
  return opt_state[1]


def _with_adam(opt_state, adam):
  return (opt_state[0], adam)


def learner_tensors(state: ppo_lib.LearnerState) -> dict[str, np.ndarray]:
  """Every tensor of params.safetensors from a (host-side, unreplicated) learner state."""
  out = {k: np.asarray(v, np.float32) for k, v in _flatten(state.params, "").items()}
  norm = state.normalizer
  for kind in ("obs", "privileged"):
    out[f"normalizer/{kind}/mean"] = np.asarray(norm.mean[kind], np.float32)
    out[f"normalizer/{kind}/std"] = np.asarray(norm.std[kind], np.float32)
    out[f"normalizer/{kind}/summed_variance"] = np.asarray(norm.summed_variance[kind],
                                                           np.float32)
  out["normalizer/count"] = np.asarray(int(norm.count.to_numpy()), np.int64)
  for opt_state, prefix, count_name in ((state.opt_state, "opt", "opt/count"),
                                        (state.adapt_opt_state, "opt", "opt/adaptation/count")):
    adam = _adam(opt_state)
    for moment in ("mu", "nu"):
      for module, tree in getattr(adam, moment).items():
        for path, v in _flatten(tree, "").items():
          out[f"{prefix}/{module}/{moment}/{path}"] = np.asarray(v, np.float32)
    out[count_name] = np.asarray(adam.count, np.int32)
  out["opt/learning_rate"] = np.asarray(state.learning_rate, np.float32)
  return out


def tensor_annotations(tensors: Mapping[str, np.ndarray],
                       config: nets_lib.NetworkConfig) -> dict[str, dict]:
  """checkpoint.json's `tensors` section: one entry per tensor."""
  out = {}
  for name, x in tensors.items():
    shape = tuple(np.shape(x))
    parts = name.split("/")
    if parts[0] == "normalizer" and len(parts) == 3:
      seg = OBS if parts[1] == "obs" else PRIV
      fill = {"mean": 0.0, "std": 1.0, "summed_variance": 0.0}[parts[2]]
      out[name] = {"shape": list(shape), "axes": [[seg]], "fill": fill}
    elif parts[0] == "opt" and len(parts) >= 4 and parts[2] in ("mu", "nu"):
      param = "/".join([parts[1]] + parts[3:])
      ann = _annotation(param, shape, config)
      ann["fill"] = 0.0
      out[name] = ann
    elif parts[0] in ("policy", "value", "encoder", "adaptation"):
      out[name] = _annotation(name, shape, config)
    else:  # scalars: counts, the learning rate
      out[name] = {"shape": list(shape), "axes": [None] * len(shape), "fill": 0.0}
  return out


# ---------------------------------------------------------------------------------------------
# Restoring state.


def _normalizer_from(tensors, template, used):
  if "normalizer/count" not in tensors:
    raise CheckpointError("checkpoint has no tensor normalizer/count")
  raw = np.asarray(tensors["normalizer/count"])
  if raw.shape != ():
    raise CheckpointError(f"tensor normalizer/count has shape {list(raw.shape)}, expected []")
  count = int(raw)
  used.add("normalizer/count")
  if count < 0:
    raise CheckpointError(f"normalizer/count is negative ({count})")
  stats = {}
  for field in ("mean", "std", "summed_variance"):
    stats[field] = {kind: _take(tensors, f"normalizer/{kind}/{field}",
                                getattr(template, field)[kind], used)
                    for kind in ("obs", "privileged")}
  return running_statistics.RunningStatisticsState(
      count=brax_types.UInt64(hi=np.uint32(count >> 32), lo=np.uint32(count & 0xFFFFFFFF)),
      mean=stats["mean"], std=stats["std"], summed_variance=stats["summed_variance"],
      std_eps=0.0, mode=template.mode)  # the learner never sets std_eps


def _opt_from(tensors, template, count_name, used, fresh: bool):
  adam = _adam(template)
  moments = {}
  for moment in ("mu", "nu"):
    tree = getattr(adam, moment)
    moments[moment] = {module: _unflatten_like(sub, f"opt/{module}/{moment}", tensors, used)
                       for module, sub in tree.items()}
  count = _take(tensors, count_name, adam.count, used)
  if fresh:
    count = jnp.zeros_like(count)
  return _with_adam(template, adam._replace(count=count, **moments))


def restore_learner(template: ppo_lib.LearnerState, tensors: Mapping[str, np.ndarray], *,
                    fresh_optimizer: bool, learning_rate: float | None = None,
                    stage_start: nets_lib.NetworkConfig | None = None
                    ) -> ppo_lib.LearnerState:
  """A learner state shaped like `template` from checkpoint tensors.

  fresh_optimizer (a stage starting from another stage's weights): Adam step counters start
  at 0 and the learning rate at `learning_rate`; moments are kept. stage_start (that stage's
  network config): the input weights of the features that never varied are zeroed (see the
  module docstring and `unseen_features`). Without them (exact resume) everything is restored
  as stored. Every tensor of the checkpoint must be used: a leftover means a layout this stage
  does not have.
  """
  used: set[str] = set()
  params = _unflatten_like(template.params, "", tensors, used)
  normalizer = _normalizer_from(tensors, template.normalizer, used)
  opt_state = _opt_from(tensors, template.opt_state, "opt/count", used, fresh_optimizer)
  adapt_opt_state = _opt_from(tensors, template.adapt_opt_state, "opt/adaptation/count", used,
                              fresh_optimizer)
  lr = _take(tensors, "opt/learning_rate", template.learning_rate, used)
  if fresh_optimizer and learning_rate is not None:
    lr = jnp.asarray(learning_rate, jnp.float32)
  extra = sorted(set(tensors) - used)
  if extra:
    raise CheckpointError(f"checkpoint has tensors this stage's network does not: "
                          f"{', '.join(extra[:8])}{' …' if len(extra) > 8 else ''}")
  if stage_start is not None:
    params = _without_unseen_inputs(params, unseen_features(normalizer), stage_start)
  return template.replace(params=params, normalizer=normalizer, opt_state=opt_state,
                          adapt_opt_state=adapt_opt_state, learning_rate=lr)


# A feature whose recorded standard deviation is at most this never varied: it is new (fill:
# summed_variance 0) or was constant (brax clips a constant's std to 1e-6).
UNSEEN_STD = 1e-4


def unseen_features(normalizer) -> dict[str, np.ndarray]:
  """{"obs", "privileged"}: bool per feature, True where the statistics never saw it vary."""
  count = max(int(normalizer.count.to_numpy()), 1)
  return {kind: np.asarray(normalizer.summed_variance[kind]) / count <= UNSEEN_STD ** 2
          for kind in ("obs", "privileged")}


def _without_unseen_inputs(params, unseen: Mapping[str, np.ndarray],
                           config: nets_lib.NetworkConfig) -> dict:
  """params with every weight that reads an unseen feature set to zero. Which axis of which
  tensor reads which feature comes from the checkpoint annotations (`_annotation`), the same
  that the CLI expands checkpoints with."""
  out = {}
  for name, x in _flatten(params, "").items():
    x = np.array(x)
    for axis, segments in enumerate(_annotation(name, x.shape, config)["axes"]):
      if not segments or not any(seg.get("features") in unseen for seg in segments):
        continue  # not an input axis (an output axis reads no feature)
      rows = np.concatenate([unseen[seg["features"]] if "features" in seg
                             else np.zeros(seg["fixed"], bool) for seg in segments])
      if rows.shape[0] != x.shape[axis]:
        raise CheckpointError(f"tensor {name}: axis {axis} has {x.shape[axis]} entries, its "
                              f"annotation {rows.shape[0]}")
      index = [slice(None)] * x.ndim
      index[axis] = rows
      x[tuple(index)] = 0.0
    out[name] = jnp.asarray(x)
  return _nest(out)


def _nest(flat: Mapping[str, Any]) -> dict:
  out: dict = {}
  for name, v in flat.items():
    *parents, leaf = name.split("/")
    node = out
    for p in parents:
      node = node.setdefault(p, {})
    node[leaf] = v
  return out


def restore_params(nets: nets_lib.Networks, tensors: Mapping[str, np.ndarray]):
  """(params, normalizer) for acting; optimizer tensors are ignored."""
  template = jax.eval_shape(
      lambda k: ppo_lib.init_learner_state(nets, nets.init(k), 1.0, 1e-3),
      jax.random.PRNGKey(0))
  used: set[str] = set()
  params = _unflatten_like(template.params, "", tensors, used)
  normalizer = _normalizer_from(tensors, template.normalizer, used)
  return params, normalizer


# ---------------------------------------------------------------------------------------------
# Metadata checks.


@dataclasses.dataclass(frozen=True)
class Checkpoint:
  dir: Path
  meta: dict
  tensors: dict[str, np.ndarray]

  def network_config(self, initial_action_std: float = 1.0) -> nets_lib.NetworkConfig:
    m = self.meta
    return nets_lib.NetworkConfig.from_meta(
        m["network"], len(m["obs_names"]), len(m["privileged_names"]), len(m["action_names"]),
        initial_action_std)


_REQUIRED = ("format_version", "stage", "env_steps", "iteration", "seed", "prng_key",
             "obs_names", "privileged_names", "action_names", "network", "action", "tensors")


def read_meta(directory: str | os.PathLike) -> dict:
  """checkpoint.json of a checkpoint directory, with the format version checked first."""
  d = Path(directory)
  if not d.is_dir():
    raise CheckpointError(f"{d}: no such checkpoint directory")
  path = d / META_FILE
  if not path.is_file():
    raise CheckpointError(f"{d}: not a checkpoint directory (no {META_FILE})")
  try:
    meta = json.loads(path.read_text())
  except (json.JSONDecodeError, UnicodeDecodeError) as e:
    raise CheckpointError(f"{path}: corrupt checkpoint metadata: {e}") from None
  if not isinstance(meta, dict):
    raise CheckpointError(f"{path}: corrupt checkpoint metadata: not a JSON object")
  version = meta.get("format_version")
  if not isinstance(version, int) or isinstance(version, bool):
    raise CheckpointError(f"{path}: missing or invalid format_version {version!r}; this "
                          f"hifar reads format_version {FORMAT_VERSION}")
  if version > FORMAT_VERSION:
    raise CheckpointError(f"{path}: checkpoint format_version {version} is newer than this "
                          f"hifar supports ({FORMAT_VERSION}); upgrade hifar to read it")
  if version != FORMAT_VERSION:
    raise CheckpointError(f"{path}: unsupported checkpoint format_version {version}; this "
                          f"hifar reads format_version {FORMAT_VERSION}")
  missing = [k for k in _REQUIRED if k not in meta]
  if missing:
    raise CheckpointError(f"{path}: corrupt checkpoint metadata: missing {', '.join(missing)}")
  return meta


def load(directory: str | os.PathLike) -> Checkpoint:
  """Metadata and tensors; every tensor must be annotated with its true shape and vice versa."""
  d = Path(directory)
  meta = read_meta(d)
  path = d / PARAMS_FILE
  if not path.is_file():
    raise CheckpointError(f"{d}: not a checkpoint directory (no {PARAMS_FILE})")
  try:
    tensors = safetensors.numpy.load(path.read_bytes())
  except Exception as e:  # safetensors raises its own error types for corrupt files
    raise CheckpointError(f"{path}: corrupt safetensors file: {e}") from None
  annotated = meta["tensors"]
  for name, x in tensors.items():
    if name not in annotated:
      raise CheckpointError(f"{path}: tensor {name} has no entry in {META_FILE}")
    if list(x.shape) != list(annotated[name].get("shape", [])):
      raise CheckpointError(f"{path}: tensor {name} has shape {list(x.shape)} but {META_FILE} "
                            f"says {annotated[name].get('shape')}")
  missing = sorted(set(annotated) - set(tensors))
  if missing:
    raise CheckpointError(f"{path}: {META_FILE} describes tensor {missing[0]}, which is not "
                          "in the file")
  return Checkpoint(d, meta, dict(tensors))


def _describe_names(kind: str, have: list[str], want: list[str]) -> str:
  gone = [n for n in have if n not in want]
  new = [n for n in want if n not in have]
  parts = [f"{kind}_names differ (checkpoint {len(have)}, stage {len(want)})"]
  if new:
    parts.append(f"new in the stage: {', '.join(new[:6])}{' …' if len(new) > 6 else ''}")
  if gone:
    parts.append(f"missing from the stage: {', '.join(gone[:6])}{' …' if len(gone) > 6 else ''}")
  if not new and not gone:
    parts.append("same names in a different order")
  return "; ".join(parts)


def check_layout(meta: Mapping[str, Any], obs_names, privileged_names, action_names,
                 network: Mapping[str, Any], where: str) -> None:
  """Raises CheckpointError naming every difference between a checkpoint and a stage."""
  problems = []
  for kind, want in (("obs", obs_names), ("privileged", privileged_names),
                     ("action", action_names)):
    have = list(meta[f"{kind}_names"])
    if have != list(want):
      problems.append(_describe_names(kind, have, list(want)))
  have_net = meta["network"]
  for key, value in network.items():
    if have_net.get(key) != value:
      problems.append(f"network.{key} is {have_net.get(key)!r} in the checkpoint, "
                      f"{value!r} in the stage")
  if problems:
    raise CheckpointError(f"{where}: checkpoint layout does not match the stage: "
                          + "; ".join(problems)
                          + " (expand it to the stage's features with `hifar expand-checkpoint`;"
                          " hidden sizes cannot change)")


def write_latest(checkpoints_dir: Path, name: str) -> None:
  """Atomically points `<checkpoints_dir>/LATEST` at the checkpoint directory `name`."""
  write_atomic(Path(checkpoints_dir) / LATEST_FILE, name + "\n")


def read_latest(checkpoints_dir: Path) -> Path | None:
  path = Path(checkpoints_dir) / LATEST_FILE
  if not path.is_file():
    return None
  name = path.read_text().strip()
  p = Path(name)
  return p if p.is_absolute() else Path(checkpoints_dir) / p


def key_to_list(key: jax.Array) -> list[int]:
  key = np.asarray(jax.random.key_data(key) if jnp.issubdtype(key.dtype, jax.dtypes.prng_key)
                   else key)
  return [int(x) for x in key.reshape(-1)]


def save(directory: str | os.PathLike, *, state: ppo_lib.LearnerState,
         config: nets_lib.NetworkConfig, stage: str, env_steps: int, iteration: int, seed: int,
         key: jax.Array, obs_names, privileged_names, action_names,
         action: Mapping[str, Any], extra: Mapping[str, Any] | None = None,
         rollout: Mapping[str, np.ndarray] | None = None) -> Path:
  """Writes a checkpoint directory atomically; returns its path."""
  tensors = learner_tensors(state)
  meta = {
      "format_version": FORMAT_VERSION, "stage": stage, "env_steps": int(env_steps),
      "iteration": int(iteration), "seed": int(seed), "prng_key": key_to_list(key),
      "obs_names": list(obs_names), "privileged_names": list(privileged_names),
      "action_names": list(action_names), "network": config.meta(), "action": dict(action),
      "tensors": tensor_annotations(tensors, config),
  }
  for k, v in (extra or {}).items():
    meta[k] = v
  files = {
      PARAMS_FILE: safetensors.numpy.save(tensors, metadata={"format_version": "1"}),
      META_FILE: (json.dumps(meta, indent=1, allow_nan=False) + "\n").encode(),
  }
  if rollout is not None:
    files[ROLLOUT_FILE] = safetensors.numpy.save(
        {k: np.ascontiguousarray(v) for k, v in rollout.items()},
        metadata={"format_version": "1"})
  write_dir_atomic(directory, files)
  return Path(directory)


def load_rollout(directory: str | os.PathLike) -> dict[str, np.ndarray]:
  path = Path(directory) / ROLLOUT_FILE
  if not path.is_file():
    raise CheckpointError(f"{directory}: no {ROLLOUT_FILE}: this checkpoint can start a stage "
                          "(init_checkpoint) but not resume one exactly")
  try:
    return dict(safetensors.numpy.load(path.read_bytes()))
  except Exception as e:
    raise CheckpointError(f"{path}: corrupt safetensors file: {e}") from None
