"""Stage configuration: parsing, validation errors, feature names and mirror maps (no physics)."""

import numpy as np
import pytest

from jax_env import config, features, names, robot
from jax_env.config import ConfigError, StageConfig, check_stage
from jax_env.defaults import default_stage_dict


@pytest.fixture(params=["planar", "full"])
def stage_dict(request):
  return default_stage_dict(request.param)


def test_default_stages_are_valid_and_follow_the_paper():
  planar = StageConfig.from_dict(default_stage_dict("planar"))
  full = StageConfig.from_dict(default_stage_dict("full"))
  assert check_stage(default_stage_dict("planar")) == []
  assert check_stage(default_stage_dict("full")) == []
  # Stage 1: sagittal joints only, key states + supine/prone, lenient constraints.
  assert set(planar.controlled_joints) == set(robot.SAGITTAL_JOINTS)
  assert {s for s, w in planar.scenarios.items() if w > 0} == set(names.KSI_SCENARIOS) | {
      "supine", "prone"}
  assert planar.constraints.joint_range_scale > 1 and planar.constraints.torque_limit_scale > 1
  # Stage 2: + hip roll, 3D falls, real limits, every DR row with the paper's ranges.
  assert set(full.controlled_joints) == set(robot.SAGITTAL_JOINTS) | set(robot.LATERAL_JOINTS)
  assert all(full.scenarios[s] > 0 for s in ("lateral", "sitting", "crossed_legs",
                                             "random_drop"))
  assert full.constraints == config.ConstraintsConfig(1.0, 1.0, 1.0)
  assert set(full.domain_randomization.params) == set(names.DR_PARAMS)
  assert full.domain_randomization.params["terrain_friction"].range == (0.1, 2.0)
  assert full.domain_randomization.params["torso_com"].range == (-0.1, 0.1)
  assert full.delay.max_s == pytest.approx(0.02)
  assert full.push.enabled and full.terrain.weights["slope"] > 0
  assert full.terrain.weights["obstacle"] > 0
  assert full.action.mapping == "current"
  # Every reward term of the paper has a weight; penalties are negative.
  for stage in (planar, full):
    assert set(stage.rewards) == set(names.REWARD_TERMS)
    assert stage.rewards["survival"] > 0 and stage.rewards["standing"] > 0
    assert all(stage.rewards[t] < 0 for t in ("orientation", "torques", "dof_vel", "dof_acc",
                                              "root_acc", "action_rate", "dof_pos_limits",
                                              "torque_fatigue", "power", "hip_roll"))


def test_feature_names_match_the_contract(stage_dict):
  stage = StageConfig.from_dict(stage_dict)
  obs, priv, act = features.feature_names(stage_dict)
  joints = [j for j in robot.JOINT_NAMES if j in stage.observed_joints]
  ctrl = [j for j in robot.JOINT_NAMES if j in stage.controlled_joints]
  assert list(obs) == (["gravity/x", "gravity/y", "gravity/z", "ang_vel/x", "ang_vel/y",
                        "ang_vel/z"] + [f"joint_pos/{j}" for j in joints]
                       + [f"joint_vel/{j}" for j in joints]
                       + [f"prev_action/{j}" for j in ctrl])
  assert list(act) == ctrl
  expected = ["friction", "compliance", "restitution"]
  expected += [f"mass_scale/{b}" for b in robot.BODY_NAMES]
  expected += [f"com_offset/{b}/{a}" for b in robot.BODY_NAMES for a in "xyz"]
  expected += [f"kp_scale/{j}" for j in robot.JOINT_NAMES]
  expected += [f"kd_scale/{j}" for j in robot.JOINT_NAMES]
  expected += ["torque_limit_scale", "delay", "base_height", "base_lin_vel/x",
               "base_lin_vel/y", "base_lin_vel/z"]
  expected += [f"contact/{b}" for b in robot.CONTACT_BODIES]
  expected += ["push_force/x", "push_force/y", "push_force/z", "push_torque/x",
               "push_torque/y", "push_torque/z", "terrain/slope_x", "terrain/slope_y",
               "terrain/obstacle"]
  assert list(priv) == expected
  assert len(priv) == 3 + 24 + 72 + 46 + 2 + 4 + 13 + 6 + 3


def test_feature_names_use_canonical_joint_order_whatever_the_config_order():
  d = default_stage_dict("planar")
  d["controlled_joints"] = list(reversed(d["controlled_joints"]))
  d["observed_joints"] = list(reversed(d["observed_joints"]))
  obs, _, act = features.feature_names(d)
  assert list(act) == [j for j in robot.JOINT_NAMES if j in robot.SAGITTAL_JOINTS]
  assert obs[6] == "joint_pos/Left_Shoulder_Pitch"


def _error(d):
  with pytest.raises(ConfigError) as info:
    StageConfig.from_dict(d)
  return info.value


def test_unknown_joint_names_the_value_and_lists_valid_ones():
  d = default_stage_dict("planar")
  d["controlled_joints"][3] = "Left_Knee"
  e = _error(d)
  assert e.path == ("controlled_joints", 3)
  assert '"Left_Knee"' in e.message and "Left_Knee_Pitch" in e.message


def test_unknown_reward_term():
  d = default_stage_dict("planar")
  d["rewards"]["uprightness"] = 1.0
  e = _error(d)
  assert e.path == ("rewards", "uprightness")
  assert "uprightness" in e.message and "orientation" in e.message and "hip_roll" in e.message


def test_unknown_scenario():
  d = default_stage_dict("full")
  d["scenarios"]["backflip"] = d["scenarios"].pop("lateral")
  e = _error(d)
  assert e.path == ("scenarios", "backflip")
  assert "backflip" in e.message and "crossed_legs" in e.message


def test_unknown_keyframe():
  d = default_stage_dict("planar")
  d["scenarios"]["ksi_prone_7"] = d["scenarios"].pop("ksi_prone_3")
  e = _error(d)
  assert e.path == ("scenarios", "ksi_prone_7")
  assert "keyframe 'ksi_prone_7'" in e.message and "ksi_supine_3" in e.message


def test_unknown_dr_parameter():
  d = default_stage_dict("full")
  d["domain_randomization"]["motor_strength"] = {"range": [0.9, 1.1], "operation": "scaling",
                                                 "distribution": "uniform"}
  e = _error(d)
  assert e.path == ("domain_randomization", "motor_strength")
  assert "motor_strength" in e.message and "terrain_restitution" in e.message


@pytest.mark.parametrize("where", ["dr", "push"])
def test_range_min_greater_than_max(where):
  d = default_stage_dict("full")
  if where == "dr":
    d["domain_randomization"]["torso_mass"]["range"] = [1.2, 0.8]
    path = ("domain_randomization", "torso_mass", "range")
    message = "torso_mass.range = [1.2, 0.8]: min 1.2 > max 0.8 (uniform ranges are [low, high])"
  else:
    d["push"]["interval_s"] = [4.0, 2.0]
    path = ("push", "interval_s")
    message = "interval_s = [4, 2]: min 4 > max 2"
  e = _error(d)
  assert (e.path, e.message) == (path, message)


@pytest.mark.parametrize("table", ["scenarios", "terrain"])
def test_mixture_must_sum_to_one(table):
  d = default_stage_dict("full")
  first = next(k for k in d[table] if k != "slope_max_deg")
  d[table][first] += 0.25
  e = _error(d)
  assert e.path == (table,) and "sum to 1" in e.message


def test_unknown_key_and_wrong_values():
  d = default_stage_dict("planar")
  d["sim"]["substeps"] = 4
  assert _error(d).path == ("sim", "substeps")
  d = default_stage_dict("planar")
  d["action"]["mapping"] = "absolute"
  e = _error(d)
  assert e.path == ("action", "mapping") and "current" in e.message and "default" in e.message
  d = default_stage_dict("planar")
  d["sim"]["ctrl_dt"] = 0.012
  assert _error(d).path == ("sim", "ctrl_dt")
  d = default_stage_dict("planar")
  d["domain_randomization"]["torso_mass"]["operation"] = "multiply"
  e = _error(d)
  assert e.path == ("domain_randomization", "torso_mass", "operation")
  assert "scaling" in e.message


def test_joint_lists_must_be_consistent_and_symmetric():
  d = default_stage_dict("full")
  d["observed_joints"].remove("Left_Hip_Roll")
  d["observed_joints"].remove("Right_Hip_Roll")
  e = _error(d)
  assert e.path == ("observed_joints",) and "Left_Hip_Roll" in e.message
  d = default_stage_dict("full")
  d["controlled_joints"].remove("Right_Hip_Roll")
  e = _error(d)
  assert e.path == ("controlled_joints",) and "Right_Hip_Roll" in e.message


def test_messages_read_like_the_cli_and_say_which_end_is_at_fault():
  d = default_stage_dict("planar")
  d["sim"]["ctrl_dt"] = 0.012
  d["ppo"]["num_envs"] = 10
  d["ppo"]["num_minibatches"] = 4
  d["success"]["hold_s"] = d["sim"]["episode_s"]
  d["scenarios"]["supine"] += 0.5
  issues = {tuple(e["path"]): (e["message"], e["at"]) for e in check_stage(d)}
  assert issues[("sim", "ctrl_dt")] == (
      "ctrl_dt = 0.012 must be an integer multiple of timestep = 0.005 (ratio 2.4)", "value")
  assert issues[("ppo", "num_envs")] == (
      "num_envs = 10 is not divisible by num_minibatches = 4 (each minibatch takes whole "
      "environments)", "value")
  assert issues[("success", "hold_s")][0].endswith(": no episode could ever count as standing")
  message, at = issues[("scenarios",)]
  assert message.startswith("scenario weights must sum to 1, got 1.4999999999999998 (") and at == "key"
  assert config._show(3e-5) == "0.00003" and config._show(2.0) == "2"


def test_gravity_gates_are_optional_pairs_in_the_gravity_range():
  d = default_stage_dict("full")
  assert StageConfig.from_dict(d).reward_params.face_down_gate is None
  d["reward_params"] |= {"face_down_gate": [0.3, 0.6], "head_down_gate": [0, 0.5]}
  params = StageConfig.from_dict(d).reward_params
  assert params.face_down_gate == (0.3, 0.6) and params.head_down_gate == (0.0, 0.5)
  for bad in ([0.6, 0.3], [0.3, 0.3], [-1.5, 0.5], [0.3], "on"):
    d["reward_params"]["head_down_gate"] = bad
    e = _error(d)
    assert e.path == ("reward_params", "head_down_gate"), bad


def test_path_start_windows_are_optional_positive_seconds_per_path_scenario():
  d = default_stage_dict("planar")
  assert StageConfig.from_dict(d).scenario_params.path_start_window_s == {}
  d["scenario_params"]["path_start_window_s"] = {"kneel_path": 1.0}
  assert StageConfig.from_dict(d).scenario_params.path_start_window_s == {"kneel_path": 1.0}
  for bad, at in (({"kneel_path": 0.0}, "kneel_path"), ({"kneel_path": "1 s"}, "kneel_path"),
                  ({"ksi_prone_3": 1.0}, "ksi_prone_3"), (1.0, None)):
    d["scenario_params"]["path_start_window_s"] = bad
    e = _error(d)
    assert e.path == ("scenario_params", "path_start_window_s") + ((at,) if at else ()), bad


def test_check_stage_collects_every_error():
  d = default_stage_dict("full")
  d["controlled_joints"].append("Tail")
  d["rewards"]["bogus"] = 1.0
  d["scenarios"]["ksi_prone_9"] = 0.0
  d["domain_randomization"]["other_mass"]["range"] = [1.1, 0.9]
  d["terrain"]["flat"] = 0.2
  del d["delay"]
  paths = {tuple(e["path"]) for e in check_stage(d)}
  assert {("controlled_joints", 12), ("rewards", "bogus"), ("scenarios", "ksi_prone_9"),
          ("domain_randomization", "other_mass", "range"), ("terrain",), ("delay",)} <= paths
  assert all(isinstance(e["message"], str) and e["message"] for e in check_stage(d))


def test_learner_sections_are_typed():
  s = StageConfig.from_dict(default_stage_dict("full"))
  assert isinstance(s.ppo.policy_hidden, tuple) and isinstance(s.ppo.num_envs, int)
  assert s.rma.enabled is True and s.mirror.weight == 0.5
  d = default_stage_dict("full")
  del d["advance"]["min_stand_rate"]
  assert StageConfig.from_dict(d).advance.min_stand_rate is None
  d["ppo"]["activation"] = "gelu"
  assert _error(d).path == ("ppo", "activation")


def test_mirror_maps_are_involutions(stage_dict):
  obs, priv, act = features.feature_names(stage_dict)
  for names, kind in ((obs, "obs"), (priv, "obs"), (act, "action")):
    perm, sign = features.mirror_map(names, kind)
    assert sorted(perm.tolist()) == list(range(len(names)))
    np.testing.assert_array_equal(perm[perm], np.arange(len(names)))
    np.testing.assert_array_equal(sign[perm] * sign, np.ones(len(names)))
    x = np.random.default_rng(0).normal(size=(5, len(names))).astype(np.float32)
    np.testing.assert_allclose((x[:, perm] * sign)[:, perm] * sign, x)


def test_mirror_map_examples():
  obs, priv, act = features.feature_names(default_stage_dict("full"))
  perm, sign = features.mirror_map(obs)
  i = obs.index("joint_pos/Left_Hip_Roll")
  assert obs[perm[i]] == "joint_pos/Right_Hip_Roll" and sign[i] == -1
  i = obs.index("joint_vel/Left_Knee_Pitch")
  assert obs[perm[i]] == "joint_vel/Right_Knee_Pitch" and sign[i] == 1
  assert [sign[obs.index(f"gravity/{a}")] for a in "xyz"] == [1, -1, 1]
  assert [sign[obs.index(f"ang_vel/{a}")] for a in "xyz"] == [-1, 1, -1]
  perm, sign = features.mirror_map(priv)
  i = priv.index("com_offset/Hip_Yaw_Left/y")
  assert priv[perm[i]] == "com_offset/Hip_Yaw_Right/y" and sign[i] == -1
  assert priv[perm[priv.index("contact/AL3")]] == "contact/AR3"
  assert [sign[priv.index(f"push_torque/{a}")] for a in "xyz"] == [-1, 1, -1]
  assert sign[priv.index("terrain/slope_y")] == -1 and sign[priv.index("terrain/slope_x")] == 1
  perm, sign = features.mirror_map(act, "action")
  assert act[perm[act.index("Left_Elbow_Yaw")]] == "Right_Elbow_Yaw"
  assert sign[act.index("Left_Elbow_Yaw")] == -1
