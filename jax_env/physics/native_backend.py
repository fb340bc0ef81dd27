"""C MuJoCo backend: `mujoco.batch.Batch` on a thread pool, called through `jax.pure_callback`.

Why this shape:
- The whole simulation state of an environment is its `mjSTATE_INTEGRATION` row (time, qpos,
  qvel, act, warm start, ctrl, applied forces, mocap, ...). That row travels inside the JAX
  state (`NativeState.integration`), and the host callback loads it into the batch, steps, and
  hands the new row back. The batch keeps nothing between calls that the result depends on, so
  `step` is a pure function of its inputs, can be jitted, scanned, checkpointed and resumed, and
  its results are bit-identical at any thread count (`mujoco.batch` guarantees that each
  simulation's result equals a loop over one MjData).
- JAX runs in float32 unless `jax_enable_x64` is set, and rounding the float64 state to float32
  would break bit-exact resume and determinism. The row is therefore stored bit-exactly as
  uint32 pairs: `integration` is `[B, nstate, 2]` uint32, the little-endian halves of each
  float64, whatever the x64 setting. `integration_rows` / `from_integration_rows` convert on
  the host. The view fields (`time`, `qpos`, ...) are JAX's default float dtype (float32, or
  float64 with x64): they are outputs for the environment to read, never fed back into the
  physics.
- Per-environment `ModelParams` go into the batch's per-simulation model fields
  (`Batch.expand`): geom_friction, geom_solref, body_mass, body_ipos, body_inertia,
  actuator_gainprm/biasprm (position servo: gainprm[0] = kp, biasprm[1] = -kp,
  biasprm[2] = -kd), actuator_forcerange and opt.gravity. They are written on every call:
  for the T1 that is about 350 numbers per environment, microseconds against milliseconds of
  physics (see `jax_env.bench`), and cheaper than detecting that they did not change.
  Constants that `mj_setConst` derives from masses (body_invweight0, dof_invweight0, ...)
  are NOT recomputed, exactly as the MJX backend does not recompute them, so both backends
  run the same equations.

View convention (the same as `mjx.step` and `mj_step`, checked in the tests): after `step`,
`time`, `qpos` and `qvel` describe the state after the last substep, while the derived
fields (`qacc`, `actuator_force`, `sensordata`, `xpos`, `xquat`) are those computed by the
forward pass of the LAST substep, i.e. at the state before its integration. After `init`,
every field describes the initial state (a full `mj_forward`, like `mjx.forward`).

Numerical blow-ups: C MuJoCo resets a simulation whose qpos/qvel/qacc become NaN, Inf or huge
(with a warning) where MJX lets NaN propagate. The environment ends an episode on a non-finite
view, so a simulation whose blow-up warnings rose during a call (or that raised a MuJoCo
error) is reported with NaN qpos/qvel/qacc in the view and NaN qpos/qvel in its state row; it
stays NaN until the environment re-initialises it, as under MJX.
"""

from __future__ import annotations

import os
import threading
import time
from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct
from mujoco import batch as mj_batch

from jax_env.physics.view import (MODEL_FIELDS, ModelParams, PhysicsView, model_fields,
                                  param_shapes)

_INTEGRATION = mujoco.mjtState.mjSTATE_INTEGRATION
_CTRL = int(mujoco.mjtState.mjSTATE_CTRL)
# Warnings that mean the simulation blew up (MuJoCo reset it to the model's defaults).
_BLOWUP_WARNINGS = np.array([
    int(mujoco.mjtWarning.mjWARN_BADQPOS), int(mujoco.mjtWarning.mjWARN_BADQVEL),
    int(mujoco.mjtWarning.mjWARN_BADQACC), int(mujoco.mjtWarning.mjWARN_BADCTRL)])
# Derived fields copied out of the batch after every call, in PhysicsView order.
_DERIVED = ("qacc", "actuator_force", "sensordata", "xpos", "xquat")


@struct.dataclass
class NativeState:
  """Physics state of a batch: the integration rows (bit-exact) and the view they produce."""

  integration: jax.Array  # [B, nstate, 2] uint32: float64 mjSTATE_INTEGRATION rows, bitcast
  time: jax.Array  # [B]
  qpos: jax.Array  # [B, nq]
  qvel: jax.Array  # [B, nv]
  qacc: jax.Array  # [B, nv]
  actuator_force: jax.Array  # [B, nu]
  sensordata: jax.Array  # [B, nsensordata]
  xpos: jax.Array  # [B, nbody, 3]
  xquat: jax.Array  # [B, nbody, 4]


def integration_rows(integration: Any) -> np.ndarray:
  """The float64 `mjSTATE_INTEGRATION` rows [B, nstate] of `NativeState.integration`."""
  bits = np.ascontiguousarray(np.asarray(integration), dtype=np.uint32)
  return bits.view(np.float64).reshape(bits.shape[:-1])


def from_integration_rows(rows: np.ndarray) -> np.ndarray:
  """`NativeState.integration` ([B, nstate, 2] uint32) for float64 rows [B, nstate]."""
  rows = np.ascontiguousarray(rows, dtype=np.float64)
  return rows.view(np.uint32).reshape(rows.shape + (2,))


def default_nthread() -> int:
  """Threads = the cores this process may run on."""
  try:
    return len(os.sched_getaffinity(0))
  except AttributeError:  # not on Linux
    return os.cpu_count() or 1


class _HostBatch:
  """One `mujoco.batch.Batch` of a given size with its bound and expanded fields."""

  def __init__(self, mj_model: mujoco.MjModel, nsim: int, nthread: int):
    b = mj_batch.Batch(mj_model, nsim, nthread)
    self.batch = b
    self.ctrl = b.bind("ctrl")
    self.xfrc = b.bind("xfrc_applied")
    self.derived = {name: b.bind(name) for name in _DERIVED}
    self.fields = {name: b.expand(name) for name in MODEL_FIELDS}
    self.gainprm = np.array(mj_model.actuator_gainprm)
    self.biasprm = np.array(mj_model.actuator_biasprm)

  def write_params(self, p: dict[str, np.ndarray]) -> None:
    params = ModelParams(**{name: np.asarray(value) for name, value in p.items()})
    for name, value in model_fields(params, self.gainprm, self.biasprm).items():
      self.fields[name][...] = value

  def blown_up(self) -> np.ndarray:
    """[nsim] bool: a blow-up warning was counted since the counters were cleared."""
    # mjWarningStat is (lastinfo, number).
    return self.batch.warning[:, _BLOWUP_WARNINGS, 1].sum(axis=1) > 0


class NativeBackend:
  """Steps a batch of environments of one `mujoco.MjModel` with C MuJoCo on a thread pool."""

  name = "native"

  def __init__(self, mj_model: mujoco.MjModel, nthread: int | None = None):
    self.mj_model = mj_model
    self.nthread = default_nthread() if nthread is None else int(nthread)
    if self.nthread < 1:
      raise ValueError(f"nthread must be >= 1, got {self.nthread}")
    m = mj_model
    self.nstate = mujoco.mj_stateSize(m, _INTEGRATION)
    self._batches: dict[int, _HostBatch] = {}
    # One call at a time: a Batch's rows are shared scratch space between calls.
    self._lock = threading.Lock()
    data = mujoco.MjData(m)
    mujoco.mj_resetData(m, data)
    self._row0 = np.empty(self.nstate)
    mujoco.mj_getState(m, data, self._row0, _INTEGRATION)
    # Where each state component sits in a row: components are stored in bit order.
    self._slices = {}
    for name, spec in (("time", mujoco.mjtState.mjSTATE_TIME),
                       ("qpos", mujoco.mjtState.mjSTATE_QPOS),
                       ("qvel", mujoco.mjtState.mjSTATE_QVEL),
                       ("ctrl", mujoco.mjtState.mjSTATE_CTRL),
                       ("mocap_pos", mujoco.mjtState.mjSTATE_MOCAP_POS)):
      offset = mujoco.mj_stateSize(m, int(_INTEGRATION) & (int(spec) - 1))
      self._slices[name] = slice(offset, offset + mujoco.mj_stateSize(m, int(spec)))
    self._float = jax.dtypes.canonicalize_dtype(jnp.float64)
    # Host-side accounting for benchmarks (a side channel: results never depend on it).
    self.stats = {"step_calls": 0, "step_s": 0.0, "init_calls": 0, "init_s": 0.0}

  # -------------------------------------------------------------------------------------------
  # Host side.

  def _host(self, nsim: int) -> _HostBatch:
    hb = self._batches.get(nsim)
    if hb is None:
      hb = _HostBatch(self.mj_model, nsim, self.nthread)
      self._batches[nsim] = hb
    return hb

  def _outputs(self, hb: _HostBatch, failed: np.ndarray) -> tuple[np.ndarray, ...]:
    """(integration bits, time, qpos, qvel, derived...) of the batch rows, failures as NaN."""
    rows = hb.batch.state.copy()
    if failed.any():
      rows[failed, self._slices["qpos"]] = np.nan
      rows[failed, self._slices["qvel"]] = np.nan
    f = self._float
    derived = {k: v.astype(f) for k, v in hb.derived.items()}
    if failed.any():
      derived["qacc"][failed] = np.nan
    return (from_integration_rows(rows), rows[:, self._slices["time"]][:, 0].astype(f),
            rows[:, self._slices["qpos"]].astype(f), rows[:, self._slices["qvel"]].astype(f),
            *(derived[k] for k in _DERIVED))

  def _run(self, hb: _HostBatch, fn) -> np.ndarray:
    """Run fn() on the batch; the simulations that blew up or raised."""
    # The batch keeps per-simulation warning counters across calls; clear them so that what
    # is counted after fn() happened in this call. (A reset inside MuJoCo's check zeroes a
    # simulation's counters before counting the warning, so deltas would miss repeats.)
    hb.batch.warning[...] = 0
    failed = np.zeros(hb.batch.nsim, bool)
    try:
      fn()
    except mj_batch.SimulationError as err:
      failed[err.ids] = True
    return failed | hb.blown_up()

  def _init_host(self, qpos, qvel, params, mocap_pos, only):
    qpos = np.asarray(qpos, np.float64)
    nsim = qpos.shape[0]
    rows = np.broadcast_to(self._row0, (nsim, self.nstate)).copy()
    rows[:, self._slices["qpos"]] = qpos
    rows[:, self._slices["qvel"]] = np.asarray(qvel, np.float64)
    # Hold the initial pose: the position servos start with ctrl = q (as the MJX backend).
    rows[:, self._slices["ctrl"]] = qpos[:, 7:7 + self.mj_model.nu]
    rows[:, self._slices["mocap_pos"]] = np.asarray(mocap_pos, np.float64).reshape(nsim, -1)
    with self._lock:
      t0 = time.perf_counter()
      hb = self._host(nsim)
      hb.batch.state[...] = rows
      hb.write_params(params)
      # Only the rows the caller keeps (an auto-reset's chunk of ended episodes holds padding
      # rows; a forward pass of every row of the batch cost 5% of a training iteration). The
      # other rows return their state unforwarded (unspecified, discarded by the caller).
      ids = np.flatnonzero(np.asarray(only)).astype(np.int32)
      failed = self._run(hb, lambda: hb.batch.forward(ids=ids))
      out = self._outputs(hb, failed)
      self.stats["init_calls"] += 1
      self.stats["init_s"] += time.perf_counter() - t0
      return out

  def _step_host(self, integration, params, ctrl, xfrc):
    ctrl = np.ascontiguousarray(ctrl, dtype=np.float64)
    xfrc = np.asarray(xfrc, np.float64)
    nsim, nsub = ctrl.shape[:2]
    rows = integration_rows(integration)
    with self._lock:
      t0 = time.perf_counter()
      hb = self._host(nsim)
      b = hb.batch
      b.state[...] = rows
      hb.xfrc[...] = xfrc
      hb.write_params(params)
      # One call for all substeps (one thread-pool dispatch, not n_substeps): rollout sets
      # ctrl from row k before substep k, exactly as a loop of mj_step would.
      b.warning[...] = 0
      failed = np.zeros(nsim, bool)
      try:
        b.rollout(nsub, control=ctrl, control_spec=_CTRL, record=())
      except mj_batch.SimulationError as err:
        failed[err.ids] = True
      # rollout stops a simulation at the first warning of any kind. Blow-ups are reported
      # as NaN anyway; a simulation stopped by a harmless warning (arena full for contacts
      # or constraints, ...) is run again from its row with one call per substep, which
      # never stops early, so its result is still the one of a plain mj_step loop.
      warned = b.warning[:, :, 1].sum(axis=1) > 0
      redo = np.flatnonzero(warned & ~hb.blown_up() & ~failed).astype(np.int32)
      if redo.size:
        b.state[redo] = rows[redo]
        hb.xfrc[redo] = xfrc[redo]

        def substeps():
          for k in range(nsub):
            hb.ctrl[redo] = ctrl[redo, k]
            b.step(ids=redo)

        b.warning[redo] = 0
        try:
          substeps()
        except mj_batch.SimulationError as err:
          failed[err.ids] = True
      failed |= hb.blown_up()
      out = self._outputs(hb, failed)
      self.stats["step_calls"] += 1
      self.stats["step_s"] += time.perf_counter() - t0
      return out

  # -------------------------------------------------------------------------------------------
  # JAX side.

  def _result_shapes(self, nsim: int) -> tuple[jax.ShapeDtypeStruct, ...]:
    m, f = self.mj_model, self._float
    s = jax.ShapeDtypeStruct
    return (s((nsim, self.nstate, 2), jnp.uint32), s((nsim,), f), s((nsim, m.nq), f),
            s((nsim, m.nv), f), s((nsim, m.nv), f), s((nsim, m.nu), f),
            s((nsim, m.nsensordata), f), s((nsim, m.nbody, 3), f), s((nsim, m.nbody, 4), f))

  def _check_params(self, params: ModelParams, nsim: int) -> dict[str, jax.Array]:
    out = {}
    for name, shape in param_shapes(self.mj_model).items():
      x = getattr(params, name)
      if tuple(x.shape) != (nsim,) + shape:
        raise ValueError(f"ModelParams.{name} has shape {tuple(x.shape)}, expected "
                         f"{(nsim,) + shape}")
      out[name] = x
    return out

  def _state(self, outs) -> NativeState:
    return NativeState(*outs)

  def init(self, qpos: jax.Array, qvel: jax.Array, params: ModelParams,
           mocap_pos: jax.Array, only: jax.Array | None = None) -> NativeState:
    m = self.mj_model
    nsim = qpos.shape[0]
    if qpos.shape != (nsim, m.nq) or qvel.shape != (nsim, m.nv):
      raise ValueError(f"qpos/qvel have shapes {qpos.shape}/{qvel.shape}, expected "
                       f"{(nsim, m.nq)}/{(nsim, m.nv)}")
    if mocap_pos.shape != (nsim, m.nmocap, 3):
      raise ValueError(f"mocap_pos has shape {mocap_pos.shape}, expected {(nsim, m.nmocap, 3)}")
    p = self._check_params(params, nsim)
    only = jnp.ones((nsim,), bool) if only is None else jnp.asarray(only, bool)
    if only.shape != (nsim,):
      raise ValueError(f"only has shape {only.shape}, expected {(nsim,)}")
    outs = jax.pure_callback(self._init_host, self._result_shapes(nsim), qpos, qvel, p,
                             mocap_pos, only, vmap_method="sequential")
    return self._state(outs)

  def step(self, state: NativeState, params: ModelParams, ctrl: jax.Array,
           xfrc_applied: jax.Array) -> NativeState:
    m = self.mj_model
    nsim = state.integration.shape[0]
    if ctrl.ndim != 3 or ctrl.shape[0] != nsim or ctrl.shape[2] != m.nu:
      raise ValueError(f"ctrl has shape {ctrl.shape}, expected ({nsim}, n_substeps, {m.nu})")
    if xfrc_applied.shape != (nsim, m.nbody, 6):
      raise ValueError(f"xfrc_applied has shape {xfrc_applied.shape}, expected "
                       f"{(nsim, m.nbody, 6)}")
    p = self._check_params(params, nsim)
    outs = jax.pure_callback(self._step_host, self._result_shapes(nsim), state.integration, p,
                             ctrl, xfrc_applied, vmap_method="sequential")
    return self._state(outs)

  def view(self, state: NativeState) -> PhysicsView:
    return PhysicsView(time=state.time, qpos=state.qpos, qvel=state.qvel, qacc=state.qacc,
                       actuator_force=state.actuator_force, sensordata=state.sensordata,
                       xpos=state.xpos, xquat=state.xquat)
