//! Feature names of a stage (docs/contracts.md, "Feature names").
//!
//! Expanded from the feature layout jax_env exports (`crate::names`, jax_env/features.py), with
//! the stage's joint lists; checkpoint expansion maps tensor rows and columns by these names.

use serde::{Deserialize, Serialize};

use super::Stage;
use crate::names::{names, JointList, Labels};

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
    names().joints.iter().copied().filter(move |j| joints.iter().any(|x| x == j))
}

/// The feature names of a stage.
pub fn feature_names(stage: &Stage) -> FeatureNames {
    joint_feature_names(&stage.controlled_joints, &stage.observed_joints)
}

/// The feature names for the given controlled and observed joints.
pub fn joint_feature_names(controlled: &[String], observed: &[String]) -> FeatureNames {
    let joints = |list: JointList| match list {
        JointList::ControlledJoints => controlled,
        JointList::ObservedJoints => observed,
    };
    let layout = &names().features;
    let mut obs = Vec::new();
    for segment in &layout.obs {
        let prefix = segment.prefix;
        match &segment.labels {
            None => obs.push(prefix.to_owned()),
            Some(Labels::Fixed(labels)) => obs.extend(labels.iter().map(|l| format!("{prefix}/{l}"))),
            Some(Labels::Joints(list)) => obs.extend(canonical(joints(*list)).map(|j| format!("{prefix}/{j}"))),
        }
    }
    FeatureNames {
        obs_names: obs,
        privileged_names: privileged_names(),
        action_names: canonical(joints(layout.action)).map(str::to_owned).collect(),
    }
}

/// The privileged (critic / RMA encoder) inputs: the same in every stage.
pub fn privileged_names() -> Vec<String> {
    names().features.privileged.iter().map(|s| s.to_string()).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    const SAGITTAL_JOINTS: [&str; 10] = [
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
        let controlled: Vec<String> = names()
            .joints
            .iter()
            .filter(|j| SAGITTAL_JOINTS.contains(j) || j.ends_with("_Hip_Roll"))
            .map(|s| s.to_string())
            .collect();
        let observed = strings(&names().joints);
        let f = joint_feature_names(&controlled, &observed);
        assert_eq!(f.obs_names.len(), 6 + 23 + 23 + 12);
        assert_eq!(f.action_names.len(), 12);
        assert_eq!(f.action_names[4], "Left_Hip_Pitch");
        assert_eq!(f.action_names[5], "Left_Hip_Roll");
    }
}
