//! Surface materials: what colour (linear RGB albedo) and LiDAR reflectivity a shape has at a
//! point. Facades are textures (windows, doors, shop fronts are flat for the LiDAR).

use super::noise::{fractal_noise, hash, unit, value_noise};
use super::scene::{Hit, Surface};
use super::shapes::V3;

/// Facade texture parameters: a grid of floors × bays with windows, a door, a shop front.
#[derive(Debug, Clone, Copy)]
pub struct Facade {
    pub base: [f32; 3],
    pub trim: [f32; 3],
    pub roof: [f32; 3],
    pub floor_height: f32,
    pub bay_width: f32,
    pub window_width: f32,
    pub window_height: f32,
    pub sill: f32,
    /// Bay index of the door on the ground floor (on every face; cheap and plausible).
    pub door_bay: i32,
    /// Ground floor is a shop front (big dark glass with a coloured band).
    pub shop: Option<[f32; 3]>,
    /// Horizontal band pattern (panels) instead of plain render.
    pub banded: bool,
    pub seed: u64,
}

#[derive(Debug, Clone, Copy)]
pub enum Material {
    Facade(Facade),
    /// A uniform material with a little grain; `reflectivity` is the LiDAR return strength.
    Plain { color: [f32; 3], reflectivity: f32, grain: f32 },
    /// Paving tiles on top, plain concrete on the curb faces.
    Pavement { color: [f32; 3] },
    Foliage { color: [f32; 3], seed: u64 },
    /// Car body: paint, with dark glass on the upper part of a cabin's sides.
    Car { color: [f32; 3], cabin: bool },
    /// Retro-reflective sign plate.
    Sign { color: [f32; 3] },
    /// Ribbed metal cladding (sheds, containers): vertical ribs every `pitch` metres.
    Corrugated { color: [f32; 3], pitch: f32 },
}

impl Material {
    /// Colour and reflectivity at `point` on `hit` (which met a shape with this material).
    pub fn surface(&self, hit: &Hit, point: &V3) -> Surface {
        let [u, v] = hit.uv;
        match *self {
            Material::Plain { color, reflectivity, grain } => {
                let n = fractal_noise(hit.primitive as u64, u * 2.0, v * 2.0 + point.z, 1.0);
                Surface { albedo: scale(color, 1.0 + grain * (n - 0.5)), reflectivity }
            }
            Material::Pavement { color } => pavement(color, point, hit.normal.z > 0.5),
            Material::Foliage { color, seed } => {
                let n = value_noise(seed, point.x * 3.0 + point.z * 1.7, point.y * 3.0 - point.z * 2.3);
                let m = value_noise(seed ^ 77, point.x * 0.7, point.z * 0.9);
                Surface { albedo: scale(color, 0.55 + 0.8 * n * (0.6 + 0.6 * m)), reflectivity: 0.32 }
            }
            Material::Car { color, cabin } => {
                // The car body's uv: v is height above the shape's bottom.
                if hit.normal.z.abs() < 0.5 && v > 0.05 && v < 0.5 && cabin {
                    Surface { albedo: [0.03, 0.035, 0.045], reflectivity: 0.05 }
                } else {
                    Surface { albedo: color, reflectivity: 0.22 }
                }
            }
            Material::Sign { color } => Surface { albedo: color, reflectivity: 0.95 },
            Material::Facade(f) => facade(&f, hit, point),
            Material::Corrugated { color, pitch } => {
                let rib = (u / pitch).rem_euclid(1.0);
                let shade = if hit.normal.z.abs() > 0.5 { 0.9 } else { 0.8 + 0.3 * (rib * std::f32::consts::TAU).sin().abs() };
                let rust = fractal_noise(hit.primitive as u64 ^ 0x51, u * 0.7, v * 0.7, 1.5);
                Surface { albedo: mix(scale(color, shade), [0.30, 0.17, 0.08], (rust - 0.6).max(0.0)), reflectivity: 0.45 }
            }
        }
    }
}

pub fn scale(c: [f32; 3], k: f32) -> [f32; 3] {
    [c[0] * k, c[1] * k, c[2] * k]
}

pub fn mix(a: [f32; 3], b: [f32; 3], k: f32) -> [f32; 3] {
    [a[0] + (b[0] - a[0]) * k, a[1] + (b[1] - a[1]) * k, a[2] + (b[2] - a[2]) * k]
}

fn pavement(color: [f32; 3], p: &V3, top: bool) -> Surface {
    if !top {
        return Surface { albedo: scale(color, 1.15), reflectivity: 0.3 };
    }
    pavement_top(color, p.x, p.y)
}

/// Paving tiles 0.6 m square with dark joints.
pub fn pavement_top(color: [f32; 3], x: f32, y: f32) -> Surface {
    let (tx, ty) = ((x / 0.6).rem_euclid(1.0), (y / 0.6).rem_euclid(1.0));
    let joint = tx < 0.04 || ty < 0.04;
    let n = fractal_noise(91, x, y, 1.5);
    let k = if joint { 0.7 } else { 0.9 + 0.25 * n };
    Surface { albedo: scale(color, k), reflectivity: 0.27 }
}

fn facade(f: &Facade, hit: &Hit, p: &V3) -> Surface {
    let [u, v] = hit.uv;
    if hit.normal.z > 0.5 {
        let n = fractal_noise(f.seed, p.x, p.y, 2.0);
        return Surface { albedo: scale(f.roof, 0.8 + 0.4 * n), reflectivity: 0.15 };
    }
    let stain = fractal_noise(f.seed, u * 0.5, v * 0.3, 3.0);
    let mut wall = scale(f.base, 0.82 + 0.3 * stain);
    if f.banded && (v / f.floor_height).rem_euclid(1.0) < 0.12 {
        wall = f.trim;
    }
    let floor = (v / f.floor_height).floor() as i32;
    let in_floor = v - floor as f32 * f.floor_height;
    let bay = (u / f.bay_width).floor() as i32;
    let in_bay = u - bay as f32 * f.bay_width;
    let margin = (f.bay_width - f.window_width) * 0.5;
    // Ground floor: a shop front or a door and smaller windows.
    if floor == 0 {
        if let Some(band) = f.shop {
            if in_floor > 2.6 && in_floor < 3.1 {
                return Surface { albedo: band, reflectivity: 0.5 };
            }
            if in_floor > 0.4 && in_floor < 2.5 && in_bay > 0.15 && in_bay < f.bay_width - 0.15 {
                let h = unit(hash(&[f.seed, bay as u64, 7]));
                return Surface { albedo: mix([0.04, 0.05, 0.06], [0.35, 0.30, 0.22], h * 0.5), reflectivity: 0.06 };
            }
        } else if bay == f.door_bay && in_bay > margin && in_bay < f.bay_width - margin && in_floor < 2.3 {
            return Surface { albedo: scale(f.trim, 0.45), reflectivity: 0.2 };
        }
    }
    let in_window = in_bay > margin && in_bay < f.bay_width - margin && in_floor > f.sill && in_floor < f.sill + f.window_height;
    if in_window {
        // Each window differs a little (curtains, lights, reflections): breaks repetition.
        let h = hash(&[f.seed, bay as u64, floor as u64]);
        let frame = in_bay - margin < 0.07 || f.bay_width - margin - in_bay < 0.07 || in_floor - f.sill < 0.07;
        if frame {
            return Surface { albedo: f.trim, reflectivity: 0.3 };
        }
        let glass = mix([0.05, 0.07, 0.09], [0.28, 0.33, 0.40], unit(h));
        let curtain = unit(super::noise::mix64(h ^ 0xDEAD_BEEF)) < 0.25;
        let albedo = if curtain { mix(glass, [0.55, 0.50, 0.42], 0.6) } else { glass };
        return Surface { albedo, reflectivity: 0.05 };
    }
    // Trim line under each window row.
    if in_floor > f.sill - 0.12 && in_floor < f.sill && in_bay > margin - 0.1 && in_bay < f.bay_width - margin + 0.1 {
        return Surface { albedo: f.trim, reflectivity: 0.35 };
    }
    Surface { albedo: wall, reflectivity: 0.28 + 0.08 * stain }
}
