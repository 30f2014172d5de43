//! Today's flat, straight street (the `classic` world): its painted layout on the ground z = 0.

use super::materials::{mix, scale};
use super::noise::{fractal_noise, hash, unit, value_noise};
use super::scene::Surface;

/// The painted ground: road, markings, crossings, side streets.
#[derive(Debug, Clone)]
pub struct Street {
    pub road_half_width: f32,
    pub sidewalk_width: f32,
    /// Whether the outer 2.2 m of each side is a parking lane.
    pub parking: bool,
    /// x positions of zebra crossings.
    pub crossings: Vec<f32>,
    /// Side streets: (x centre, half width).
    pub side_streets: Vec<(f32, f32)>,
    pub asphalt: [f32; 3],
    pub lot: [f32; 3],
    pub seed: u64,
}

impl Street {
    /// The ground's colour at (x, y): asphalt with markings on the road and side streets,
    /// a grassy/gravel lot elsewhere (the sidewalks are shapes above the ground).
    pub fn ground(&self, x: f32, y: f32) -> Surface {
        let ay = y.abs();
        let side_street = self.side_streets.iter().find(|(cx, hw)| (x - cx).abs() < *hw);
        let on_road = ay < self.road_half_width + 0.05 || side_street.is_some();
        if !on_road {
            let n = fractal_noise(self.seed ^ 5, x, y, 1.2);
            let m = value_noise(self.seed ^ 6, x * 0.2, y * 0.2);
            let albedo = mix(self.lot, [0.33, 0.30, 0.25], (m * 1.4 - 0.3).clamp(0.0, 1.0));
            return Surface { albedo: scale(albedo, 0.75 + 0.5 * n), reflectivity: 0.3 };
        }
        let patch = fractal_noise(self.seed, x * 0.25, y * 0.25, 1.0);
        let grain = value_noise(self.seed ^ 3, x * 4.0, y * 4.0);
        let mut albedo = scale(self.asphalt, 0.8 + 0.25 * grain + if patch > 0.68 { -0.25 } else { 0.0 });
        let paint = [0.85, 0.85, 0.80];
        let marking = Surface { albedo: paint, reflectivity: 0.75 };
        if let Some((cx, hw)) = side_street {
            // Stop line where the side street meets the main road.
            if ay > self.road_half_width + 0.3 && ay < self.road_half_width + 0.7 && (x - cx) * y.signum() > 0.0 && (x - cx).abs() < hw - 0.5 {
                return marking;
            }
            if ay > self.road_half_width {
                return Surface { albedo, reflectivity: 0.12 };
            }
        }
        // Centre line: dashed (3 m of paint every 9 m) or solid, per 60 m section.
        let section = (x / 60.0).floor() as i64 as u64;
        let solid = unit(hash(&[self.seed, section])) < 0.3;
        if ay < 0.07 && (solid || (x / 9.0).rem_euclid(1.0) < 0.33) {
            return marking;
        }
        // Edge lines (before the parking lane when there is one).
        let edge = if self.parking { self.road_half_width - 2.2 } else { self.road_half_width - 0.3 };
        if (ay - edge).abs() < 0.06 && side_street.is_none() {
            return marking;
        }
        // Zebra crossings: 0.5 m stripes across the road.
        for &cx in &self.crossings {
            if (x - cx).abs() < 2.0 && ay < edge && (y / 0.5).rem_euclid(2.0) < 1.0 {
                return marking;
            }
        }
        if self.parking && ay > edge {
            albedo = scale(albedo, 1.1);
        }
        Surface { albedo, reflectivity: 0.12 }
    }
}

