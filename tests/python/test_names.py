"""jax_env/names.json: the vocabularies the Rust CLI compiles in, exported from their owners."""

import json

from jax_env import features, names, rewards, robot, scenarios
from jax_env.defaults import default_stage_dict

REGENERATE = "regenerate it with `.venv/bin/python -m jax_env.names` and commit it"


def test_names_json_is_current():
  assert names.NAMES_JSON.read_text() == names.render(), (
      f"{names.NAMES_JSON} is stale: a vocabulary or the feature layout changed; {REGENERATE}")


def test_vocabularies_come_from_their_owners():
  exported = json.loads(names.render())
  assert exported["reward_terms"] == list(rewards.TERMS)
  assert exported["scenarios"] == list(scenarios.SCENARIOS)
  assert exported["joints"] == list(robot.JOINT_NAMES)
  # Key-state scenarios start at the keyframe of their name.
  assert set(scenarios.KSI_SCENARIOS) <= set(exported["keyframes"])
  for vocabulary in ("scenarios", "terrains", "reward_terms", "dr_parameters"):
    assert len(set(exported[vocabulary])) == len(exported[vocabulary]), vocabulary


def test_exported_layout_expands_to_the_feature_names():
  """What the Rust CLI computes from the exported layout is what Python computes."""
  layout = json.loads(names.render())["features"]
  for kind in ("planar", "full"):
    stage = default_stage_dict(kind)
    obs, priv, act = features.feature_names(stage)
    joints = lambda key: [j for j in robot.JOINT_NAMES if j in stage[key]]
    expanded = []
    for segment in layout["obs"]:
      labels = segment["labels"]
      labels = joints(labels) if isinstance(labels, str) else labels
      expanded += [f"{segment['prefix']}/{label}" for label in labels]
    assert expanded == list(obs)
    assert layout["privileged"] == list(priv)
    assert joints(layout["action"]) == list(act)
