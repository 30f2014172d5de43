//! Appearance randomisation per sequence (`--look random`): sky from clear blue to overcast
//! white, the sun anywhere above the horizon, and procedural textures on every surface (noise,
//! stripes, bricks, checks) with albedo drawn over a wide range, unnatural colours included
//! for a share of sequences. Per-frame camera effects are in `camera_fx`. `--look classic`
//! keeps today's rendering exactly.

use rand::Rng;
use serde::{Deserialize, Serialize};

use super::materials::mix;
use super::noise::{fractal_noise, gaussian, hash, unit};
use super::render::Lighting;
use super::scene::{Class, Hit, Surface, GROUND};
use super::shapes::V3;
use super::style::Style;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum LookMode {
    /// Today's rendering: the style preset only, no texture randomisation, no camera effects.
    Classic,
    /// Sky, sun, textures and camera effects drawn per sequence and per frame.
    Random,
}

/// One sequence's drawn appearance (recorded in synth.json).
#[derive(Debug, Clone, Serialize)]
pub struct Look {
    /// 0 = clear sky, 1 = fully overcast (white sky, no direct sun to speak of).
    pub overcast: f32,
    /// Sun elevation above the horizon, degrees (3–85).
    pub sun_elevation_deg: f32,
    /// Zenith colour multiplier (deeper or paler blue).
    pub sky_tint: [f32; 3],
    pub textures: Textures,
}

/// Surface randomisation: a pattern and an albedo change per primitive, hashed from `seed`.
#[derive(Debug, Clone, Serialize)]
pub struct Textures {
    pub seed: u64,
    /// 0..1: how far patterns and albedo changes go.
    pub strength: f32,
    /// Share of primitives given an arbitrary (often unnatural) colour.
    pub unnatural: f32,
}

impl Look {
    /// Draws a look; a sun elevation fixed on the command line (through the time of day) is kept.
    pub fn draw(rng: &mut impl Rng, style: &Style, sun_fixed: bool) -> Look {
        let overcast = if rng.random_bool(0.35) { rng.random_range(0.6..1.0) } else { rng.random_range(0.0..0.4) };
        Look {
            overcast,
            sun_elevation_deg: if sun_fixed { style.sun_elevation_deg() } else { rng.random_range(3.0..85.0) },
            sky_tint: [rng.random_range(0.6..1.3), rng.random_range(0.8..1.2), rng.random_range(0.8..1.25)],
            textures: Textures {
                seed: rng.random(),
                strength: rng.random_range(0.2..1.0),
                unnatural: if rng.random_bool(0.25) { rng.random_range(0.2..0.8) } else { rng.random_range(0.0..0.05) },
            },
        }
    }

    /// The style's lighting changed by this look: sun direction and strength, sky colours.
    pub fn lighting(&self, style: &Style) -> Lighting {
        let mut l = Lighting::from_style(style);
        let (e, a) = (self.sun_elevation_deg.to_radians(), style.sun_azimuth_deg.to_radians());
        l.sun_dir = V3::new(e.cos() * a.cos(), e.cos() * a.sin(), e.sin());
        let low = 1.0 - (e / 62f32.to_radians()).clamp(0.0, 1.0);
        let strength = 2.6 * (0.45 + 0.55 * (1.0 - low)) * (1.0 - 0.9 * self.overcast);
        l.sun = [strength, strength * (0.93 - 0.18 * low), strength * (0.85 - 0.35 * low)];
        let o = self.overcast;
        let grey = [0.95, 0.96, 0.98];
        l.zenith = mix(std::array::from_fn(|c| l.zenith[c] * self.sky_tint[c]), grey, o);
        l.horizon = mix(l.horizon, [1.05, 1.05, 1.06], o);
        l.sky_ambient = mix(l.sky_ambient, [0.75, 0.76, 0.8], o * 0.8);
        l
    }
}

impl Textures {
    /// Changes `surface` by the primitive's pattern and albedo draw.
    pub fn apply(&self, surface: Surface, class: Class, hit: &Hit, point: &V3) -> Surface {
        let id = hit.primitive as u64;
        let h = hash(&[self.seed, id, class as u64]);
        let s = self.strength;
        let (u, v) = if hit.primitive == GROUND { (point.x, point.y) } else { (hit.uv[0], hit.uv[1]) };
        let scale = 0.3 + 2.0 * unit(h ^ 1);
        let pattern = match h % 10 {
            0..=3 => 0.0,
            4..=6 => fractal_noise(h, u, v, scale) - 0.5,
            7 => {
                // Stripes at some angle.
                let a = unit(h ^ 2) * std::f32::consts::PI;
                if ((u * a.cos() + v * a.sin()) / scale).rem_euclid(1.0) < 0.5 { 0.35 } else { -0.35 }
            }
            8 => {
                // Bricks: rows of blocks offset every other row, dark mortar.
                let (bw, bh) = (scale * 1.6, scale * 0.6);
                let row = (v / bh).floor();
                let col = u / bw + if row as i64 % 2 == 0 { 0.0 } else { 0.5 };
                let mortar = (v / bh).fract() < 0.08 || col.fract() < 0.05;
                if mortar { -0.45 } else { 0.3 * (unit(hash(&[h, row as i64 as u64, col.floor() as i64 as u64])) - 0.5) }
            }
            _ => {
                if ((u / scale).floor() + (v / scale).floor()) as i64 % 2 == 0 { 0.3 } else { -0.3 }
            }
        };
        // Ground keeps its markings readable: weaker changes.
        let k = if class == Class::Ground { 0.5 * s } else { s };
        let mut albedo = surface.albedo;
        if unit(h ^ 3) < self.unnatural && class != Class::Ground {
            let c = [unit(h ^ 4), unit(h ^ 5), unit(h ^ 6)];
            albedo = mix(albedo, [c[0] * c[0], c[1] * c[1], c[2] * c[2]], 0.85);
        } else {
            let bright = (0.9 * gaussian(h ^ 7) * k).exp();
            albedo = std::array::from_fn(|c| albedo[c] * bright * (0.35 * gaussian(h ^ (8 + c as u64)) * k).exp());
        }
        let m = (1.0 + 1.4 * k * pattern).max(0.05);
        Surface { albedo: albedo.map(|a| (a * m).clamp(0.0, 1.0)), reflectivity: surface.reflectivity }
    }
}
