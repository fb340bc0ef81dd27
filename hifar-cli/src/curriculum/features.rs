//! Feature names of a stage (docs/contracts.md, "Feature names").
//!
//! A pure function of the stage's joint lists. The Python environment builds the same lists
//! (`jax_env.config.feature_names`); checkpoint expansion maps tensor rows and columns by these
//! names, so `hifar check` and `hifar train` compare both sides before training.

use serde::{Deserialize, Serialize};

use super::Stage;
use crate::robot::{BODY_NAMES, CONTACT_BODIES, JOINT_NAMES};

/// The three ordered name lists that give every observation, privileged-observation and action
/// index a meaning.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct FeatureNames {
    pub obs_names: Vec<String>,
    pub privileged_names: Vec<String>,
    pub action_names: Vec<String>,
}

/// Which of the three lists a tensor axis segment refers to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FeatureKind {
    Obs,
    Privileged,
    Action,
}

impl FeatureKind {
    pub const ALL: [FeatureKind; 3] = [FeatureKind::Obs, FeatureKind::Privileged, FeatureKind::Action];

    pub fn as_str(self) -> &'static str {
        match self {
            FeatureKind::Obs => "obs",
            FeatureKind::Privileged => "privileged",
            FeatureKind::Action => "action",
        }
    }
}

impl FeatureNames {
    pub fn get(&self, kind: FeatureKind) -> &[String] {
        match kind {
            FeatureKind::Obs => &self.obs_names,
            FeatureKind::Privileged => &self.privileged_names,
            FeatureKind::Action => &self.action_names,
        }
    }
}

/// `joints` in canonical order, whatever order the curriculum lists them in.
fn canonical<'a>(joints: &'a [String]) -> impl Iterator<Item = &'static str> + 'a {
    JOINT_NAMES.iter().copied().filter(move |j| joints.iter().any(|x| x == j))
}

/// The feature names of a stage.
pub fn feature_names(stage: &Stage) -> FeatureNames {
    joint_feature_names(&stage.controlled_joints, &stage.observed_joints)
}

/// The feature names for the given controlled and observed joints.
pub fn joint_feature_names(controlled: &[String], observed: &[String]) -> FeatureNames {
    let mut obs: Vec<String> = ["gravity/x", "gravity/y", "gravity/z", "ang_vel/x", "ang_vel/y", "ang_vel/z"]
        .iter()
        .map(|s| s.to_string())
        .collect();
    obs.extend(canonical(observed).map(|j| format!("joint_pos/{j}")));
    obs.extend(canonical(observed).map(|j| format!("joint_vel/{j}")));
    obs.extend(canonical(controlled).map(|j| format!("prev_action/{j}")));
    FeatureNames {
        obs_names: obs,
        privileged_names: privileged_names(),
        action_names: canonical(controlled).map(str::to_owned).collect(),
    }
}

/// The privileged (critic / RMA encoder) inputs: the same in every stage.
pub fn privileged_names() -> Vec<String> {
    let mut names: Vec<String> = vec!["friction".into(), "compliance".into(), "restitution".into()];
    names.extend(BODY_NAMES.iter().map(|b| format!("mass_scale/{b}")));
    for b in BODY_NAMES {
        names.extend(["x", "y", "z"].iter().map(|a| format!("com_offset/{b}/{a}")));
    }
    names.extend(JOINT_NAMES.iter().map(|j| format!("kp_scale/{j}")));
    names.extend(JOINT_NAMES.iter().map(|j| format!("kd_scale/{j}")));
    names.extend(["torque_limit_scale", "delay"].map(String::from));
    names.extend(["base_height", "base_lin_vel/x", "base_lin_vel/y", "base_lin_vel/z"].map(String::from));
    names.extend(CONTACT_BODIES.iter().map(|b| format!("contact/{b}")));
    names.extend(["x", "y", "z"].iter().map(|a| format!("push_force/{a}")));
    names.extend(["x", "y", "z"].iter().map(|a| format!("push_torque/{a}")));
    names.extend(["terrain/slope_x", "terrain/slope_y", "terrain/obstacle"].map(String::from));
    names
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::robot::{LATERAL_JOINTS, SAGITTAL_JOINTS};

    fn strings(names: &[&str]) -> Vec<String> {
        names.iter().map(|s| s.to_string()).collect()
    }

    #[test]
    fn privileged_layout() {
        let names = privileged_names();
        assert_eq!(names.len(), 3 + 24 + 72 + 46 + 2 + 4 + 13 + 6 + 3);
        assert_eq!(names[3], "mass_scale/Trunk");
        assert_eq!(names[27], "com_offset/Trunk/x");
        assert_eq!(names[99], "kp_scale/AAHead_yaw");
        assert_eq!(names.last().unwrap(), "terrain/obstacle");
        let unique: std::collections::HashSet<_> = names.iter().collect();
        assert_eq!(unique.len(), names.len());
    }

    #[test]
    fn joints_follow_canonical_order_whatever_the_config_order() {
        let mut controlled = strings(&SAGITTAL_JOINTS);
        controlled.reverse();
        let f = joint_feature_names(&controlled, &controlled);
        assert_eq!(f.action_names, strings(&SAGITTAL_JOINTS));
        assert_eq!(f.obs_names.len(), 6 + 10 + 10 + 10);
        assert_eq!(f.obs_names[6], "joint_pos/Left_Shoulder_Pitch");
        assert_eq!(f.obs_names[16], "joint_vel/Left_Shoulder_Pitch");
        assert_eq!(f.obs_names[26], "prev_action/Left_Shoulder_Pitch");
    }

    #[test]
    fn observed_and_controlled_differ() {
        let controlled: Vec<String> = JOINT_NAMES
            .iter()
            .filter(|j| SAGITTAL_JOINTS.contains(j) || LATERAL_JOINTS.contains(j))
            .map(|s| s.to_string())
            .collect();
        let observed = strings(&JOINT_NAMES);
        let f = joint_feature_names(&controlled, &observed);
        assert_eq!(f.obs_names.len(), 6 + 23 + 23 + 12);
        assert_eq!(f.action_names.len(), 12);
        assert_eq!(f.action_names[4], "Left_Hip_Pitch");
        assert_eq!(f.action_names[5], "Left_Hip_Roll");
    }
}
