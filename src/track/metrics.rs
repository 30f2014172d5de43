//! Errors of a tracked trajectory against the truth, TUM-benchmark style (Sturm et al. 2012),
//! without any alignment: the map frame is known, so an offset of the whole trajectory is an
//! error too.
//!
//! - ATE: RMSE over frames of ‖c_est − c_gt‖, the camera centres in the map frame (metres).
//! - RPE of frame k ≥ 1: E = Δ_gtᵀ·Δ_est with Δ = P_{k−1}⁻¹·P_k the camera's motion since the
//!   previous frame (P = map_from_camera); its translation norm (metres) and rotation angle
//!   (geodesic, degrees). Frame 0 has none.
//!
//! Poses in and out are camera_from_map; per-frame RTE/RRE are `geometry::PoseError`'s.

use serde::Serialize;

use crate::geometry::{Pose, PoseError};

/// One frame's errors.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct FrameError {
    /// ‖c_est − c_gt‖, camera centres in the map frame, metres.
    pub position_m: f64,
    /// Heading difference in the map's ground plane, degrees in (−180, 180].
    pub heading_deg: f64,
    /// The paper's RTE / RRE of camera_from_map.
    pub pose: PoseError,
    /// Relative pose error against the previous frame (None for the first).
    pub rpe_translation_m: Option<f64>,
    pub rpe_rotation_deg: Option<f64>,
}

/// Errors of the whole trajectory.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct TrajectoryError {
    pub frames: usize,
    /// RMSE of the position errors, metres.
    pub ate_rmse_m: f64,
    pub ate_mean_m: f64,
    pub ate_max_m: f64,
    /// RMSE / mean of the RPE translations, metres per frame.
    pub rpe_translation_rmse_m: f64,
    pub rpe_translation_mean_m: f64,
    /// RMSE / mean of the RPE rotations, degrees per frame.
    pub rpe_rotation_rmse_deg: f64,
    pub rpe_rotation_mean_deg: f64,
    /// Frames registered under the paper's thresholds (RRE < 10°, RTE < 5 m), fraction.
    pub registration_recall: f64,
}

/// Per-frame errors of `estimates` against `truth` (both camera_from_map, same length).
pub fn frame_errors(estimates: &[Pose], truth: &[Pose]) -> Vec<FrameError> {
    assert_eq!(estimates.len(), truth.len(), "one estimate per true pose");
    (0..estimates.len())
        .map(|k| {
            let (est, gt) = (&estimates[k], &truth[k]);
            let position_m = (est.camera_position_in_map() - gt.camera_position_in_map()).norm();
            let heading_deg = wrap_deg(est.camera_heading_in_map_deg() - gt.camera_heading_in_map_deg());
            let (rpe_translation_m, rpe_rotation_deg) = if k == 0 {
                (None, None)
            } else {
                let motion = |a: &Pose, b: &Pose| a.compose(&b.inverse()); // P_a⁻¹·P_b with P = T⁻¹
                let e = motion(&truth[k - 1], gt).inverse().compose(&motion(&estimates[k - 1], est));
                (Some(e.translation().norm()), Some(PoseError::between(&e, &Pose::identity()).rre_geodesic_deg))
            };
            FrameError { position_m, heading_deg, pose: PoseError::between(est, gt), rpe_translation_m, rpe_rotation_deg }
        })
        .collect()
}

/// The trajectory's summary of [`frame_errors`].
pub fn trajectory_error(errors: &[FrameError]) -> TrajectoryError {
    let rmse = |v: &[f64]| if v.is_empty() { 0.0 } else { (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt() };
    let mean = |v: &[f64]| if v.is_empty() { 0.0 } else { v.iter().sum::<f64>() / v.len() as f64 };
    let positions: Vec<f64> = errors.iter().map(|e| e.position_m).collect();
    let rpe_t: Vec<f64> = errors.iter().filter_map(|e| e.rpe_translation_m).collect();
    let rpe_r: Vec<f64> = errors.iter().filter_map(|e| e.rpe_rotation_deg).collect();
    let registered = errors.iter().filter(|e| e.pose.is_registered()).count();
    TrajectoryError {
        frames: errors.len(),
        ate_rmse_m: rmse(&positions),
        ate_mean_m: mean(&positions),
        ate_max_m: positions.iter().copied().fold(0.0, f64::max),
        rpe_translation_rmse_m: rmse(&rpe_t),
        rpe_translation_mean_m: mean(&rpe_t),
        rpe_rotation_rmse_deg: rmse(&rpe_r),
        rpe_rotation_mean_deg: mean(&rpe_r),
        registration_recall: if errors.is_empty() { 0.0 } else { registered as f64 / errors.len() as f64 },
    }
}

fn wrap_deg(d: f64) -> f64 {
    let w = d.rem_euclid(360.0);
    if w > 180.0 { w - 360.0 } else { w }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Matrix3, Vector3};

    fn camera_at(x: f64, y: f64, yaw_deg: f64) -> Pose {
        let rig = Pose::from_rt(Matrix3::new(0.0, -1.0, 0.0, 0.0, 0.0, -1.0, 1.0, 0.0, 0.0), Vector3::zeros());
        rig.compose(&Pose::ground_motion(yaw_deg.to_radians(), x, y).inverse())
    }

    #[test]
    fn a_constant_offset_is_ate_but_not_rpe() {
        let truth: Vec<Pose> = (0..5).map(|i| camera_at(i as f64, 0.0, 0.0)).collect();
        let shifted: Vec<Pose> = (0..5).map(|i| camera_at(i as f64, 0.3, 0.0)).collect();
        let e = trajectory_error(&frame_errors(&shifted, &truth));
        assert!((e.ate_rmse_m - 0.3).abs() < 1e-12 && e.rpe_translation_rmse_m < 1e-12, "{e:?}");
        assert_eq!(e.registration_recall, 1.0);
        // One frame 1 m off: ATE = sqrt(1/5); RPE sees the jump there and back (1 m twice of 4).
        let mut one_off = truth.clone();
        one_off[2] = camera_at(2.0, 1.0, 0.0);
        let errors = frame_errors(&one_off, &truth);
        let e = trajectory_error(&errors);
        assert!((e.ate_rmse_m - (0.2f64).sqrt()).abs() < 1e-12, "{e:?}");
        assert!((errors[2].rpe_translation_m.unwrap() - 1.0).abs() < 1e-12 && (errors[3].rpe_translation_m.unwrap() - 1.0).abs() < 1e-12);
        assert!((e.rpe_translation_mean_m - 0.5).abs() < 1e-12);
        assert!(errors[0].rpe_translation_m.is_none());
        // A heading error of 3° at one frame.
        let mut turned = truth.clone();
        turned[4] = camera_at(4.0, 0.0, 3.0);
        let errors = frame_errors(&turned, &truth);
        assert!((errors[4].heading_deg - 3.0).abs() < 1e-9 && (errors[4].rpe_rotation_deg.unwrap() - 3.0).abs() < 1e-9);
        assert!(errors[4].position_m < 1e-12);
    }
}
