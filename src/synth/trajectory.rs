//! The vehicle's path: along the road in a lane, weaving gently (a slow lateral sine) so the
//! heading changes by a few degrees. On a flat street (`terrain: None`) the LiDAR stays level
//! at its mounting height; on terrain the vehicle follows the road's centreline, climbs with its
//! grade and rolls with its bank.

use std::sync::Arc;

use nalgebra::{Matrix3, Rotation3, Vector3};

use super::terrain::Terrain;
use crate::geometry::Pose;

/// Lengths in metres, angles in radians; x is the scene's along-road axis.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Trajectory {
    pub start_x: f64,
    pub spacing_m: f64,
    /// Lateral lane position: scene y on a flat street, the road coordinate ŷ on terrain.
    pub lane_y: f64,
    pub weave_amplitude_m: f64,
    pub weave_wavelength_m: f64,
    pub weave_phase: f64,
    /// LiDAR origin above the road surface.
    pub lidar_height_m: f64,
    #[serde(skip)]
    pub terrain: Option<Arc<Terrain>>,
}

/// Half the wheelbase and half the track: the footprint over which pitch and roll are measured.
const HALF_WHEELBASE_M: f32 = 1.35;
const HALF_TRACK_M: f32 = 0.8;

impl Trajectory {
    pub fn length_m(&self, frames: usize) -> f64 {
        self.spacing_m * frames.saturating_sub(1) as f64
    }

    fn weave(&self, x: f64) -> (f64, f64) {
        let k = std::f64::consts::TAU / self.weave_wavelength_m;
        let y = self.lane_y + self.weave_amplitude_m * (k * x + self.weave_phase).sin();
        let slope = self.weave_amplitude_m * k * (k * x + self.weave_phase).cos();
        (y, slope)
    }

    /// world_from_lidar at frame `i`.
    pub fn world_from_lidar(&self, i: usize) -> Pose {
        let x = self.start_x + self.spacing_m * i as f64;
        let (y, slope) = self.weave(x);
        let Some(terrain) = &self.terrain else {
            let heading = slope.atan();
            return Pose::ground_motion(heading, x, y).compose(&Pose::from_rt(Matrix3::identity(), Vector3::new(0.0, 0.0, self.lidar_height_m)));
        };
        let along = terrain.along(x as f32);
        let wy = along.centre as f64 + y;
        let heading = (slope + along.centre_slope as f64).atan();
        let (c, s) = (heading.cos() as f32, heading.sin() as f32);
        let (px, py) = (x as f32, wy as f32);
        let h = |dx: f32, dy: f32| terrain.height(px + dx, py + dy);
        let ground = h(0.0, 0.0);
        let pitch_slope = (h(c * HALF_WHEELBASE_M, s * HALF_WHEELBASE_M) - h(-c * HALF_WHEELBASE_M, -s * HALF_WHEELBASE_M)) / (2.0 * HALF_WHEELBASE_M);
        let roll_slope = (h(-s * HALF_TRACK_M, c * HALF_TRACK_M) - h(s * HALF_TRACK_M, -c * HALF_TRACK_M)) / (2.0 * HALF_TRACK_M);
        // Nose up on a climb (negative rotation about y), left side up when the left is higher.
        let rotation = Rotation3::from_euler_angles((roll_slope as f64).atan(), -(pitch_slope as f64).atan(), heading);
        let up = rotation * Vector3::new(0.0, 0.0, self.lidar_height_m);
        Pose::from_rt(*rotation.matrix(), Vector3::new(x, wy, ground as f64) + up)
    }
}
