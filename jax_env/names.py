"""Every name jax_env shares with the Rust CLI, gathered from the modules that own them.

A name belongs to the module that gives it meaning: reward terms to `rewards` (its `TERMS`),
start scenarios to `scenarios`, terrains and DR parameters to `randomization`, joints, bodies
and keyframes to `robot`, the feature layout to `features`. This module only collects them, for
the stage parser (`jax_env.config`) and for `jax_env/names.json`, the copy the Rust CLI compiles
in (`include_str!`) so that it can check a curriculum, expand a checkpoint and check `hifar
rollout`'s arguments without starting Python.

After changing a vocabulary, regenerate the JSON (tests/python/test_names.py fails until then):

    .venv/bin/python -m jax_env.names
"""

from __future__ import annotations

import json
from pathlib import Path

from jax_env import features, physics, randomization, rewards, robot, scenarios, stage_config
from jax_env.evaluation import conditions, policy
from jax_env.learner import networks

JOINT_NAMES: tuple[str, ...] = robot.JOINT_NAMES
BODY_NAMES: tuple[str, ...] = robot.BODY_NAMES
CONTACT_BODIES: tuple[str, ...] = robot.CONTACT_BODIES
KEYFRAMES: tuple[str, ...] = robot.KEYFRAME_NAMES
SAGITTAL_JOINTS: tuple[str, ...] = robot.SAGITTAL_JOINTS
LATERAL_JOINTS: tuple[str, ...] = robot.LATERAL_JOINTS

KSI_SCENARIOS: tuple[str, ...] = scenarios.KSI_SCENARIOS
SCENARIOS: tuple[str, ...] = scenarios.SCENARIOS
TERRAINS: tuple[str, ...] = randomization.TERRAINS
REWARD_TERMS: tuple[str, ...] = rewards.REWARD_TERMS
DR_PARAMS: tuple[str, ...] = randomization.DR_PARAMS
ACTIVATIONS: tuple[str, ...] = tuple(networks.ACTIVATIONS)
PUSH_DIRECTIONS: tuple[str, ...] = tuple(conditions.PUSH_DIRECTIONS)
PHYSICS_BACKENDS: tuple[str, ...] = physics.BACKENDS
# The actors `hifar eval --actor` offers, the deployable one first (the default).
ACTORS: tuple[str, ...] = policy.ACTORS

NAMES_JSON = Path(__file__).with_name("names.json")


def export() -> dict:
  """The vocabularies as JSON data (the content of names.json)."""
  return {
      "generated_by": "python -m jax_env.names (do not edit by hand)",
      "joints": list(JOINT_NAMES),
      # The left/right partner of each joint, in joint order (itself on the centre line).
      "joint_mirror": [features.mirror_joint_name(j) for j in JOINT_NAMES],
      "keyframes": list(KEYFRAMES),
      "scenarios": list(SCENARIOS),
      "terrains": list(TERRAINS),
      "reward_terms": list(REWARD_TERMS),
      "dr_parameters": list(DR_PARAMS),
      "dr_operations": list(stage_config.DR_OPERATIONS),
      "dr_distributions": list(stage_config.DR_DISTRIBUTIONS),
      "action_mappings": list(stage_config.ACTION_MAPPINGS),
      "lr_schedules": list(stage_config.LR_SCHEDULES),
      "activations": list(ACTIVATIONS),
      "on_miss": list(stage_config.ON_MISS),
      "schedule_keys": list(stage_config.SCHEDULE_KEYS),
      "push_directions": list(PUSH_DIRECTIONS),
      "physics_backends": list(PHYSICS_BACKENDS),
      "actors": list(ACTORS),
      "features": features.export(),
  }


def render() -> str:
  """names.json's text: one name a line, so that a diff shows what changed."""
  return json.dumps(export(), indent=2) + "\n"


def main() -> None:
  NAMES_JSON.write_text(render())
  print(f"wrote {NAMES_JSON}")


if __name__ == "__main__":
  main()
