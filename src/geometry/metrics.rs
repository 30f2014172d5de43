//! Registration errors (the paper's RTE / RRE / RR) and the agent's point-to-point reward.

use nalgebra::{Matrix3, Point3};
use serde::{Deserialize, Serialize};

use super::pose::Pose;

/// The paper's success thresholds for registration recall (RR).
pub const RR_MAX_ROTATION_DEG: f64 = 10.0;
pub const RR_MAX_TRANSLATION_M: f64 = 5.0;

/// The paper's step rewards (ε−, ε0, ε+).
pub const REWARD_WORSE: f64 = -0.5;
pub const REWARD_SAME: f64 = 0.0;
pub const REWARD_BETTER: f64 = 0.5;

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PoseError {
    /// ‖t_est − t_gt‖ of the camera_from_map translations, metres.
    pub rte_m: f64,
    /// Sum of the absolute Euler angles (z-y-x) of R_estᵀ R_gt, degrees (the paper's RRE).
    pub rre_euler_deg: f64,
    /// Geodesic angle of R_estᵀ R_gt, degrees.
    pub rre_geodesic_deg: f64,
}

impl PoseError {
    pub fn between(estimate: &Pose, truth: &Pose) -> Self {
        let delta = estimate.rotation().transpose() * truth.rotation();
        let (roll, pitch, yaw) = euler_zyx(&delta);
        let cos = ((delta.trace() - 1.0) / 2.0).clamp(-1.0, 1.0);
        PoseError {
            rte_m: (estimate.translation() - truth.translation()).norm(),
            rre_euler_deg: (roll.abs() + pitch.abs() + yaw.abs()).to_degrees(),
            rre_geodesic_deg: cos.acos().to_degrees(),
        }
    }

    /// Success under the paper's protocol (RRE < 10°, RTE < 5 m), RRE as the Euler sum.
    pub fn is_registered(&self) -> bool {
        self.within(RR_MAX_ROTATION_DEG, RR_MAX_TRANSLATION_M)
    }

    pub fn within(&self, max_rotation_deg: f64, max_translation_m: f64) -> bool {
        self.rre_euler_deg < max_rotation_deg && self.rte_m < max_translation_m
    }
}

/// Euler angles (roll about x, pitch about y, yaw about z) with R = Rz(yaw) Ry(pitch) Rx(roll).
pub fn euler_zyx(r: &Matrix3<f64>) -> (f64, f64, f64) {
    let pitch = (-r[(2, 0)]).clamp(-1.0, 1.0).asin();
    if r[(2, 0)].abs() < 1.0 - 1e-9 {
        (r[(2, 1)].atan2(r[(2, 2)]), pitch, r[(1, 0)].atan2(r[(0, 0)]))
    } else {
        // Gimbal lock: put the whole remaining rotation into yaw.
        (0.0, pitch, (-r[(0, 1)]).atan2(r[(1, 1)]))
    }
}

/// Mean distance between the points placed by the true pose and by the current pose: the
/// paper's D_p2p, where back-projecting the true pixels at their true depth gives T_gt p.
/// `points_map` are the points inside the true frustum.
pub fn p2p_distance(current: &Pose, truth: &Pose, points_map: &[Point3<f64>]) -> f64 {
    if points_map.is_empty() {
        return 0.0;
    }
    let total: f64 = points_map.iter().map(|p| (truth.transform(p) - current.transform(p)).norm()).sum();
    total / points_map.len() as f64
}

/// The step reward: ε+ when the distance shrank, ε− when it grew, ε0 when it stayed.
pub fn step_reward(distance_before: f64, distance_after: f64) -> f64 {
    const SAME: f64 = 1e-9;
    if distance_after < distance_before - SAME {
        REWARD_BETTER
    } else if distance_after > distance_before + SAME {
        REWARD_WORSE
    } else {
        REWARD_SAME
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Rotation3;

    #[test]
    fn euler_round_trip() {
        let r = Rotation3::from_euler_angles(0.1, -0.3, 2.0).into_inner();
        let (roll, pitch, yaw) = euler_zyx(&r);
        assert!((roll - 0.1).abs() < 1e-12 && (pitch + 0.3).abs() < 1e-12 && (yaw - 2.0).abs() < 1e-12);
    }

    #[test]
    fn pure_yaw_error_reads_the_same_in_both_conventions() {
        let truth = Pose::identity();
        let est = Pose::ground_motion(7f64.to_radians(), 3.0, 4.0);
        let e = PoseError::between(&est, &truth);
        assert!((e.rte_m - 5.0).abs() < 1e-12);
        assert!((e.rre_euler_deg - 7.0).abs() < 1e-9);
        assert!((e.rre_geodesic_deg - 7.0).abs() < 1e-9);
        assert!(!e.is_registered());
    }

    #[test]
    fn reward_signs() {
        assert_eq!(step_reward(2.0, 1.0), REWARD_BETTER);
        assert_eq!(step_reward(1.0, 2.0), REWARD_WORSE);
        assert_eq!(step_reward(1.0, 1.0), REWARD_SAME);
    }
}
