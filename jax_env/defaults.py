"""Complete, valid stage tables for tests and benchmarks: the paper's two stages at test scale.
"""

from __future__ import annotations

import copy

from jax_env.names import DR_PARAMS, JOINT_NAMES, KSI_SCENARIOS, LATERAL_JOINTS, SAGITTAL_JOINTS

# The paper's DR table (Table "Domain Randomization Parameters"), verbatim.
PAPER_DR: dict[str, dict] = {
    "dof_position": {"range": [0.0, 0.05], "operation": "additive", "distribution": "gaussian"},
    "base_xy_position": {"range": [-1.0, 1.0], "operation": "additive",
                         "distribution": "uniform"},
    "base_linear_velocity": {"range": [0.0, 0.1], "operation": "additive",
                             "distribution": "gaussian"},
    "joint_stiffness": {"range": [0.95, 1.05], "operation": "scaling", "distribution": "uniform"},
    "joint_damping": {"range": [0.95, 1.05], "operation": "scaling", "distribution": "uniform"},
    "terrain_friction": {"range": [0.1, 2.0], "operation": "additive", "distribution": "uniform"},
    "terrain_compliance": {"range": [0.5, 1.5], "operation": "additive",
                           "distribution": "uniform"},
    "terrain_restitution": {"range": [0.1, 0.9], "operation": "additive",
                            "distribution": "uniform"},
    "torso_com": {"range": [-0.1, 0.1], "operation": "additive", "distribution": "uniform"},
    "torso_mass": {"range": [0.8, 1.2], "operation": "scaling", "distribution": "uniform"},
    "other_com": {"range": [-0.005, 0.005], "operation": "additive", "distribution": "uniform"},
    "other_mass": {"range": [0.98, 1.02], "operation": "scaling", "distribution": "uniform"},
}

_PENALTIES = {
    # Per control step (50 Hz). Penalties are negative weights; magnitudes are sized so that
    # each term contributes O(0.01–0.1) per step in a typical get-up.
    "orientation": -1.0,
    "dof_pos_ref": -0.05,
    "torques": -1e-5,
    "dof_vel": -1e-3,
    "dof_acc": -1e-7,
    "root_acc": -1e-4,
    "action_rate": -0.01,
    "dof_pos_limits": -1.0,
    "torque_fatigue": -0.01,
    "power": -1e-3,
    "hip_roll": -0.5,
}


def default_stage_dict(kind: str) -> dict:
  """A complete, valid stage table: "planar" (stage 1) or "full" (stage 2).

  Values follow the paper: stage 1 is planar (sagittal joints, key states + supine/prone, lenient
  constraints: 1.2× range, 1.5× torque and velocity), stage 2 adds hip roll, 3D falls, terrain,
  the robot's real limits and every DR row. The action mapping is "current" (target = q +
  scale·a): for get-up the pose changes by radians, and offsets from the current pose keep the
  useful action range small everywhere (Playground's and mjlab's get-up tasks found it to work
  better than offsets from a fixed default). Learner sizes are small (tests); real curricula set
  their own.
  """
  if kind not in ("planar", "full"):
    raise ValueError(f"unknown default stage kind {kind!r}; valid: planar, full")
  planar = kind == "planar"
  controlled = list(SAGITTAL_JOINTS) if planar else list(SAGITTAL_JOINTS) + list(LATERAL_JOINTS)
  controlled = [j for j in JOINT_NAMES if j in controlled]
  observed = list(controlled) if planar else list(JOINT_NAMES)
  if planar:
    scenarios = {k: 0.1 for k in KSI_SCENARIOS} | {"supine": 0.2, "prone": 0.2}
    terrain = {"flat": 1.0, "slope_max_deg": 0.0}
    dr_names = ("dof_position", "joint_stiffness", "joint_damping", "terrain_friction",
                "torso_mass", "other_mass")
    penalty_scale = 0.1  # lenient: explore first, smooth later
  else:
    scenarios = ({k: 0.05 for k in KSI_SCENARIOS}
                 | {"supine": 0.1, "prone": 0.1, "lateral": 0.1, "sitting": 0.1,
                    "crossed_legs": 0.1, "random_drop": 0.2})
    terrain = {"flat": 0.6, "slope": 0.3, "obstacle": 0.1, "slope_max_deg": 10.0}
    dr_names = DR_PARAMS
    penalty_scale = 1.0
  rewards = {"survival": 0.1, "base_height": 1.0, "standing": 2.0}
  rewards |= {k: w * penalty_scale for k, w in _PENALTIES.items()}
  return {
      "name": kind,
      "init_from": "none" if planar else "previous",
      "controlled_joints": controlled,
      "observed_joints": observed,
      "sim": {"timestep": 0.005, "ctrl_dt": 0.02, "episode_s": 6.0 if planar else 8.0},
      "action": {"mapping": "current", "scale": 0.5, "clip": 1.0},
      "constraints": ({"torque_limit_scale": 1.5, "joint_range_scale": 1.2,
                       "velocity_limit_scale": 1.5} if planar else
                      {"torque_limit_scale": 1.0, "joint_range_scale": 1.0,
                       "velocity_limit_scale": 1.0}),
      "scenarios": scenarios,
      "scenario_params": {"ksi_joint_noise": 0.05, "settle_s": 1.0},
      "terrain": terrain,
      "rewards": rewards,
      "reward_params": {"base_height_target": 0.67, "base_height_sigma": 20.0,
                        "hip_roll_ref": 0.0},
      "success": {"height_tolerance": 0.05, "upright_tolerance": 0.1, "dof_tolerance": 0.3,
                  "hold_s": 1.0},
      "domain_randomization": {"enabled": True} | {k: copy.deepcopy(PAPER_DR[k])
                                                   for k in dr_names},
      "delay": {"max_s": 0.0 if planar else 0.02},
      "push": {"enabled": not planar, "interval_s": [2.0, 4.0], "duration_s": 0.2,
               "force_max": 100.0, "torque_max": 10.0},
      "ppo": {"num_envs": 8, "unroll_length": 4, "num_minibatches": 2, "update_epochs": 1,
              "learning_rate": 3e-4, "lr_schedule": "adaptive_kl", "desired_kl": 0.01,
              "entropy_cost": 0.005, "clip_epsilon": 0.2, "value_loss_coef": 0.5,
              "discount": 0.97, "gae_lambda": 0.95, "max_grad_norm": 1.0,
              "reward_scaling": 1.0, "normalize_observations": True,
              "policy_hidden": [32, 32], "value_hidden": [32, 32], "activation": "elu",
              "initial_action_std": 1.0, "checkpoint_every": 50},
      "rma": {"enabled": True, "latent_dim": 8, "encoder_hidden": [32], "history_len": 10,
              "adaptation_env_steps": 256, "adaptation_learning_rate": 1e-3},
      "mirror": {"weight": 0.5},
      "advance": {"env_steps": 1024, "min_stand_rate": 0.8, "window": 5, "on_miss": "continue"},
  }
