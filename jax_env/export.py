"""A checkpoint's deployable actor as an ONNX file (docs/contracts.md, "facade.export_onnx").

The graph is written op for op from the checkpoint's tensors with `onnx.helper`, mirroring
`networks.deployable_mean` exactly (float32 throughout):

  obs_n    = clip((obs - mean) / std, -10, 10)                      (the running statistics)
  window   = concat(history[:, 1:], obs[:, None])                   [N, H, n_obs], oldest first
  window_n = clip((window - mean) / std, -10, 10)
  z        = Dense(flatten(act(Conv(act(Conv(window_n))))))         adaptation module (RMA)
  action   = MLP([obs_n, z])                                         unclipped policy mean
  joint_target = base + scale · clip(action, -clip, clip)            the stage's action mapping

`base` is, for the "current" mapping, the measured angle of each controlled joint: its
`joint_pos/<J>` observation (relative to the `stand` keyframe) plus the keyframe angle; for
"default" the keyframe angle itself. The simulator then limits the target's rate of change and
clamps it to the joint range; those two steps depend on the robot's PD gains and limits and are
left to the robot's controller (the metadata says so).

Nothing is written until onnxruntime reproduces the JAX actor (the path `hifar act` takes) on a
few hundred rows within the tolerance: rows drawn from the checkpoint's own observation
statistics (with nonzero histories, and with the all-zero history an episode starts with), wide
random rows, and far out-of-distribution rows that saturate the ±10 normalization clip. The
tolerance bounds |onnx - jax| where |action| <= 1 and the relative difference beyond (see
`compare`); the result reports the plain max abs difference as well.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

from jax_env import facade_requests
from jax_env.files import write_atomic

OPSET = 17
# The IR version that goes with opset 17; onnx's newest would be refused by older runtimes.
IR_VERSION = 8
DEFAULT_TOLERANCE = 1e-5
# Parity rows per kind (see `parity_rows`).
ROWS_PER_KIND = 64
BATCH_DIM = "N"

# The flax/brax activation of each checkpoint `network.activation`, as ONNX ops.
_ACTIVATIONS = ("elu", "swish", "tanh", "relu")


@dataclasses.dataclass(frozen=True)
class ExportJob:
  """A checked `facade_requests.ExportRequest`."""
  checkpoint: Path
  out: Path
  tolerance: float
  stage: dict | None

  @classmethod
  def from_dict(cls, request: dict) -> "ExportJob":
    req = facade_requests.parse("export_onnx", facade_requests.ExportRequest, request)
    tol = DEFAULT_TOLERANCE if req.tolerance is None else float(req.tolerance)
    if not (math.isfinite(tol) and tol > 0):
      raise ValueError(f"export_onnx: tolerance must be a positive number, got {tol!r}")
    out = Path(req.out)
    if out.is_dir():
      raise ValueError(f"{out}: is a directory; give the path of the .onnx file to write")
    if not out.parent.is_dir():
      raise ValueError(f"{out.parent}: no such directory (the parent of the output file must "
                       "exist)")
    if req.stage is not None and not isinstance(req.stage, dict):
      raise ValueError(f"export_onnx: stage must be a stage table (dict) or None, got "
                       f"{type(req.stage).__name__}")
    return cls(checkpoint=Path(req.checkpoint), out=out, tolerance=tol, stage=req.stage)


# ---------------------------------------------------------------------------------------------
# What the graph needs from the checkpoint.


@dataclasses.dataclass(frozen=True)
class ActorSpec:
  """Everything the graph is built from: tensors, sizes and the action mapping."""

  meta: dict
  tensors: dict[str, np.ndarray]
  obs_names: tuple[str, ...]
  action_names: tuple[str, ...]
  history_len: int
  rma: bool
  activation: str
  policy_layers: int           # dense layers of the policy MLP (hidden + output)
  conv_shapes: tuple[tuple[int, int], ...]
  mapping: str
  scale: float
  clip: float
  q_stand: np.ndarray          # [n_act] stand keyframe angle of each controlled joint
  joint_pos_index: np.ndarray  # [n_act] obs column of `joint_pos/<J>` per controlled joint

  @property
  def obs_size(self) -> int:
    return len(self.obs_names)

  @property
  def action_size(self) -> int:
    return len(self.action_names)


def actor_spec(checkpoint_dir: Path) -> ActorSpec:
  from jax_env import robot
  from jax_env.evaluation import policy as policy_lib
  from jax_env.learner import checkpoint as ckpt_lib
  from jax_env.learner import networks as nets_lib

  ck = ckpt_lib.load(checkpoint_dir)
  policy_lib.check_adaptation_trained(ck.meta, checkpoint_dir)
  config = ck.network_config()
  meta = ck.meta
  action = meta["action"]
  mapping = str(action.get("mapping"))
  if mapping not in ("current", "default"):
    raise ValueError(f"{checkpoint_dir}: unknown action mapping {mapping!r}; valid: current, "
                     "default")
  if config.activation not in _ACTIVATIONS:
    raise ValueError(f"{checkpoint_dir}: activation {config.activation!r} has no ONNX "
                     f"translation; valid: {', '.join(_ACTIVATIONS)}")
  obs_names = tuple(meta["obs_names"])
  action_names = tuple(meta["action_names"])
  joints = {n: i for i, n in enumerate(robot.JOINT_NAMES)}
  unknown = [a for a in action_names if a not in joints]
  if unknown:
    raise ValueError(f"{checkpoint_dir}: action_names {', '.join(unknown)} are not T1 joints")
  stand = robot.stand_pose()
  q_stand = np.asarray([stand[joints[a]] for a in action_names], np.float32)
  index = {n: i for i, n in enumerate(obs_names)}
  missing = [a for a in action_names if f"joint_pos/{a}" not in index]
  if mapping == "current" and missing:
    raise ValueError(f"{checkpoint_dir}: the 'current' action mapping needs joint_pos/<J> of "
                     f"every controlled joint; obs_names lack {', '.join(missing)}")
  joint_pos_index = np.asarray([index.get(f"joint_pos/{a}", -1) for a in action_names],
                               np.int64)
  tensors = {k: np.asarray(v) for k, v in ck.tensors.items()}
  return ActorSpec(
      meta=meta, tensors=tensors, obs_names=obs_names, action_names=action_names,
      history_len=config.history_len, rma=config.rma, activation=config.activation,
      policy_layers=len(config.policy_hidden) + 1,
      conv_shapes=tuple(nets_lib.AdaptationModule.conv_shapes(config.history_len)),
      mapping=mapping, scale=float(action["scale"]), clip=float(action["clip"]),
      q_stand=q_stand, joint_pos_index=joint_pos_index)


# ---------------------------------------------------------------------------------------------
# Graph construction.


class _Graph:
  """Accumulates nodes and float32 initializers; names every intermediate after its module."""

  def __init__(self):
    self.nodes = []
    self.initializers = []
    self._names: set[str] = set()

  def _unique(self, name: str) -> str:
    base, i = name, 1
    while name in self._names:
      name, i = f"{base}_{i}", i + 1
    self._names.add(name)
    return name

  def reserve(self, *names: str) -> None:
    """Graph input and output names no intermediate may take."""
    self._names.update(names)

  def const(self, name: str, value, dtype=np.float32) -> str:
    from onnx import numpy_helper
    name = self._unique(name)
    self.initializers.append(numpy_helper.from_array(np.asarray(value, dtype), name))
    return name

  def op(self, op_type: str, inputs: list[str], name: str, **attrs) -> str:
    from onnx import helper
    out = self._unique(name)
    self.nodes.append(helper.make_node(op_type, inputs, [out], name=out, **attrs))
    return out

  def activation(self, kind: str, x: str, name: str) -> str:
    if kind == "elu":
      return self.op("Elu", [x], name, alpha=1.0)
    if kind == "relu":
      return self.op("Relu", [x], name)
    if kind == "tanh":
      return self.op("Tanh", [x], name)
    if kind == "swish":  # jax.nn.swish = x · sigmoid(x)
      return self.op("Mul", [x, self.op("Sigmoid", [x], f"{name}/sigmoid")], name)
    raise ValueError(f"unknown activation {kind!r}; valid: {', '.join(_ACTIVATIONS)}")


def _normalized(g: _Graph, x: str, mean: str, std: str, lo: str, hi: str, name: str) -> str:
  """clip((x - mean) / std, ±10), as networks.normalize (a division, not a reciprocal)."""
  centered = g.op("Sub", [x, mean], f"{name}/centered")
  scaled = g.op("Div", [centered, std], f"{name}/scaled")
  return g.op("Clip", [scaled, lo, hi], name)


def _dense(g: _Graph, spec: ActorSpec, x: str, module: str) -> str:
  kernel = g.const(f"{module}/kernel", spec.tensors[f"{module}/kernel"])
  bias = g.const(f"{module}/bias", spec.tensors[f"{module}/bias"])
  return g.op("Add", [g.op("MatMul", [x, kernel], f"{module}/matmul"), bias], module)


def _adaptation(g: _Graph, spec: ActorSpec, window_n: str) -> str:
  """AdaptationModule: Conv1D (flax kernel [k, C_in, C_out] == ONNX W[C_out, C_in, k]) over
  time with 'VALID' padding, activation, again, then time-major flatten and a Dense."""
  x = g.op("Transpose", [window_n], "adaptation/channels_first", perm=[0, 2, 1])  # [N, C, H]
  for i, (k, s) in enumerate(spec.conv_shapes):
    kernel = spec.tensors[f"adaptation/conv_{i}/kernel"]
    if kernel.shape[0] != k:
      raise ValueError(f"adaptation/conv_{i}/kernel has kernel size {kernel.shape[0]}, "
                       f"history_len {spec.history_len} implies {k}")
    w = g.const(f"adaptation/conv_{i}/kernel", np.transpose(kernel, (2, 1, 0)))
    b = g.const(f"adaptation/conv_{i}/bias", spec.tensors[f"adaptation/conv_{i}/bias"])
    x = g.op("Conv", [x, w, b], f"adaptation/conv_{i}", kernel_shape=[k], strides=[s],
             pads=[0, 0], dilations=[1], group=1)
    x = g.activation(spec.activation, x, f"adaptation/conv_{i}/act")
  # flax flattens [N, L, C] row-major (time-major); ONNX Conv gives [N, C, L].
  x = g.op("Transpose", [x], "adaptation/time_first", perm=[0, 2, 1])
  x = g.op("Flatten", [x], "adaptation/flatten", axis=1)
  return _dense(g, spec, x, "adaptation/output")


def build_model(spec: ActorSpec, metadata_props: dict[str, str]):
  """The ONNX ModelProto of the deployable actor and its action mapping."""
  import onnx
  from onnx import TensorProto, helper

  g = _Graph()
  n_obs, n_act, hist = spec.obs_size, spec.action_size, spec.history_len
  obs, history = "obs", "history"
  g.reserve(obs, history, "action", "joint_target")
  mean = g.const("normalizer/obs/mean", spec.tensors["normalizer/obs/mean"])
  std = g.const("normalizer/obs/std", spec.tensors["normalizer/obs/std"])
  lo = g.const("normalizer/clip_low", -10.0)
  hi = g.const("normalizer/clip_high", 10.0)
  obs_n = _normalized(g, obs, mean, std, lo, hi, "obs_normalized")

  policy_in = obs_n
  if spec.rma:
    current = g.op("Unsqueeze", [obs, g.const("axis_1", [1], np.int64)], "obs_as_step")
    if hist > 1:
      older = g.op("Slice", [history, g.const("slice_start", [1], np.int64),
                             g.const("slice_end", [hist], np.int64),
                             g.const("slice_axes", [1], np.int64)], "history_without_oldest")
      window = g.op("Concat", [older, current], "window", axis=1)
    else:
      window = current
    window_n = _normalized(g, window, mean, std, lo, hi, "window_normalized")
    z = _adaptation(g, spec, window_n)
    policy_in = g.op("Concat", [obs_n, z], "policy_input", axis=1)

  x = policy_in
  for i in range(spec.policy_layers):
    x = _dense(g, spec, x, f"policy/hidden_{i}")
    if i < spec.policy_layers - 1:
      x = g.activation(spec.activation, x, f"policy/hidden_{i}/act")
  g.nodes.append(helper.make_node("Identity", [x], ["action"], name="action"))

  clipped = g.op("Clip", ["action", g.const("action_clip_low", -spec.clip),
                          g.const("action_clip_high", spec.clip)], "action_clipped")
  offset = g.op("Mul", [clipped, g.const("action_scale", spec.scale)], "action_offset")
  q_stand = g.const("q_stand", spec.q_stand)
  if spec.mapping == "current":
    rel = g.op("Gather", [obs, g.const("joint_pos_index", spec.joint_pos_index, np.int64)],
               "joint_pos_relative", axis=1)
    base = g.op("Add", [rel, q_stand], "joint_pos_measured")
  else:
    base = q_stand
  g.nodes.append(helper.make_node("Add", [base, offset], ["joint_target"], name="joint_target"))

  f32 = TensorProto.FLOAT
  inputs = [helper.make_tensor_value_info(obs, f32, [BATCH_DIM, n_obs]),
            helper.make_tensor_value_info(history, f32, [BATCH_DIM, hist, n_obs])]
  outputs = [helper.make_tensor_value_info("action", f32, [BATCH_DIM, n_act]),
             helper.make_tensor_value_info("joint_target", f32, [BATCH_DIM, n_act])]
  graph = helper.make_graph(g.nodes, "hifar_deployable_actor", inputs, outputs,
                            initializer=g.initializers,
                            doc_string=metadata_props.get("description", ""))
  model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)],
                            producer_name="hifar", producer_version=_version("hifar-jax-env"),
                            doc_string=metadata_props.get("description", ""))
  model.ir_version = IR_VERSION
  helper.set_model_props(model, metadata_props)
  onnx.checker.check_model(model, full_check=True)
  return model


# ---------------------------------------------------------------------------------------------
# Metadata.


def _version(dist: str) -> str | None:
  try:
    return metadata.version(dist)
  except metadata.PackageNotFoundError:
    return None


def _stage_table(spec: ActorSpec, stage: dict | None, where: Path) -> dict | None:
  """The stage table the actor acts in (the request's, else checkpoint.json's), or None."""
  from jax_env import features
  from jax_env.learner import checkpoint as ckpt_lib

  if stage is not None:
    obs, _, act = features.feature_names(stage)
    if tuple(obs) != spec.obs_names or tuple(act) != spec.action_names:
      raise ValueError(f"{where}: the given stage {stage.get('name')!r} does not produce the "
                       "checkpoint's obs_names/action_names; it is not the stage this checkpoint "
                       "acts in")
  else:
    stage = spec.meta.get(ckpt_lib.STAGE_CONFIG_KEY)
  return stage if isinstance(stage, dict) else None


def metadata_props(spec: ActorSpec, checkpoint_dir: Path, stage: dict | None) -> dict:
  """onnx metadata_props: every value a string, lists and numbers as JSON. With the stage table
  at hand they carry its control period, physics timestep and success tolerances, which a
  deployment or a plain-MuJoCo check (evaluation/plain_mujoco.py) needs besides the network."""
  sim = (stage or {}).get("sim", {})
  ctrl_dt = sim.get("ctrl_dt")
  params = checkpoint_dir / "params.safetensors"
  digest = hashlib.sha256(params.read_bytes()).hexdigest()
  base = ("joint_pos/<J> (the obs value, relative to the stand keyframe) + q_stand[J]"
          if spec.mapping == "current" else "q_stand[J]")
  history_doc = (
      f"history [N, {spec.history_len}, n_obs]: the {spec.history_len} observations before obs, "
      "oldest first (zeros at an episode start); the adaptation module reads "
      "[history[1:], obs]. After each step drop history[0] and append obs."
      if spec.rma else
      f"history [N, {spec.history_len}, n_obs] is accepted for a uniform interface and IGNORED: "
      "this checkpoint has no adaptation module (rma = false).")
  description = (
      "hifar deployable actor (Booster T1 fall recovery). Inputs: obs [N, n_obs] in the order "
      f"of obs_names; {history_doc} Outputs: action [N, n_act] = the unclipped policy mean "
      "(what `hifar act` prints); joint_target [N, n_act] = PD position targets (rad) of the "
      f"controlled joints in action_names order: {base} + scale * clip(action, -clip, clip). "
      "The simulator additionally limits the target's rate of change by the joint velocity "
      "limits and clamps it to the joint range; the robot's controller should do the same. "
      "Joints not in action_names are held at their stand keyframe angle.")
  props: dict[str, Any] = {
      "description": description,
      "obs_names": list(spec.obs_names),
      "action_names": list(spec.action_names),
      "history_len": spec.history_len,
      "history_input": "used" if spec.rma else "ignored",
      "rma": spec.rma,
      "ctrl_dt": ctrl_dt,
      "mapping": spec.mapping,
      "scale": spec.scale,
      "clip": spec.clip,
      # float32 values written in their shortest form (0.4, not 0.4000000059604645)
      "q_stand": [float(str(x)) for x in spec.q_stand],
      "normalization": "clip((x - normalizer mean) / std, -10, 10), statistics baked in",
      "hifar": {"jax_env": _version("hifar-jax-env"), "jax": _version("jax"),
                "onnx": _version("onnx"), "onnxruntime": _version("onnxruntime")},
      "checkpoint": str(checkpoint_dir),
      "checkpoint_stage": spec.meta.get("stage"),
      "checkpoint_env_steps": spec.meta.get("env_steps"),
      "checkpoint_iteration": spec.meta.get("iteration"),
      "checkpoint_seed": spec.meta.get("seed"),
      "checkpoint_params_sha256": digest,
  }
  if ctrl_dt is None:  # no stage table at hand: say so rather than guess
    del props["ctrl_dt"]
  if sim.get("timestep") is not None:
    props["timestep"] = sim["timestep"]
  if isinstance((stage or {}).get("success"), dict):
    props["success"] = stage["success"]
  return {k: v if isinstance(v, str) else json.dumps(v) for k, v in props.items()}


# ---------------------------------------------------------------------------------------------
# Parity.


def parity_rows(spec: ActorSpec, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
  """(obs [R, n_obs], history [R, H, n_obs]) float32 rows for the parity check, four kinds,
  all around the checkpoint's observation statistics (mean + std · noise):

  realistic  noise N(0, 1) in obs and history;
  start      realistic obs with the all-zero history of an episode start;
  wide       noise N(0, 3²): rarer states;
  saturated  realistic rows with a tenth of the features 15 std out, so the ±10 normalization
             clip is active (a sensor glitch, a feature that was constant in training).
  """
  rng = np.random.default_rng(seed)
  mean = spec.tensors["normalizer/obs/mean"].astype(np.float64)
  std = spec.tensors["normalizer/obs/std"].astype(np.float64)
  n, h, d = ROWS_PER_KIND, spec.history_len, spec.obs_size

  def rows(shape, width=1.0):
    return mean + width * std * rng.standard_normal(shape + (d,))

  def saturated(shape):
    x = rows(shape)
    out = rng.random(shape + (d,)) < 0.1
    return np.where(out, mean + 15.0 * std * rng.choice([-1.0, 1.0], shape + (d,)), x)

  obs = np.concatenate([rows((n,)), rows((n,)), rows((n,), 3.0), saturated((n,))])
  history = np.concatenate([rows((n, h)), np.zeros((n, h, d)), rows((n, h), 3.0),
                            saturated((n, h))])
  return obs.astype(np.float32), history.astype(np.float32)


def reference_outputs(spec: ActorSpec, checkpoint_dir: Path, obs, history):
  """(action, joint_target) of the JAX deployable actor (the path `hifar act` takes) and the
  action mapping applied to its action in numpy."""
  import jax

  from jax_env.evaluation import policy as policy_lib

  policy = policy_lib.load(checkpoint_dir)
  action = np.asarray(jax.jit(policy.act)(obs, history), np.float32)
  clipped = np.clip(action, np.float32(-spec.clip), np.float32(spec.clip))
  base = (obs[:, spec.joint_pos_index] + spec.q_stand if spec.mapping == "current"
          else np.broadcast_to(spec.q_stand, action.shape))
  return action, (base + np.float32(spec.scale) * clipped).astype(np.float32)


def run_onnx(model_bytes: bytes, obs, history):
  import onnxruntime as ort

  options = ort.SessionOptions()
  options.intra_op_num_threads = 1
  options.log_severity_level = 3  # the unused `history` of a non-RMA actor is not a problem
  session = ort.InferenceSession(model_bytes, options, providers=["CPUExecutionProvider"])
  action, target = session.run(["action", "joint_target"], {"obs": obs, "history": history})
  return action, target


@dataclasses.dataclass(frozen=True)
class Parity:
  """How far onnxruntime's outputs are from the reference, over every parity row."""

  max_abs_diff: float     # max |onnx - ref|
  max_scaled_diff: float  # max |onnx - ref| / max(1, |ref|): what the tolerance bounds
  worst: str              # where max_scaled_diff occurs ("row 3, Left_Knee_Pitch")


def compare(got: np.ndarray, ref: np.ndarray, names) -> Parity:
  """Absolute difference where |ref| <= 1 (every action inside the usual clip range),
  relative beyond: float32 carries ~7 digits, so an out-of-distribution row whose action is
  ±30 cannot be reproduced to 1e-5 absolute by any two summation orders (its ulp is 4e-6)."""
  diff = np.abs(got.astype(np.float64) - ref.astype(np.float64))
  if diff.size == 0:
    return Parity(0.0, 0.0, "-")
  scaled = diff / np.maximum(1.0, np.abs(ref.astype(np.float64)))
  row, col = np.unravel_index(int(np.argmax(scaled)), scaled.shape)
  return Parity(float(diff.max()), float(scaled.max()), f"row {row}, {names[col]}")


# ---------------------------------------------------------------------------------------------
# Writing.


def export_onnx(request: dict) -> dict:
  """Builds, checks and writes the ONNX file; see the module docstring and docs/contracts.md.

  Returns {"path", "opset", "inputs", "outputs" ([{"name", "shape"}], "N" the batch),
  "parity_max_abs_diff", "parity_max_scaled_diff" (see `compare`: what the tolerance
  bounds), "parity_rows", "joint_target_max_abs_diff", "history_input"
  ("used", or "ignored" without an adaptation module)}.
  """
  req = ExportJob.from_dict(request)
  checkpoint_dir = req.checkpoint.resolve()
  spec = actor_spec(checkpoint_dir)
  props = metadata_props(spec, checkpoint_dir, _stage_table(spec, req.stage, checkpoint_dir))
  model = build_model(spec, props)
  data = model.SerializeToString()

  obs, history = parity_rows(spec)
  ref_action, ref_target = reference_outputs(spec, checkpoint_dir, obs, history)
  action, target = run_onnx(data, obs, history)
  if not (np.all(np.isfinite(action)) and np.all(np.isfinite(target))):
    raise ValueError("ONNX parity check failed: onnxruntime produced non-finite values; "
                     f"nothing was written to {req.out}")
  parity = compare(action, ref_action, spec.action_names)
  target_parity = compare(target, ref_target, spec.action_names)
  for output, p, ref in (("action", parity, "jax"), ("joint_target", target_parity, "reference")):
    if p.max_scaled_diff > req.tolerance:
      raise ValueError(
          f"ONNX parity check failed: |onnx - {ref}| / max(1, |{ref}|) of `{output}` reaches "
          f"{p.max_scaled_diff:.3g} ({p.worst}; max abs diff {p.max_abs_diff:.3g}) over "
          f"{len(obs)} rows, above the tolerance {req.tolerance:g}; nothing was written to "
          f"{req.out}")

  write_atomic(req.out, data)

  def io(values):
    return [{"name": v.name,
             "shape": [d.dim_param or d.dim_value for d in v.type.tensor_type.shape.dim]}
            for v in values]

  return {"path": str(req.out.resolve()), "opset": OPSET, "inputs": io(model.graph.input),
          "outputs": io(model.graph.output), "parity_max_abs_diff": parity.max_abs_diff,
          "parity_max_scaled_diff": parity.max_scaled_diff, "parity_rows": int(len(obs)),
          "joint_target_max_abs_diff": target_parity.max_abs_diff,
          "history_input": "used" if spec.rma else "ignored"}
