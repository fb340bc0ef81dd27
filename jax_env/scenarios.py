"""Initial states of fall-recovery episodes: a configurable mixture of fall scenarios.

A reset is pure sampling — no physics runs — so the auto-reset inside the jitted step can draw a
fresh state for every episode at the cost of a few hundred flops (no cached first state, unlike
brax/Playground's auto-reset). Scenarios whose pose does not already rest on the floor (3D falls,
random drops) start at their pose just above the floor, and the first `settle_s` seconds of the
episode are "settling": the env ignores actions and its PD servos hold the initial joint targets
while the robot falls into a resting configuration; control and recovery time start afterwards.

Every pose is placed so that its lowest collision point sits `clearance` above the floor
(computed with `kinematics.Kinematics`, exact for the model's primitive geoms), at a random
heading, with the DR draws for joint angles, base xy and base velocity applied.

Scenarios (docs/contracts.md): the six key states of the paper's KSI (keyframes, with Gaussian
joint noise `ksi_joint_noise`), lying `supine` / `prone`, the 3D falls of stage 2 — `lateral`
(on either side), `sitting`, `crossed_legs`, and `random_drop` (random orientation and joint
angles, dropped from up to 0.3 m) — and two upright starts from the paper authors' code:
`stand` (the `stand` keyframe with the key-state joint noise; 3 of 10 of its stage-1 episodes
start standing, so that the policy learns to hold the goal it is pushed towards) and `squat`
(its deep squat on the feet: hip −1.46, knee 1.64, ankle −0.41, Trunk pitched 0.24 forward).

`kneel_to_crouch` (ours) is a reverse-curriculum bridge for the prone get-up: a posture drawn
uniformly on the straight line (joints and Trunk pitch) from `ksi_prone_3` — on the knees and
toes, hands down — to a crouch on the balls of the feet with the knees off the floor. A zero
action (PD targets at the stand pose) stands the T1 up from the crouch end in plain MuJoCo but
not from the kneeling end; starts spread along the line let a policy learn the rise from the
crouch first and then from ever lower on the knees. `sit_to_crouch` (ours) does the same for
the supine get-up's hardest step, between `ksi_supine_2` (sitting, leaning back 0.79 rad on the
hands) and `ksi_supine_3` (the crouch on the feet, leaning forward 0.27): stage-1 policies rise
from ksi_supine_3 within 1–2M env steps and hold ksi_supine_2 sitting, and the move between
them came (for the whole supine family at once) after 8–10M env steps in 2 of 4 runs, in none
by 11M in the other two. Measured with 10% of cpu.toml's stage-1 starts (seed 1): the policy
rose from the crouch half of the line from 2.5M env steps on and never from the sitting half
(docs/experiments.md); like `kneel_to_crouch`, available but unused by the shipped curricula.

`rock_back` (ours) is a key state of the supine get-up that the policies which learned it
actually pass through: rocked back onto the shoulders, Trunk tilted head-down (pitched 2.4 rad
back from upright: gravity in the Trunk frame ≈ (−0.68, 0, 0.74)), knees tucked (2.0), hips at
their extension limit (1.55), shoulders swung back (−1.8), at rest. Traced in plain MuJoCo, such
a policy (cpu.toml with hifar.toml's stage-1 extension, seed 1) goes through this posture 0.6–
0.7 s after leaving `ksi_supine_2` or `ksi_supine_1` and swings forward onto its feet; from the
static posture it stands up within 0.6 s (6 of 6, with joint noise), a zero action does not
(Trunk ≤ 0.43 m), and a policy without the get-up falls flat instead of tucking
(docs/experiments.md). As a stage-1 start it did not teach the get-up (docs/experiments.md, "A
supine trap"); unused by the shipped curricula.

`supine_path` (ours) is reference state initialisation on that motion: a state drawn uniformly
in time from the rise of the stored supine get-up path (`jax_env.getup_paths`: open-loop PD
targets found by a cross-entropy search in C MuJoCo), with its joint angles (plus the key-state
joint noise), Trunk orientation and every velocity, placed at the height its lowest point had
there — states with the momentum of the rock that a static key state such as `rock_back` lacks.
`prone_path` does the same on the stored prone path: a roll from lying prone onto the back with
stage 2's joints (hip roll included), then the supine get-up — for stage 2, whose prone get-up
rolls onto the back. `kneel_path` starts on the stored kneel path: from `ksi_prone_3` (on the
shins, hands down) onto the back with the sagittal joints alone — the planar stage's action
space, within its side-roll and upside-down terminations — then the supine get-up: the prone key
states' way up that the planar stage can learn (a direct rise onto the feet was never found).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct

from jax_env import getup_paths, kinematics, robot
from jax_env.kinematics import axis_angle_quat, quat_mul
from jax_env.randomization import OBSTACLE_PARK, EpisodeDraw, Randomizer
from jax_env.stage_config import StageConfig

# The key states of the paper's KSI: each starts at the model keyframe of its name.
KSI_SCENARIOS: tuple[str, ...] = ("ksi_prone_1", "ksi_prone_2", "ksi_prone_3", "ksi_supine_1",
                                  "ksi_supine_2", "ksi_supine_3")
# The start-state vocabulary of curricula (`[stage.scenarios]` keys), in this order everywhere
# (an episode's scenario is an index into it).
SCENARIOS: tuple[str, ...] = KSI_SCENARIOS + ("supine", "prone", "lateral", "sitting",
                                              "crossed_legs", "random_drop", "stand", "squat",
                                              "kneel_to_crouch", "sit_to_crouch", "rock_back",
                                              "supine_path", "prone_path", "kneel_path")

# Scenarios whose initial pose is not a resting pose: their episodes start with settling.
SETTLING_SCENARIOS = frozenset({"lateral", "sitting", "crossed_legs", "random_drop"})
# Lowest point above the floor at the start: resting poses touch down within a few ms.
REST_CLEARANCE = 0.005
DROP_HEIGHT = (0.05, 0.3)
# Scenarios that start at the keyframe of their own name (plus joint noise).
KEYFRAME_SCENARIOS = KSI_SCENARIOS + ("stand",)
# The paper code's deep squat (its stage-1 initial state 2): hip, knee and ankle pitch, and the
# Trunk's forward pitch; the feet end up flat (0.24 − 1.46 + 1.64 − 0.41 ≈ 0).
SQUAT = {"Hip_Pitch": -1.46, "Knee_Pitch": 1.64, "Ankle_Pitch": -0.41}
SQUAT_PITCH = 0.24
# The crouch end of `kneel_to_crouch`: on the balls of the feet (ankle −0.2, heels up), knees
# bent fully, arms hanging forward, Trunk pitched 0.25 forward (its other joints: `stand`).
TOE_CROUCH = {"Hip_Pitch": -1.7, "Knee_Pitch": 2.3, "Ankle_Pitch": -0.2, "Shoulder_Pitch": 0.0,
              "Elbow_Yaw": -0.3}
TOE_CROUCH_PITCH = 0.25
# `rock_back`: its joints (left side; the rest at `stand`) and Trunk pitch (negative: backwards;
# −π/2 lies flat on the back), rounded from the traced get-up (docstring above).
ROCK_BACK = {"Hip_Pitch": 1.55, "Knee_Pitch": 2.0, "Ankle_Pitch": -0.9, "Shoulder_Pitch": -1.8,
             "Elbow_Yaw": 0.0}
ROCK_BACK_PITCH = -2.4


# Reference state initialisation: the scenario drawing from each stored get-up path
# (`jax_env.getup_paths`).
PATH_SCENARIOS = {"supine_path": "supine", "prone_path": "prone", "kneel_path": "kneel"}


# Reverse-curriculum bridges: a start drawn uniformly between two ends (keyframes, or the toe
# crouch above), so that a policy that rises from the end nearer standing learns from ever
# further back along the line.
BRIDGES = {"kneel_to_crouch": ("ksi_prone_3", "toe_crouch"),
           "sit_to_crouch": ("ksi_supine_2", "ksi_supine_3")}


def symmetric_posture(stand: np.ndarray, left: dict[str, float]) -> np.ndarray:
  """The 23 joints of a symmetric posture: `stand` with the `left` joint values (names without
  the side prefix) set on the left side and mirrored onto the right (roll and yaw change sign)."""
  q = np.array(stand, np.float32)
  for joint, value in left.items():
    q[robot.JOINT_NAMES.index(f"Left_{joint}")] = value
  return robot.mirror_left_to_right(q)


def toe_crouch_joints(stand: np.ndarray) -> np.ndarray:
  """The 23 joints of the crouch end of `kneel_to_crouch`."""
  return symmetric_posture(stand, TOE_CROUCH)


# With an obstacle, the legs start spread by this hip roll so the ball fits between them.
OBSTACLE_LEG_SPREAD = 0.15

_X = np.array([1.0, 0.0, 0.0], np.float32)
_Y = np.array([0.0, 1.0, 0.0], np.float32)
_Z = np.array([0.0, 0.0, 1.0], np.float32)


@struct.dataclass
class InitialState:
  qpos: jax.Array  # [B, nq]
  qvel: jax.Array  # [B, nv]
  mocap_pos: jax.Array  # [B, nmocap, 3]
  scenario: jax.Array  # [B] int32 index into SCENARIOS
  settles: jax.Array  # [B] bool: the episode starts with settle_s of settling
  geom_lowest: jax.Array  # [B, ngeom_robot] lowest z of each robot collision geom (Kinematics)
  # [B] int32 row of `ScenarioSampler.teacher` for the start state of a path scenario (the
  # plan's targets there), −1 for every other scenario.
  teacher_row: jax.Array


@struct.dataclass
class _Noise:
  """Pre-drawn randomness of one env's pose (see `_pose_fn`)."""

  u: jax.Array  # [8] U(0, 1); u[7] is the heading
  joints: jax.Array  # [23] U(0, 1)
  normal: jax.Array  # [23] N(0, 1)
  quat: jax.Array  # [4] N(0, 1)


@struct.dataclass
class _Pose:
  joints: jax.Array  # [23]
  quat: jax.Array  # [4] before the random heading
  clearance: jax.Array  # []
  qvel: jax.Array | None = None  # [nv] before the random heading; None: at rest
  teacher_row: jax.Array | None = None  # [] int32 (see InitialState); None: −1


class ScenarioSampler:
  """Samples initial states of a stage's scenario mixture (batched, pure, jit-able)."""

  def __init__(self, stage: StageConfig, mj_model: mujoco.MjModel, randomizer: Randomizer):
    self.stage = stage
    self.randomizer = randomizer
    self.kin = kinematics.Kinematics(mj_model)
    self.nq, self.nv = mj_model.nq, mj_model.nv
    self.nmocap = mj_model.nmocap
    jnt = np.array([mj_model.joint(j).id for j in robot.JOINT_NAMES])
    self.lo = np.asarray(mj_model.jnt_range[jnt, 0], np.float32)
    self.hi = np.asarray(mj_model.jnt_range[jnt, 1], np.float32)
    self.stand = np.asarray(robot.stand_pose(mj_model), np.float32)
    self.key_qpos = np.stack([robot.keyframe(mj_model, k)[0] for k in KEYFRAME_SCENARIOS]
                             ).astype(np.float32)
    self.noise = stage.scenario_params.ksi_joint_noise
    weights = np.array([stage.scenarios[s] for s in SCENARIOS], np.float32)
    self.logits = np.log(np.maximum(weights, 1e-30))
    self.settles = np.array([s in SETTLING_SCENARIOS for s in SCENARIOS])
    self.j = {name: i for i, name in enumerate(robot.JOINT_NAMES)}
    obstacle_body = mj_model.body(robot.OBSTACLE_BODY)
    self.obstacle_mocap = int(obstacle_body.mocapid[0])
    self.park = OBSTACLE_PARK
    geom = int(obstacle_body.geomadr[0])
    self.obstacle_radius = float(mj_model.geom_size[geom, 0])
    self.ankles = (int(mj_model.body("Ankle_Cross_Left").id),
                   int(mj_model.body("Ankle_Cross_Right").id))
    # One `lax.switch` branch per pose family: the KSI keyframes share one branch (they differ
    # only in a gathered keyframe row), as do supine and prone. Under vmap every branch is
    # evaluated, so fewer branches mean a smaller reset to compile (and to run).
    families = [self._family(s) for s in SCENARIOS]
    unique = list(dict.fromkeys(families))
    self._branch = np.array([unique.index(f) for f in families], np.int32)
    self._poses = [self._with_velocity(self._pose_fn(f)) for f in unique]

  # -- poses (one env, before heading, DR and placement) ----------------------------------------

  def _bridge_end(self, end: str) -> tuple[np.ndarray, float]:
    """(23 joints, Trunk pitch) of an end of a bridge scenario: a keyframe or the toe crouch."""
    if end == "toe_crouch":
      return toe_crouch_joints(self.stand), TOE_CROUCH_PITCH
    qpos = self.key_qpos[KEYFRAME_SCENARIOS.index(end)]
    return qpos[7:], 2.0 * math.atan2(float(qpos[5]), float(qpos[3]))  # a pure pitch (y) quat

  def _clip(self, q):
    return jnp.clip(q, self.lo, self.hi)

  def _set(self, q, name, value):
    return q.at[self.j[name]].set(value)

  @staticmethod
  def _family(scenario: str) -> str:
    if scenario in KEYFRAME_SCENARIOS:
      return "keyframe"
    if scenario in ("supine", "prone"):
      return "lying"
    if scenario in PATH_SCENARIOS:
      return "path"
    return scenario

  def _with_velocity(self, pose_fn):
    """`pose_fn` with the zero velocity of a start at rest filled in, so that every branch of
    the `lax.switch` returns the same structure."""
    def pose(z, scenario):
      p = pose_fn(z, scenario)
      if p.qvel is None:
        p = p.replace(qvel=jnp.zeros(self.nv))
      if p.teacher_row is None:
        p = p.replace(teacher_row=jnp.int32(-1))
      return p
    return pose

  def _pose_fn(self, family: str):
    """The pose sampler of one pose family: (`_Noise`, scenario index) -> `_Pose`.

    Every scenario reads the same pre-drawn noise (one uniform and one normal draw per env), so
    the `lax.switch` over scenarios holds arithmetic only: a dozen branches each with their own
    PRNG calls made the reset several times slower to compile.
    """
    stand = jnp.asarray(self.stand)
    rest = jnp.float32(REST_CLEARANCE)
    lo, hi = jnp.asarray(self.lo), jnp.asarray(self.hi)

    def between(u, a, b):
      return a + (b - a) * u

    if family == "keyframe":
      # Row i of the table is the keyframe of SCENARIOS[i] (zeros for other scenarios).
      table = np.zeros((len(SCENARIOS), self.key_qpos.shape[1]), np.float32)
      for i, name in enumerate(KEYFRAME_SCENARIOS):
        table[SCENARIOS.index(name)] = self.key_qpos[i]
      table = jnp.asarray(table)

      def ksi(z, scenario):
        qpos = table[scenario]
        return _Pose(self._clip(qpos[7:] + self.noise * z.normal), qpos[3:7], rest)
      return ksi

    if family == "lying":
      # Supine lies on the back (the torso's x axis points up), prone on the front.
      supine = SCENARIOS.index("supine")

      def lying(z, scenario):
        pitch = jnp.where(scenario == supine, -math.pi / 2, math.pi / 2)
        q = stand + between(z.joints, -0.1, 0.1)
        tilt = between(z.u[0], -0.1, 0.1)
        quat = quat_mul(axis_angle_quat(_X, tilt), axis_angle_quat(_Y, pitch))
        return _Pose(self._clip(q), quat, rest)
      return lying

    if family == "squat":
      def squat(z, scenario):
        q = stand
        for side in ("Left", "Right"):
          for joint, value in SQUAT.items():
            q = self._set(q, f"{side}_{joint}", value)
        q = q + self.noise * z.normal
        return _Pose(self._clip(q), axis_angle_quat(_Y, SQUAT_PITCH), rest)
      return squat

    if family == "rock_back":
      rock = jnp.asarray(symmetric_posture(self.stand, ROCK_BACK))

      def rock_back(z, scenario):
        return _Pose(self._clip(rock + self.noise * z.normal),
                     axis_angle_quat(_Y, ROCK_BACK_PITCH), rest)
      return rock_back

    if family == "path":
      # A state drawn uniformly (in time) from the rise of a stored get-up path, before its
      # standing streak starts: joints (plus the key-state noise), Trunk orientation and every
      # velocity as simulated, at the height its lowest point had there. The rises of all
      # paths are rows of one table; a scenario reads its own rows.
      stored = getup_paths.load()
      missing = sorted(set(PATH_SCENARIOS.values()) - set(stored))
      if missing:
        raise ValueError(f"{getup_paths.PATHS_FILE} holds no {', '.join(missing)} path; "
                         "regenerate it with `python -m jax_env.getup_paths`")
      rises = {name: stored[name].stand_index for name in PATH_SCENARIOS.values()}
      first = np.zeros(len(SCENARIOS), np.int32)
      count = np.ones(len(SCENARIOS), np.int32)
      offset = 0
      for scenario_name, path_name in PATH_SCENARIOS.items():
        first[SCENARIOS.index(scenario_name)] = offset
        window = self.stage.scenario_params.path_start_window_s.get(scenario_name)
        frames = rises[path_name] if window is None else int(round(window / getup_paths.CTRL_DT))
        count[SCENARIOS.index(scenario_name)] = max(1, min(rises[path_name], frames))
        offset += rises[path_name]
      qpos = jnp.asarray(np.concatenate([stored[n].qpos[:rises[n]] for n in rises]), jnp.float32)
      qvel = jnp.asarray(np.concatenate([stored[n].qvel[:rises[n]] for n in rises]), jnp.float32)
      lowest = jax.vmap(lambda q: jnp.min(self.kin.geom_lowest_of(*self.kin.bodies(q))))(qpos)
      clearance = jnp.maximum(lowest, rest)
      first, count = jnp.asarray(first), jnp.asarray(count)
      # The plan's targets in every stored state of every path (not only the rise), rows in
      # the order of PATH_SCENARIOS, for `[stage.imitation]`.
      knots = getup_paths.stored_knots()
      lengths = {n: len(stored[n].qpos) for n in rises}
      self.teacher = np.concatenate([getup_paths.teacher_offsets(n, knots, lengths[n])
                                     for n in rises]).astype(np.float32)
      self.teacher_paths = tuple(rises)
      starts = np.cumsum([0] + [lengths[n] for n in rises])
      # Per row: the index of its path in `teacher_paths`, and the end of that path's rows.
      self.teacher_row_path = np.repeat(np.arange(len(rises)), list(lengths.values()))
      self.teacher_row_end = starts[1:][self.teacher_row_path].astype(np.int32)
      t_first = np.zeros(len(SCENARIOS), np.int32)
      for k, scenario_name in enumerate(PATH_SCENARIOS):
        t_first[SCENARIOS.index(scenario_name)] = starts[k]
      t_first = jnp.asarray(t_first)

      def on_path(z, scenario):
        local = jnp.minimum((z.u[0] * count[scenario]).astype(jnp.int32), count[scenario] - 1)
        i = first[scenario] + local
        return _Pose(self._clip(qpos[i, 7:] + self.noise * z.normal), qpos[i, 3:7],
                     clearance[i], qvel[i], t_first[scenario] + local)
      return on_path

    if family in BRIDGES:
      # A posture drawn uniformly on the straight line (joints and Trunk pitch) between two ends.
      ends = [self._bridge_end(end) for end in BRIDGES[family]]
      (q0, pitch0), (q1, pitch1) = [(jnp.asarray(q), pitch) for q, pitch in ends]

      def bridge(z, scenario):
        u = z.u[0]
        q = between(u, q0, q1) + self.noise * z.normal
        return _Pose(self._clip(q), axis_angle_quat(_Y, between(u, pitch0, pitch1)), rest)
      return bridge

    if family == "lateral":
      def lateral(z, scenario):
        side = jnp.where(z.u[0] < 0.5, 1.0, -1.0)
        q = stand + between(z.joints, -0.3, 0.3)
        lean = between(z.u[1], -0.3, 0.3)
        quat = quat_mul(axis_angle_quat(_X, side * math.pi / 2), axis_angle_quat(_Y, lean))
        return _Pose(self._clip(q), quat, rest)
      return lateral

    if family == "sitting":
      def sitting(z, scenario):
        lean = between(z.u[0], 0.1, 0.5)  # the torso leans back
        hip = -math.pi / 2 + lean + between(z.u[1], -0.2, 0.2)  # thighs along the floor
        knee, ankle = between(z.u[2], 0.2, 1.4), between(z.u[3], -0.5, 0.3)
        arm = between(z.u[4], 0.2, 1.0)  # arms reach back to the floor
        q = stand
        for side in ("Left", "Right"):
          q = self._set(q, f"{side}_Hip_Pitch", hip)
          q = self._set(q, f"{side}_Knee_Pitch", knee)
          q = self._set(q, f"{side}_Ankle_Pitch", ankle)
          q = self._set(q, f"{side}_Shoulder_Pitch", arm)
        q = q + 0.05 * z.normal
        return _Pose(self._clip(q), axis_angle_quat(_Y, -lean), rest)
      return sitting

    if family == "crossed_legs":
      def crossed(z, scenario):
        pitch = jnp.where(z.u[0] < 0.5, -math.pi / 2, math.pi / 2)  # on the back or front
        # Both hips roll inward, up to their limits, and one leg lies over the other.
        left_on_top = z.u[1] < 0.5
        lift = between(z.u[2], 0.2, 0.6)
        roll = between(z.u[3], 0.5, 1.0)
        yaw = between(z.u[4], 0.0, 0.4)
        q = stand
        q = self._set(q, "Left_Hip_Roll", roll * self.lo[self.j["Left_Hip_Roll"]])
        q = self._set(q, "Right_Hip_Roll", roll * self.hi[self.j["Right_Hip_Roll"]])
        q = self._set(q, "Left_Hip_Yaw", -yaw)
        q = self._set(q, "Right_Hip_Yaw", yaw)
        q = q.at[self.j["Left_Hip_Pitch"]].add(jnp.where(left_on_top, -lift, 0.0))
        q = q.at[self.j["Right_Hip_Pitch"]].add(jnp.where(left_on_top, 0.0, -lift))
        q = q + 0.05 * z.normal
        return _Pose(self._clip(q), axis_angle_quat(_Y, pitch), rest)
      return crossed

    if family == "random_drop":
      def drop(z, scenario):
        quat = z.quat / jnp.maximum(jnp.linalg.norm(z.quat), 1e-6)  # uniform on SO(3)
        q = between(z.joints, lo, hi)
        return _Pose(q, quat, between(z.u[0], *DROP_HEIGHT))
      return drop

    raise ValueError(f"unknown pose family {family!r}")

  # -- batch sampling --------------------------------------------------------------------------

  def sample(self, keys: jax.Array, draw: EpisodeDraw, scenario: jax.Array | None = None
             ) -> InitialState:
    """Initial states from per-env keys [B]; `scenario` [B] forces scenario indices (else each
    env draws one from the stage's mixture)."""
    if scenario is None:
      scenario = jnp.full(keys.shape[:1], -1, jnp.int32)
    return jax.vmap(self._one)(keys, scenario, draw.dof_position, draw.base_xy,
                               draw.base_lin_vel, draw.obstacle)

  def _one(self, key, scenario, dof_draw, xy_draw, vel_draw, obstacle):
    k_scn, k_u, k_n = jax.random.split(key, 3)
    drawn = jax.random.categorical(k_scn, jnp.asarray(self.logits)).astype(jnp.int32)
    scenario = jnp.where(scenario >= 0, scenario, drawn)
    nj = robot.NUM_JOINTS
    u = jax.random.uniform(k_u, (8 + nj,))
    normal = jax.random.normal(k_n, (4 + nj,))
    z = _Noise(u=u[:8], joints=u[8:], normal=normal[:nj], quat=normal[nj:])
    yaw = 2 * math.pi * u[7]
    pose = jax.lax.switch(jnp.asarray(self._branch)[scenario], self._poses, z, scenario)
    q = self._clip(self.randomizer.perturb_joints(pose.joints, dof_draw))
    # With the ball between the legs, spread the legs so it fits (hip roll outward).
    spread = OBSTACLE_LEG_SPREAD * obstacle
    q = q.at[self.j["Left_Hip_Roll"]].add(spread).at[self.j["Right_Hip_Roll"]].add(-spread)
    q = self._clip(q)
    quat = quat_mul(axis_angle_quat(_Z, yaw), pose.quat)
    xy, lin_vel = self.randomizer.perturb_base(jnp.zeros(2), jnp.zeros(3), xy_draw, vel_draw)
    qpos = jnp.concatenate([xy, jnp.zeros(1), quat, q])
    bpos, bquat = self.kin.bodies(qpos)  # at base height 0
    low = self.kin.geom_lowest_of(bpos, bquat)
    lift = pose.clearance - jnp.min(low)
    qpos = qpos.at[2].set(lift)
    # The free joint's linear velocity is in the world frame (turned with the heading), its
    # angular velocity in the Trunk frame (unchanged).
    cos, sin = jnp.cos(yaw), jnp.sin(yaw)
    v = pose.qvel
    qvel = v.at[0:2].set(jnp.stack([cos * v[0] - sin * v[1], sin * v[0] + cos * v[1]]))
    qvel = qvel.at[0:3].add(lin_vel)
    mocap = jnp.broadcast_to(jnp.asarray(OBSTACLE_PARK), (self.nmocap, 3))
    if self.nmocap:
      between = 0.5 * (bpos[self.ankles[0]] + bpos[self.ankles[1]])
      ball = jnp.stack([between[0], between[1], jnp.float32(self.obstacle_radius + 1e-3)])
      mocap = mocap.at[self.obstacle_mocap].set(jnp.where(obstacle > 0, ball,
                                                          jnp.asarray(OBSTACLE_PARK)))
    settles = jnp.asarray(self.settles)[scenario]
    return InitialState(qpos=qpos, qvel=qvel, mocap_pos=mocap, scenario=scenario,
                        settles=settles, geom_lowest=low + lift, teacher_row=pose.teacher_row)
