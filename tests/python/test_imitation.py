"""Learning from the stored get-up paths' plans (`[stage.imitation]`): the plan's actions
replayed in the environment reproduce the stored path, path episodes carry the plan's action
for their current state (and only they, and only where the stage can follow it), a share of
them is forced to act with it, PPO's loss adds the weighted imitation error, and the section
is validated."""

import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jax_env import config, getup_paths
from jax_env.env import FallRecoveryEnv
from jax_env.learner import networks as nets_lib
from jax_env.learner import ppo as ppo_lib
from jax_env.learner import train as train_lib
from jax_env.names import SCENARIOS

from test_getup_task import _stage
from toy_env import ToyStandUpEnv


def _path_stage(scenarios, forcing=0.0, **kw):
  d = _stage(scenarios=scenarios, **kw)
  d["sim"]["episode_s"] = 8.0
  d["scenario_params"]["ksi_joint_noise"] = 0.0
  d["imitation"] = {"weight": 1.0, "forcing": forcing}
  return d


def _first_row(env, path_name):
  k = env.sampler.teacher_paths.index(path_name)
  return sum(len(getup_paths.load()[n].qpos) for n in env.sampler.teacher_paths[:k])


@pytest.fixture(scope="module")
def kneel_env():
  return FallRecoveryEnv(_path_stage({"kneel_path": 0.5, "ksi_prone_3": 0.5}, forcing=0.5),
                         backend="native")


def test_the_plans_actions_replay_the_stored_path_in_the_environment(kneel_env):
  """From the supine path's first state, the plan's action of each step (the "default"
  mapping, scale 1) moves the environment's robot through the stored states."""
  env, path = kneel_env, getup_paths.load()["supine"]
  first = _first_row(env, "supine")
  state = env.reset_to(jax.random.split(jax.random.PRNGKey(0), 1), jnp.asarray(path.qpos[:1]),
                       jnp.asarray(path.qvel[:1]))
  step = jax.jit(env.step)
  for k in range(50):  # 1 s: onto the shoulders and swinging forward
    state = step(state, jnp.asarray(env.teacher_actions[first + k][None]))
    q = np.asarray(env.backend.view(state.physics).qpos[0])
    assert np.max(np.abs(q[7:] - path.qpos[k + 1, 7:])) < 1e-2, k
    assert abs(q[2] - path.qpos[k + 1, 2]) < 1e-2, k
  # The plan moves the joints a long way in that second: the check is not of a robot at rest.
  assert np.max(np.abs(path.qpos[50, 7:] - path.qpos[0, 7:])) > 1.0


def test_path_episodes_carry_the_plans_action_step_by_step_until_the_path_ends(kneel_env):
  env = kneel_env
  keys = jax.random.split(jax.random.PRNGKey(3), 32)
  state = jax.jit(env.reset)(keys)
  on_path = np.asarray(state.scenario) == SCENARIOS.index("kneel_path")
  assert 0 < on_path.sum() < 32
  action, mask = env.teacher_action(state)
  np.testing.assert_array_equal(np.asarray(mask), on_path.astype(np.float32))
  row0 = np.asarray(state.teacher_row)
  assert np.all(row0[~on_path] == -1)
  first, length = _first_row(env, "kneel"), len(getup_paths.load()["kneel"].qpos)
  assert np.all((row0[on_path] >= first) & (row0[on_path] < first + length))
  np.testing.assert_array_equal(np.asarray(action)[on_path],
                                env.teacher_actions[row0[on_path]])
  # Half the path episodes (forcing = 0.5) act with the plan; no other episode does.
  forced = np.asarray(state.teacher_forced)
  assert np.all(forced[~on_path] == 0) and 0 < forced[on_path].sum() < on_path.sum()
  step = jax.jit(env.step)
  zeros = jnp.zeros((32, env.action_size))
  nxt = step(state, zeros)
  alive = on_path & (np.asarray(nxt.done) == 0)
  np.testing.assert_array_equal(np.asarray(nxt.teacher_row)[alive], row0[alive] + 1)
  # Past its last stored state an episode has no plan left.
  ends = env.sampler.teacher_row_end[np.maximum(row0, 0)]
  late = state.replace(teacher_row=jnp.where(jnp.asarray(row0) >= 0, jnp.asarray(ends) - 1, -1))
  assert np.all(np.asarray(env.teacher_action(step(late, zeros))[1]) == 0)


def test_a_path_the_stage_cannot_follow_has_no_plan():
  """The prone path rolls with the hip roll joints, which the planar stage holds."""
  env = FallRecoveryEnv(_path_stage({"prone_path": 1.0}), backend="native")
  state = jax.jit(env.reset)(jax.random.split(jax.random.PRNGKey(1), 4))
  assert np.all(np.asarray(state.teacher_row) >= 0)
  assert np.all(np.asarray(env.teacher_action(state)[1]) == 0)


# The PPO settings the loss tests need.
LOSS_CFG = types.SimpleNamespace(clip_epsilon=0.2, value_loss_coef=0.5, entropy_cost=0.0)


def _toy_learner(n: int):
  """The toy task, a small freshly initialised learner on it, n random observations and the
  policy's mean on them, and a spare key: for the loss tests."""
  toy = ToyStandUpEnv()
  net_cfg = nets_lib.NetworkConfig(
      obs_size=toy.obs_size, privileged_size=toy.privileged_size, action_size=toy.action_size,
      policy_hidden=(16,), value_hidden=(16,), activation="elu", rma=False, latent_dim=2,
      encoder_hidden=(8,), history_len=4, initial_action_std=0.5)
  nets = nets_lib.Networks(net_cfg)
  params, normalizer = nets.init(jax.random.PRNGKey(0)), nets_lib.init_normalizer(net_cfg)
  k = jax.random.split(jax.random.PRNGKey(1), 3)
  obs = jax.random.normal(k[0], (n, toy.obs_size))
  priv = jax.random.normal(k[1], (n, toy.privileged_size))
  loc = nets_lib.privileged_mean(nets, params, normalizer, obs, priv)
  return toy, nets, params, normalizer, obs, priv, loc, k[2]


def test_the_imitation_term_is_the_weighted_error_on_the_path_samples():
  n = 64
  toy, nets, params, normalizer, obs, priv, loc, key = _toy_learner(n)
  teacher = jax.random.normal(key, loc.shape)
  on = (jnp.arange(n) % 4 == 0).astype(jnp.float32)
  mb = {"obs": obs, "privileged": priv, "action": loc, "loc": loc,
        "log_prob": jnp.zeros(n), "target": jnp.zeros(n), "advantage": jnp.zeros(n),
        "weight": jnp.ones(n), "teacher": teacher, "teacher_weight": on}

  def loss(weight, mb=mb):
    return ppo_lib.ppo_loss(params, normalizer, mb, nets, LOSS_CFG, 0.0, toy.mirror,
                            params["policy"]["log_std"], imitation_weight=weight)

  base, _ = loss(0.0)
  off, metrics = loss(None)  # no [stage.imitation]: no term at all
  assert float(off) == pytest.approx(float(base), rel=1e-6)
  assert float(metrics["imitation_error"]) == 0.0
  total, metrics = loss(3.0)
  error = np.sum(np.mean(np.square(np.asarray(loc - teacher)), -1) * np.asarray(on)) / 16
  assert float(metrics["imitation_error"]) == pytest.approx(error, rel=1e-5)
  assert float(total - base) == pytest.approx(3.0 * error, rel=1e-4)
  # No path samples in the minibatch: no imitation term.
  none, _ = loss(3.0, {**mb, "teacher_weight": jnp.zeros(n)})
  assert float(none) == pytest.approx(float(base), rel=1e-6)


def test_a_forced_sample_far_off_the_policy_leaves_the_loss_finite():
  """A forced step's action (the plan's, plus noise) can have a log-probability hundreds of
  nats below the policy's; with weight 0 it must drop out of the surrogate, not overflow the
  ratio into inf × 0 = NaN (a training run failed so at iteration 5)."""
  n = 8
  toy, nets, params, normalizer, obs, priv, loc, key = _toy_learner(n)
  forced = (jnp.arange(n) == 0).astype(jnp.float32)
  mb = {"obs": obs, "privileged": priv, "action": loc, "loc": loc,
        "log_prob": jnp.where(forced > 0, -300.0, 0.0), "target": jnp.zeros(n),
        "advantage": jax.random.normal(key, (n,)), "weight": 1.0 - forced,
        "teacher": loc, "teacher_weight": forced}

  def loss(params, mb):
    return ppo_lib.ppo_loss(params, normalizer, mb, nets, LOSS_CFG, 0.0, toy.mirror,
                            params["policy"]["log_std"], imitation_weight=1.0)

  (total, metrics), grads = jax.value_and_grad(loss, has_aux=True)(params, mb)
  assert np.isfinite(float(total)) and np.isfinite(float(metrics["policy"]))
  assert all(np.all(np.isfinite(np.asarray(g))) for g in jax.tree_util.tree_leaves(grads))
  # The same as with an ordinary log-probability on the weight-0 sample.
  same, _ = loss(params, {**mb, "log_prob": jnp.zeros(n)})
  assert float(total) == pytest.approx(float(same), rel=1e-6)


def test_the_imitation_section_is_parsed_and_validated():
  fade = config.Schedule(by="env_steps", points=((0.0, 1.0), (1000.0, 0.0)))
  d = _path_stage({"kneel_path": 1.0})
  d["imitation"] = {"weight": 2.0, "forcing": 0.25,
                    "schedule": {"by": "env_steps", "points": [[0, 1], [1000, 0]]}}
  stage = config.parse_stage(d)
  assert stage.imitation == config.ImitationConfig(weight=2.0, schedule=fade, forcing=0.25)
  assert train_lib.LearnerConfig.from_stage(stage).imitation == stage.imitation
  imitation = train_lib.ScheduleScale(fade, ratchet=min)
  assert imitation.after(1.0, 500, None) == pytest.approx(0.5)
  # Off by default: the learner gets no imitation.
  assert train_lib.LearnerConfig.from_stage(config.parse_stage(_stage())).imitation is None
  d["imitation"] = {"weight": -1.0, "forcing": 1.5, "weigth": 1.0}
  assert sorted(tuple(e["path"]) for e in config.check_stage(d)) == [
      ("imitation", "forcing"), ("imitation", "weight"), ("imitation", "weigth")]
