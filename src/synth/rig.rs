//! A sensor rig: the camera (image size, intrinsics, where it sits and how it is tilted relative
//! to the LiDAR), the LiDAR (mounting height, beams, sampling, noise), and the KITTI calibration
//! file that describes it, so every reader of `calib.txt` works unchanged.
//!
//! Frames: LiDAR x forward, y left, z up; cameras OpenCV (x right, y down, z forward).

use nalgebra::{Matrix3, Rotation3, Vector3};
use serde::{Deserialize, Serialize};

use super::lidar::LidarConfig;
use crate::geometry::{Intrinsics, Pose};
use crate::kitti::Calib;

/// KITTI's full image size (sequence 00's image_2).
pub const KITTI_WIDTH: u32 = 1241;
pub const KITTI_HEIGHT: u32 = 376;

/// One rig. Lengths in metres, angles in degrees, intrinsics in pixels at `width` × `height`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Rig {
    pub name: String,
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    /// Principal point; pixel centres are at integer coordinates.
    pub cx: f64,
    pub cy: f64,
    /// cam0's centre in the LiDAR frame.
    pub camera_in_lidar_m: [f64; 3],
    /// Camera tilt relative to a level camera looking along the LiDAR's x axis: pitch about the
    /// camera's x axis (positive = looking down), roll about its z axis (positive = image turns
    /// clockwise), yaw about its y axis (positive = looking right).
    pub camera_pitch_deg: f64,
    pub camera_roll_deg: f64,
    pub camera_yaw_deg: f64,
    /// image_2's offset from cam0 in cam0's frame (p_cam2 = p_cam0 + t2), written as P2's 4th
    /// column `K t2`.
    pub color_offset_m: [f64; 3],
    /// P1's and P3's offsets from cam0 (stereo partners, written for completeness).
    pub partner_offsets_m: [[f64; 3]; 2],
    /// LiDAR origin above the road surface under the vehicle.
    pub lidar_height_m: f64,
    pub lidar: LidarConfig,
}

impl Rig {
    /// image_2's intrinsics.
    pub fn intrinsics(&self) -> Intrinsics {
        Intrinsics { fx: self.fx, fy: self.fy, cx: self.cx, cy: self.cy }
    }

    /// The same rig with another image size: focal lengths scale with the width (pixels stay
    /// as square as they were), the principal point keeps its relative position.
    pub fn with_image_size(mut self, width: u32, height: u32) -> Rig {
        if (width, height) == (self.width, self.height) {
            return self;
        }
        let sx = width as f64 / self.width as f64;
        let sy = height as f64 / self.height as f64;
        self.fx *= sx;
        self.fy *= sx;
        self.cx = (self.cx + 0.5) * sx - 0.5;
        self.cy = (self.cy + 0.5) * sy - 0.5;
        (self.width, self.height) = (width, height);
        self
    }

    /// The same rig with `beams` evenly spaced between its top and bottom beams.
    pub fn with_beams(mut self, beams: u32) -> Rig {
        if beams != self.lidar.beams || self.lidar.elevations_deg.is_some() {
            self.lidar.beams = beams;
            self.lidar.elevations_deg = None;
        }
        self
    }

    pub fn validate(&self) -> Result<(), String> {
        if self.width < 16 || self.height < 16 || self.width > 8192 || self.height > 8192 {
            return Err(format!("image size {}x{} out of range (16..=8192 per side)", self.width, self.height));
        }
        self.intrinsics().validate()?;
        if !(0.3..=5.0).contains(&self.lidar_height_m) {
            return Err(format!("LiDAR height {} m out of range (0.3..=5)", self.lidar_height_m));
        }
        if [self.camera_pitch_deg, self.camera_roll_deg, self.camera_yaw_deg].iter().any(|a| a.abs() > 30.0) {
            return Err("camera tilt angles must be within ±30°".into());
        }
        self.lidar.validate()
    }

    /// velodyne → cam0: the axis permutation (cam z = lidar x, cam x = −lidar y, cam y = −lidar
    /// z), then the camera's tilt, with cam0 at `camera_in_lidar_m`.
    pub fn velo_to_cam0(&self) -> Pose {
        let permutation = Matrix3::new(0.0, -1.0, 0.0, 0.0, 0.0, -1.0, 1.0, 0.0, 0.0);
        let (p, r, y) = (self.camera_pitch_deg, self.camera_roll_deg, self.camera_yaw_deg);
        // A level camera's rotation is exactly the permutation (no rounding in Tr).
        let rotation = if p == 0.0 && r == 0.0 && y == 0.0 {
            permutation
        } else {
            let tilt = Rotation3::from_axis_angle(&Vector3::z_axis(), r.to_radians())
                * Rotation3::from_axis_angle(&Vector3::x_axis(), p.to_radians())
                * Rotation3::from_axis_angle(&Vector3::y_axis(), y.to_radians());
            tilt.matrix() * permutation
        };
        let c = Vector3::from(self.camera_in_lidar_m);
        Pose::from_rt(rotation, -(rotation * c))
    }

    /// The calibration file: P0..P3 = K [I | t] with each camera's offset t from cam0, and Tr.
    pub fn calibration(&self) -> Calib {
        let k = self.intrinsics();
        let projection = |t: [f64; 3]| -> [f64; 12] {
            // P = K [I | t]: the 4th column is K t.
            [k.fx, 0.0, k.cx, k.fx * t[0] + k.cx * t[2], 0.0, k.fy, k.cy, k.fy * t[1] + k.cy * t[2], 0.0, 0.0, 1.0, t[2]]
        };
        Calib {
            projections: [
                Some(projection([0.0, 0.0, 0.0])),
                Some(projection(self.partner_offsets_m[0])),
                Some(projection(self.color_offset_m)),
                Some(projection(self.partner_offsets_m[1])),
            ],
            velo_to_cam0: self.velo_to_cam0(),
            r0_rect: None,
        }
    }

    /// One line for `--list-rigs`.
    pub fn describe(&self) -> String {
        let e = self.lidar.elevations();
        let spacing: Vec<f32> = e.windows(2).map(|w| w[0] - w[1]).collect();
        let (lo, hi) = spacing.iter().fold((f32::INFINITY, 0f32), |(lo, hi), s| (lo.min(*s), hi.max(*s)));
        let c = self.camera_in_lidar_m;
        format!(
            "{:<9} camera {}x{} fx {:.1} fy {:.1} cx {:.1} cy {:.1} (hfov {:.0}°), {:.2} m above ground, {:+.2}/{:+.2}/{:+.2} m from the LiDAR, \
             pitch {:+.1}° roll {:+.1}° yaw {:+.1}°\n          LiDAR {:.2} m above ground, {} beams {:+.1}°..{:+.1}° (spacing {:.2}°..{:.2}°), \
             {} columns ({:.3}°), range {}–{} m, noise σ {:.3} m, dropout {:.0} %",
            self.name,
            self.width,
            self.height,
            self.fx,
            self.fy,
            self.cx,
            self.cy,
            2.0 * (self.width as f64 / 2.0 / self.fx).atan().to_degrees(),
            self.lidar_height_m + c[2],
            c[0],
            c[1],
            c[2],
            self.camera_pitch_deg,
            self.camera_roll_deg,
            self.camera_yaw_deg,
            self.lidar_height_m,
            self.lidar.beams,
            e.first().unwrap_or(&0.0),
            e.last().unwrap_or(&0.0),
            if lo.is_finite() { lo } else { 0.0 },
            hi,
            self.lidar.columns,
            360.0 / self.lidar.columns as f64,
            self.lidar.min_range_m,
            self.lidar.max_range_m,
            self.lidar.range_noise_m,
            self.lidar.dropout * 100.0,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::super::rigs::{named, RIG_NAMES};
    use nalgebra::Point3;

    #[test]
    fn kitti_matches_kitti_and_cam2_is_left_of_cam0() {
        let rig = named("kitti").unwrap();
        let k = rig.intrinsics();
        assert!((k.fx - 718.856).abs() < 1e-9 && (k.cx - 607.1928).abs() < 1e-9 && (k.cy - 185.2157).abs() < 1e-9);
        let calib = rig.calibration();
        assert!((calib.color_intrinsics().unwrap().fx - 718.856).abs() < 1e-12);
        let cam2 = calib.color_camera_from_lidar().unwrap();
        // image_2's centre in the LiDAR frame: forward 0.27 m, ~8 cm below, 6 cm to the left (+y).
        let centre = cam2.camera_position_in_map();
        assert!((centre.y - 0.06).abs() < 1e-9 && (centre.x - 0.27).abs() < 1e-9, "{centre:?}");
        // A point straight ahead of the LiDAR projects near the principal point.
        let p = cam2.transform(&Point3::new(30.0, 0.06, -0.08));
        let (u, _) = k.project(&p).unwrap();
        assert!((u - k.cx).abs() < 0.1);
        // Half size: intrinsics follow the width.
        let half = rig.with_image_size(620, 188).intrinsics();
        assert!((half.fx - 718.856 * 620.0 / 1241.0).abs() < 1e-9 && (half.cy - ((185.2157 + 0.5) * 0.5 - 0.5)).abs() < 1e-9);
    }

    #[test]
    fn full_p2_projection_and_the_convention_agree_for_every_rig() {
        for name in RIG_NAMES {
            let calib = named(name).unwrap().calibration();
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
                assert!((u - h[0] / h[2]).abs() < 1e-9 && (v - h[1] / h[2]).abs() < 1e-9, "{name}");
            }
        }
    }

    #[test]
    fn a_camera_pitched_down_sees_the_horizon_above_the_image_centre() {
        let mut rig = named("kitti").unwrap();
        rig.camera_pitch_deg = 3.0;
        let cam = rig.calibration().color_camera_from_lidar().unwrap();
        let (_, v) = rig.intrinsics().project(&cam.transform(&Point3::new(1000.0, 0.0, 0.0))).unwrap();
        let expected = rig.cy - rig.fy * 3f64.to_radians().tan();
        assert!((v - expected).abs() < 0.5, "{v} vs {expected}");
    }
}
