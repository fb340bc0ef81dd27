"""MuJoCo MJX (JAX implementation) backend.

Per-environment physical parameters are realised the way brax/Playground domain randomization
does it: the batched `ModelParams` replace the matching `mjx.Model` fields (one copy per env),
and `mjx.step` is vmapped over (model, data) with an `in_axes` tree that is 0 for exactly those
fields and None for everything else. Unlike Playground, the batched fields are rebuilt from the
params on every call, so parameters drawn at an episode reset take effect immediately (no
per-slot model drawn once at start-up).

A control step runs `ctrl.shape[1]` physics substeps in a `lax.scan`, writing one control row
per substep, so the environment can realise a control delay at physics-step resolution.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
from mujoco import mjx

from jax_env.physics.view import MODEL_FIELDS, ModelParams, PhysicsView, model_fields


class MjxBackend:
  """Steps a batch of environments of one `mujoco.MjModel` with MJX."""

  name = "mjx"

  def __init__(self, mj_model: mujoco.MjModel, forward_on_init: bool = True):
    """`forward_on_init=False` makes `init` skip the forward pass: the state is then complete
    for stepping (mjx.step recomputes every derived quantity from qpos, qvel, ctrl and mocap
    first) but its view holds zeros for derived fields until the first step. The environment
    uses this because its resets never read derived fields, and a forward pass inside the
    jitted step (for auto-resets) roughly doubles the step's XLA compile time on CPU."""
    self.mj_model = mj_model
    self.forward_on_init = forward_on_init
    self.model = mjx.put_model(mj_model, impl="jax")
    axes = jax.tree_util.tree_map(lambda _: None, self.model)
    self._in_axes = axes.tree_replace({k: 0 for k in MODEL_FIELDS})
    self._step1 = jax.vmap(mjx.step, in_axes=(self._in_axes, 0))
    self._forward = jax.vmap(mjx.forward, in_axes=(self._in_axes, 0))

  def batched_model(self, params: ModelParams) -> mjx.Model:
    """The mjx.Model with the per-env fields of `params` (leading axis B)."""
    return self.model.tree_replace(
        model_fields(params, self.model.actuator_gainprm, self.model.actuator_biasprm))

  def init(self, qpos: jax.Array, qvel: jax.Array, params: ModelParams,
           mocap_pos: jax.Array, only: jax.Array | None = None) -> mjx.Data:
    del only  # every row is computed: a vectorized forward costs the same for a subset
    batch = qpos.shape[0]
    data = mjx.make_data(self.model)
    data = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (batch,) + x.shape), data)
    # Hold the initial pose: the position servos start with ctrl = q.
    ctrl = qpos[:, 7:7 + self.mj_model.nu]
    data = data.replace(qpos=qpos, qvel=qvel, mocap_pos=mocap_pos, ctrl=ctrl)
    if not self.forward_on_init:
      return data
    return self._forward(self.batched_model(params), data)

  def step(self, state: mjx.Data, params: ModelParams, ctrl: jax.Array,
           xfrc_applied: jax.Array) -> mjx.Data:
    model = self.batched_model(params)
    state = state.replace(xfrc_applied=xfrc_applied)

    def substep(data, ctrl_k):
      return self._step1(model, data.replace(ctrl=ctrl_k)), None

    state, _ = jax.lax.scan(substep, state, jnp.swapaxes(ctrl, 0, 1))
    return state

  def view(self, state: mjx.Data) -> PhysicsView:
    return PhysicsView(time=state.time, qpos=state.qpos, qvel=state.qvel, qacc=state.qacc,
                       actuator_force=state.actuator_force, sensordata=state.sensordata,
                       xpos=state.xpos, xquat=state.xquat)
