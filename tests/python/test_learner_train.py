"""train_stage on the toy task: it learns, RMA adaptation learns, the same seed gives the same
curve, resume is bit-exact, and "finish" / "interrupt" / init_checkpoint behave as specified.

Every run uses toy_env.learner_config() (only budgets differ, which never enter a jitted
function), so the two jitted iteration functions are compiled once and then come from the
persistent compilation cache.
"""

import types

import jax.numpy as jnp
import numpy as np
import pytest
import safetensors.numpy

from jax_env.learner import checkpoint as ckpt_lib
from jax_env.learner import train
from jax_env.stage_config import EPISODE_ENDS
from toy_env import ToyStandUpEnv, learner_config

ITER_STEPS = 64 * 32  # num_envs × unroll_length of learner_config()


class Recorder:
  """Progress callback that records reports and answers from a script {iteration: answer}."""

  def __init__(self, answers=None):
    self.reports = []
    self.answers = answers or {}

  def __call__(self, progress):
    self.reports.append(progress)
    return self.answers.get(progress["iteration"], "continue")

  def phase(self, name):
    return [r for r in self.reports if r["phase"] == name]


@pytest.fixture(scope="module")
def learned(tmp_path_factory):
  """One full training run: 80 PPO iterations (163,840 env steps) + 20 adaptation ones."""
  rec = Recorder()
  stage_dir = tmp_path_factory.mktemp("learned")
  log = stage_dir / "run.log"
  result = train.train_stage(ToyStandUpEnv(), learner_config(), stage_dir=stage_dir, seed=0,
                             callback=rec, log_file=log)
  return result, rec, stage_dir


def _params(checkpoint_dir):
  return safetensors.numpy.load_file(f"{checkpoint_dir}/params.safetensors")


def _run(tmp_path, name, answers=None, **kw):
  rec = Recorder(answers)
  cfg = learner_config(env_steps=kw.pop("env_steps", 4 * ITER_STEPS),
                       rma={"adaptation_env_steps": kw.pop("adaptation", 2 * ITER_STEPS)})
  result = train.train_stage(ToyStandUpEnv(), cfg, stage_dir=tmp_path / name, seed=0,
                             callback=rec, **kw)
  return result, rec


def test_learns_the_toy_task(learned):
  result, rec, _ = learned
  assert result["status"] == "completed"
  assert result["env_steps"] == 100 * ITER_STEPS
  ppo = rec.phase("ppo")
  assert len(ppo) == 80
  first = [r["episode_return"] for r in ppo[:6] if r["episode_return"] is not None]
  last = [r for r in ppo[-10:] if r["stand_rate"] is not None]
  assert np.mean(first) < -20, first  # fallen pendulum, random actions
  assert np.mean([r["stand_rate"] for r in last]) >= 0.8
  assert np.mean([r["episode_return"] for r in last]) > 20
  assert all(r["recovery_time"] > 0 for r in last)


def test_progress_reports_follow_the_contract(learned):
  _, rec, stage_dir = learned
  r = rec.reports[0]
  assert set(r) == {"iteration", "env_steps", "steps_per_s", "total_env_steps", "phase",
                    "losses", "rewards", "stand_rate", "recovery_time", "episode_return",
                    "penalty_scale", "assist_force"}
  assert all(x["penalty_scale"] == 1.0 for x in rec.reports)  # no schedule: full penalties
  assert all(x["assist_force"] == 0.0 for x in rec.reports)  # no assist
  assert [x["iteration"] for x in rec.reports] == list(range(1, 101))
  assert [x["env_steps"] for x in rec.reports] == [ITER_STEPS * i for i in range(1, 101)]
  assert r["total_env_steps"] == 160 * 1024
  assert rec.reports[-1]["total_env_steps"] == 100 * ITER_STEPS
  assert set(r["rewards"]) == {"upright", "effort"}
  assert {"policy", "value", "entropy", "mirror", "symmetry_error", "kl", "learning_rate",
          "total"} <= set(r["losses"])
  assert set(rec.phase("adaptation")[0]["losses"]) == {"adaptation", "adaptation_before"}
  latest = ckpt_lib.read_latest(stage_dir / "checkpoints")
  assert latest.name == f"{100 * ITER_STEPS:012d}"
  meta = ckpt_lib.read_meta(latest)
  assert meta["learner"]["phase"] == "done" and meta["iteration"] == 100
  assert (stage_dir / "run.log").read_text().count("checkpoint") >= 2


def _held_out_latent_error(checkpoint_dirs):
  """Latent regression error of each checkpoint's adaptation module on ONE fixed batch:
  400 steps of 64 toy envs acting with the last checkpoint's deployable actor."""
  import jax
  import jax.numpy as jnp
  from jax_env.learner import networks as nets_lib
  from jax_env.learner import rma as rma_lib

  env = ToyStandUpEnv()
  loaded = []
  for d in checkpoint_dirs:
    ck = ckpt_lib.load(d)
    nets = nets_lib.Networks(ck.network_config())
    loaded.append((nets,) + ckpt_lib.restore_params(nets, ck.tensors))
  nets, params, normalizer = loaded[-1]

  def step(carry, _):
    es, hist = carry
    window = nets_lib.history_window(hist, es.obs)
    nxt = env.step(es, nets_lib.deployable_mean(nets, params, normalizer, es.obs, hist))
    return (nxt, nets_lib.push_history(hist, es.obs, nxt.done)), (window, es.privileged)

  state = env.reset(jax.random.split(jax.random.PRNGKey(123), 64))
  hist = jnp.zeros((64, nets.config.history_len, env.obs_size))
  _, (windows, priv) = jax.jit(lambda c: jax.lax.scan(step, c, None, length=400))((state, hist))
  windows = windows.reshape((-1,) + windows.shape[2:])
  priv = priv.reshape((-1, priv.shape[-1]))
  errors = []
  for nets_i, params_i, norm_i in loaded:
    target = rma_lib.latent_targets(nets_i, params_i, norm_i, priv)
    errors.append(float(rma_lib.adaptation_loss(
        {"adaptation": params_i["adaptation"]}, norm_i, windows, target, nets_i)))
  return errors


def test_rma_adaptation_reduces_the_latent_error(learned):
  result, rec, stage_dir = learned
  adapt = rec.phase("adaptation")
  assert len(adapt) == 20 and all(np.isfinite(r["losses"]["adaptation"]) for r in adapt)
  # The checkpoint at the phase boundary holds the adaptation module before phase 2.
  boundary = stage_dir / "checkpoints" / f"{80 * ITER_STEPS:012d}"
  assert ckpt_lib.read_meta(boundary)["learner"]["phase"] == "adaptation"
  before, after = _held_out_latent_error([boundary, result["checkpoint"]])
  assert after < 0.6 * before, (before, after)  # measured: 2.10 -> 1.02
  # Acting with its own estimate, the deployable actor still stands the pendulum up.
  rates = [r["stand_rate"] for r in adapt[-10:] if r["stand_rate"] is not None]
  assert np.mean(rates) >= 0.8


def test_latent_regularization_trains_the_module_during_ppo(tmp_path, learned):
  # [stage.rma] latent_regularization: the module learns beside PPO, so that at the end of
  # PPO (before any adaptation phase) it already estimates the latent, and the encoder's latent
  # is pulled toward what it estimates. Without the option the module at that point is the
  # untrained one (the `learned` run's boundary checkpoint).
  _, _, plain_dir = learned
  rec = Recorder()
  cfg = learner_config(rma={"adaptation_env_steps": 2 * ITER_STEPS,
                            "latent_regularization": 1.0})
  result = train.train_stage(ToyStandUpEnv(), cfg, stage_dir=tmp_path, seed=0, callback=rec)
  ppo = rec.phase("ppo")
  assert {"latent_error", "adaptation", "adaptation_before"} <= set(ppo[0]["losses"])
  assert ppo[-1]["losses"]["latent_error"] < ppo[0]["losses"]["latent_error"]
  boundary = f"checkpoints/{80 * ITER_STEPS:012d}"
  roa, plain = _held_out_latent_error([tmp_path / boundary, plain_dir / boundary])
  assert roa < 0.25 * plain, (roa, plain)
  # It still learns the task, more slowly than without (measured: a stand rate of 0.46 over
  # the last 10 PPO iterations against 0.8 or more), and the deployable actor (the adaptation
  # phase's rollouts act with it) stands the pendulum up about as often as the policy.
  first = [r["stand_rate"] for r in ppo[:10] if r["stand_rate"] is not None]
  last = [r["stand_rate"] for r in ppo[-10:] if r["stand_rate"] is not None]
  assert np.mean(first) < 0.05 and np.mean(last) >= 0.3, (first, last)
  rates = [r["stand_rate"] for r in rec.phase("adaptation") if r["stand_rate"] is not None]
  assert rates and np.mean(rates) >= 0.3, rates
  assert result["status"] == "completed"


def test_latent_regularization_is_validated():
  from jax_env import config
  from jax_env.defaults import default_stage_dict
  d = default_stage_dict("planar")
  assert config.parse_stage(d).rma.latent_regularization == 0.0  # absent: off
  d["rma"]["latent_regularization"] = 0.5
  assert config.check_stage(d) == []
  assert config.parse_stage(d).rma.latent_regularization == 0.5
  d["rma"]["latent_regularization"] = -1.0
  assert [e["path"] for e in config.check_stage(d)] == [["rma", "latent_regularization"]]
  d["rma"].update(latent_regularization=0.5, enabled=False)
  assert config.check_stage(d) == [{"path": ["rma", "latent_regularization"], "message":
                                    "latent_regularization 0.5 needs enabled = true: without "
                                    "RMA there is no latent to regularize", "at": "key"}]


def test_same_seed_same_curve(tmp_path, learned):
  _, full, _ = learned
  _, rec = _run(tmp_path, "again", env_steps=6 * ITER_STEPS, adaptation=0)
  assert [r["losses"] for r in rec.reports] == [r["losses"] for r in full.reports[:6]]
  assert ([r["episode_return"] for r in rec.reports]
          == [r["episode_return"] for r in full.reports[:6]])


@pytest.mark.parametrize("stop_at", [2, 5])  # in the PPO phase / in the adaptation phase
def test_resume_is_bit_exact(tmp_path, stop_at):
  straight, rec_straight = _run(tmp_path, "straight")
  assert straight["status"] == "completed"
  stopped, rec_stopped = _run(tmp_path, "resumed", answers={stop_at: "interrupt"})
  assert stopped["status"] == "interrupted"
  assert stopped["env_steps"] == stop_at * ITER_STEPS
  assert ckpt_lib.read_latest(tmp_path / "resumed" / "checkpoints").name == \
      f"{stop_at * ITER_STEPS:012d}"
  resumed, rec_resumed = _run(tmp_path, "resumed", resume_checkpoint=stopped["checkpoint"])
  assert resumed["status"] == "completed"
  assert resumed["env_steps"] == straight["env_steps"] == 6 * ITER_STEPS
  a, b = _params(straight["checkpoint"]), _params(resumed["checkpoint"])
  assert a.keys() == b.keys()
  for k in a:
    np.testing.assert_array_equal(a[k], b[k], err_msg=k)  # bitwise on CPU
  # The resumed run reports exactly what the uninterrupted one did from there on.
  assert [r["losses"] for r in rec_stopped.reports + rec_resumed.reports] == \
      [r["losses"] for r in rec_straight.reports]
  ra = safetensors.numpy.load_file(f"{straight['checkpoint']}/rollout_state.safetensors")
  rb = safetensors.numpy.load_file(f"{resumed['checkpoint']}/rollout_state.safetensors")
  for k in ra:
    np.testing.assert_array_equal(ra[k], rb[k], err_msg=k)


def test_finish_ends_ppo_but_still_adapts(tmp_path):
  result, rec = _run(tmp_path, "finish", answers={2: "finish", 3: "finish"})
  assert result["status"] == "finished_early"
  assert [r["phase"] for r in rec.reports] == ["ppo", "ppo", "adaptation", "adaptation"]
  assert result["env_steps"] == 4 * ITER_STEPS
  meta = ckpt_lib.read_meta(result["checkpoint"])
  assert meta["learner"]["phase"] == "done" and meta["learner"]["finished_early"]
  # Resuming a finished stage returns at once with the same answer.
  again = train.train_stage(ToyStandUpEnv(), learner_config(env_steps=4 * ITER_STEPS),
                            stage_dir=tmp_path / "finish", seed=0,
                            resume_checkpoint=result["checkpoint"],
                            callback=lambda p: pytest.fail("no iteration expected"))
  assert again == result


def test_init_checkpoint_starts_from_trained_weights(tmp_path, learned):
  result, _, _ = learned
  init, rec = _run(tmp_path, "next", env_steps=ITER_STEPS, adaptation=0,
                   init_checkpoint=result["checkpoint"])
  assert rec.reports[0]["stand_rate"] is None or rec.reports[0]["stand_rate"] >= 0.8
  assert rec.reports[0]["iteration"] == 1 and rec.reports[0]["env_steps"] == ITER_STEPS
  ck = ckpt_lib.load(init["checkpoint"])
  assert int(ck.tensors["opt/count"]) == 4 * 4  # fresh counter: one iteration of steps
  assert int(ck.tensors["opt/adaptation/count"]) == 0
  # A checkpoint of another layout is refused with the differences named.
  with pytest.raises(ckpt_lib.CheckpointError, match="network.policy_hidden"):
    train.train_stage(ToyStandUpEnv(), learner_config(ppo={"policy_hidden": (64, 64)}),
                      stage_dir=tmp_path / "bad", seed=0, init_checkpoint=result["checkpoint"])


def test_bad_settings_are_refused(tmp_path):
  with pytest.raises(ValueError, match=r"num_envs 30 must be a positive multiple of "
                     r"num_minibatches \(4\)"):
    train.train_stage(ToyStandUpEnv(), learner_config(), stage_dir=tmp_path, seed=0,
                      num_envs=30)
  with pytest.raises(ValueError, match="progress callback answered 'stop'"):
    _run(tmp_path, "answer", answers={1: "stop"})


def test_u64_seeds_keep_every_bit():
  import jax
  assert np.array_equal(train.seed_key(7), jax.random.PRNGKey(7))
  assert not np.array_equal(train.seed_key(2**32 + 7), train.seed_key(7))
  assert train.seed_key(2**64 - 1).tolist() == [2**32 - 1, 2**32 - 1]
  with pytest.raises(ValueError, match="not a u64"):
    train.seed_key(-1)


def _script_monitor(monkeypatch, rates):
  """The toy task has no MuJoCo scene for the real monitor (tested on a held `stand` in
  test_getup_task.py): its mean stand rates are scripted, one per monitor point. Returns the
  actors the monitor was asked to judge, in order."""
  actors = []

  def scripted_monitor(*_args):  # one per stage, as make_monitor
    readings = iter(rates)

    def monitor(params, normalizer, actor):
      actors.append(actor)
      rate = next(readings)
      return {"stand_rate": {"stand": rate}, "recovery_time": {"stand": None},
              "max_height": {"stand": 0.0}, "mean_stand_rate": rate, "actor": actor}
    return monitor

  monkeypatch.setattr(train.monitor_lib, "make_monitor", scripted_monitor)
  return actors


def _keep_best_config(ppo_iterations: int, adaptation_iterations: int, **rma):
  import dataclasses

  from jax_env import config as config_lib

  cfg = learner_config(env_steps=ppo_iterations * ITER_STEPS,
                       rma={"adaptation_env_steps": adaptation_iterations * ITER_STEPS, **rma})
  return dataclasses.replace(cfg, monitor=config_lib.MonitorConfig(
      every=1, episodes=1, scenarios=("stand",), keep_best=True))


def test_keep_best_ends_the_stage_from_the_best_monitor_point(tmp_path, monkeypatch):
  # [stage.monitor] keep_best: the adaptation phase and the final checkpoint build on the PPO
  # parameters of the monitor point with the best mean stand rate, the latest of equals
  # (scripted readings: 0.2, 0.6, 0.6, 0.1; then 0.3, 0.3 for the adaptation phase's two
  # iterations, where the deployable actor is judged).
  import dataclasses

  actors = _script_monitor(monkeypatch, [0.2, 0.6, 0.6, 0.1, 0.3, 0.3])

  def run(name, keep_best):
    cfg = _keep_best_config(4, 2)
    cfg = dataclasses.replace(cfg, monitor=dataclasses.replace(cfg.monitor, keep_best=keep_best))
    return train.train_stage(ToyStandUpEnv(), cfg, stage_dir=tmp_path / name, seed=0,
                             log_file=tmp_path / f"{name}.log")

  result = run("best", keep_best=True)
  assert actors == ["privileged"] * 4 + ["deployable"] * 2
  best_dir = tmp_path / "best" / "checkpoints" / f"{3 * ITER_STEPS:012d}"
  assert best_dir.is_dir()  # checkpointed when it became the best (checkpoint_every is 1000)
  final, best = _params(result["checkpoint"]), _params(best_dir)
  learned_by_ppo = [k for k in final if k.startswith(("policy/", "value/"))]
  assert learned_by_ppo and all(np.array_equal(final[k], best[k]) for k in learned_by_ppo)
  # The adaptation phase's own keep_best: of its equal readings, the last module.
  meta = ckpt_lib.read_meta(result["checkpoint"])["learner"]
  assert (meta["best_monitor_rate"], meta["best_monitor_env_steps"]) == (0.3, 6 * ITER_STEPS)
  log = (tmp_path / "best.log").read_text()
  assert "keeping the PPO parameters of" in log
  assert "the last adaptation iteration is the best monitor point" in log

  actors.clear()
  last = _params(run("last", keep_best=False)["checkpoint"])
  assert not all(np.array_equal(last[k], final[k]) for k in learned_by_ppo)


@pytest.mark.parametrize("boundary, kept", [(0.9, "boundary"), (0.5, "adapted")])
def test_keep_best_keeps_the_online_module_unless_the_adaptation_phase_betters_it(
    tmp_path, monkeypatch, boundary, kept):
  # With latent_regularization (ROA) PPO trains the adaptation module online, so the module the
  # adaptation phase starts from competes with the phase's own: the deployable actor is judged
  # at the phase boundary (`boundary`) and after each adaptation iteration (0.4, 0.7).
  actors = _script_monitor(monkeypatch, [0.5, 0.5, boundary, 0.4, 0.7])
  cfg = _keep_best_config(2, 2, latent_regularization=1.0)
  result = train.train_stage(ToyStandUpEnv(), cfg, stage_dir=tmp_path / "run", seed=0,
                             log_file=tmp_path / "run.log")
  assert actors == ["privileged"] * 2 + ["deployable"] * 3
  boundary_dir = tmp_path / "run" / "checkpoints" / f"{2 * ITER_STEPS:012d}"
  final, at_boundary = _params(result["checkpoint"]), _params(boundary_dir)
  module = [k for k in final if k.startswith("adaptation/")]
  same = all(np.array_equal(final[k], at_boundary[k]) for k in module)
  log = (tmp_path / "run.log").read_text()
  assert "the deployable actor with the module PPO trained online" in log
  if kept == "boundary":
    assert module and same
    assert f"keeping the adaptation module of {boundary_dir}" in log
  else:
    assert module and not same
    assert "the last adaptation iteration is the best monitor point" in log


def test_keep_best_forgets_the_points_before_the_std_bound_tightens(tmp_path, monkeypatch):
  # ppo.action_std_schedule halves the bound after the third iteration: the monitor points of
  # iterations 1–3 (0.6, 0.6, 0.2) were trained at the looser bound and no longer compete, so
  # the stage ends from the last iteration (0.1) although it reads worst.
  import dataclasses

  from jax_env import config as config_lib

  _script_monitor(monkeypatch, [0.6, 0.6, 0.2, 0.1])
  schedule = config_lib.Schedule("env_steps", ((0.0, 1.0), (2.0 * ITER_STEPS, 1.0),
                                               (2.0 * ITER_STEPS, 0.5)))
  cfg = learner_config(env_steps=4 * ITER_STEPS, rma={"adaptation_env_steps": 0},
                       ppo={"max_action_std": 1.0, "action_std_schedule": schedule})
  cfg = dataclasses.replace(cfg, monitor=config_lib.MonitorConfig(
      every=1, episodes=1, scenarios=("stand",), keep_best=True))
  bounds = []

  def callback(progress):
    bounds.append(progress["max_action_std"])
    return "continue"

  result = train.train_stage(ToyStandUpEnv(), cfg, stage_dir=tmp_path / "run", seed=0,
                             log_file=tmp_path / "run.log", callback=callback)
  assert bounds == [1.0, 1.0, 1.0, 0.5]
  meta = ckpt_lib.read_meta(result["checkpoint"])["learner"]
  assert (meta["best_monitor_rate"], meta["best_monitor_env_steps"]) == (0.1, 4 * ITER_STEPS)
  log = (tmp_path / "run.log").read_text()
  assert "keep_best forgets the monitor points before" in log
  assert "the last PPO iteration is the best monitor point" in log


def test_a_new_best_monitor_point_is_at_least_as_good_as_the_best_so_far():
  assert train.is_new_best(None, 0.0)
  assert train.is_new_best(0.5, 0.5)  # the latest of equals: the more trained policy
  assert not train.is_new_best(0.5, 0.25)


def test_episode_ends_are_shares_of_the_ended_episodes():
  # Three episodes end (one at its time limit, two by the face-down rule); the fourth runs on.
  zeros = jnp.zeros(4)
  end = jnp.asarray([EPISODE_ENDS.index(n) for n in
                     ("time_limit", "upside_down_face_down", "upside_down_face_down",
                      "low_height")], jnp.float32)
  nxt = types.SimpleNamespace(
      done=jnp.asarray([1.0, 1.0, 1.0, 0.0]), metrics={},
      episode_metrics={"success": jnp.asarray([1.0, 0.0, 0.0, 0.0]), "return": zeros,
                       "recovery_time": jnp.asarray([0.5, jnp.nan, jnp.nan, jnp.nan]),
                       "end": end})
  out = train._summarize(train._step_stats(nxt))
  assert out["stand_rate"] == pytest.approx(1 / 3)
  expected = dict.fromkeys(EPISODE_ENDS, 0.0)
  expected.update(time_limit=1 / 3, upside_down_face_down=2 / 3)
  assert out["episode_ends"] == pytest.approx(expected)
