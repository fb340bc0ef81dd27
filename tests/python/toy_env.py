"""A small, fast task with the batched Environment API of docs/contracts.md, for learner tests.

"Stand up a pendulum with two opposing motors": a pole hinged at its base starts fallen
(hanging well past horizontal, to a random side) and must be raised to upright and held there.
Two motors act on the hinge in opposite directions (torque ∝ left − right), so the task has a
left/right mirror symmetry that permutes the actions (left ↔ right) and flips the sign of the
angle and the angular velocity, exactly the kind of maps the humanoid has. Each episode draws
a mass scale, a damping and a constant disturbance torque: these are the privileged features
the RMA encoder sees and the adaptation module has to infer from the observation history.

Same contract as FallRecoveryEnv: batched natively, pure jit-able reset/step, auto-reset with a
fresh draw on `done`, fixed-length episodes with `truncation`, a short settling phase where
`control_active` is 0 and actions are ignored, per-term reward metrics, `standing`, and
episode metrics (`success`, `recovery_time`, `return`) valid where `done`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jax_env.env import MirrorMaps

GRAVITY = 10.0  # g / l, 1/s²
MOTOR_GAIN = 9.0  # angular acceleration per unit action at mass scale 1
SUBSTEPS = 4
UPRIGHT_TOLERANCE = 0.3  # rad
SPEED_TOLERANCE = 1.5  # rad/s


@struct.dataclass
class ToyState:
  obs: jax.Array
  privileged: jax.Array
  reward: jax.Array
  done: jax.Array
  truncation: jax.Array
  control_active: jax.Array
  metrics: dict
  episode_metrics: dict
  theta: jax.Array
  omega: jax.Array
  mass: jax.Array
  damping: jax.Array
  disturbance: jax.Array
  last_action: jax.Array
  step_count: jax.Array
  hold: jax.Array
  success: jax.Array
  recovery_time: jax.Array
  episode_return: jax.Array
  rng: jax.Array


class ToyStandUpEnv:
  """Twin-motor pendulum stand-up; see the module docstring."""

  obs_names = ("angle/sin", "angle/cos", "ang_vel", "prev_action/left", "prev_action/right")
  privileged_names = ("mass_scale", "damping", "disturbance")
  action_names = ("left", "right")

  def __init__(self, episode_steps: int = 50, ctrl_dt: float = 0.05, settle_steps: int = 2,
               hold_steps: int = 5, clip: float = 1.0):
    self.obs_size = len(self.obs_names)
    self.privileged_size = len(self.privileged_names)
    self.action_size = len(self.action_names)
    self.ctrl_dt = ctrl_dt
    self.episode_steps = episode_steps
    self.settle_steps = settle_steps
    self.hold_steps = hold_steps
    self.clip = clip
    self.mirror = MirrorMaps(
        obs_perm=np.array([0, 1, 2, 4, 3], np.int32),
        obs_sign=np.array([-1, 1, -1, 1, 1], np.float32),
        privileged_perm=np.array([0, 1, 2], np.int32),
        privileged_sign=np.array([1, 1, -1], np.float32),
        action_perm=np.array([1, 0], np.int32),
        action_sign=np.array([1, 1], np.float32))

  # -- reset -----------------------------------------------------------------------------------

  def _draw(self, keys):
    def one(key):
      k_side, k_angle, k_mass, k_damp, k_dist, k_next = jax.random.split(key, 6)
      side = jnp.where(jax.random.bernoulli(k_side), 1.0, -1.0)
      theta = side * jax.random.uniform(k_angle, minval=2.2, maxval=jnp.pi)
      mass = jax.random.uniform(k_mass, minval=0.7, maxval=1.3)
      damping = jax.random.uniform(k_damp, minval=0.1, maxval=1.0)
      dist = jax.random.uniform(k_dist, minval=-2.0, maxval=2.0)
      return theta, mass, damping, dist, k_next
    return jax.vmap(one)(keys)

  def reset(self, keys: jax.Array) -> ToyState:
    theta, mass, damping, dist, rng = self._draw(keys)
    b = keys.shape[0]
    z = jnp.zeros((b,))
    zeros_a = jnp.zeros((b, self.action_size))
    omega = z
    return ToyState(
        obs=self._obs(theta, omega, zeros_a), privileged=self._priv(mass, damping, dist),
        reward=z, done=z, truncation=z,
        control_active=(self.settle_steps == 0) * jnp.ones((b,)),
        metrics={"reward/upright": z, "reward/effort": z, "standing": z},
        episode_metrics={"success": z, "recovery_time": jnp.full((b,), jnp.nan), "return": z},
        theta=theta, omega=omega, mass=mass, damping=damping, disturbance=dist,
        last_action=zeros_a, step_count=jnp.zeros((b,), jnp.int32),
        hold=jnp.zeros((b,), jnp.int32), success=jnp.zeros((b,), bool),
        recovery_time=jnp.full((b,), jnp.nan), episode_return=z, rng=rng)

  def _obs(self, theta, omega, last_action):
    return jnp.concatenate([jnp.sin(theta)[:, None], jnp.cos(theta)[:, None], omega[:, None],
                            last_action], axis=-1)

  def _priv(self, mass, damping, dist):
    return jnp.stack([mass, damping, dist], axis=-1)

  # -- step ------------------------------------------------------------------------------------

  def step(self, state: ToyState, action: jax.Array) -> ToyState:
    a = jnp.clip(action, -self.clip, self.clip)
    active = state.step_count >= self.settle_steps
    a = jnp.where(active[:, None], a, 0.0)
    torque = MOTOR_GAIN * (a[:, 0] - a[:, 1]) / state.mass + state.disturbance
    theta, omega = state.theta, state.omega
    h = self.ctrl_dt / SUBSTEPS
    for _ in range(SUBSTEPS):  # semi-implicit Euler; theta = 0 is upright (unstable)
      omega = omega + h * (GRAVITY * jnp.sin(theta) - state.damping * omega + torque)
      theta = theta + h * omega
    theta = jnp.arctan2(jnp.sin(theta), jnp.cos(theta))

    upright = jnp.cos(theta)
    effort = -0.02 * jnp.sum(jnp.square(a), axis=-1)
    gate = active.astype(jnp.float32)
    reward = (upright + effort) * gate
    standing = (jnp.abs(theta) < UPRIGHT_TOLERANCE) & (jnp.abs(omega) < SPEED_TOLERANCE)
    hold = jnp.where(standing & active, state.hold + 1, 0)
    step_count = state.step_count + 1
    newly = (hold >= self.hold_steps) & ~state.success
    success = state.success | newly
    recovery_time = jnp.where(newly, step_count * self.ctrl_dt, state.recovery_time)
    episode_return = state.episode_return + reward

    finite = jnp.isfinite(theta) & jnp.isfinite(omega)
    time_up = step_count >= self.episode_steps
    done = time_up | ~finite
    nxt = state.replace(
        obs=self._obs(theta, omega, a), reward=jnp.where(finite, reward, 0.0),
        done=done.astype(jnp.float32), truncation=(time_up & finite).astype(jnp.float32),
        control_active=(step_count >= self.settle_steps).astype(jnp.float32),
        metrics={"reward/upright": upright * gate, "reward/effort": effort * gate,
                 "standing": (standing & active).astype(jnp.float32)},
        episode_metrics={"success": success.astype(jnp.float32),
                         "recovery_time": jnp.where(success, recovery_time, jnp.nan),
                         "return": episode_return},
        theta=theta, omega=omega, last_action=a, step_count=step_count, hold=hold,
        success=success, recovery_time=recovery_time, episode_return=episode_return)

    fresh = self.reset(state.rng)
    keep = dict(reward=nxt.reward, done=nxt.done, truncation=nxt.truncation,
                metrics=nxt.metrics, episode_metrics=nxt.episode_metrics)
    merged = jax.tree_util.tree_map(
        lambda new, old: jnp.where(done.reshape((-1,) + (1,) * (old.ndim - 1)), new, old),
        fresh, nxt)
    # A fresh per-env key every step, whether or not the episode ended.
    rng = jax.vmap(lambda k: jax.random.split(k)[0])(fresh.rng)
    return merged.replace(rng=rng, **keep)


def learner_config(env_steps: int = 160 * 1024, mirror_weight: float = 0.1, ppo=None, rma=None,
                   stage_name: str = "toy"):
  """Learner settings under which PPO solves the toy task in ~130k env steps (a few seconds
  of CPU once compiled). Tests share them so the persistent compilation cache is reused."""
  from jax_env import config as config_lib
  from jax_env.learner import train

  p = dict(num_envs=64, unroll_length=32, num_minibatches=4, update_epochs=4,
           learning_rate=1e-3, lr_schedule="adaptive_kl", desired_kl=0.01, entropy_cost=0.0,
           clip_epsilon=0.2, value_loss_coef=0.5, discount=0.97, gae_lambda=0.95,
           max_grad_norm=1.0, reward_scaling=1.0, normalize_observations=True,
           policy_hidden=(32, 32), value_hidden=(32, 32), activation="elu",
           initial_action_std=0.5, checkpoint_every=1000)
  p.update(ppo or {})
  r = dict(enabled=True, latent_dim=2, encoder_hidden=(16,), history_len=8,
           adaptation_env_steps=20 * 2048, adaptation_learning_rate=3e-3)
  r.update(rma or {})
  return train.LearnerConfig(stage_name=stage_name, ppo=config_lib.PPOConfig(**p),
                             rma=config_lib.RMAConfig(**r), mirror_weight=mirror_weight,
                             env_steps=env_steps,
                             action={"mapping": "current", "scale": 1.0, "clip": 1.0})
