//! A spinning multi-beam LiDAR ray-cast against the scene: evenly spaced beams between two
//! elevations (HDL-64E-like by default) or an explicit beam elevation table.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::noise::{gaussian, hash, unit};
use super::scene::{Class, Scene};
use super::shapes::V3;
use crate::geometry::Pose;
use crate::kitti::LidarPoint;

/// The LiDAR's beams, sampling and noise. Angles in degrees in the LiDAR frame (x forward,
/// y left, z up; elevation positive upwards), ranges in metres.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LidarConfig {
    pub beams: u32,
    /// Azimuth steps per revolution (2083 ≈ 0.173° like the HDL-64E at 10 Hz).
    pub columns: u32,
    pub elevation_top_deg: f32,
    pub elevation_bottom_deg: f32,
    pub max_range_m: f32,
    pub min_range_m: f32,
    /// Standard deviation of the range noise.
    pub range_noise_m: f32,
    /// Base probability that a return is lost; weak, far returns are lost more often.
    pub dropout: f32,
    /// Per-beam elevations, top beam first (degrees); `None` = evenly spaced from
    /// `elevation_top_deg` to `elevation_bottom_deg`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub elevations_deg: Option<Vec<f32>>,
}

impl Default for LidarConfig {
    fn default() -> Self {
        LidarConfig {
            beams: 64,
            columns: 2083,
            elevation_top_deg: 2.0,
            elevation_bottom_deg: -24.8,
            max_range_m: 80.0,
            min_range_m: 2.0,
            range_noise_m: 0.02,
            dropout: 0.02,
            elevations_deg: None,
        }
    }
}

impl LidarConfig {
    pub fn validate(&self) -> Result<(), String> {
        if self.beams == 0 || self.beams > 512 || self.columns < 8 || self.columns > 20_000 {
            return Err(format!("lidar beams {} / columns {} out of range (1..=512, 8..=20000)", self.beams, self.columns));
        }
        if !(self.elevation_top_deg > self.elevation_bottom_deg && self.max_range_m > self.min_range_m && self.min_range_m >= 0.0) {
            return Err("lidar elevation/range limits are inconsistent".into());
        }
        if !(0.0..1.0).contains(&self.dropout) || self.range_noise_m < 0.0 {
            return Err("lidar dropout must be in [0, 1) and range noise ≥ 0".into());
        }
        if let Some(table) = &self.elevations_deg {
            if table.len() != self.beams as usize {
                return Err(format!("lidar elevation table has {} entries for {} beams", table.len(), self.beams));
            }
            if table.windows(2).any(|w| w[0] <= w[1]) || table.iter().any(|e| !(-90.0..90.0).contains(e)) {
                return Err("lidar elevation table must be strictly decreasing (top beam first) within ±90°".into());
            }
        }
        Ok(())
    }

    /// Beam `beam`'s elevation in radians (beam 0 is the top one).
    pub fn elevation_rad(&self, beam: u32) -> f32 {
        if let Some(table) = &self.elevations_deg {
            return table[beam as usize].to_radians();
        }
        let k = if self.beams == 1 { 0.0 } else { beam as f32 / (self.beams - 1) as f32 };
        (self.elevation_top_deg + (self.elevation_bottom_deg - self.elevation_top_deg) * k).to_radians()
    }

    /// Every beam's elevation in degrees, top first.
    pub fn elevations(&self) -> Vec<f32> {
        (0..self.beams).map(|b| self.elevation_rad(b).to_degrees()).collect()
    }
}

/// One sweep from `world_from_lidar`; points in the LiDAR frame, beam by beam (top beam first),
/// each beam's columns in azimuth order starting behind the vehicle (−180°).
pub fn scan(scene: &Scene, config: &LidarConfig, world_from_lidar: &Pose, seed: u64) -> Vec<LidarPoint> {
    scan_labelled(scene, config, world_from_lidar, seed).into_iter().map(|(p, _, _)| p).collect()
}

/// As [`scan`], with each point's beam index and the class of the surface it came from.
pub fn scan_labelled(scene: &Scene, config: &LidarConfig, world_from_lidar: &Pose, seed: u64) -> Vec<(LidarPoint, u32, Class)> {
    let r = world_from_lidar.rotation().cast::<f32>();
    let origin: V3 = world_from_lidar.translation().cast::<f32>();
    let per_beam: Vec<Vec<(LidarPoint, u32, Class)>> = (0..config.beams)
        .into_par_iter()
        .map(|beam| {
            let elevation = config.elevation_rad(beam);
            let (se, ce) = elevation.sin_cos();
            let mut points = Vec::with_capacity(config.columns as usize);
            for column in 0..config.columns {
                let azimuth = -std::f32::consts::PI + std::f32::consts::TAU * column as f32 / config.columns as f32;
                let local = V3::new(ce * azimuth.cos(), ce * azimuth.sin(), se);
                let dir = r * local;
                let Some(hit) = scene.intersect(&origin, &dir, config.max_range_m) else { continue };
                if hit.t < config.min_range_m {
                    continue;
                }
                let point = origin + dir * hit.t;
                let surface = scene.surface(&hit, &point);
                let cos_incidence = (-dir.dot(&hit.normal)).clamp(0.0, 1.0);
                let strength = surface.reflectivity * (0.45 + 0.55 * cos_incidence);
                let h = hash(&[seed, beam as u64, column as u64]);
                let far = hit.t / config.max_range_m;
                let loss = config.dropout + 0.25 * far * far * (1.0 - strength);
                if unit(h) < loss {
                    continue;
                }
                let range = hit.t + config.range_noise_m * gaussian(h ^ 0x5151);
                let p = local * range;
                let intensity = ((strength + 0.02 * gaussian(h ^ 0x7777)).clamp(0.0, 1.0) * 100.0).round() / 100.0;
                points.push((LidarPoint { x: p.x, y: p.y, z: p.z, intensity }, beam, scene.class_of(&hit)));
            }
            points
        })
        .collect();
    per_beam.concat()
}
