"""The narrow API the Rust CLI calls (docs/contracts.md, "The facade").

Arguments and results are JSON-like (dict / list / str / float / int / None). Errors are
exceptions whose LAST LINE says what is wrong (the CLI prints it; the traceback goes to the
log). Heavy imports (JAX, MuJoCo, the environment) happen inside the functions, so importing
this module is cheap and `versions()` works even when something else is broken.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Callable

from jax_env import versions as versions_lib


def versions() -> dict:
  """Python and the versions of the packages hifar depends on (None where not installed)."""
  return versions_lib.versions()


def doctor() -> dict:
  """Devices, the physics backend `backend = "auto"` resolves to, and what is missing.

  "auto" means MJX where JAX has an accelerator (MJX is built for it) and C MuJoCo (native)
  on a CPU-only machine (it steps a humanoid far faster on a CPU and compiles in seconds).
  """
  problems: list[str] = []
  devices: list[str] = []
  accelerator = False
  try:
    import jax
    for d in jax.devices():
      devices.append(f"{d.platform}:{d.id} {d.device_kind}")
      accelerator |= d.platform != "cpu"
  except Exception as e:  # a broken jaxlib install, a CUDA plugin that fails to load, ...
    problems.append(f"JAX cannot list devices: {_last_line(e)}")
  native = True
  try:
    import jax_env.physics.native_backend  # noqa: F401  (needs mujoco.batch)
  except Exception as e:
    native = False
    problems.append(f"native backend unavailable: {_last_line(e)} (reinstall mujoco==3.17.0 "
                    "with `hifar setup`)")
  mjx = True
  try:
    import mujoco.mjx  # noqa: F401
  except Exception as e:
    mjx = False
    problems.append(f"MuJoCo MJX unavailable: {_last_line(e)} (reinstall mujoco-mjx with "
                    "`hifar setup`)")
  for key, version in versions().items():
    if version is None:
      problems.append(f"package {versions_lib.PACKAGES.get(key, key)} is not installed (run `hifar setup`)")
  if accelerator and mjx:
    backend, reason = "mjx", "JAX sees an accelerator; MJX runs the batch on it"
  elif native:
    backend = "native"
    reason = ("no accelerator: C MuJoCo steps the batch on the CPU threads"
              if not accelerator else "MJX is unavailable; falling back to C MuJoCo")
  else:
    backend, reason = "mjx", "the native backend is unavailable; MJX runs on the CPU (slow)"
  return {"devices": devices, "default_backend": backend, "reason": reason,
          "problems": problems}


def check_stage(stage: dict) -> list[dict]:
  """Semantic problems of a stage table: [{"path": [...], "message": str}] (empty if valid)."""
  from jax_env import config
  return config.check_stage(stage)


def feature_names(stage: dict) -> dict:
  """{"obs_names", "privileged_names", "action_names"} of a stage."""
  from jax_env import features
  obs, priv, act = features.feature_names(stage)
  return {"obs_names": list(obs), "privileged_names": list(priv), "action_names": list(act)}


def train_stage(request: dict, callback: Callable[[dict], str] | None) -> dict:
  """Trains one stage; see docs/contracts.md for the request and progress keys.

  Returns {"status": "completed"|"finished_early"|"interrupted", "checkpoint": dir,
  "env_steps": int}.
  """
  from jax_env import facade_requests
  req = facade_requests.parse("train_stage", facade_requests.TrainRequest, request)
  backend = facade_requests.check_backend("train_stage", req.backend)

  from jax_env.env import FallRecoveryEnv
  from jax_env.learner import train
  from jax_env.stage_config import StageConfig

  stage = StageConfig.from_dict(req.stage)
  learner_config = train.LearnerConfig.from_stage(stage)
  if req.stage_name:
    learner_config = dataclasses.replace(learner_config, stage_name=req.stage_name)
  env = FallRecoveryEnv(stage, backend=backend)
  return train.train_stage(
      env, learner_config, stage_dir=req.stage_dir, seed=int(req.seed), num_envs=req.num_envs,
      init_checkpoint=req.init_checkpoint, resume_checkpoint=req.resume_checkpoint,
      callback=callback, log_file=req.log_file, stage_config=req.stage)


def evaluate(request: dict, callback: Callable[[dict], str] | None = None) -> dict:
  """Runs an evaluation protocol on a checkpoint and writes eval.json, eval.csv and eval.md.

  See docs/contracts.md ("Evaluation") for the request, progress and result keys.
  """
  from jax_env.evaluation import runner
  return runner.evaluate(request, callback)


def rollout(request: dict) -> dict:
  """One recorded episode of a checkpoint's policy (docs/contracts.md, "Rollout")."""
  from jax_env.evaluation import recording
  return recording.rollout(request)


def report(request: dict) -> dict:
  """PNG plots and a markdown summary of a run (docs/contracts.md, "Report")."""
  from jax_env.evaluation import report as report_lib
  return report_lib.report(request)


def export_onnx(request: dict) -> dict:
  """The deployable actor of a checkpoint as ONNX, checked with onnxruntime
  (docs/contracts.md, "Export")."""
  from jax_env import export
  return export.export_onnx(request)


_ACTORS: dict = {}


def _actor(checkpoint_dir: str):
  """(network config, jitted deployable actor) of a checkpoint, cached by its files' mtimes;
  an RMA checkpoint whose adaptation module was never trained is refused."""
  import jax

  from jax_env.evaluation import policy as policy_lib
  from jax_env.learner import checkpoint as ckpt_lib
  from jax_env.learner import networks as nets_lib

  d = Path(checkpoint_dir)
  stamp = tuple((d / f).stat().st_mtime_ns if (d / f).exists() else None
                for f in (ckpt_lib.META_FILE, ckpt_lib.PARAMS_FILE))
  cached = _ACTORS.get(str(d))
  if cached is not None and cached[0] == stamp:
    return cached[1]
  ck = ckpt_lib.load(d)
  policy_lib.check_adaptation_trained(ck.meta, d)
  nets = nets_lib.Networks(ck.network_config())
  params, normalizer = ckpt_lib.restore_params(nets, ck.tensors)
  fn = jax.jit(lambda obs, history: nets_lib.deployable_mean(nets, params, normalizer, obs,
                                                             history))
  _ACTORS[str(d)] = (stamp, (nets.config, fn))
  return nets.config, fn


def act(request: dict) -> list:
  """Deterministic actions [N][n_action] of the deployable actor (adaptation module + base
  policy) for `request["obs"]`, observation rows [N][n_obs], of `request["checkpoint"]`.

  `request["history"]`: N × history_len × n_obs, oldest first: the observations BEFORE `obs`
  (the module reads the window [history[1:], obs]); omitted, it is zeros, exactly what an
  episode starts with in training.
  """
  import numpy as np

  from jax_env import facade_requests
  req = facade_requests.parse("act", facade_requests.ActRequest, request)
  history = req.history
  config, fn = _actor(req.checkpoint)
  o = np.asarray(req.obs, dtype=np.float32)
  if o.ndim != 2 or o.shape[1] != config.obs_size:
    raise ValueError(f"act: obs must be N × {config.obs_size} (the checkpoint's obs_names), "
                     f"got shape {list(o.shape)}")
  shape = (o.shape[0], config.history_len, config.obs_size)
  if history is None:
    h = np.zeros(shape, np.float32)
  else:
    h = np.asarray(history, dtype=np.float32)
    if h.shape != shape:
      raise ValueError(f"act: history must be N × history_len × n_obs = {list(shape)}, got "
                       f"{list(h.shape)}")
  if not (np.all(np.isfinite(o)) and np.all(np.isfinite(h))):
    raise ValueError("act: obs and history must be finite numbers")
  return np.asarray(fn(o, h), dtype=np.float64).tolist()


def _last_line(e: BaseException) -> str:
  lines = str(e).strip().splitlines()
  return lines[-1] if lines else type(e).__name__
