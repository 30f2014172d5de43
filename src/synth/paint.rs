//! The painted ground of a road in any world family, in road coordinates: x along the road,
//! ŷ = y − c(x) across it (positive = left; traffic keeps right, so our lanes are at ŷ < 0).
//! From the centre out: a median (paint, tram tracks, grass or concrete), lanes with dashed
//! dividers, a parking strip, a paved shoulder, then beyond the carriageway's edge a sidewalk
//! (when the road has kerbs) and a verge (grass, gravel, field rows, concrete yard, or lot).

use serde::Serialize;

use super::materials::{mix, pavement_top, scale};
use super::noise::{fractal_noise, hash, unit, value_noise};
use super::scene::Surface;

#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Median {
    /// Centre line(s) only.
    Paint,
    /// Two tram tracks (standard gauge) on a ballast/concrete strip.
    Tram,
    Grass,
    /// Concrete strip (under a barrier).
    Concrete,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Verge {
    Grass,
    Gravel,
    /// Ploughed or planted rows running at an angle to the road.
    Field,
    /// Concrete slabs (yards).
    Concrete,
    /// Today's lot: grass patches on gravel.
    Lot,
}

/// Metres; colours linear RGB.
#[derive(Debug, Clone, Serialize)]
pub struct RoadPaint {
    pub lanes_each_way: u32,
    pub lane_width_m: f32,
    pub median_m: f32,
    pub median: Median,
    /// Solid (true) or dashed centre line.
    pub solid_centre: bool,
    /// Yellow instead of white centre line.
    pub yellow_centre: bool,
    pub parking_m: f32,
    pub shoulder_m: f32,
    pub edge_lines: bool,
    pub sidewalk_m: f32,
    pub verge: [Verge; 2],
    /// (x centre, half width) of crossing roads: asphalt across the whole roadside.
    pub junctions: Vec<(f32, f32)>,
    /// x of zebra crossings.
    pub crossings: Vec<f32>,
    /// (x centre, width, side ±1, length out from the edge): driveways.
    pub driveways: Vec<(f32, f32, f32, f32)>,
    pub asphalt: [f32; 3],
    pub verge_color: [f32; 3],
    pub pavement: [f32; 3],
    pub seed: u64,
}

const PAINT: Surface = Surface { albedo: [0.85, 0.85, 0.80], reflectivity: 0.75 };
const YELLOW: Surface = Surface { albedo: [0.80, 0.62, 0.12], reflectivity: 0.7 };

impl RoadPaint {
    /// Half width of the carriageway (everything paved at road level).
    pub fn half_width(&self) -> f32 {
        self.median_m * 0.5 + self.lanes_each_way as f32 * self.lane_width_m + self.parking_m + self.shoulder_m
    }

    /// ŷ of the centre of lane `lane` (0 = next to the median) on `side` (−1: ours, +1: oncoming).
    pub fn lane_centre(&self, side: f32, lane: u32) -> f32 {
        side * (self.median_m * 0.5 + (lane as f32 + 0.5) * self.lane_width_m)
    }

    /// ŷ of the parking strip's centre on `side` (if there is one).
    pub fn parking_centre(&self, side: f32) -> f32 {
        side * (self.median_m * 0.5 + self.lanes_each_way as f32 * self.lane_width_m + self.parking_m * 0.5)
    }

    pub fn in_junction(&self, x: f32, extra: f32) -> bool {
        self.junctions.iter().any(|(cx, hw)| (x - cx).abs() < hw + extra)
    }

    fn asphalt(&self, x: f32, y: f32) -> Surface {
        let patch = fractal_noise(self.seed, x * 0.25, y * 0.25, 1.0);
        let grain = value_noise(self.seed ^ 3, x * 4.0, y * 4.0);
        let k = 0.8 + 0.25 * grain + if patch > 0.68 { -0.25 } else { 0.0 };
        Surface { albedo: scale(self.asphalt, k), reflectivity: 0.12 }
    }

    /// Colour and reflectivity of the ground at road coordinates (x, ŷ).
    pub fn surface(&self, x: f32, yh: f32) -> Surface {
        let a = yh.abs();
        let rw = self.half_width();
        let junction = self.in_junction(x, 0.0);
        if a >= rw {
            let out = a - rw;
            if junction {
                return self.asphalt(x, yh);
            }
            let side = yh.signum();
            if self.driveways.iter().any(|&(dx, w, s, len)| s == side && (x - dx).abs() < w * 0.5 && out < len) {
                let n = fractal_noise(self.seed ^ 9, x, yh, 0.8);
                return Surface { albedo: scale(self.pavement, 0.95 + 0.2 * n), reflectivity: 0.3 };
            }
            if out < self.sidewalk_m {
                return pavement_top(self.pavement, x, yh);
            }
            return self.verge(self.verge[if yh >= 0.0 { 0 } else { 1 }], x, yh);
        }
        let m = self.median_m * 0.5;
        if a < m {
            return self.median(x, yh);
        }
        let mut s = self.asphalt(x, yh);
        let centre = if self.yellow_centre { YELLOW } else { PAINT };
        // Centre line at the median's edge (double when there is no median).
        if self.median == Median::Paint && !junction {
            let dashed = (x / 9.0).rem_euclid(1.0) < 0.33;
            if (a - m).abs() < 0.07 && (self.solid_centre || dashed) {
                return centre;
            }
        } else if !junction && (a - m) < 0.2 && (a - m) > 0.08 {
            return PAINT;
        }
        // Lane dividers: 3 m dashes every 9 m (12 m on wide lanes).
        let lanes_out = (a - m) / self.lane_width_m;
        let period = if self.lane_width_m > 3.4 { 12.0 } else { 9.0 };
        if lanes_out < self.lanes_each_way as f32 && !junction {
            let frac = lanes_out.fract();
            let near = frac.min(1.0 - frac) * self.lane_width_m;
            if lanes_out > 0.5 && lanes_out < self.lanes_each_way as f32 - 0.5 && near < 0.07 && (x / period).rem_euclid(1.0) < 0.3 {
                return PAINT;
            }
        }
        // Edge line before the parking strip or shoulder.
        let edge = m + self.lanes_each_way as f32 * self.lane_width_m;
        if self.edge_lines && !junction && (a - edge).abs() < 0.08 && (self.parking_m + self.shoulder_m) > 0.3 {
            return PAINT;
        }
        if self.edge_lines && !junction && (a - (rw - 0.25)).abs() < 0.07 && self.parking_m + self.shoulder_m < 0.3 {
            return PAINT;
        }
        for &cx in &self.crossings {
            if (x - cx).abs() < 2.0 && a < edge && (yh / 0.5).rem_euclid(2.0) < 1.0 {
                return PAINT;
            }
        }
        if a > edge {
            s.albedo = scale(s.albedo, if self.parking_m > 0.0 { 1.1 } else { 1.2 });
        }
        s
    }

    fn median(&self, x: f32, yh: f32) -> Surface {
        match self.median {
            Median::Paint => self.asphalt(x, yh),
            Median::Grass => self.verge(Verge::Grass, x, yh),
            Median::Concrete => {
                let n = fractal_noise(self.seed ^ 21, x, yh, 1.0);
                Surface { albedo: scale([0.42, 0.41, 0.38], 0.85 + 0.3 * n), reflectivity: 0.3 }
            }
            Median::Tram => {
                // Two tracks, 1.435 m gauge, centred at ±(median/4).
                let track = (yh.abs() - self.median_m * 0.25).abs();
                if (track - 0.7175).abs() < 0.04 {
                    return Surface { albedo: [0.38, 0.36, 0.34], reflectivity: 0.6 };
                }
                let sleeper = track < 1.2 && (x / 0.65).rem_euclid(1.0) < 0.35;
                let n = fractal_noise(self.seed ^ 22, x * 3.0, yh * 3.0, 1.0);
                let base = if sleeper { [0.30, 0.28, 0.26] } else { [0.34, 0.32, 0.29] };
                Surface { albedo: scale(base, 0.7 + 0.5 * n), reflectivity: 0.25 }
            }
        }
    }

    fn verge(&self, kind: Verge, x: f32, y: f32) -> Surface {
        let n = fractal_noise(self.seed ^ 5, x, y, 1.2);
        let m = value_noise(self.seed ^ 6, x * 0.2, y * 0.2);
        match kind {
            Verge::Grass => Surface { albedo: scale(self.verge_color, 0.7 + 0.6 * n * (0.7 + 0.5 * m)), reflectivity: 0.3 },
            Verge::Gravel => Surface { albedo: scale([0.36, 0.33, 0.29], 0.75 + 0.5 * n), reflectivity: 0.28 },
            Verge::Field => {
                let angle = unit(hash(&[self.seed, 31])) * 3.0;
                let along = x * angle.cos() + y * angle.sin();
                // Soft rows 1.5–3 m apart (hard 0.75 m rows alias into moiré at a distance).
                let pitch = 1.5 + 1.5 * unit(hash(&[self.seed, 32]));
                let crop = 0.92 + 0.18 * (std::f32::consts::TAU * along / pitch).sin();
                let plot = unit(hash(&[self.seed, (x / 80.0).floor() as i64 as u64, (y.abs() / 60.0).floor() as u64]));
                let color = mix(self.verge_color, [0.42, 0.33, 0.20], plot * 0.8);
                Surface { albedo: scale(color, crop * (0.8 + 0.4 * n)), reflectivity: 0.3 }
            }
            Verge::Concrete => {
                let joint = (x / 6.0).rem_euclid(1.0) < 0.01 || (y / 6.0).rem_euclid(1.0) < 0.01;
                let stain = fractal_noise(self.seed ^ 8, x * 0.3, y * 0.3, 1.0);
                Surface { albedo: scale([0.45, 0.44, 0.41], if joint { 0.6 } else { 0.8 + 0.35 * stain }), reflectivity: 0.3 }
            }
            Verge::Lot => {
                let albedo = mix(self.verge_color, [0.33, 0.30, 0.25], (m * 1.4 - 0.3).clamp(0.0, 1.0));
                Surface { albedo: scale(albedo, 0.75 + 0.5 * n), reflectivity: 0.3 }
            }
        }
    }
}
