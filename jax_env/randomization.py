"""Domain randomization, control delay, pushes, terrain and the stage's physical constraints.

Everything here is drawn fresh at every episode reset (the auto-reset inside the jitted step calls
`Randomizer.draw` with a new key), so no environment slot keeps the parameters it started with.

The twelve rows of the paper's DR table map onto the simulation as follows (`value` is the drawn
number: U(low, high) for "uniform", mean + std·N(0, 1) for "gaussian"; "additive" adds it to the
nominal quantity, "scaling" multiplies the nominal quantity by it):

| parameter            | what it changes                                                     |
|----------------------|---------------------------------------------------------------------|
| dof_position         | initial joint angles, one draw per joint                            |
| base_xy_position     | initial Trunk x, y (one draw each)                                  |
| base_linear_velocity | initial Trunk linear velocity, one draw per world axis              |
| joint_stiffness      | PD kp per joint (actuator gainprm[0] and biasprm[1])                |
| joint_damping        | PD kd per joint (actuator biasprm[2])                               |
| terrain_friction     | floor sliding friction μ (the floor has contact priority, so it    |
|                      | alone sets every floor contact's friction)                          |
| terrain_compliance   | floor contact spring: stiffness k = 1/(τ0·compliance)²             |
| terrain_restitution  | floor contact damper: b = 2ζ√k with ζ the damping ratio whose      |
|                      | linear spring-damper bounce keeps the fraction e of the speed:      |
|                      | e = exp(−ζπ/√(1−ζ²)) ⇔ ζ = −ln e / √(π² + ln² e)                    |
| torso_com            | Trunk CoM (body_ipos) offset, one draw per axis                     |
| torso_mass           | Trunk mass (and inertia, by the same factor: density is kept)       |
| other_com            | CoM offset of every other robot body, per body and axis             |
| other_mass           | mass (and inertia) of every other robot body, one draw per body     |

Terrain properties are absolute properties of the ground, so their "additive" draws are added to
a zero base (friction ~ U(0.1, 2.0) *is* the floor's μ, as in the paper's table) while "scaling"
multiplies the model's floor value (μ from scene.xml, compliance 1, restitution of the model's
damping ratio). The floor's solref is written in MuJoCo's direct form (−stiffness, −damping)
rather than (timeconst, dampratio): in the latter, a low damping ratio raises the stiffness
(k = 1/(τ²ζ²)), and restitutions above ~0.5 then make the contact spring faster than the
timestep can resolve (we saw the robot launched to kilometres). In the direct form compliance
alone sets the spring (nominal τ0 from scene.xml, natural frequency 1/(τ0·compliance); compliance
1.5 is a softer floor) and restitution alone sets the damper, so every draw keeps the contact's
frequency at or below the nominal one (τ0·compliance is kept ≥ 2·timestep, MuJoCo's own
stability bound). MuJoCo's impedance (solimp) makes the bounce approximate. e ≤ 0 gives ζ = 1
(critical damping, no bounce), which reproduces the nominal contact exactly.

Beyond the table: a control delay per episode (U(0, max_s), quantised to the physics timestep),
pushes (force and torque on the Trunk), and the terrain (slope by tilting gravity, obstacle ball).
"""

from __future__ import annotations

import copy
import math

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct

from jax_env import robot
from jax_env.kinematics import quat_to_mat
from jax_env.physics.view import ModelParams, model_params
from jax_env.stage_config import DRParam, StageConfig

# The DR vocabulary of curricula (`[stage.domain_randomization]` keys): the rows of the table
# above, in its order.
DR_PARAMS: tuple[str, ...] = ("dof_position", "base_xy_position", "base_linear_velocity",
                              "joint_stiffness", "joint_damping", "terrain_friction",
                              "terrain_compliance", "terrain_restitution", "torso_com",
                              "torso_mass", "other_com", "other_mass")
# The terrain vocabulary (`[stage.terrain]` weights); an episode's terrain is an index into it.
TERRAINS: tuple[str, ...] = ("flat", "slope", "obstacle")
OBSTACLE_PARK = np.array([0.0, 0.0, -5.0], np.float32)  # far below the floor, touches nothing


# ---------------------------------------------------------------------------------------------
# The stage's constraints, applied to the compiled model.


def constrained_model(stage: StageConfig, mj_model: mujoco.MjModel | None = None
                      ) -> mujoco.MjModel:
  """A copy of the T1 scene with the stage's timestep, joint ranges and torque limits.

  joint_range_scale stretches every joint range about its midpoint (clamped to ±π) and the
  position servos' ctrlrange with it; torque_limit_scale scales every actuator forcerange. The
  velocity limit has no MuJoCo field; `velocity_limited_target` realises it in the env.
  """
  m = robot.load_model() if mj_model is None else mj_model
  m = copy.deepcopy(m)
  m.opt.timestep = stage.sim.timestep
  c = stage.constraints
  jnt = np.array([m.joint(j).id for j in robot.JOINT_NAMES])
  lo, hi = m.jnt_range[jnt, 0].copy(), m.jnt_range[jnt, 1].copy()
  mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo) * c.joint_range_scale
  new_lo, new_hi = np.maximum(mid - half, -math.pi), np.minimum(mid + half, math.pi)
  m.jnt_range[jnt, 0], m.jnt_range[jnt, 1] = new_lo, new_hi
  m.actuator_ctrlrange[:, 0], m.actuator_ctrlrange[:, 1] = new_lo, new_hi
  m.actuator_forcerange[:] = m.actuator_forcerange * c.torque_limit_scale
  return m


def velocity_limited_target(target, q, qd, kp, kd, v_max):
  """Clamps PD targets so a motor never drives a joint further beyond its velocity limit.

  The servo torque is τ = kp (target − q) − kd q̇. Where |q̇| ≥ v_max in some direction, the
  target is limited so that τ has no component along q̇ at the moment the target is issued
  (target ≤ q + kd q̇ / kp for q̇ ≥ v_max, mirrored for q̇ ≤ −v_max): the motor may brake but no
  longer accelerate the joint, which is what a saturated motor at its no-load speed does. It acts
  at the control rate (targets are issued every ctrl_dt), so a joint can overshoot its limit
  within one control period, as a real motor can under load.
  """
  free = q + kd * qd / kp  # target that makes τ = 0 at this velocity
  upper = jnp.where(qd >= v_max, jnp.minimum(target, free), target)
  return jnp.where(qd <= -v_max, jnp.maximum(upper, free), upper)


def delayed_ctrl(history: jax.Array, delay_substeps: jax.Array, n_substeps: int) -> jax.Array:
  """Control rows [B, n_substeps, nu] that realise a control delay at physics-step resolution.

  history[:, i] is the PD target issued i control steps ago (i = 0: now). Substep k of this
  control step starts k·timestep after the newest target was issued, so it applies the newest
  target issued at least `delay` substeps before it: the one issued ⌈(delay − k)/n_substeps⌉
  control steps ago. The target in force until then is the one it replaces.
  """
  k = jnp.arange(n_substeps)
  age = jnp.ceil((delay_substeps[:, None] - k[None, :]) / n_substeps)
  age = jnp.clip(age, 0, history.shape[1] - 1).astype(jnp.int32)
  return jnp.take_along_axis(history, age[..., None], axis=1)


# ---------------------------------------------------------------------------------------------
# Per-episode draws.


@struct.dataclass
class EpisodeDraw:
  """Everything drawn at an episode reset, [B, ...]. Feeds ModelParams and privileged features."""

  params: ModelParams
  friction: jax.Array  # [B]
  compliance: jax.Array  # [B]
  restitution: jax.Array  # [B]
  mass_scale: jax.Array  # [B, 24] robot bodies in BODY_NAMES order
  com_offset: jax.Array  # [B, 24, 3]
  kp_scale: jax.Array  # [B, 23]
  kd_scale: jax.Array  # [B, 23]
  delay_substeps: jax.Array  # [B] int32
  delay_s: jax.Array  # [B]
  terrain: jax.Array  # [B] int32, index into TERRAINS
  slope: jax.Array  # [B, 2] (slope_x, slope_y), radians
  obstacle: jax.Array  # [B] 0/1
  dof_position: jax.Array  # [B, 23] raw draw (apply with `perturb_joints`)
  base_xy: jax.Array  # [B, 2] raw draw
  base_lin_vel: jax.Array  # [B, 3] raw draw


def restitution_to_dampratio(e):
  """Damping ratio of a linear spring-damper whose bounce keeps the fraction e of the speed."""
  e = jnp.clip(e, 0.0, 0.999)
  log_e = jnp.log(jnp.maximum(e, 1e-12))
  zeta = -log_e / jnp.sqrt(math.pi ** 2 + log_e ** 2)
  return jnp.where(e <= 0.0, 1.0, jnp.minimum(zeta, 1.0))


def dampratio_to_restitution(zeta):
  zeta = jnp.asarray(zeta)
  return jnp.where(zeta >= 1.0, 0.0,
                   jnp.exp(-zeta * math.pi / jnp.sqrt(jnp.maximum(1.0 - zeta ** 2, 1e-12))))


def slope_gravity(slope, g: float):
  """Gravity in the floor's frame for a ground inclined by (slope_x, slope_y).

  The ground is h(x, y) = x·tan(slope_x) + y·tan(slope_y) in the true world. The simulation keeps
  its floor at z = 0 and instead tilts gravity: in the floor frame, gravity points along
  (−tan slope_x, −tan slope_y, −1) (downhill), with magnitude g.
  """
  v = jnp.stack([-jnp.tan(slope[..., 0]), -jnp.tan(slope[..., 1]),
                 -jnp.ones_like(slope[..., 0])], axis=-1)
  return g * v / jnp.linalg.norm(v, axis=-1, keepdims=True)


def _sample(uniform, normal, p: DRParam):
  """A DR parameter's draw from pre-drawn U(0, 1) and N(0, 1) variates of its shape."""
  lo, hi = p.range
  if p.distribution == "uniform":
    return lo + (hi - lo) * uniform
  return lo + hi * normal


class _Variates:
  """Consecutive columns of one uniform and one normal block drawn up front.

  Every draw of an episode comes out of two PRNG calls instead of one call per parameter: each
  call is a separate threefry kernel in the compiled reset, which runs inside every environment
  step, so fewer calls compile markedly faster.
  """

  def __init__(self, key, batch: int, count: int):
    ku, kn = jax.random.split(key)
    self.uniform = jax.random.uniform(ku, (batch, count))
    self.normal = jax.random.normal(kn, (batch, count))
    self.batch, self.used = batch, 0

  def take(self, shape: tuple[int, ...]) -> tuple[jax.Array, jax.Array]:
    n = int(np.prod(shape, dtype=np.int64))
    cols = slice(self.used, self.used + n)
    self.used += n
    reshape = lambda x: x[:, cols].reshape((self.batch,) + shape)
    return reshape(self.uniform), reshape(self.normal)


def _apply(nominal, value, p: DRParam | None):
  if p is None:
    return jnp.broadcast_to(nominal, jnp.broadcast_shapes(jnp.shape(nominal), jnp.shape(value)))
  return nominal + value if p.operation == "additive" else nominal * value


class Randomizer:
  """Draws the per-episode physical parameters of a stage for a batch of episodes."""

  def __init__(self, stage: StageConfig, mj_model: mujoco.MjModel):
    self.stage = stage
    m = mj_model
    self.dr = stage.domain_randomization
    self.body_ids = robot.body_ids(m)
    self.trunk = int(m.body("Trunk").id)
    self.floor = int(m.geom(robot.FLOOR_GEOM).id)
    self.nominal = model_params(m)
    self.floor_friction = float(m.geom_friction[self.floor, 0])
    self.floor_timeconst = float(m.geom_solref[self.floor, 0])
    self.floor_dampratio = float(m.geom_solref[self.floor, 1])
    z = self.floor_dampratio
    self.floor_restitution = 0.0 if z >= 1.0 else math.exp(-z * math.pi / math.sqrt(1 - z * z))
    self.min_timeconst = 2.0 * float(m.opt.timestep)
    self.g = float(np.linalg.norm(m.opt.gravity))
    self.n_substeps = stage.sim.n_substeps
    self.timestep = stage.sim.timestep
    self.max_delay_substeps = int(math.floor(stage.delay.max_s / self.timestep + 1e-9))
    weights = np.array([stage.terrain.weights[t] for t in TERRAINS], np.float32)
    self.terrain_weights = weights
    self.slope_max = math.radians(stage.terrain.slope_max_deg)

  def draw(self, key: jax.Array, batch: int, terrain: jax.Array | None = None) -> EpisodeDraw:
    """Fresh parameters for `batch` episodes from one key.

    `terrain` [batch] forces terrain indices into TERRAINS (−1: draw from the stage's mixture),
    for evaluation; a forced slope still draws its angle U(0, slope_max_deg) and heading, and a
    forced obstacle is placed as in training. It reuses the same variates, so no PRNG call is
    added.
    """
    nb, nj = len(self.body_ids), robot.NUM_JOINTS
    dr = self.dr.active
    n = self.nominal
    # 3 terrain scalars, masses, centres of mass, gains, initial-state perturbations, then the
    # delay, the terrain choice, the slope angle and its heading.
    count = 3 + (1 + nb) + 3 * (1 + nb) + 2 * nj + nj + 2 + 3 + 4
    variates = _Variates(key, batch, count)

    def draw_or(name, shape, neutral):
      p = dr(name)
      u, z = variates.take(shape)
      return (_sample(u, z, p) if p is not None
              else jnp.full((batch,) + shape, neutral, jnp.float32)), p

    # Terrain contact properties.
    f_draw, f_p = draw_or("terrain_friction", (), 0.0)
    friction = (f_draw if f_p is not None and f_p.operation == "additive" else
                self.floor_friction * f_draw if f_p is not None else
                jnp.full((batch,), self.floor_friction))
    friction = jnp.maximum(friction, 0.0)
    c_draw, c_p = draw_or("terrain_compliance", (), 1.0)
    compliance = jnp.maximum(c_draw, 1e-3)  # additive onto 0 or scaling of 1: the draw itself
    e0 = self.floor_restitution
    r_draw, r_p = draw_or("terrain_restitution", (), e0)
    restitution = (r_draw * e0 if r_p is not None and r_p.operation == "scaling" else r_draw)
    restitution = jnp.clip(restitution, 0.0, 0.999)
    geom_friction = jnp.broadcast_to(n.geom_friction, (batch,) + n.geom_friction.shape)
    geom_friction = geom_friction.at[:, self.floor, 0].set(friction)
    # Direct (−stiffness, −damping) solref: compliance sets the spring, restitution the damper.
    timeconst = jnp.maximum(self.floor_timeconst * compliance, self.min_timeconst)
    dampratio = (restitution_to_dampratio(restitution) if r_p is not None
                 else jnp.full((batch,), self.floor_dampratio))
    stiffness = 1.0 / timeconst ** 2
    damping = 2.0 * dampratio * jnp.sqrt(stiffness)
    geom_solref = jnp.broadcast_to(n.geom_solref, (batch,) + n.geom_solref.shape)
    geom_solref = geom_solref.at[:, self.floor, 0].set(-stiffness)
    geom_solref = geom_solref.at[:, self.floor, 1].set(-damping)

    # Masses and centres of mass.
    is_trunk = (self.body_ids == self.trunk)[None, :]
    tm, tm_p = draw_or("torso_mass", (1,), 1.0)
    om, om_p = draw_or("other_mass", (nb,), 1.0)
    m0 = jnp.asarray(n.body_mass[self.body_ids])
    trunk_mass = _mass(m0, tm, tm_p)
    other_mass = _mass(m0, om, om_p)
    mass = jnp.where(is_trunk, trunk_mass, other_mass)
    mass_scale = mass / m0
    tc, tc_p = draw_or("torso_com", (1, 3), 0.0)
    oc, oc_p = draw_or("other_com", (nb, 3), 0.0)
    ipos0 = jnp.asarray(n.body_ipos[self.body_ids])
    ipos = jnp.where(is_trunk[..., None], _apply(ipos0, tc, tc_p), _apply(ipos0, oc, oc_p))
    com_offset = ipos - ipos0
    body_mass = jnp.broadcast_to(n.body_mass, (batch,) + n.body_mass.shape)
    body_mass = body_mass.at[:, self.body_ids].set(mass)
    body_inertia = jnp.broadcast_to(n.body_inertia, (batch,) + n.body_inertia.shape)
    body_inertia = body_inertia.at[:, self.body_ids].multiply(mass_scale[..., None])
    body_ipos = jnp.broadcast_to(n.body_ipos, (batch,) + n.body_ipos.shape)
    body_ipos = body_ipos.at[:, self.body_ids].set(ipos)

    # PD gains.
    ks, ks_p = draw_or("joint_stiffness", (nj,), 1.0)
    ds, ds_p = draw_or("joint_damping", (nj,), 1.0)
    kp = jnp.maximum(_apply(jnp.asarray(n.actuator_kp), ks, ks_p), 1e-3)
    kd = jnp.maximum(_apply(jnp.asarray(n.actuator_kd), ds, ds_p), 0.0)

    # Initial-state perturbations (applied by the scenario sampler).
    dof, _ = draw_or("dof_position", (nj,), 0.0 if self._additive("dof_position")
                     else 1.0)
    bxy, _ = draw_or("base_xy_position", (2,), 0.0)
    blv, _ = draw_or("base_linear_velocity", (3,), 0.0)

    # Control delay, uniform over the whole timesteps 0..max.
    u, _ = variates.take((4,))
    delay_substeps = jnp.minimum(jnp.floor(u[:, 0] * (self.max_delay_substeps + 1)),
                                 self.max_delay_substeps)

    # Terrain: inverse CDF of the terrain weights (a zero weight is never chosen).
    cdf = np.cumsum(self.terrain_weights)
    edges = jnp.asarray(cdf[:-1] / cdf[-1], jnp.float32)
    forced, terrain = terrain, jnp.sum(u[:, 1:2] >= edges, axis=-1)
    if forced is not None:
      terrain = jnp.where(forced >= 0, forced, terrain)
    angle = u[:, 2] * self.slope_max
    heading = u[:, 3] * (2 * math.pi)
    on_slope = terrain == TERRAINS.index("slope")
    slope = jnp.where(on_slope[:, None],
                      jnp.stack([angle * jnp.cos(heading), angle * jnp.sin(heading)], -1), 0.0)
    gravity = slope_gravity(slope, self.g)
    obstacle = (terrain == TERRAINS.index("obstacle")).astype(jnp.float32)
    assert variates.used == count, "every variate column is drawn once"

    params = ModelParams(
        geom_friction=geom_friction, geom_solref=geom_solref, body_mass=body_mass,
        body_ipos=body_ipos, body_inertia=body_inertia, actuator_kp=kp, actuator_kd=kd,
        actuator_forcerange=jnp.broadcast_to(n.actuator_forcerange, (batch,) + n.actuator_forcerange.shape),
        gravity=gravity)
    return EpisodeDraw(
        params=params, friction=friction, compliance=compliance, restitution=restitution,
        mass_scale=mass_scale, com_offset=com_offset, kp_scale=kp / n.actuator_kp,
        kd_scale=kd / jnp.maximum(n.actuator_kd, 1e-9), delay_substeps=delay_substeps.astype(jnp.int32),
        delay_s=delay_substeps.astype(jnp.float32) * self.timestep, terrain=terrain.astype(
            jnp.int32), slope=slope, obstacle=obstacle, dof_position=dof, base_xy=bxy,
        base_lin_vel=blv)

  def _additive(self, name) -> bool:
    p = self.dr.active(name)
    return p is None or p.operation == "additive"

  def perturb_joints(self, q, dof_draw):
    """Initial joint angles with the dof_position draw applied."""
    p = self.dr.active("dof_position")
    return q if p is None else _apply(q, dof_draw, p)

  def perturb_base(self, xy, lin_vel, draw_xy, draw_vel):
    pxy, pv = self.dr.active("base_xy_position"), self.dr.active("base_linear_velocity")
    xy = xy if pxy is None else _apply(xy, draw_xy, pxy)
    lin_vel = lin_vel if pv is None else _apply(lin_vel, draw_vel, pv)
    return xy, lin_vel


def _mass(m0, draw, p):
  if p is None:
    return jnp.broadcast_to(m0, draw.shape[:1] + m0.shape)
  return jnp.maximum(_apply(m0, draw, p), 0.01 * m0)


# ---------------------------------------------------------------------------------------------
# Pushes.


@struct.dataclass
class PushState:
  """The push schedule of each env, in control steps since the episode start."""

  next_step: jax.Array  # [B] int32, control step of the next push start
  end_step: jax.Array  # [B] int32, the current push is applied while step < end_step
  force: jax.Array  # [B, 3] world frame, N
  torque: jax.Array  # [B, 3] world frame, N·m
  # The evaluation protocols' scheduled push (zero / never in training): a force fixed in the
  # Trunk frame, rotated into the world frame with the Trunk's orientation at every control step
  # while scheduled_start <= step < scheduled_end.
  local_force: jax.Array  # [B, 3] Trunk frame, N
  scheduled_start: jax.Array  # [B] int32 control step
  scheduled_end: jax.Array  # [B] int32 control step (exclusive)


class Pusher:
  """Random pushes on the Trunk: every U(interval) seconds a force of magnitude U(0, force_max)
  in a random horizontal direction and a torque of magnitude U(0, torque_max) about a random
  axis, held for duration_s (quantised to control steps). Pushes start only once the episode's
  control is active (never while a dropped robot settles)."""

  def __init__(self, stage: StageConfig):
    p = stage.push
    self.enabled = p.enabled and (p.force_max > 0 or p.torque_max > 0)
    self.ctrl_dt = stage.sim.ctrl_dt
    self.interval = p.interval_s
    self.duration_steps = max(int(round(p.duration_s / self.ctrl_dt)), 0)
    self.force_max, self.torque_max = p.force_max, p.torque_max

  def _interval_steps(self, keys):
    s = jax.vmap(lambda k: jax.random.uniform(k, (), minval=self.interval[0],
                                              maxval=self.interval[1]))(keys)
    return jnp.maximum(jnp.round(s / self.ctrl_dt), 1).astype(jnp.int32)

  def reset(self, keys, control_start):
    """Schedules the first push U(interval) after the control start; keys [B]."""
    batch = control_start.shape[0]
    never = jnp.full((batch,), jnp.iinfo(jnp.int32).max, jnp.int32)
    first = control_start + self._interval_steps(keys) if self.enabled else never
    return PushState(next_step=first, end_step=jnp.zeros((batch,), jnp.int32),
                     force=jnp.zeros((batch, 3)), torque=jnp.zeros((batch, 3)),
                     local_force=jnp.zeros((batch, 3)), scheduled_start=never,
                     scheduled_end=never)

  def _draw_one(self, key):
    k1, k2, k3, k4 = jax.random.split(key, 4)
    heading = jax.random.uniform(k1, (), maxval=2 * math.pi)
    force = jax.random.uniform(k2, (), maxval=self.force_max) * jnp.stack(
        [jnp.cos(heading), jnp.sin(heading), jnp.zeros(())])
    axis = jax.random.normal(k3, (3,))
    axis = axis / jnp.maximum(jnp.linalg.norm(axis), 1e-9)
    torque = jax.random.uniform(k4, (), maxval=self.torque_max) * axis
    return force, torque

  def update(self, keys, push: PushState, step):
    """Starts a push where one is due at control step `step` [B]; keys [B]. Returns the new
    schedule and whether a push acts during this step."""
    if not self.enabled:
      return push, jnp.zeros(step.shape, bool)
    k_draw, k_next = jax.vmap(lambda k: tuple(jax.random.split(k)))(keys)
    start = step >= push.next_step
    force, torque = jax.vmap(self._draw_one)(k_draw)
    push = push.replace(
        next_step=jnp.where(start, step + self._interval_steps(k_next), push.next_step),
        end_step=jnp.where(start, step + self.duration_steps, push.end_step),
        force=jnp.where(start[:, None], force, push.force),
        torque=jnp.where(start[:, None], torque, push.torque))
    return push, step < push.end_step

  @staticmethod
  def scheduled(push: PushState, step, trunk_quat):
    """The scheduled push in the world frame [B, 3] during control step `step` [B], rotated with
    the Trunk orientation `trunk_quat` [B, 4] (w, x, y, z) at the step's start, and whether it
    acts [B]."""
    on = (step >= push.scheduled_start) & (step < push.scheduled_end)
    world = jnp.einsum("...ij,...j->...i", quat_to_mat(trunk_quat), push.local_force)
    return jnp.where(on[:, None], world, 0.0), on
