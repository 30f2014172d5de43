//! A map region's local frame: the region keeps an origin in the map frame (float64, metres) and
//! stores its points relative to it, so float32 coordinates keep sub-millimetre steps at
//! UTM-size coordinates (a point 5,400,000 m north of the map frame's origin would be rounded to
//! 0.5 m as a float32). The local frame is the map frame moved by `origin`; the axes are the
//! same: p_map = p_local + origin.
//!
//! Requests and responses stay in the map frame (camera_from_map, f64); the agent, the cached
//! points and the embeddings work in the local frame. [`LocalFrame`] converts both ways, and is
//! the only place that does.

use nalgebra::{Isometry3, Translation3, Vector3};

use super::pose::{MAX_COORDINATE_M, Pose};

/// An automatic origin is the cloud's bounding-box centre rounded to a multiple of this (metres):
/// a region near the map frame's origin keeps origin (0, 0, 0) and its points exactly as given.
pub const ORIGIN_GRID_M: f64 = 1000.0;

/// The local frame of one region: p_map = p_local + origin.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct LocalFrame {
    /// Map-frame coordinates of the local frame's origin, metres.
    pub origin: Vector3<f64>,
}

impl LocalFrame {
    /// A frame at `origin` (map frame, metres). Errors: a non-finite component, or one beyond
    /// ±[`MAX_COORDINATE_M`].
    pub fn new(origin: [f64; 3]) -> Result<Self, String> {
        if origin.iter().any(|v| !v.is_finite()) {
            return Err(format!("origin {origin:?} is not finite"));
        }
        if origin.iter().any(|v| v.abs() > MAX_COORDINATE_M) {
            return Err(format!("origin {origin:?} is beyond ±{MAX_COORDINATE_M:e} m"));
        }
        Ok(Self { origin: Vector3::from(origin) })
    }

    /// The automatic origin of a cloud spanning `min..max` (map frame): the box's centre rounded
    /// to a multiple of [`ORIGIN_GRID_M`] per axis.
    pub fn centred_on(min: [f64; 3], max: [f64; 3]) -> Self {
        let c = |i: usize| ((min[i] + max[i]) / 2.0 / ORIGIN_GRID_M).round() * ORIGIN_GRID_M + 0.0;
        Self { origin: Vector3::new(c(0), c(1), c(2)) }
    }

    pub fn origin(&self) -> [f64; 3] {
        [self.origin.x, self.origin.y, self.origin.z]
    }

    pub fn is_identity(&self) -> bool {
        self.origin == Vector3::zeros()
    }

    /// camera_from_local of a camera_from_map: t_local = t + R·origin.
    pub fn camera_from_local(&self, camera_from_map: &Pose) -> Pose {
        Pose(camera_from_map.0 * Isometry3::from_parts(Translation3::from(self.origin), Default::default()))
    }

    /// camera_from_map of a camera_from_local: t = t_local − R·origin.
    pub fn camera_from_map(&self, camera_from_local: &Pose) -> Pose {
        Pose(camera_from_local.0 * Isometry3::from_parts(Translation3::from(-self.origin), Default::default()))
    }

    /// A map-frame point in the local frame, as stored (float32).
    pub fn point_to_local(&self, p: [f64; 3]) -> [f32; 3] {
        [(p[0] - self.origin.x) as f32, (p[1] - self.origin.y) as f32, (p[2] - self.origin.z) as f32]
    }

    /// A stored (local) point in the map frame.
    pub fn point_to_map(&self, p: [f32; 3]) -> [f64; 3] {
        [p[0] as f64 + self.origin.x, p[1] as f64 + self.origin.y, p[2] as f64 + self.origin.z]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Point3, Rotation3};

    #[test]
    fn poses_round_trip_and_project_the_same_points() {
        let frame = LocalFrame::new([500_000.0, 5_400_000.0, 100.0]).unwrap();
        let r = Rotation3::from_euler_angles(0.02, -0.01, 1.2).into_inner();
        let centre = Vector3::new(500_123.456, 5_400_078.9, 101.7);
        let camera_from_map = Pose::from_rt(r, -(r * centre));
        let local = frame.camera_from_local(&camera_from_map);
        assert!(local.translation().norm() < 200.0, "small in the local frame: {}", local.translation());
        let back = frame.camera_from_map(&local);
        assert!((back.matrix() - camera_from_map.matrix()).abs().max() < 1e-8);
        let p_map = [500_140.25, 5_400_090.5, 102.0];
        let p_local = frame.point_to_local(p_map);
        let in_cam_map = camera_from_map.transform(&Point3::from(p_map));
        let in_cam_local = local.transform(&Point3::new(p_local[0] as f64, p_local[1] as f64, p_local[2] as f64));
        assert!((in_cam_map - in_cam_local).norm() < 1e-5);
        let again = frame.point_to_map(p_local);
        assert!((0..3).all(|i| (again[i] - p_map[i]).abs() < 1e-5));
    }

    #[test]
    fn automatic_origin_rounds_to_the_grid_and_checks_bounds() {
        let near = LocalFrame::centred_on([-40.0, -30.0, -2.0], [60.0, 35.0, 8.0]);
        assert!(near.is_identity(), "{:?}", near.origin);
        let utm = LocalFrame::centred_on([499_800.0, 5_399_700.0, 90.0], [500_900.0, 5_400_100.0, 140.0]);
        assert_eq!(utm.origin(), [500_000.0, 5_400_000.0, 0.0]);
        assert!(LocalFrame::new([f64::NAN, 0.0, 0.0]).is_err());
        assert!(LocalFrame::new([0.0, 2e7, 0.0]).is_err());
    }
}
