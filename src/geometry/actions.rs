//! The agent's discrete action space and the disentangled pose update.
//!
//! The paper's 3-DoF protocol: the unknown error is a yaw about the vertical axis and a
//! ground-plane translation, so the agent acts on three degrees of freedom: one rotation and two
//! translations. Rotation turns the cloud about its own centroid (the pivot, as seen from the
//! camera), translation is added afterwards; this keeps a rotation from dragging the cloud
//! sideways (DeepIM's disentangled update).
//!
//! Two [`ActionFrame`]s say which axes those three are; a model's manifest names the one it was
//! trained with (`actions.frame`, absent = `camera_y`):
//! - `camera_y` (models up to v3): rotation about the camera's y axis, translation along the
//!   camera's x and z axes. Exact only for a camera whose y axis is the map's vertical.
//! - `map_z`: rotation about the map's z axis (its up axis), translation in the map's xy plane
//!   along the camera's ground heading: `forward` = the optical axis projected onto the map's xy
//!   plane and normalised, `right` = forward × map z (so forward, right and map z are
//!   orthonormal; for a level camera `right` is the camera's x axis). If the optical axis is
//!   within 1e-6 of vertical, forward = map z × (camera x projected onto xy) instead.
//!   Signs are those of `camera_y` for a level camera (y axis = map down), where both frames give
//!   the same motion: a positive yaw turns the camera's heading counter-clockwise about map +z
//!   (seen from above) and its centre about the pivot by the same angle; a positive `tx` / `tz`
//!   moves the map by that many metres along `right` / `forward` relative to the camera (the
//!   camera moves the other way). The camera's pitch and roll relative to the map's up axis
//!   never change, so on any rig the protocol's error (a yaw about map z and a ground shift) is
//!   exactly reachable.
//!
//! In formulas, with camera_from_map = (R, t), pivot p (map frame), yaw θ:
//! - `camera_y`: R' = Ry(θ) R, t' = Ry(θ) (t − c) + c + (tx, 0, tz), c = R p + t;
//! - `map_z`:    R' = R Rz(−θ), t' = t + R (p − Rz(−θ) p) + R (tx·right + tz·forward).
//!
//! `map_z`'s heading vectors seen from the camera (R·right, R·forward) do not change under its
//! own yaw, so it does not matter whether the translation is read before or after the turn.

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use super::pose::Pose;

/// The degrees of freedom the agent controls, in the order of the policy's output rows.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Dof {
    /// Rotation about the frame's vertical axis (camera y, or map down), degrees.
    YawDeg,
    /// Translation along camera x (or the ground heading's `right`), metres.
    TxM,
    /// Translation along camera z (or the ground heading's `forward`), metres.
    TzM,
}

/// Which axes the three degrees of freedom act along (see the module's documentation).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ActionFrame {
    /// Yaw about camera y, translation along camera x and z (every model up to v3).
    #[default]
    CameraY,
    /// Yaw about the map's z axis, translation in the map's ground plane along the camera's heading.
    MapZ,
}

impl ActionFrame {
    pub const ALL: [ActionFrame; 2] = [ActionFrame::CameraY, ActionFrame::MapZ];

    /// The name in manifests, fixtures and flags.
    pub fn as_str(self) -> &'static str {
        match self {
            ActionFrame::CameraY => "camera_y",
            ActionFrame::MapZ => "map_z",
        }
    }

    pub fn parse(name: &str) -> Result<Self, String> {
        Self::ALL.into_iter().find(|f| f.as_str() == name).ok_or_else(|| {
            format!("unknown action frame {name:?}; expected one of \"camera_y\", \"map_z\"")
        })
    }

    pub fn is_camera_y(&self) -> bool {
        *self == ActionFrame::CameraY
    }
}

impl std::fmt::Display for ActionFrame {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for ActionFrame {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        Self::parse(s)
    }
}

pub const DOFS: [Dof; 3] = [Dof::YawDeg, Dof::TxM, Dof::TzM];

/// Candidate step sizes per degree of freedom, in ascending order (so index `len/2` is zero).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ActionSet {
    pub rotation_deg: Vec<f64>,
    pub translation_m: Vec<f64>,
    /// The axes the steps act along; absent in JSON = `camera_y`.
    #[serde(default, skip_serializing_if = "ActionFrame::is_camera_y")]
    pub frame: ActionFrame,
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
            frame: ActionFrame::CameraY,
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
    /// The same steps acting in `frame`.
    pub fn with_frame(self, frame: ActionFrame) -> Self {
        ActionSet { frame, ..self }
    }

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
    /// (ties go to the smaller step), in this set's frame. `pivot_map` is the cloud centroid in
    /// the map frame.
    pub fn expert(&self, current: &Pose, target: &Pose, pivot_map: &Point3<f64>) -> AgentAction {
        let (yaw_deg, tx, tz) = needed_motion(self.frame, current, target, pivot_map);
        let indices = [
            nearest_step(&self.rotation_deg, yaw_deg),
            nearest_step(&self.translation_m, tx),
            nearest_step(&self.translation_m, tz),
        ];
        self.action(indices)
    }

    /// Applies one of this set's actions in this set's frame.
    pub fn apply(&self, pose: &Pose, pivot_map: &Point3<f64>, action: &AgentAction) -> Pose {
        apply_action(self.frame, pose, pivot_map, action)
    }
}

/// The continuous motion (yaw in degrees, the two translations in metres) that the disentangled
/// update in `frame` would need to take `current` to `target`, projected onto the three DoF.
///
/// - `camera_y`: yaw = atan2(ΔR₀₂, ΔR₂₂) of ΔR = R_target R_currentᵀ; translation = the x and z
///   of s = target(p) − current(p) (the pivot as each pose sees it).
/// - `map_z`: yaw = atan2(M₀₁ − M₁₀, M₀₀ + M₁₁) of M = R_currentᵀ R_target (the turn about map z
///   closest to M; exact when the two poses differ by such a turn); translation = s · R·right and
///   s · R·forward of the current pose's ground heading (the vertical part of s is out of reach
///   and is dropped; it is zero when the poses differ by a ground motion).
pub fn needed_motion(frame: ActionFrame, current: &Pose, target: &Pose, pivot_map: &Point3<f64>) -> (f64, f64, f64) {
    let shift = target.transform(pivot_map) - current.transform(pivot_map);
    match frame {
        ActionFrame::CameraY => {
            let delta_r = target.rotation() * current.rotation().transpose();
            let yaw = delta_r[(0, 2)].atan2(delta_r[(2, 2)]).to_degrees();
            (yaw, shift.x, shift.z)
        }
        ActionFrame::MapZ => {
            let r = current.rotation();
            let m = r.transpose() * target.rotation();
            let yaw = (m[(0, 1)] - m[(1, 0)]).atan2(m[(0, 0)] + m[(1, 1)]).to_degrees();
            let (right, forward) = ground_heading(current);
            (yaw, (r * right).dot(&shift), (r * forward).dot(&shift))
        }
    }
}

/// The camera's ground heading in the map frame: (`right`, `forward`), unit vectors in the map's
/// xy plane with right = forward × z (see the module's documentation for the definition).
pub fn ground_heading(pose: &Pose) -> (Vector3<f64>, Vector3<f64>) {
    let r = pose.rotation();
    // Rows of R are the camera's axes expressed in the map frame.
    let mut forward = Vector3::new(r[(2, 0)], r[(2, 1)], 0.0);
    if forward.norm() < 1e-6 {
        let right = Vector3::new(r[(0, 0)], r[(0, 1)], 0.0);
        forward = Vector3::z().cross(&right);
    }
    let forward = forward.normalize();
    (forward.cross(&Vector3::z()), forward)
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

/// Applies one step in `frame`: rotate by `yaw_deg` about the frame's vertical axis through the
/// pivot (the cloud centroid, given in the map frame), then translate by `tx_m` / `tz_m`.
pub fn apply_action(frame: ActionFrame, pose: &Pose, pivot_map: &Point3<f64>, action: &AgentAction) -> Pose {
    apply_motion(frame, pose, pivot_map, action.yaw_deg, action.tx_m, action.tz_m)
}

/// `apply_action` for any amounts, not only the action set's (e.g. the starts of a multi-start
/// search, which are the prior turned about the pivot).
pub fn apply_motion(frame: ActionFrame, pose: &Pose, pivot_map: &Point3<f64>, yaw_deg: f64, tx_m: f64, tz_m: f64) -> Pose {
    match frame {
        ActionFrame::CameraY => {
            let pivot_cam = pose.transform(pivot_map).coords;
            let turn = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), yaw_deg.to_radians());
            let rotation = turn * pose.0.rotation;
            let translation = turn * (pose.translation() - pivot_cam) + pivot_cam + Vector3::new(tx_m, 0.0, tz_m);
            Pose(Isometry3::from_parts(Translation3::from(translation), rotation))
        }
        ActionFrame::MapZ => {
            // Turning the camera by +θ about map z is turning the map by −θ under it.
            let turn = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), -yaw_deg.to_radians());
            let (right, forward) = ground_heading(pose);
            let r = pose.0.rotation;
            let p = pivot_map.coords;
            let translation = pose.translation() + r * (p - turn * p) + r * (right * tx_m + forward * tz_m);
            Pose(Isometry3::from_parts(Translation3::from(translation), r * turn))
        }
    }
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
        let moved = apply_action(ActionFrame::CameraY, &pose, &pivot, &action);
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
            pose = set.apply(&pose, &pivot, &a);
        }
        let (yaw, tx, tz) = needed_motion(ActionFrame::CameraY, &pose, &target, &pivot);
        assert!(yaw.abs() <= 0.05 + 1e-9, "yaw {yaw}");
        assert!(tx.abs() <= 0.05 + 1e-9 && tz.abs() <= 0.05 + 1e-9, "t {tx} {tz}");
    }

    /// A rig pitched down by `pitch_deg` and rolled by `roll_deg` relative to the map's up axis
    /// (a tilt in the camera frame applied to the level rig).
    fn tilted_rig(pitch_deg: f64, roll_deg: f64) -> Pose {
        let tilt = nalgebra::Rotation3::from_euler_angles(pitch_deg.to_radians(), 0.0, roll_deg.to_radians()).into_inner();
        Pose::from_rt(tilt, Vector3::zeros()).compose(&rig())
    }

    fn close(a: &Pose, b: &Pose, tol: f64) -> bool {
        (a.matrix() - b.matrix()).abs().max() < tol
    }

    #[test]
    fn map_z_is_camera_y_for_a_level_camera() {
        let pivot = Point3::new(4.0, -3.0, 0.7);
        for (yaw_rad, dx, dy) in [(0.0, 0.0, 0.0), (1.3, 4.0, -2.0), (-2.9, -7.5, 9.0)] {
            let pose = rig().compose(&Pose::ground_motion(yaw_rad, dx, dy));
            for (yaw, tx, tz) in [(62.5, 0.0, 0.0), (-0.1, 2.7, -8.1), (12.5, -0.3, 0.9), (-179.0, 8.1, 8.1)] {
                let a = apply_motion(ActionFrame::CameraY, &pose, &pivot, yaw, tx, tz);
                let b = apply_motion(ActionFrame::MapZ, &pose, &pivot, yaw, tx, tz);
                assert!(close(&a, &b, 1e-12), "{yaw} {tx} {tz}\n{a:?}\n{b:?}");
            }
            let target = rig().compose(&Pose::ground_motion(0.4, 1.0, 2.0));
            let (a, b) = (needed_motion(ActionFrame::CameraY, &pose, &target, &pivot), needed_motion(ActionFrame::MapZ, &pose, &target, &pivot));
            assert!((a.0 - b.0).abs() < 1e-9 && (a.1 - b.1).abs() < 1e-9 && (a.2 - b.2).abs() < 1e-9, "{a:?} {b:?}");
        }
    }

    #[test]
    fn map_z_turns_about_the_map_vertical_and_keeps_the_tilt() {
        let pivot = Point3::new(5.0, 1.0, -1.0);
        let pose = tilted_rig(7.0, -4.0).compose(&Pose::ground_motion(0.3, 2.0, -1.0));
        let moved = apply_motion(ActionFrame::MapZ, &pose, &pivot, 40.0, 0.0, 0.0);
        // The pivot stays where the camera sees it; the map's up axis too (no pitch or roll change).
        assert!((moved.transform(&pivot) - pose.transform(&pivot)).norm() < 1e-12);
        assert!((moved.rotation() * Vector3::z() - pose.rotation() * Vector3::z()).norm() < 1e-12);
        // The heading turns counter-clockwise about map +z by the yaw.
        let turned = moved.camera_heading_in_map_deg() - pose.camera_heading_in_map_deg();
        assert!((turned - 40.0).abs() < 1e-9, "{turned}");
        // Translations move the camera in the ground plane, against right / forward.
        let (right, forward) = ground_heading(&pose);
        let shifted = apply_motion(ActionFrame::MapZ, &pose, &pivot, 0.0, 1.5, -2.0);
        let moved_by = shifted.camera_position_in_map() - pose.camera_position_in_map();
        assert!((moved_by - (-1.5 * right + 2.0 * forward)).norm() < 1e-12, "{moved_by:?}");
        // The same pose change is a ground motion of the map: camera_from_map · G.
        let g = pose.inverse().compose(&apply_motion(ActionFrame::MapZ, &pose, &pivot, -33.0, 0.9, 2.7));
        assert!((g.rotation() * Vector3::z() - Vector3::z()).norm() < 1e-12 && g.translation().z.abs() < 1e-12);
    }

    #[test]
    fn ground_heading_is_orthonormal_and_handles_a_vertical_optical_axis() {
        for pose in [rig(), tilted_rig(20.0, 15.0), tilted_rig(-89.9999999, 0.0), tilted_rig(90.0, 0.0)] {
            let (right, forward) = ground_heading(&pose);
            assert!(right.z == 0.0 && forward.z == 0.0);
            assert!((right.norm() - 1.0).abs() < 1e-12 && (forward.norm() - 1.0).abs() < 1e-12 && right.dot(&forward).abs() < 1e-12);
            // `right` leans towards the camera's x axis.
            assert!(right.dot(&(pose.rotation().transpose() * Vector3::x())) > 0.0);
        }
        let (right, forward) = ground_heading(&rig());
        assert!((right - Vector3::new(0.0, -1.0, 0.0)).norm() < 1e-15 && (forward - Vector3::x()).norm() < 1e-15);
    }

    #[test]
    fn map_z_expert_reaches_the_truth_on_a_pitched_and_rolled_rig() {
        let pivot = Point3::new(3.0, -2.0, -0.5);
        let target = tilted_rig(6.0, -9.0);
        let start = target.compose(&Pose::ground_motion(2.9, 7.3, -9.1));
        let run = |frame: ActionFrame| {
            let set = ActionSet::default().with_frame(frame);
            let mut pose = start;
            for _ in 0..12 {
                pose = set.apply(&pose, &pivot, &set.expert(&pose, &target, &pivot));
            }
            crate::geometry::PoseError::between(&pose, &target)
        };
        let e = run(ActionFrame::MapZ);
        assert!(e.rre_geodesic_deg < 0.06 && e.rte_m < 0.08, "{e:?}");
        // The camera-frame expert cannot undo a yaw about map z on this rig.
        let e = run(ActionFrame::CameraY);
        assert!(e.rre_geodesic_deg > 0.5, "{e:?}");
    }

    #[test]
    fn frame_names_round_trip_and_default_to_camera_y() {
        for f in ActionFrame::ALL {
            assert_eq!(ActionFrame::parse(f.as_str()).unwrap(), f);
            assert_eq!(serde_json::to_value(f).unwrap(), serde_json::json!(f.as_str()));
        }
        assert!(ActionFrame::parse("camera_z").is_err());
        let json = serde_json::to_value(ActionSet::default()).unwrap();
        assert!(json.get("frame").is_none());
        let back: ActionSet = serde_json::from_value(json).unwrap();
        assert_eq!(back.frame, ActionFrame::CameraY);
        let map_z: ActionSet = serde_json::from_value(serde_json::to_value(ActionSet::default().with_frame(ActionFrame::MapZ)).unwrap()).unwrap();
        assert_eq!(map_z.frame, ActionFrame::MapZ);
    }
}
