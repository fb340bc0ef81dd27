"""The fall-recovery environment of the Booster T1 (docs/contracts.md, "Environment API").

Batched natively: every array in `EnvState` has a leading batch axis and `reset`/`step` are pure
functions of (state, action) that jit as they are (no outer vmap). Physics is read only through
`PhysicsView` and driven through `ModelParams`, so the MJX and the native C MuJoCo backends are
interchangeable by name.

One control step:
  1. actions → PD targets of the controlled joints ("current": q + scale·a, "default":
     q_stand + scale·a); every other joint is held at its `stand` value; while the episode is
     still settling, actions are ignored and the initial joint targets are held;
  2. targets are clamped by the velocity limit (randomization.velocity_limited_target) and the
     stage's joint range, then enter a short history from which each physics substep takes the
     target that was issued at least `delay` earlier (the per-episode control delay);
  3. a push (force and torque on the Trunk) is applied where one is scheduled: the random pushes
     of training, or the evaluation protocols' push fixed in the Trunk frame;
  4. physics runs ctrl_dt / timestep substeps;
  5. observations, privileged features, rewards and the success detector read the new view;
  6. episodes that reached their time limit, met a termination condition of the stage (Trunk
     low for too long, upside down, rolled on a side: true terminations, no value bootstrap)
     or blew up numerically (NaN) are reset with a fresh draw (scenario, randomization, delay,
     terrain) in the same step.

Penalties are scaled by `EnvState.penalty_scale`, and an assisting upward force on the Trunk
is `EnvState.assist_force`; the learner sets both from the stage's schedules (a schedule is
data in the curriculum; the step only multiplies and adds). Outside training both stay at
their reset values: full penalties, no assist. Training
staggers the episode clocks once at the start (`stagger`), so that the batch does not hold one
phase of every episode at a time.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jax_env import features, getup_paths
from jax_env import rewards as rewards_lib
from jax_env import robot
from jax_env.kinematics import Kinematics, quat_to_mat, rotate_inverse
from jax_env.physics import make_backend
from jax_env.physics.view import PhysicsView
from jax_env.randomization import (TERRAINS, EpisodeDraw, PushState, Pusher, Randomizer,
                                   constrained_model, delayed_ctrl,
                                   velocity_limited_target)
from jax_env.scenarios import SCENARIOS, ScenarioSampler
from jax_env.stage_config import EPISODE_ENDS, TERMINATION_RULES, StageConfig


def _forced_index(value, names, what, shape):
  """A forced choice as per-env indices [B] (−1: draw), from a name or an index array."""
  if value is None or not isinstance(value, str):
    return value
  if value not in names:
    raise ValueError(f"unknown {what} {value!r}; valid: {', '.join(names)}")
  return jnp.full(shape, names.index(value), jnp.int32)


# A state whose joint or base speed exceeds this (rad/s or m/s) has blown up numerically.
BLOWUP_SPEED = 1e3
# On the native backend (CPUs), auto-resets compute fresh episodes for the rows that ended,
# this many at a time (gathered; a loop takes more), not for the whole batch. Every row's reset
# is its own (per-row keys, vmapped), so the rows are the same either way; of 128 episodes of
# 300 steps about one ends per step, and a reset of all 128 rows (under vmap every start
# scenario's pose is computed for every row) cost several percent of a training step on a CPU.
# MJX (accelerators) resets every row: a vectorized reset costs little next to the MJX step.
RESET_ROWS = 8


@dataclasses.dataclass(frozen=True)
class MirrorMaps:
  """mirror(x) = x[..., perm] * sign for each feature list; every map is an involution."""

  obs_perm: np.ndarray
  obs_sign: np.ndarray
  privileged_perm: np.ndarray
  privileged_sign: np.ndarray
  action_perm: np.ndarray
  action_sign: np.ndarray


@struct.dataclass
class EnvState:
  """The batched state of the environment (every array has a leading axis B)."""

  physics: Any
  draw: EpisodeDraw
  obs: jax.Array  # [B, n_obs]
  privileged: jax.Array  # [B, n_priv]
  reward: jax.Array  # [B]
  done: jax.Array  # [B] float 0/1: the episode ended at this step (already auto-reset)
  truncation: jax.Array  # [B] float 0/1: the end was the time limit
  control_active: jax.Array  # [B] float 0/1: actions take effect in the next step
  metrics: dict  # "reward/<term>", "standing": [B]
  episode_metrics: dict  # "success", "recovery_time", "return", "scenario", "max_height",
  #                        "time_standing", "end" (index into EPISODE_ENDS), "rule_met" (as
  #                        `rule_met` below): valid where done
  step_count: jax.Array  # [B] int32 control steps since the episode start
  episode_limit: jax.Array  # [B] int32 control steps after which the episode times out
  low_steps: jax.Array  # [B] int32 consecutive controlled steps with the Trunk below low_height
  # [B] int32 the first termination rule that held before the episode succeeded, as its index
  # into EPISODE_ENDS (0: none). Where rules end episodes it is the rule that ended it; where they
  # do not (evaluation), it says whether, and by which rule, the stage would have ended it.
  rule_met: jax.Array
  max_height: jax.Array  # [B] highest Trunk height of the episode so far
  stand_steps: jax.Array  # [B] int32 controlled steps spent standing this episode
  penalty_scale: jax.Array  # [B] the penalty schedule's current scale (set by the learner)
  assist_force: jax.Array  # [B] N, upward on the Trunk while controlled (set by the learner)
  control_start: jax.Array  # [B] int32 first controlled step (settling before it)
  scenario: jax.Array  # [B] int32 index into SCENARIOS
  targets: jax.Array  # [B, K, nu] issued PD targets, newest first (for the delay)
  hold_target: jax.Array  # [B, nu] initial joint targets held while settling
  last_action: jax.Array  # [B, nA] the action that took effect in the last step (0 if none)
  prev_action: jax.Array  # [B, nA] the one before
  prev_qvel: jax.Array  # [B, nv] for finite-difference accelerations
  push: PushState
  push_active: jax.Array  # [B] bool, a push acted during the last step
  success: rewards_lib.SuccessState
  episode_return: jax.Array  # [B]
  rng: jax.Array  # [B] per-env PRNG keys
  # [B] int32 row of the stored path's plan for the current state of an episode that started on
  # a get-up path (−1: none, or past the path's end; `teacher_action`).
  teacher_row: jax.Array
  teacher_forced: jax.Array  # [B] float 0/1: the episode acts with the plan ([stage.imitation])


class FallRecoveryEnv:
  """Booster T1 fall recovery for one curriculum stage."""

  def __init__(self, stage: StageConfig | dict, backend: str = "mjx", mj_model=None,
               rules_end_episodes: bool = True):
    """`rules_end_episodes`: the stage's termination rules end an episode (training, the
    monitor). Off, an episode runs to its time limit (or a blow-up) as in the paper's
    evaluation, and each rule that holds is only recorded (`EnvState.rule_met`)."""
    if not isinstance(stage, StageConfig):
      stage = StageConfig.from_dict(stage)
    self.stage = stage
    self.rules_end_episodes = rules_end_episodes
    base_model = robot.load_model() if mj_model is None else mj_model
    self.mj_model = constrained_model(stage, base_model)
    # Resets never read derived physics quantities (see `_start`), so MJX may skip the forward
    # pass at init: that keeps a second copy of the MJX pipeline out of the step's compile.
    self.backend_name = backend
    self.reset_rows = RESET_ROWS if backend == "native" else 0  # 0: every row
    self.backend = make_backend(backend, self.mj_model,
                                **({"forward_on_init": False} if backend == "mjx" else {}))
    m = self.mj_model

    self.obs_names, self.privileged_names, self.action_names = features.feature_names(stage)
    self.obs_size, self.privileged_size = len(self.obs_names), len(self.privileged_names)
    self.action_size = len(self.action_names)
    self.ctrl_dt = stage.sim.ctrl_dt
    self.n_substeps = stage.sim.n_substeps
    self.episode_steps = stage.sim.episode_steps
    self.settle_steps = int(round(stage.scenario_params.settle_s / self.ctrl_dt))
    self.hold_steps = max(int(math.ceil(stage.success.hold_s / self.ctrl_dt - 1e-9)), 1)
    self.mirror = MirrorMaps(
        *features.mirror_map(self.obs_names),
        *features.mirror_map(self.privileged_names),
        *features.mirror_map(self.action_names, kind="action"))

    # Ids and constants, cached once by name.
    j = {n: i for i, n in enumerate(robot.JOINT_NAMES)}
    self.ctrl_idx = np.array([j[n] for n in stage.controlled_joints], np.int32)
    self.obs_idx = np.array([j[n] for n in stage.observed_joints], np.int32)
    self.observed_mask = np.zeros(robot.NUM_JOINTS, np.float32)
    self.observed_mask[self.obs_idx] = 1.0
    self.hip_roll_idx = np.array([j["Left_Hip_Roll"], j["Right_Hip_Roll"]], np.int32)
    self.trunk = int(m.body("Trunk").id)
    self.waist = int(m.body("Waist").id)
    # The robot's bodies for its centre of mass (nominal masses: a shaping term's estimate) and
    # the feet for `feet_under_com`.
    self.com_bodies = np.array(robot.body_ids(m), np.int32)
    mass = m.body_mass[self.com_bodies]
    self.com_mass = np.asarray(mass / mass.sum(), np.float32)
    self.com_ipos = np.asarray(m.body_ipos[self.com_bodies], np.float32)
    self.feet = np.array([m.body(n).id for n in robot.FOOT_BODIES], np.int32)
    t = stage.termination
    self.low_height_steps = max(int(math.ceil(t.low_height_s / self.ctrl_dt - 1e-9)), 1)
    stand_qpos, _ = robot.keyframe(m, "stand")
    self.q_stand = np.asarray(stand_qpos[7:], np.float32)
    self.stand_height = float(stand_qpos[2])
    real = robot.joint_arrays(base_model)
    self.real_lo = real.range_low.astype(np.float32)
    self.real_hi = real.range_high.astype(np.float32)
    self.real_torque_limit = real.torque_limit.astype(np.float32)
    jnt = np.array([m.joint(n).id for n in robot.JOINT_NAMES])
    self.lo = np.asarray(m.jnt_range[jnt, 0], np.float32)
    self.hi = np.asarray(m.jnt_range[jnt, 1], np.float32)
    self.v_max = (robot.VELOCITY_LIMITS * stage.constraints.velocity_limit_scale
                  ).astype(np.float32)
    self.gyro = robot.sensor_slice(m, robot.GYRO_SENSOR)
    self.contact_adr = np.array([robot.sensor_slice(m, s).start
                                 for s in robot.CONTACT_SENSOR_NAMES], np.int32)

    # Floor contact of each contact body at a reset, from the cheap kinematics (see `_start`).
    self.kin = Kinematics(m)
    geom_body = [int(m.geom_bodyid[g]) for g in self.kin.geom_ids]
    self.contact_geoms = np.array([[geom_body[i] == m.body(b).id for i in range(len(geom_body))]
                                   for b in robot.CONTACT_BODIES])
    self.randomizer = Randomizer(stage, m)
    self.pusher = Pusher(stage)
    self.sampler = ScenarioSampler(stage, m, self.randomizer)
    self._init_teacher()
    # Targets must be kept long enough to serve the longest delay.
    max_delay = self.randomizer.max_delay_substeps
    self.target_history = int(math.ceil(max_delay / self.n_substeps)) + 1

  # -------------------------------------------------------------------------------------------
  # Reset.

  def reset(self, keys: jax.Array, scenario: str | jax.Array | None = None,
            terrain: str | jax.Array | None = None) -> EnvState:
    """Fresh episodes from per-env keys [B] (jax.random.split(key, B)).

    `scenario` forces one scenario (a name from SCENARIOS) or per-env indices [B] into
    SCENARIOS (−1: draw from the mixture); by default every env draws from the stage's
    mixture. `terrain` likewise forces a terrain of TERRAINS (a slope draws its angle up
    to the stage's slope_max_deg, an obstacle sits between the legs, as in training). Forcing is
    for evaluation; training and every auto-reset use the mixtures.
    """
    scenario = _forced_index(scenario, SCENARIOS, "scenario", keys.shape[:1])
    terrain = _forced_index(terrain, TERRAINS, "terrain", keys.shape[:1])
    return self._reset(keys, scenario, terrain)

  def reset_to(self, keys: jax.Array, qpos: jax.Array, qvel: jax.Array,
               settle: bool = False) -> EnvState:
    """Episodes starting from a given state [B, nq], [B, nv] (DR parameters still drawn).

    Used by evaluation and tests to start from poses outside the scenario list (e.g. `stand`).
    """
    keys, k_draw, _ = self._split(keys, 3)
    draw = self._draw(k_draw)
    batch = keys.shape[0]
    mocap = jnp.broadcast_to(self.sampler.park, (batch, self.mj_model.nmocap, 3))
    settles = jnp.full((batch,), settle)
    none = jnp.full((batch,), -1, jnp.int32)
    return self._start(keys, draw, qpos, qvel, mocap, none, settles, teacher_row=none)

  def _split(self, keys, n):
    out = jax.vmap(lambda k: jax.random.split(k, n))(keys)
    return tuple(out[:, i] for i in range(n))

  def _draw(self, keys, terrain=None) -> EpisodeDraw:
    if terrain is None:
      draw = jax.vmap(lambda k: self.randomizer.draw(k, 1))(keys)
    else:
      draw = jax.vmap(lambda k, t: self.randomizer.draw(k, 1, t[None]))(keys, terrain)
    return jax.tree_util.tree_map(lambda x: x[:, 0], draw)

  def _reset(self, keys, scenario=None, terrain=None, only=None) -> EnvState:
    keys, k_draw, k_scn = self._split(keys, 3)
    draw = self._draw(k_draw, terrain)
    init = self.sampler.sample(k_scn, draw, scenario)
    return self._start(keys, draw, init.qpos, init.qvel, init.mocap_pos, init.scenario,
                       init.settles, init.geom_lowest, init.teacher_row, only=only)

  def _start(self, keys, draw, qpos, qvel, mocap, scenario, settles, geom_lowest=None,
             teacher_row=None, only=None) -> EnvState:
    """Fresh episodes; `only` [B] bool marks the rows the caller keeps (the backend may skip
    the physics of the others, whose `physics` is then unspecified)."""
    batch = qpos.shape[0]
    keys, k_push = self._split(keys, 2)
    qpos = qpos.astype(jnp.float32)
    qvel = qvel.astype(jnp.float32)
    physics = self.backend.init(qpos, qvel, draw.params, mocap, only=only)
    control_start = jnp.where(settles, self.settle_steps, 0).astype(jnp.int32)
    hold = qpos[:, 7:]
    push = self.pusher.reset(k_push, control_start)
    zeros_a = jnp.zeros((batch, self.action_size))
    # Reset features come from qpos/qvel alone, the same for every backend: the IMU gyro of a
    # free Trunk equals qvel[3:6] (body-frame angular velocity), and floor contact is read off
    # the kinematics (a geom touches the floor when its lowest point is at or below it).
    if geom_lowest is None:
      geom_lowest = jax.vmap(self.kin.geom_lowest)(qpos)
    view = self._reset_view(qpos, qvel, geom_lowest)
    obs = self._obs(view, draw, zeros_a)
    priv = self._privileged(view, draw, push, jnp.zeros((batch,), bool))
    zeros = jnp.zeros((batch,))
    return EnvState(
        physics=physics, draw=draw, obs=obs, privileged=priv, reward=zeros, done=zeros,
        truncation=zeros, control_active=(control_start == 0).astype(jnp.float32),
        metrics=self._zero_metrics(batch), episode_metrics=self._zero_episode_metrics(batch),
        step_count=jnp.zeros((batch,), jnp.int32), control_start=control_start,
        episode_limit=jnp.full((batch,), self.episode_steps, jnp.int32),
        low_steps=jnp.zeros((batch,), jnp.int32), rule_met=jnp.zeros((batch,), jnp.int32),
        max_height=qpos[:, 2],
        stand_steps=jnp.zeros((batch,), jnp.int32), penalty_scale=jnp.ones((batch,)),
        assist_force=jnp.zeros((batch,)),
        scenario=scenario.astype(jnp.int32),
        targets=jnp.broadcast_to(hold[:, None], (batch, self.target_history, hold.shape[-1])),
        hold_target=hold, last_action=zeros_a, prev_action=zeros_a, prev_qvel=qvel, push=push,
        push_active=jnp.zeros((batch,), bool), success=rewards_lib.success_init(batch),
        episode_return=zeros, rng=keys, teacher_row=teacher_row.astype(jnp.int32),
        teacher_forced=self._teacher_forced(keys, teacher_row))

  def _reset_view(self, qpos, qvel, geom_lowest) -> PhysicsView:
    batch = qpos.shape[0]
    touching = jnp.any(jnp.asarray(self.contact_geoms)[None] & (geom_lowest[:, None, :] <= 1e-4),
                       -1)
    sensordata = jnp.zeros((batch, self.mj_model.nsensordata))
    sensordata = sensordata.at[:, self.gyro].set(qvel[:, 3:6])
    sensordata = sensordata.at[:, self.contact_adr].set(touching.astype(jnp.float32))
    quat = qpos[:, 3:7] / jnp.linalg.norm(qpos[:, 3:7], axis=-1, keepdims=True)
    xquat = jnp.zeros((batch, self.mj_model.nbody, 4)).at[:, self.trunk].set(quat)
    z = lambda n: jnp.zeros((batch, n))
    return PhysicsView(time=jnp.zeros((batch,)), qpos=qpos, qvel=qvel, qacc=z(self.mj_model.nv),
                       actuator_force=z(self.mj_model.nu), sensordata=sensordata,
                       xpos=jnp.zeros((batch, self.mj_model.nbody, 3)), xquat=xquat)

  def _zero_metrics(self, batch):
    z = jnp.zeros((batch,))
    return {**{f"reward/{t}": z for t in rewards_lib.TERMS}, "standing": z}

  def _zero_episode_metrics(self, batch):
    z = jnp.zeros((batch,))
    return {"success": z, "recovery_time": jnp.full((batch,), jnp.nan, jnp.float32), "return": z,
            "scenario": z, "max_height": z, "time_standing": z, "end": z, "rule_met": z}

  def stagger(self, state: EnvState, key: jax.Array) -> EnvState:
    """The same episodes with their first time limits drawn uniformly in (control start,
    episode length]: a training batch then holds every phase of an episode at once rather
    than all episodes in lockstep (legged_gym's random initial episode lengths). Later
    episodes run the full length."""
    low = state.control_start + 1
    limit = jax.random.randint(key, low.shape, low, self.episode_steps + 1)
    return state.replace(episode_limit=limit.astype(jnp.int32))

  def with_penalty_scale(self, state: EnvState, scale) -> EnvState:
    """The state with the penalty schedule's scale for the coming steps."""
    return state.replace(penalty_scale=jnp.broadcast_to(
        jnp.asarray(scale, jnp.float32), state.penalty_scale.shape))

  def with_assist_force(self, state: EnvState, force) -> EnvState:
    """The state with the assist schedule's upward force (N) for the coming steps."""
    return state.replace(assist_force=jnp.broadcast_to(
        jnp.asarray(force, jnp.float32), state.assist_force.shape))

  # -------------------------------------------------------------------------------------------
  # Step.

  def step(self, state: EnvState, action: jax.Array) -> EnvState:
    s = self.stage
    batch = action.shape[0]
    a = jnp.clip(action, -s.action.clip, s.action.clip)
    view0 = self.backend.view(state.physics)
    q, qd = view0.qpos[:, 7:], view0.qvel[:, 6:]
    active = state.step_count >= state.control_start

    # 1-2. Targets, velocity limit, joint range, delay.
    base = q[:, self.ctrl_idx] if s.action.mapping == "current" else self.q_stand[self.ctrl_idx]
    target = jnp.broadcast_to(jnp.asarray(self.q_stand), q.shape)
    target = target.at[:, self.ctrl_idx].set(base + s.action.scale * a)
    target = velocity_limited_target(target, q, qd, state.draw.params.actuator_kp,
                                     state.draw.params.actuator_kd, self.v_max)
    target = jnp.clip(target, self.lo, self.hi)
    target = jnp.where(active[:, None], target, state.hold_target)
    history = jnp.concatenate([target[:, None], state.targets[:, :-1]], axis=1)
    ctrl = delayed_ctrl(history, state.draw.delay_substeps, self.n_substeps)

    # 3. Pushes.
    rng, k_push, k_reset = self._split(state.rng, 3)
    push, pushing = self.pusher.update(k_push, state.push, state.step_count)
    # The evaluation protocols' scheduled push, fixed in the Trunk frame (never in training).
    scheduled_force, scheduled = self.pusher.scheduled(push, state.step_count,
                                                       view0.qpos[:, 3:7])
    xfrc = jnp.zeros((batch, self.mj_model.nbody, 6))
    wrench = jnp.concatenate([push.force, push.torque], axis=-1) * pushing[:, None]
    wrench = wrench.at[:, :3].add(scheduled_force)
    # The training assist pulls only while the policy acts (not while a drop settles).
    wrench = wrench.at[:, 2].add(state.assist_force * active)
    xfrc = xfrc.at[:, self.trunk].set(wrench)

    # 4. Physics.
    physics = self.backend.step(state.physics, state.draw.params, ctrl, xfrc)
    view = self.backend.view(physics)

    # 5. Observation, reward, success.
    applied = jnp.where(active[:, None], a, 0.0)
    x = self._quantities(view, state, applied)
    success = rewards_lib.success_update(state.success, x.standing, state.step_count,
                                         state.control_start, self.hold_steps, self.ctrl_dt)
    reward, terms = rewards_lib.compute(x, s.rewards, s.reward_params, s.reward_shaping,
                                        self.ctrl_dt, state.penalty_scale)
    gate = active.astype(jnp.float32)  # no reward while settling: the policy is not acting
    finite = (jnp.all(jnp.isfinite(view.qpos), -1) & jnp.all(jnp.isfinite(view.qvel), -1)
              & (jnp.max(jnp.abs(view.qvel), -1) < BLOWUP_SPEED))
    clean = lambda r: jnp.where(finite, jnp.nan_to_num(r * gate), 0.0)
    reward = clean(reward)
    metrics = {k: clean(v) for k, v in terms.items()}
    metrics["standing"] = (x.standing & active & finite).astype(jnp.float32)

    step_count = state.step_count + 1
    time_up = step_count >= state.episode_limit
    low_steps, rules = self._terminations(state, x, active)
    held = jnp.any(rules, axis=-1)
    first_rule = 1 + jnp.argmax(rules, axis=-1)  # its index into EPISODE_ENDS
    # A rule that holds once the episode has succeeded does not undo the success.
    met = held & ~success.success & finite & (state.rule_met == 0)
    rule_met = jnp.where(met, first_rule, state.rule_met)
    terminated = held & self.rules_end_episodes
    done = time_up | ~finite | terminated
    # EPISODE_ENDS is the time limit, then the rules in `rules`' column order, then a blow-up.
    end = jnp.where(~finite, EPISODE_ENDS.index("blow_up"),
                    jnp.where(terminated, first_rule,
                              EPISODE_ENDS.index("time_limit")))
    episode_return = state.episode_return + reward
    # A blown-up step's height is the numerics', not the robot's: the episode ends on it and
    # keeps the highest height it had reached before.
    max_height = jnp.where(finite, jnp.maximum(state.max_height, view.qpos[:, 2]), state.max_height)
    stand_steps = state.stand_steps + metrics["standing"].astype(jnp.int32)
    episode_metrics = {
        "success": success.success.astype(jnp.float32),
        "recovery_time": jnp.where(success.success, success.recovery_time, jnp.nan),
        "return": episode_return,
        "scenario": state.scenario.astype(jnp.float32),
        "max_height": max_height,
        "time_standing": stand_steps.astype(jnp.float32) * self.ctrl_dt,
        "end": end.astype(jnp.float32),
        "rule_met": rule_met.astype(jnp.float32),
    }
    obs = self._obs(view, state.draw, applied)
    priv = self._privileged(view, state.draw, push, pushing, scheduled_force)
    pushing = pushing | scheduled
    nxt = state.replace(
        physics=physics, obs=obs, privileged=priv, reward=reward,
        done=done.astype(jnp.float32),
        truncation=(time_up & finite & ~terminated).astype(jnp.float32),
        control_active=(step_count >= state.control_start).astype(jnp.float32),
        metrics=metrics, episode_metrics=episode_metrics, step_count=step_count,
        low_steps=low_steps, rule_met=rule_met, max_height=max_height, stand_steps=stand_steps,
        targets=history[:, :self.target_history], last_action=applied,
        prev_action=state.last_action, prev_qvel=view.qvel, push=push, push_active=pushing,
        success=success, episode_return=episode_return, rng=rng,
        teacher_row=self._next_teacher_row(state))

    # 6. Auto-reset with fresh draws, only computed when some episode ended: on the native
    #    backend for the rows that ended, `reset_rows` at a time (gathered), else every row.
    def keep(merged):
      return merged.replace(
          reward=nxt.reward, done=nxt.done, truncation=nxt.truncation, metrics=nxt.metrics,
          episode_metrics=nxt.episode_metrics, penalty_scale=nxt.penalty_scale,
          assist_force=nxt.assist_force)

    def reset_all(nxt):
      fresh = self._reset(k_reset, only=done)
      return keep(jax.tree_util.tree_map(
          lambda new, old: jnp.where(done.reshape((-1,) + (1,) * (old.ndim - 1)), new, old),
          fresh, nxt))

    def reset_ended(nxt):
      def chunk(carry):
        merged, left = carry
        rows = jnp.flatnonzero(left, size=self.reset_rows, fill_value=batch)  # batch: none
        valid = rows < batch
        fresh = self._reset(k_reset[jnp.minimum(rows, batch - 1)], only=valid)
        merged = jax.tree_util.tree_map(lambda old, new: old.at[rows].set(new, mode="drop"),
                                        merged, fresh)
        return merged, left.at[rows].set(False, mode="drop")

      merged, _ = jax.lax.while_loop(lambda c: jnp.any(c[1]), chunk, (nxt, done))
      return keep(merged)

    gathered = 0 < self.reset_rows < batch
    return jax.lax.cond(jnp.any(done), reset_ended if gathered else reset_all, lambda n: n, nxt)

  # -------------------------------------------------------------------------------------------
  # The get-up paths' plans (`[stage.imitation]`).

  def _init_teacher(self):
    """The plan's actions of every stored path state under this stage's action mapping, and
    which rows a policy of this stage can follow: the "default" mapping (the plan's targets
    are offsets from the stand pose), the paths' control period, and every joint the path
    moves among the controlled ones (the others are held at the stand pose)."""
    sampler, s = self.sampler, self.stage
    controlled = set(s.controlled_joints)
    followable = [s.action.mapping == "default"
                  and abs(self.ctrl_dt - getup_paths.CTRL_DT) < 1e-9
                  and getup_paths.driven_joints(n) <= controlled
                  for n in sampler.teacher_paths]
    self.teacher_actions = (sampler.teacher[:, self.ctrl_idx] / s.action.scale
                            ).astype(np.float32)
    self.teacher_ok = np.array(followable)[sampler.teacher_row_path]

  def _teacher_forced(self, keys, row) -> jax.Array:
    """[B] 1 for the share `forcing` of the path episodes (a draw of its own: fold_in leaves
    every other random stream as it is)."""
    u = jax.vmap(lambda k: jax.random.uniform(jax.random.fold_in(k, 7)))(keys)
    return ((row >= 0) & (u < self.stage.imitation.forcing)).astype(jnp.float32)

  def _next_teacher_row(self, state: EnvState) -> jax.Array:
    row = state.teacher_row
    end = jnp.asarray(self.sampler.teacher_row_end)[jnp.maximum(row, 0)]
    return jnp.where((row >= 0) & (row + 1 < end), row + 1, -1).astype(jnp.int32)

  def teacher_action(self, state: EnvState) -> tuple[jax.Array, jax.Array]:
    """([B, nA] the stored path's action for the current state, [B] 1 where there is one):
    an episode started on a get-up path has, at its k-th step, the action the path's plan
    issued k steps after the start state (whether or not the policy has kept to the path)."""
    row = state.teacher_row
    ok = (row >= 0) & jnp.asarray(self.teacher_ok)[jnp.maximum(row, 0)]
    action = jnp.asarray(self.teacher_actions)[jnp.maximum(row, 0)]
    return action, ok.astype(jnp.float32)

  def _terminations(self, state: EnvState, x: rewards_lib.Quantities, active):
    """(low-height streak [B], [B, len(TERMINATION_RULES)] bool: which rules end the episode
    after this step); only while control is on, and never a rule whose threshold is 0."""
    t = self.stage.termination
    never = jnp.zeros_like(active)
    low = (x.base_height < t.low_height) & active if t.low_height > 0 else never
    low_steps = jnp.where(low, state.low_steps + 1, 0)
    g = x.gravity
    face_down = g[:, 0] > 0  # the chest (Trunk +x) toward the floor
    if t.upside_down_face_down_max_roll > 0:  # pitched over the head, not rolling over a shoulder
      face_down = face_down & (jnp.abs(g[:, 1]) < t.upside_down_face_down_max_roll)
    holds = {
        "low_height": low_steps > self.low_height_steps,
        "upside_down": active & (g[:, 2] > t.upside_down),
        "upside_down_face_down": active & face_down & (g[:, 2] > t.upside_down_face_down),
        "side_roll": active & (jnp.abs(g[:, 1]) > t.side_roll),
    }
    on = {k: getattr(t, k) > 0 for k in TERMINATION_RULES}
    return low_steps, jnp.stack([holds[k] if on[k] else never for k in TERMINATION_RULES], -1)

  # -------------------------------------------------------------------------------------------
  # Features.

  def _gravity(self, view: PhysicsView, draw: EpisodeDraw) -> jax.Array:
    g = draw.params.gravity / jnp.linalg.norm(draw.params.gravity, axis=-1, keepdims=True)
    return rotate_inverse(view.xquat[:, self.trunk], g)

  def _obs(self, view: PhysicsView, draw: EpisodeDraw, last_action) -> jax.Array:
    q = view.qpos[:, 7:] - self.q_stand
    qd = view.qvel[:, 6:]
    return features.assemble(features.OBS_LAYOUT, {
        "gravity": self._gravity(view, draw), "ang_vel": view.sensordata[:, self.gyro],
        "joint_pos": q[:, self.obs_idx], "joint_vel": qd[:, self.obs_idx],
        "prev_action": last_action}, self.stage)

  def _privileged(self, view: PhysicsView, draw: EpisodeDraw, push: PushState, pushing,
                  scheduled_force=0.0):
    batch = view.qpos.shape[0]
    col = lambda x: x[:, None]
    on = pushing[:, None].astype(jnp.float32)
    contact = (view.sensordata[:, self.contact_adr] > 0).astype(jnp.float32)
    tls = jnp.full((batch, 1), self.stage.constraints.torque_limit_scale)
    return features.assemble(features.PRIVILEGED_LAYOUT, {
        "friction": col(draw.friction), "compliance": col(draw.compliance),
        "restitution": col(draw.restitution), "mass_scale": draw.mass_scale,
        "com_offset": draw.com_offset.reshape(batch, -1), "kp_scale": draw.kp_scale,
        "kd_scale": draw.kd_scale, "torque_limit_scale": tls, "delay": col(draw.delay_s),
        "base_height": view.qpos[:, 2:3], "base_lin_vel": view.qvel[:, 0:3],
        "contact": contact, "push_force": push.force * on + scheduled_force,
        "push_torque": push.torque * on,
        "terrain": jnp.concatenate([draw.slope, col(draw.obstacle)], axis=-1)})

  def _quantities(self, view: PhysicsView, state: EnvState, action) -> rewards_lib.Quantities:
    q, qd = view.qpos[:, 7:], view.qvel[:, 6:]
    gravity = self._gravity(view, state.draw)
    standing = rewards_lib.is_standing(view.qpos[:, 2], gravity, q, self.q_stand,
                                       self.stand_height, self.observed_mask, self.stage.success)
    return rewards_lib.Quantities(
        base_height=view.qpos[:, 2], waist_height=view.xpos[:, self.waist, 2], gravity=gravity,
        q=q, q_ref=jnp.asarray(self.q_stand),
        qd=qd, qdd=(qd - state.prev_qvel[:, 6:]) / self.ctrl_dt,
        root_acc=(view.qvel[:, 0:3] - state.prev_qvel[:, 0:3]) / self.ctrl_dt,
        torque=view.actuator_force,
        torque_limit=jnp.broadcast_to(jnp.asarray(self.real_torque_limit), q.shape),
        range_low=jnp.asarray(self.real_lo), range_high=jnp.asarray(self.real_hi),
        action=action, prev_action=state.last_action, prev_prev_action=state.prev_action,
        hip_roll=q[:, self.hip_roll_idx], standing=standing,
        com=self._com(view), feet=view.xpos[:, self.feet])

  def _com(self, view: PhysicsView) -> jax.Array:
    """[B, 3] the robot's centre of mass: body frames carry their inertial offsets."""
    rot = quat_to_mat(view.xquat[:, self.com_bodies])
    centres = view.xpos[:, self.com_bodies] + jnp.einsum("bnij,nj->bni", rot, self.com_ipos)
    return jnp.einsum("bni,n->bi", centres, self.com_mass)
