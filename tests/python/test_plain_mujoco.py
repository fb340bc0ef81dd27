"""The plain-MuJoCo sim-to-sim check (jax_env/evaluation/plain_mujoco.py) on a hand-built ONNX
actor that outputs zero actions, with the metadata keys `jax_env.export.metadata_props` writes.

With the "default" mapping a zero action holds the `stand` pose: a robot started standing stays
standing (success from the first step), a robot lying on its back stays lying. Nothing here
compiles JAX; every test runs in a few seconds.
"""

import json

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from jax_env import defaults, features
from jax_env import robot
from jax_env.evaluation import plain_mujoco as pm

HISTORY_LEN = 4


def _zero_actor(path, *, mapping="default", ctrl_dt=0.02, scale=1.0, clip=1.0,
                extra_props=None):
  """An ONNX file with export.py's interface and metadata whose `action` is zero (it still
  reads obs and history: 0 · x), and whose `joint_target` applies the mapping."""
  obs_names, _, action_names = features.feature_names(defaults.default_stage_dict("full"))
  n_obs, n_act = len(obs_names), len(action_names)
  stand = robot.stand_pose()
  q_stand = np.array([stand[robot.JOINT_NAMES.index(a)] for a in action_names], np.float32)
  jp = np.array([obs_names.index(f"joint_pos/{a}") for a in action_names], np.int64)
  init = [numpy_helper.from_array(v, k) for k, v in {
      "w_obs": np.zeros((n_obs, n_act), np.float32),
      "w_hist": np.zeros((HISTORY_LEN * n_obs, n_act), np.float32),
      "lo": np.array(-clip, np.float32), "hi": np.array(clip, np.float32),
      "scale": np.array(scale, np.float32), "q_stand": q_stand, "jp": jp}.items()]
  nodes = [
      helper.make_node("MatMul", ["obs", "w_obs"], ["a_obs"]),
      helper.make_node("Flatten", ["history"], ["hist_flat"], axis=1),
      helper.make_node("MatMul", ["hist_flat", "w_hist"], ["a_hist"]),
      helper.make_node("Add", ["a_obs", "a_hist"], ["action"]),
      helper.make_node("Clip", ["action", "lo", "hi"], ["clipped"]),
      helper.make_node("Mul", ["clipped", "scale"], ["offset"]),
  ]
  if mapping == "current":
    nodes += [helper.make_node("Gather", ["obs", "jp"], ["rel"], axis=1),
              helper.make_node("Add", ["rel", "q_stand"], ["base"]),
              helper.make_node("Add", ["base", "offset"], ["joint_target"])]
  else:
    nodes.append(helper.make_node("Add", ["q_stand", "offset"], ["joint_target"]))
  f32 = TensorProto.FLOAT
  graph = helper.make_graph(
      nodes, "zero_actor",
      [helper.make_tensor_value_info("obs", f32, ["N", n_obs]),
       helper.make_tensor_value_info("history", f32, ["N", HISTORY_LEN, n_obs])],
      [helper.make_tensor_value_info("action", f32, ["N", n_act]),
       helper.make_tensor_value_info("joint_target", f32, ["N", n_act])],
      initializer=init)
  model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
  model.ir_version = 8
  props = {"description": "zero actor for tests", "obs_names": list(obs_names),
           "action_names": list(action_names), "history_len": HISTORY_LEN,
           "history_input": "used", "rma": True, "ctrl_dt": ctrl_dt, "mapping": mapping,
           "scale": scale, "clip": clip, "q_stand": [float(str(x)) for x in q_stand],
           "normalization": "none", "checkpoint": "none"}
  if ctrl_dt is None:
    del props["ctrl_dt"]
  props.update(extra_props or {})
  helper.set_model_props(model, {k: v if isinstance(v, str) else json.dumps(v)
                                 for k, v in props.items()})
  onnx.checker.check_model(model, full_check=True)
  onnx.save(model, str(path))
  return path


@pytest.fixture(scope="module")
def zero_actor(tmp_path_factory):
  return _zero_actor(tmp_path_factory.mktemp("plain") / "zero.onnx")


def test_zero_action_holds_stand_and_stays_lying(zero_actor, tmp_path, capsys):
  out = tmp_path / "plain.json"
  rc = pm.main([str(zero_actor), "--start-states", "stand,ksi_supine_1", "--trials", "2",
                "--duration", "1.5", "--json", str(out)])
  assert rc == 0
  table = capsys.readouterr().out
  assert "stand" in table and "2/2" in table and "ksi_supine_1" in table and "0/2" in table
  result = json.loads(out.read_text())
  stand, supine = result["start_states"]
  assert stand["start_state"] == "stand" and stand["successes"] == 2
  assert stand["recovery_time_mean"] == 0.0  # standing from the first controlled step
  assert supine["start_state"] == "ksi_supine_1" and supine["successes"] == 0
  assert supine["recovery_time_mean"] is None
  assert not any(r["blew_up"] for c in result["start_states"] for r in c["results"])
  # trial 0 exact, later trials with joint noise
  assert [r["joint_noise"] for r in stand["results"]] == [0.0, pm.JOINT_NOISE]
  assert result["ctrl_dt"] == 0.02 and result["n_substeps"] == 4  # the scene's 0.005 s
  assert result["timestep_source"] == "scene"
  assert result["success_criterion"]["source"] == "default"
  assert result["success_criterion"]["upright_tolerance"] == 0.2
  assert len(result["success_criterion"]["observed_joints"]) == robot.NUM_JOINTS
  # our mapping equals the graph's own joint_target
  assert result["joint_target_max_abs_diff"] < 1e-5


def test_timestep_and_tolerances_from_a_stage_table(tmp_path):
  stage = {"sim": {"timestep": 0.002, "ctrl_dt": 0.02},
           "success": {"height_tolerance": 0.04, "upright_tolerance": 0.15,
                       "dof_tolerance": 0.25, "hold_s": 0.5}}
  path = _zero_actor(tmp_path / "staged.onnx", ctrl_dt=None,
                     extra_props={"stage_config": stage})
  result = pm.run(path, ("stand",), trials=1, duration_s=0.6)
  assert result["timestep"] == 0.002 and result["n_substeps"] == 10
  assert result["timestep_source"] == "metadata" and result["ctrl_dt"] == 0.02
  crit = result["success_criterion"]
  assert (crit["source"], crit["height_tolerance"], crit["hold_s"]) == ("metadata", 0.04, 0.5)
  assert result["start_states"][0]["successes"] == 1


def test_current_mapping_matches_the_graphs_joint_target(tmp_path):
  """"current": targets are the measured angles plus the offset, as the graph computes them
  from joint_pos + q_stand (a zero action only damps, so the robot sags: no success asked)."""
  path = _zero_actor(tmp_path / "current.onnx", mapping="current", scale=0.5)
  result = pm.run(path, ("ksi_prone_2",), trials=2, duration_s=0.5)
  assert result["mapping"] == "current" and result["scale"] == 0.5
  assert result["joint_target_max_abs_diff"] < 1e-5


def test_missing_ctrl_dt_is_an_error_unless_given(tmp_path):
  path = _zero_actor(tmp_path / "no_dt.onnx", ctrl_dt=None)
  with pytest.raises(ValueError, match="ctrl_dt"):
    pm.run(path, ("stand",), trials=1, duration_s=0.1)
  assert pm.run(path, ("stand",), trials=1, duration_s=0.1, ctrl_dt=0.02)["ctrl_dt"] == 0.02
  with pytest.raises(ValueError, match="unknown start state"):
    pm.run(path, ("nowhere",), trials=1, duration_s=0.1, ctrl_dt=0.02)


def test_observations_follow_the_contract(zero_actor):
  import mujoco

  meta = pm.actor_meta(pm.read_metadata(zero_actor))
  model = robot.load_model()
  rob = pm.Robot(model, meta)
  data = mujoco.MjData(model)
  names = meta.obs_names
  col = {n: i for i, n in enumerate(names)}
  prev = np.linspace(-1, 1, len(meta.action_names)).astype(np.float32)

  mujoco.mj_resetDataKeyframe(model, data, model.key("stand").id)
  mujoco.mj_forward(model, data)
  obs = rob.observe(data, prev)
  assert obs.dtype == np.float32 and obs.shape == (len(names),)
  np.testing.assert_allclose(obs[[col["gravity/x"], col["gravity/y"], col["gravity/z"]]],
                             [0, 0, -1], atol=1e-6)
  np.testing.assert_allclose([obs[col[f"joint_pos/{j}"]] for j in robot.JOINT_NAMES], 0,
                             atol=1e-6)
  np.testing.assert_array_equal([obs[col[f"prev_action/{a}"]] for a in meta.action_names],
                                prev)
  assert rob.standing(data, meta.success)

  # Pitched forward by θ about y (prone side): gravity in the Trunk frame is (sin θ, 0, −cos θ);
  # a base spin about its own x axis shows in ang_vel/x; joint angles relative to stand.
  theta = 0.7
  data.qpos[3:7] = [np.cos(theta / 2), 0, np.sin(theta / 2), 0]
  data.qvel[:] = 0
  data.qvel[3] = 0.5  # free-joint angular velocity is in the body frame
  knee = robot.JOINT_NAMES.index("Left_Knee_Pitch")
  data.qpos[7 + knee] += 0.2
  data.qvel[6 + knee] = -1.5
  mujoco.mj_forward(model, data)
  obs = rob.observe(data, prev)
  np.testing.assert_allclose(obs[[col["gravity/x"], col["gravity/y"], col["gravity/z"]]],
                             [np.sin(theta), 0, -np.cos(theta)], atol=1e-6)
  np.testing.assert_allclose(obs[[col["ang_vel/x"], col["ang_vel/y"], col["ang_vel/z"]]],
                             [0.5, 0, 0], atol=1e-6)
  assert obs[col["joint_pos/Left_Knee_Pitch"]] == pytest.approx(0.2, abs=1e-6)
  assert obs[col["joint_vel/Left_Knee_Pitch"]] == pytest.approx(-1.5, abs=1e-6)
  assert not rob.standing(data, meta.success)


def test_history_is_the_observations_before_obs_oldest_first(zero_actor):
  """The actor sees zeros at the start, then [.., obs_{t-2}, obs_{t-1}] beside obs_t."""
  meta = pm.actor_meta(pm.read_metadata(zero_actor))
  model = robot.load_model()
  rob = pm.Robot(model, meta)
  seen = []

  def spy(obs, history):
    seen.append((obs.copy(), history.copy()))
    return np.zeros(len(meta.action_names), np.float32), None

  pm.run_trial(model, rob, spy, meta, "ksi_prone_2", None, n_steps=6, n_substeps=4)
  assert len(seen) == 6
  assert np.all(seen[0][1] == 0) and seen[0][1].shape == (HISTORY_LEN, len(meta.obs_names))
  for t in range(1, 6):
    history = seen[t][1]
    expected = [seen[s][0] if s >= 0 else np.zeros_like(seen[0][0])
                for s in range(t - HISTORY_LEN, t)]
    np.testing.assert_array_equal(history, np.stack(expected))
