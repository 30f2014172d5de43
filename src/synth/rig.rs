//! The sensor rig (a KITTI-like calibration) and the vehicle's path along the street.

use nalgebra::{Matrix3, Vector3};

use crate::geometry::{Intrinsics, Pose};
use crate::kitti::Calib;

/// LiDAR height above the ground, as on KITTI's car.
pub const LIDAR_HEIGHT_M: f64 = 1.73;

/// KITTI's full image size and image_2 intrinsics (sequence 00).
pub const KITTI_WIDTH: u32 = 1241;
pub const KITTI_HEIGHT: u32 = 376;
const KITTI_FOCAL: f64 = 718.856;
const KITTI_CX: f64 = 607.1928;
const KITTI_CY: f64 = 185.2157;

/// cam0's centre in the LiDAR frame: 27 cm forward, 8 cm below.
const CAM0_IN_LIDAR: [f64; 3] = [0.27, 0.0, -0.08];
/// image_2's offset from cam0 in cam0's (rectified) frame, as `P2`'s 4th column encodes it:
/// 6 cm to the left (p_cam2 = p_cam0 + t2, so t2.x > 0) and a KITTI-sized small y term. The z
/// term is 0 so that reading P2 as a full projection matrix (K [I | t2]) and the project's
/// convention t2 = (P2[0,3]/fx, P2[1,3]/fy, P2[2,3]) give exactly the same camera.
const CAM2_OFFSET: [f64; 3] = [0.06, -0.00016, 0.0];

/// Intrinsics for an image of `width` × `height`: KITTI's, scaled with the image width (the
/// principal point keeps its relative position; pixels stay square).
pub fn intrinsics_for(width: u32, height: u32) -> Intrinsics {
    let sx = width as f64 / KITTI_WIDTH as f64;
    let sy = height as f64 / KITTI_HEIGHT as f64;
    Intrinsics {
        fx: KITTI_FOCAL * sx,
        fy: KITTI_FOCAL * sx,
        cx: (KITTI_CX + 0.5) * sx - 0.5,
        cy: (KITTI_CY + 0.5) * sy - 0.5,
    }
}

/// velodyne → cam0: an exact axis permutation (cam z = lidar x, cam x = −lidar y,
/// cam y = −lidar z) and cam0 slightly forward of and below the LiDAR.
pub fn velo_to_cam0() -> Pose {
    let r = Matrix3::new(0.0, -1.0, 0.0, 0.0, 0.0, -1.0, 1.0, 0.0, 0.0);
    let c = Vector3::from(CAM0_IN_LIDAR);
    Pose::from_rt(r, -(r * c))
}

/// The calibration file for images of `width` × `height`: P0..P3 as KITTI writes them (P1/P3
/// the stereo partners at −0.54 m and +0.48 m), Tr = `velo_to_cam0`.
pub fn calibration(width: u32, height: u32) -> Calib {
    let k = intrinsics_for(width, height);
    let projection = |t: [f64; 3]| -> [f64; 12] {
        // P = K [I | t]: the 4th column is K t.
        [k.fx, 0.0, k.cx, k.fx * t[0] + k.cx * t[2], 0.0, k.fy, k.cy, k.fy * t[1] + k.cy * t[2], 0.0, 0.0, 1.0, t[2]]
    };
    Calib {
        projections: [
            Some(projection([0.0, 0.0, 0.0])),
            Some(projection([-0.537, 0.0, 0.0])),
            Some(projection(CAM2_OFFSET)),
            Some(projection([-0.4727, 0.0033, 0.0])),
        ],
        velo_to_cam0: velo_to_cam0(),
        r0_rect: None,
    }
}

/// The vehicle's path: along the street's x axis in the right-hand lane, weaving gently
/// (a slow lateral sine) so the heading changes by a few degrees.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct Trajectory {
    pub start_x: f64,
    pub spacing_m: f64,
    pub lane_y: f64,
    pub weave_amplitude_m: f64,
    pub weave_wavelength_m: f64,
    pub weave_phase: f64,
}

impl Trajectory {
    pub fn length_m(&self, frames: usize) -> f64 {
        self.spacing_m * frames.saturating_sub(1) as f64
    }

    /// world_from_lidar at frame `i`: position on the path at LiDAR height, heading along it.
    pub fn world_from_lidar(&self, i: usize) -> Pose {
        let x = self.start_x + self.spacing_m * i as f64;
        let k = std::f64::consts::TAU / self.weave_wavelength_m;
        let y = self.lane_y + self.weave_amplitude_m * (k * x + self.weave_phase).sin();
        let slope = self.weave_amplitude_m * k * (k * x + self.weave_phase).cos();
        let heading = slope.atan();
        Pose::ground_motion(heading, x, y).compose(&Pose::from_rt(Matrix3::identity(), Vector3::new(0.0, 0.0, LIDAR_HEIGHT_M)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Point3;

    #[test]
    fn full_size_matches_kitti_and_cam2_is_left_of_cam0() {
        let k = intrinsics_for(1241, 376);
        assert!((k.fx - 718.856).abs() < 1e-9 && (k.cx - 607.1928).abs() < 1e-9 && (k.cy - 185.2157).abs() < 1e-9);
        let calib = calibration(1241, 376);
        assert!((calib.color_intrinsics().unwrap().fx - 718.856).abs() < 1e-12);
        let cam2 = calib.color_camera_from_lidar().unwrap();
        // image_2's centre in the LiDAR frame: forward 0.27 m, ~8 cm below, 6 cm to the left (+y).
        let centre = cam2.camera_position_in_map();
        assert!((centre.y - 0.06).abs() < 1e-9 && (centre.x - 0.27).abs() < 1e-9, "{centre:?}");
        // A point straight ahead of the LiDAR projects near the principal point.
        let p = cam2.transform(&Point3::new(30.0, 0.06, -0.08));
        let (u, _) = k.project(&p).unwrap();
        assert!((u - k.cx).abs() < 0.1);
    }

    #[test]
    fn full_p2_projection_and_the_convention_agree() {
        let calib = calibration(1241, 376);
        let p2 = calib.projections[2].unwrap();
        let cam2 = calib.color_camera_from_lidar().unwrap();
        let k = calib.color_intrinsics().unwrap();
        for lidar_point in [Point3::new(4.0, 1.0, -1.5), Point3::new(30.0, -6.0, 2.0), Point3::new(70.0, 20.0, -1.7)] {
            let c0 = calib.velo_to_cam0.transform(&lidar_point);
            let h = [
                p2[0] * c0.x + p2[1] * c0.y + p2[2] * c0.z + p2[3],
                p2[4] * c0.x + p2[5] * c0.y + p2[6] * c0.z + p2[7],
                p2[8] * c0.x + p2[9] * c0.y + p2[10] * c0.z + p2[11],
            ];
            let (u, v) = k.project(&cam2.transform(&lidar_point)).unwrap();
            assert!((u - h[0] / h[2]).abs() < 1e-9 && (v - h[1] / h[2]).abs() < 1e-9);
        }
    }
}
