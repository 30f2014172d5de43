//! The agent's discrete action space and the disentangled pose update.
//!
//! The paper's 3-DoF protocol: the unknown error is a yaw about the camera's vertical axis and a
//! ground-plane translation, so the agent acts on three degrees of freedom expressed in the
//! current camera frame: rotation about camera y, translation along camera x and along camera z.
//! Rotation turns the cloud about its own centroid (as seen from the camera), translation is
//! added afterwards; this keeps a rotation from dragging the cloud sideways (DeepIM's
//! disentangled update).

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use super::pose::Pose;

/// The degrees of freedom the agent controls, in the order of the policy's output rows.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Dof {
    /// Rotation about the camera's y axis (right-handed), degrees.
    YawDeg,
    /// Translation along the camera's x axis, metres.
    TxM,
    /// Translation along the camera's z axis, metres.
    TzM,
}

pub const DOFS: [Dof; 3] = [Dof::YawDeg, Dof::TxM, Dof::TzM];

/// Candidate step sizes per degree of freedom, in ascending order (so index `len/2` is zero).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ActionSet {
    pub rotation_deg: Vec<f64>,
    pub translation_m: Vec<f64>,
}

impl Default for ActionSet {
    /// The paper's exponential steps: 0.1°×{0,±1,±5,±25,±125,±625} and 0.1 m×{0,±1,±3,±9,±27,±81}.
    fn default() -> Self {
        let symmetric = |unit: f64, magnitudes: &[f64]| {
            let mut steps: Vec<f64> = magnitudes.iter().rev().map(|m| -m * unit).collect();
            steps.push(0.0);
            steps.extend(magnitudes.iter().map(|m| m * unit));
            steps
        };
        ActionSet {
            rotation_deg: symmetric(0.1, &[1.0, 5.0, 25.0, 125.0, 625.0]),
            translation_m: symmetric(0.1, &[1.0, 3.0, 9.0, 27.0, 81.0]),
        }
    }
}

/// One chosen step per degree of freedom, as indices into the action set and as values.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct AgentAction {
    pub indices: [usize; 3],
    pub yaw_deg: f64,
    pub tx_m: f64,
    pub tz_m: f64,
}

impl AgentAction {
    pub fn is_zero(&self) -> bool {
        self.yaw_deg == 0.0 && self.tx_m == 0.0 && self.tz_m == 0.0
    }
}

impl ActionSet {
    pub fn num_actions(&self) -> usize {
        self.rotation_deg.len()
    }

    /// Checks the layout every consumer relies on: equal odd lengths, ascending, zero in the middle.
    pub fn validate(&self) -> Result<(), String> {
        for (name, steps) in [("rotation_deg", &self.rotation_deg), ("translation_m", &self.translation_m)] {
            if steps.len() % 2 == 0 || steps.len() < 3 {
                return Err(format!("{name} must have an odd number (>= 3) of steps"));
            }
            if steps.windows(2).any(|w| w[0] >= w[1]) || steps[steps.len() / 2] != 0.0 {
                return Err(format!("{name} must be ascending with 0 in the middle"));
            }
        }
        if self.rotation_deg.len() != self.translation_m.len() {
            return Err("rotation and translation sets must have the same length".into());
        }
        Ok(())
    }

    pub fn steps(&self, dof: Dof) -> &[f64] {
        match dof {
            Dof::YawDeg => &self.rotation_deg,
            Dof::TxM => &self.translation_m,
            Dof::TzM => &self.translation_m,
        }
    }

    pub fn action(&self, indices: [usize; 3]) -> AgentAction {
        AgentAction {
            indices,
            yaw_deg: self.rotation_deg[indices[0]],
            tx_m: self.translation_m[indices[1]],
            tz_m: self.translation_m[indices[2]],
        }
    }

    /// The greedy expert: per degree of freedom, the step closest to what would reach `target`
    /// (ties go to the smaller step). `pivot_map` is the cloud centroid in the map frame.
    pub fn expert(&self, current: &Pose, target: &Pose, pivot_map: &Point3<f64>) -> AgentAction {
        let (yaw_deg, tx, tz) = needed_motion(current, target, pivot_map);
        let indices = [
            nearest_step(&self.rotation_deg, yaw_deg),
            nearest_step(&self.translation_m, tx),
            nearest_step(&self.translation_m, tz),
        ];
        self.action(indices)
    }
}

/// The continuous motion (yaw in degrees, camera-x and camera-z translation in metres) that the
/// disentangled update would need to take `current` to `target`, projected onto the three DoF.
pub fn needed_motion(current: &Pose, target: &Pose, pivot_map: &Point3<f64>) -> (f64, f64, f64) {
    let delta_r = target.rotation() * current.rotation().transpose();
    let yaw = delta_r[(0, 2)].atan2(delta_r[(2, 2)]).to_degrees();
    let shift = target.transform(pivot_map) - current.transform(pivot_map);
    (yaw, shift.x, shift.z)
}

/// Index of the step closest to `value`; on a tie the one of smaller magnitude.
pub fn nearest_step(steps: &[f64], value: f64) -> usize {
    let mut best = steps.len() / 2;
    for (i, s) in steps.iter().enumerate() {
        let (d, d_best) = ((s - value).abs(), (steps[best] - value).abs());
        if d < d_best - 1e-12 || ((d - d_best).abs() <= 1e-12 && s.abs() < steps[best].abs()) {
            best = i;
        }
    }
    best
}

/// Applies one step: rotate by `yaw_deg` about camera y through the pivot (the cloud centroid,
/// given in the map frame), then translate by (tx, 0, tz) in the camera frame.
pub fn apply_action(pose: &Pose, pivot_map: &Point3<f64>, action: &AgentAction) -> Pose {
    apply_motion(pose, pivot_map, action.yaw_deg, action.tx_m, action.tz_m)
}

/// `apply_action` for any amounts, not only the action set's (e.g. the starts of a multi-start
/// search, which are the prior turned about the pivot).
pub fn apply_motion(pose: &Pose, pivot_map: &Point3<f64>, yaw_deg: f64, tx_m: f64, tz_m: f64) -> Pose {
    let pivot_cam = pose.transform(pivot_map).coords;
    let turn = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), yaw_deg.to_radians());
    let rotation = turn * pose.0.rotation;
    let translation = turn * (pose.translation() - pivot_cam) + pivot_cam + Vector3::new(tx_m, 0.0, tz_m);
    Pose(Isometry3::from_parts(Translation3::from(translation), rotation))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Matrix3;

    fn rig() -> Pose {
        let r = Matrix3::new(0.0, -1.0, 0.0, 0.0, 0.0, -1.0, 1.0, 0.0, 0.0);
        Pose::from_rt(r, Vector3::new(0.0, -0.08, -0.27))
    }

    #[test]
    fn default_set_matches_the_paper() {
        let set = ActionSet::default();
        set.validate().unwrap();
        assert_eq!(set.num_actions(), 11);
        assert!((set.rotation_deg[10] - 62.5).abs() < 1e-12);
        assert!((set.translation_m[0] + 8.1).abs() < 1e-12);
    }

    #[test]
    fn nearest_step_prefers_smaller_on_ties() {
        let set = ActionSet::default();
        assert_eq!(set.rotation_deg[nearest_step(&set.rotation_deg, 7.5)], 2.5);
        assert_eq!(set.rotation_deg[nearest_step(&set.rotation_deg, -7.5)], -2.5);
        assert_eq!(set.translation_m[nearest_step(&set.translation_m, 100.0)], 8.1);
        assert_eq!(nearest_step(&set.translation_m, 0.0), 5);
    }

    #[test]
    fn rotation_keeps_the_pivot_in_place() {
        let pivot = Point3::new(5.0, 1.0, -1.0);
        let pose = rig();
        let action = AgentAction { indices: [0; 3], yaw_deg: 40.0, tx_m: 0.0, tz_m: 0.0 };
        let moved = apply_action(&pose, &pivot, &action);
        assert!((moved.transform(&pivot) - pose.transform(&pivot)).norm() < 1e-12);
    }

    #[test]
    fn greedy_expert_converges_from_a_large_ground_error() {
        let set = ActionSet::default();
        let pivot = Point3::new(3.0, -2.0, -0.5);
        let target = rig();
        let start = target.compose(&Pose::ground_motion(2.9, 7.3, -9.1));
        let mut pose = start;
        for _ in 0..12 {
            let a = set.expert(&pose, &target, &pivot);
            pose = apply_action(&pose, &pivot, &a);
        }
        let (yaw, tx, tz) = needed_motion(&pose, &target, &pivot);
        assert!(yaw.abs() <= 0.05 + 1e-9, "yaw {yaw}");
        assert!(tx.abs() <= 0.05 + 1e-9 && tz.abs() <= 0.05 + 1e-9, "t {tx} {tz}");
    }
}
