//! The Booster T1 names that cross the Rust/Python boundary (docs/contracts.md, "Robot names").
//!
//! Python (`jax_env/robot.py`, `jax_env/config.py`) hard-codes the same lists; the curriculum
//! validator checks names against them before Python starts, and the feature-name lists that
//! checkpoint expansion relies on are built from them.

/// Canonical joint order (T1-FACTS §1): actuator order and `qpos[7:]`.
pub const JOINT_NAMES: [&str; 23] = [
    "AAHead_yaw",
    "Head_pitch",
    "Left_Shoulder_Pitch",
    "Left_Shoulder_Roll",
    "Left_Elbow_Pitch",
    "Left_Elbow_Yaw",
    "Right_Shoulder_Pitch",
    "Right_Shoulder_Roll",
    "Right_Elbow_Pitch",
    "Right_Elbow_Yaw",
    "Waist",
    "Left_Hip_Pitch",
    "Left_Hip_Roll",
    "Left_Hip_Yaw",
    "Left_Knee_Pitch",
    "Left_Ankle_Pitch",
    "Left_Ankle_Roll",
    "Right_Hip_Pitch",
    "Right_Hip_Roll",
    "Right_Hip_Yaw",
    "Right_Knee_Pitch",
    "Right_Ankle_Pitch",
    "Right_Ankle_Roll",
];

/// Robot bodies in model order (model body id = index + 1; 0 is the world).
pub const BODY_NAMES: [&str; 24] = [
    "Trunk",
    "H1",
    "H2",
    "AL1",
    "AL2",
    "AL3",
    "left_hand_link",
    "AR1",
    "AR2",
    "AR3",
    "right_hand_link",
    "Waist",
    "Hip_Pitch_Left",
    "Hip_Roll_Left",
    "Hip_Yaw_Left",
    "Shank_Left",
    "Ankle_Cross_Left",
    "left_foot_link",
    "Hip_Pitch_Right",
    "Hip_Roll_Right",
    "Hip_Yaw_Right",
    "Shank_Right",
    "Ankle_Cross_Right",
    "right_foot_link",
];

/// Bodies with a floor-contact sensor `contact/<body>`, in sensor order.
pub const CONTACT_BODIES: [&str; 13] = [
    "Trunk",
    "H2",
    "AL3",
    "left_hand_link",
    "AR3",
    "right_hand_link",
    "Waist",
    "Hip_Yaw_Left",
    "Shank_Left",
    "left_foot_link",
    "Hip_Yaw_Right",
    "Shank_Right",
    "right_foot_link",
];

/// Joints that move in the sagittal (x–z) plane (T1-FACTS §8): shoulder pitch, elbow yaw
/// (the elbow flexion of this robot; `Elbow_Pitch` is humeral rotation), hip pitch, knee,
/// ankle pitch. Canonical order. The paper's stage 1 controls these.
pub const SAGITTAL_JOINTS: [&str; 10] = [
    "Left_Shoulder_Pitch",
    "Left_Elbow_Yaw",
    "Right_Shoulder_Pitch",
    "Right_Elbow_Yaw",
    "Left_Hip_Pitch",
    "Left_Knee_Pitch",
    "Left_Ankle_Pitch",
    "Right_Hip_Pitch",
    "Right_Knee_Pitch",
    "Right_Ankle_Pitch",
];

/// Hip roll: the joints the paper's stage 2 adds to the action space.
pub const LATERAL_JOINTS: [&str; 2] = ["Left_Hip_Roll", "Right_Hip_Roll"];

/// MJCF keyframes of `assets/t1/scene.xml`.
pub const KEYFRAMES: [&str; 7] =
    ["stand", "ksi_prone_1", "ksi_prone_2", "ksi_prone_3", "ksi_supine_1", "ksi_supine_2", "ksi_supine_3"];

/// Initial-state scenarios; `ksi_*` start from the keyframe of the same name, `stand` and
/// `squat` on the feet (jax_env/scenarios.py).
pub const SCENARIOS: [&str; 14] = [
    "ksi_prone_1",
    "ksi_prone_2",
    "ksi_prone_3",
    "ksi_supine_1",
    "ksi_supine_2",
    "ksi_supine_3",
    "supine",
    "prone",
    "lateral",
    "sitting",
    "crossed_legs",
    "random_drop",
    "stand",
    "squat",
];

pub const TERRAINS: [&str; 3] = ["flat", "slope", "obstacle"];

/// Reward terms of the paper's Table "Components of the Reward Function", then our additions
/// (`trunk_height`, `waist_height`, `upright`; jax_env/rewards.py).
pub const REWARD_TERMS: [&str; 17] = [
    "survival",
    "base_height",
    "standing",
    "orientation",
    "dof_pos_ref",
    "torques",
    "dof_vel",
    "dof_acc",
    "root_acc",
    "action_rate",
    "dof_pos_limits",
    "torque_fatigue",
    "power",
    "hip_roll",
    "trunk_height",
    "waist_height",
    "upright",
];

/// Rows of the paper's Table "Domain Randomization Parameters".
pub const DR_PARAMETERS: [&str; 12] = [
    "dof_position",
    "base_xy_position",
    "base_linear_velocity",
    "joint_stiffness",
    "joint_damping",
    "terrain_friction",
    "terrain_compliance",
    "terrain_restitution",
    "torso_com",
    "torso_mass",
    "other_com",
    "other_mass",
];

/// Index of a joint in canonical order.
pub fn joint_index(name: &str) -> Option<usize> {
    JOINT_NAMES.iter().position(|j| *j == name)
}

/// The left/right partner of a joint (itself for centre-line joints).
pub fn mirror_joint(name: &str) -> Option<&'static str> {
    joint_index(name)?;
    let swapped = if let Some(rest) = name.strip_prefix("Left_") {
        format!("Right_{rest}")
    } else if let Some(rest) = name.strip_prefix("Right_") {
        format!("Left_{rest}")
    } else {
        name.to_owned()
    };
    JOINT_NAMES.iter().copied().find(|j| *j == swapped)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn groups_are_canonical_subsets() {
        for group in [&SAGITTAL_JOINTS[..], &LATERAL_JOINTS[..]] {
            let indices: Vec<usize> = group.iter().map(|j| joint_index(j).expect("known joint")).collect();
            assert!(indices.windows(2).all(|w| w[0] < w[1]), "{group:?} is not in canonical order");
        }
        assert!(SAGITTAL_JOINTS.iter().all(|j| !LATERAL_JOINTS.contains(j)));
    }

    #[test]
    fn mirror_is_an_involution() {
        for j in JOINT_NAMES {
            let m = mirror_joint(j).unwrap();
            assert_eq!(mirror_joint(m), Some(j));
        }
        assert_eq!(mirror_joint("Left_Hip_Roll"), Some("Right_Hip_Roll"));
        assert_eq!(mirror_joint("Waist"), Some("Waist"));
        assert_eq!(mirror_joint("Elbow"), None);
    }

    #[test]
    fn curriculum_vocabularies_match_these_lists() {
        use crate::curriculum::schema::{RewardTerm, Scenario};
        let scenarios: Vec<&str> = Scenario::ALL.iter().map(|s| s.as_str()).collect();
        assert_eq!(scenarios, SCENARIOS);
        let terms: Vec<&str> = RewardTerm::ALL.iter().map(|t| t.as_str()).collect();
        assert_eq!(terms, REWARD_TERMS);
    }

    #[test]
    fn ksi_scenarios_are_keyframes() {
        for s in SCENARIOS.iter().filter(|s| s.starts_with("ksi_")) {
            assert!(KEYFRAMES.contains(s));
        }
    }
}
