//! A procedural street: the shapes, their materials, the ground's painted layout, and the
//! queries both sensors use (closest hit, shadow test, surface colour and LiDAR reflectivity).
//!
//! Scene frame: z up, ground at z = 0, the street's centre line is the x axis.

use rand::Rng;
use rand_chacha::ChaCha8Rng;

use super::bvh::Bvh;
use super::noise::{fractal_noise, hash, unit, value_noise};
use super::shapes::{Shape, ShapeHit, V3, T_EPSILON};
use super::style::{Colors, Style};

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
    /// Car body: paint below, dark glass on the upper part of the cabin.
    Car { color: [f32; 3] },
    /// Retro-reflective sign plate.
    Sign { color: [f32; 3] },
}

#[derive(Debug, Clone, Copy)]
pub struct Primitive {
    pub shape: Shape,
    pub material: Material,
}

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

/// Colour and LiDAR reflectivity at a surface point.
#[derive(Debug, Clone, Copy)]
pub struct Surface {
    pub albedo: [f32; 3],
    pub reflectivity: f32,
}

/// Index used in hits for the ground plane.
pub const GROUND: u32 = u32::MAX;

#[derive(Debug, Clone, Copy)]
pub struct Hit {
    pub t: f32,
    pub normal: V3,
    pub uv: [f32; 2],
    pub primitive: u32,
}

pub struct Scene {
    pub street: Street,
    pub shapes: Vec<Shape>,
    pub materials: Vec<Material>,
    bvh: Bvh,
    /// The x range the trajectory may use (the scene extends beyond it by the LiDAR range).
    pub drive_range: (f32, f32),
}

impl Scene {
    pub fn new(street: Street, primitives: Vec<Primitive>, drive_range: (f32, f32)) -> Self {
        let shapes: Vec<Shape> = primitives.iter().map(|p| p.shape).collect();
        let materials = primitives.iter().map(|p| p.material).collect();
        let bvh = Bvh::build(&shapes);
        Scene { street, shapes, materials, bvh, drive_range }
    }

    pub fn len(&self) -> usize {
        self.shapes.len()
    }

    pub fn is_empty(&self) -> bool {
        self.shapes.is_empty()
    }

    /// The closest surface along the ray (shapes and the ground plane z = 0).
    pub fn intersect(&self, origin: &V3, dir: &V3, t_max: f32) -> Option<Hit> {
        let mut limit = t_max;
        let mut best = None;
        if dir.z < 0.0 && origin.z > 0.0 {
            let t = -origin.z / dir.z;
            if t > T_EPSILON && t < limit {
                limit = t;
                let p = origin + dir * t;
                best = Some(Hit { t, normal: V3::z(), uv: [p.x, p.y], primitive: GROUND });
            }
        }
        if let Some((index, ShapeHit { t, normal, uv })) = self.bvh.closest(&self.shapes, origin, dir, limit) {
            best = Some(Hit { t, normal, uv, primitive: index });
        }
        best
    }

    /// Whether the segment from `origin` along `dir` up to `t_max` is blocked (shadow rays).
    pub fn occluded(&self, origin: &V3, dir: &V3, t_max: f32) -> bool {
        self.bvh.any_hit(&self.shapes, origin, dir, t_max)
    }

    /// Surface colour (linear RGB) and LiDAR reflectivity at `point` on `hit`.
    pub fn surface(&self, hit: &Hit, point: &V3) -> Surface {
        if hit.primitive == GROUND {
            return self.street.ground(point.x, point.y);
        }
        let [u, v] = hit.uv;
        match self.materials[hit.primitive as usize] {
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
            Material::Car { color } => {
                // The car body's uv: v is height above the shape's bottom.
                if hit.normal.z.abs() < 0.5 && v > 0.05 && v < 0.5 && is_cabin(&self.shapes[hit.primitive as usize]) {
                    Surface { albedo: [0.03, 0.035, 0.045], reflectivity: 0.05 }
                } else {
                    Surface { albedo: color, reflectivity: 0.22 }
                }
            }
            Material::Sign { color } => Surface { albedo: color, reflectivity: 0.95 },
            Material::Facade(f) => facade(&f, hit, point),
        }
    }
}

fn is_cabin(shape: &Shape) -> bool {
    // Cabins are the boxes whose bottom is above 0.9 m.
    matches!(shape, Shape::Box { center, half, .. } if center.z - half.z > 0.9)
}

fn scale(c: [f32; 3], k: f32) -> [f32; 3] {
    [c[0] * k, c[1] * k, c[2] * k]
}

fn mix(a: [f32; 3], b: [f32; 3], k: f32) -> [f32; 3] {
    [a[0] + (b[0] - a[0]) * k, a[1] + (b[1] - a[1]) * k, a[2] + (b[2] - a[2]) * k]
}

fn pavement(color: [f32; 3], p: &V3, top: bool) -> Surface {
    if !top {
        return Surface { albedo: scale(color, 1.15), reflectivity: 0.3 };
    }
    let (tx, ty) = ((p.x / 0.6).rem_euclid(1.0), (p.y / 0.6).rem_euclid(1.0));
    let joint = tx < 0.04 || ty < 0.04;
    let n = fractal_noise(91, p.x, p.y, 1.5);
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
        let curtain = unit(mix_hash(h)) < 0.25;
        let albedo = if curtain { mix(glass, [0.55, 0.50, 0.42], 0.6) } else { glass };
        return Surface { albedo, reflectivity: 0.05 };
    }
    // Trim line under each window row.
    if in_floor > f.sill - 0.12 && in_floor < f.sill && in_bay > margin - 0.1 && in_bay < f.bay_width - margin + 0.1 {
        return Surface { albedo: f.trim, reflectivity: 0.35 };
    }
    Surface { albedo: wall, reflectivity: 0.28 + 0.08 * stain }
}

fn mix_hash(h: u64) -> u64 {
    super::noise::mix64(h ^ 0xDEAD_BEEF)
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

/// Generates a street covering x in `[x0, x1]` (the drive range plus the sensor range).
pub fn build_street(rng: &mut ChaCha8Rng, drive_range: (f32, f32), margin: f32, style: &Style) -> Scene {
    let colors = style.palette.colors();
    let (x0, x1) = (drive_range.0 - margin, drive_range.1 + margin);
    let parking = rng.random_bool(0.6);
    let road_half_width = if parking { rng.random_range(6.8..8.2) } else { rng.random_range(3.6..5.5) };
    let sidewalk_width = rng.random_range(2.0..4.5);
    let mut side_streets = Vec::new();
    let mut x = x0 + rng.random_range(20.0..80.0);
    while x < x1 {
        if rng.random_bool(0.55) {
            side_streets.push((x, rng.random_range(4.0..6.5)));
        }
        x += rng.random_range(70.0..160.0);
    }
    let mut crossings = Vec::new();
    for &(cx, hw) in &side_streets {
        if rng.random_bool(0.6) {
            crossings.push(cx - hw - 2.5);
        }
    }
    let street = Street {
        road_half_width,
        sidewalk_width,
        parking,
        crossings,
        side_streets,
        asphalt: colors.asphalt,
        lot: colors.lot,
        seed: rng.random(),
    };
    let mut builder = Builder { rng, colors: &colors, clutter: style.clutter, street: &street, out: Vec::new() };
    for side in [1.0f32, -1.0] {
        builder.sidewalk(side, x0, x1);
        builder.buildings(side, x0, x1);
        builder.street_furniture(side, x0, x1);
        if street.parking {
            builder.parked_cars(side, x0, x1);
        }
    }
    let primitives = builder.out;
    Scene::new(street, primitives, drive_range)
}

struct Builder<'a> {
    rng: &'a mut ChaCha8Rng,
    colors: &'a Colors,
    clutter: f32,
    street: &'a Street,
    out: Vec<Primitive>,
}

impl Builder<'_> {
    fn pick(&mut self, list: &'static [[f32; 3]]) -> [f32; 3] {
        let c = list[self.rng.random_range(0..list.len())];
        let k = self.rng.random_range(0.85..1.15);
        scale(c, k)
    }

    fn push_box(&mut self, center: V3, half: V3, yaw: f32, material: Material) {
        self.out.push(Primitive { shape: Shape::Box { center, half, cos: yaw.cos(), sin: yaw.sin() }, material });
    }

    /// Whether [xa, xb] overlaps a side street (nothing is built there).
    fn in_side_street(&self, xa: f32, xb: f32, extra: f32) -> bool {
        self.street.side_streets.iter().any(|(cx, hw)| xb > cx - hw - extra && xa < cx + hw + extra)
    }

    fn curb_y(&self) -> f32 {
        self.street.road_half_width
    }

    /// Raised sidewalk boxes, cut into 20 m pieces (long thin boxes would defeat the BVH).
    fn sidewalk(&mut self, side: f32, x0: f32, x1: f32) {
        let w = self.street.sidewalk_width;
        let y = side * (self.curb_y() + w * 0.5);
        let color = self.colors.pavement;
        let mut x = x0;
        while x < x1 {
            let mut end = (x + 20.0).min(x1);
            if let Some(&(cx, hw)) = self.street.side_streets.iter().find(|(cx, hw)| end > cx - hw && x < cx + hw) {
                if x < cx - hw {
                    end = cx - hw;
                } else {
                    x = cx + hw;
                    continue;
                }
            }
            let height = 0.15;
            self.push_box(V3::new((x + end) * 0.5, y, height * 0.5), V3::new((end - x) * 0.5, w * 0.5, height * 0.5), 0.0, Material::Pavement { color });
            x = end;
        }
    }

    fn facade(&mut self) -> Facade {
        let floor_height = self.rng.random_range(2.9..3.8);
        let bay_width = self.rng.random_range(2.2..4.2);
        let base = self.pick(self.colors.facades);
        let trim = self.pick(self.colors.trims);
        Facade {
            base,
            trim,
            roof: self.pick(self.colors.roofs),
            floor_height,
            bay_width,
            window_width: bay_width * self.rng.random_range(0.35..0.7),
            window_height: floor_height * self.rng.random_range(0.35..0.6),
            sill: self.rng.random_range(0.8..1.1),
            door_bay: self.rng.random_range(0..4),
            shop: self.rng.random_bool(0.35).then(|| self.pick(&[[0.6, 0.1, 0.1], [0.1, 0.3, 0.6], [0.8, 0.6, 0.1], [0.1, 0.45, 0.2], [0.9, 0.9, 0.9]])),
            banded: self.rng.random_bool(0.3),
            seed: self.rng.random(),
        }
    }

    fn buildings(&mut self, side: f32, x0: f32, x1: f32) {
        let front_line = self.curb_y() + self.street.sidewalk_width;
        // A slowly varying "district" factor: taller, denser blocks in some stretches.
        let phase: f32 = self.rng.random_range(0.0..std::f32::consts::TAU);
        let wavelength: f32 = self.rng.random_range(120.0..260.0);
        let mut x = x0;
        while x < x1 {
            let district = 0.5 + 0.5 * (x / wavelength * std::f32::consts::TAU + phase).sin();
            let gap = if self.rng.random_bool(0.35 - 0.2 * district as f64) { self.rng.random_range(2.0..14.0) } else { 0.0 };
            x += gap;
            let width: f32 = self.rng.random_range(6.0..24.0);
            if self.in_side_street(x, x + width, 1.0) {
                x += 4.0;
                continue;
            }
            if self.rng.random_bool(0.08) {
                // Empty lot with a few trees.
                for _ in 0..self.rng.random_range(1..4) {
                    let tx = x + self.rng.random_range(0.0..width);
                    let ty = side * (front_line + self.rng.random_range(3.0..12.0));
                    self.tree(tx, ty);
                }
                x += width;
                continue;
            }
            let facade = self.facade();
            let floors = (1.0 + district * 6.0 + self.rng.random_range(-1.0..2.5)).round().clamp(1.0, 9.0);
            let height = floors * facade.floor_height + self.rng.random_range(0.2..1.2);
            let depth: f32 = self.rng.random_range(8.0..18.0);
            let setback = if self.rng.random_bool(0.6) { self.rng.random_range(0.0..0.6) } else { self.rng.random_range(1.0..5.0) };
            let yaw = if self.rng.random_bool(0.2) { self.rng.random_range(-0.12..0.12) } else { 0.0 };
            let cy = side * (front_line + setback + depth * 0.5);
            self.push_box(V3::new(x + width * 0.5, cy, height * 0.5), V3::new(width * 0.5, depth * 0.5, height * 0.5), yaw, Material::Facade(facade));
            if floors >= 4.0 && self.rng.random_bool(0.3) {
                // A set-back upper storey block for a varied roof line.
                let upper = self.rng.random_range(1.0..3.0) * facade.floor_height;
                let inset = self.rng.random_range(1.0..3.0);
                let upper_facade = Facade { seed: self.rng.random(), shop: None, ..facade };
                self.push_box(
                    V3::new(x + width * 0.5, cy + side * inset * 0.5, height + upper * 0.5),
                    V3::new((width * 0.5 - inset).max(1.5), (depth * 0.5 - inset).max(1.5), upper * 0.5),
                    yaw,
                    Material::Facade(Facade { door_bay: -10, ..upper_facade }),
                );
            }
            if self.rng.random_bool(0.5) {
                // A second row behind, seen through gaps and above low fronts.
                let back_facade = self.facade();
                let back_depth = self.rng.random_range(8.0..16.0);
                let back_height = self.rng.random_range(2.0..9.0) * back_facade.floor_height;
                let back_y = side * (front_line + setback + depth + self.rng.random_range(3.0..12.0) + back_depth * 0.5);
                let back_width = width * self.rng.random_range(0.6..1.2);
                let back_x = x + width * 0.5 + self.rng.random_range(-3.0..3.0);
                self.push_box(
                    V3::new(back_x, back_y, back_height * 0.5),
                    V3::new(back_width * 0.5, back_depth * 0.5, back_height * 0.5),
                    0.0,
                    Material::Facade(Facade { shop: None, ..back_facade }),
                );
            }
            if setback > 1.8 && self.rng.random_bool(0.7) {
                // Hedge or bushes in the front yard.
                let color = self.pick(self.colors.foliage);
                let hy = side * (front_line + setback * 0.5);
                if self.rng.random_bool(0.5) {
                    let h = self.rng.random_range(0.7..1.5);
                    let seed = self.rng.random();
                    self.push_box(V3::new(x + width * 0.5, hy, h * 0.5), V3::new(width * 0.4, 0.4, h * 0.5), 0.0, Material::Foliage { color, seed });
                } else {
                    for _ in 0..self.rng.random_range(1..4) {
                        let bx = x + self.rng.random_range(0.0..width);
                        let r = self.rng.random_range(0.5..1.1);
                        self.out.push(Primitive {
                            shape: Shape::Ellipsoid { center: V3::new(bx, hy, r * 0.6), radii: V3::new(r, r * 0.9, r * 0.8) },
                            material: Material::Foliage { color, seed: self.rng.random() },
                        });
                    }
                }
            }
            x += width;
        }
    }

    fn tree(&mut self, x: f32, y: f32) {
        let trunk_h = self.rng.random_range(1.8..3.5);
        let trunk_r = self.rng.random_range(0.12..0.28);
        let bark = [0.22, 0.16, 0.11];
        self.out.push(Primitive {
            shape: Shape::Cylinder { x, y, radius: trunk_r, z0: 0.0, z1: trunk_h + 0.5 },
            material: Material::Plain { color: bark, reflectivity: 0.35, grain: 0.4 },
        });
        let r = self.rng.random_range(1.3..3.2);
        let color = self.pick(self.colors.foliage);
        let rz = r * self.rng.random_range(0.8..1.4);
        self.out.push(Primitive {
            shape: Shape::Ellipsoid { center: V3::new(x, y, trunk_h + rz * 0.8), radii: V3::new(r, r * self.rng.random_range(0.85..1.15), rz) },
            material: Material::Foliage { color, seed: self.rng.random() },
        });
    }

    fn street_furniture(&mut self, side: f32, x0: f32, x1: f32) {
        let curb = self.curb_y();
        let metal = Material::Plain { color: [0.32, 0.33, 0.34], reflectivity: 0.45, grain: 0.2 };
        // Street lights.
        let mut x = x0 + self.rng.random_range(0.0..20.0);
        while x < x1 {
            if !self.in_side_street(x - 1.0, x + 1.0, 0.5) {
                let h = self.rng.random_range(6.5..9.0);
                let py = side * (curb + 0.5);
                self.out.push(Primitive { shape: Shape::Cylinder { x, y: py, radius: 0.1, z0: 0.0, z1: h }, material: metal });
                let arm = self.rng.random_range(0.8..2.2);
                self.push_box(V3::new(x, py - side * arm * 0.5, h - 0.1), V3::new(0.05, arm * 0.5, 0.05), 0.0, metal);
                self.push_box(V3::new(x, py - side * arm, h - 0.2), V3::new(0.25, 0.35, 0.08), 0.0, Material::Plain { color: [0.75, 0.74, 0.7], reflectivity: 0.5, grain: 0.0 });
            }
            x += self.rng.random_range(22.0..38.0) / self.clutter.max(0.5);
        }
        // Trees along the sidewalk, with irregular spacing and occasional long gaps.
        let mut x = x0 + self.rng.random_range(0.0..10.0);
        while x < x1 {
            let ty = side * (curb + self.street.sidewalk_width * self.rng.random_range(0.45..0.75));
            if !self.in_side_street(x - 2.0, x + 2.0, 1.0) && self.rng.random_bool((0.55 * self.clutter as f64).min(1.0)) {
                self.tree(x, ty);
            }
            x += self.rng.random_range(7.0..22.0);
        }
        // Signs, bins, bollards.
        let mut x = x0 + self.rng.random_range(0.0..15.0);
        while x < x1 {
            if !self.in_side_street(x - 1.0, x + 1.0, 0.5) {
                let y = side * (curb + self.rng.random_range(0.3..0.8));
                match self.rng.random_range(0..3) {
                    0 => {
                        let h = self.rng.random_range(2.2..3.0);
                        self.out.push(Primitive { shape: Shape::Cylinder { x, y, radius: 0.04, z0: 0.0, z1: h }, material: metal });
                        let colors = [[0.7, 0.05, 0.05], [0.05, 0.2, 0.6], [0.85, 0.7, 0.05], [0.9, 0.9, 0.9], [0.05, 0.45, 0.15]];
                        let color = colors[self.rng.random_range(0..colors.len())];
                        let size = self.rng.random_range(0.25..0.45);
                        self.push_box(V3::new(x, y, h + size * 0.8), V3::new(0.02, size, size), 0.0, Material::Sign { color });
                    }
                    1 => {
                        let color = [[0.1, 0.25, 0.1], [0.3, 0.3, 0.3], [0.5, 0.3, 0.1]][self.rng.random_range(0..3)];
                        self.push_box(V3::new(x, y + side * 0.4, 0.5), V3::new(0.3, 0.3, 0.5), 0.0, Material::Plain { color, reflectivity: 0.3, grain: 0.2 });
                    }
                    _ => {
                        for k in 0..self.rng.random_range(2..6) {
                            self.out.push(Primitive {
                                shape: Shape::Cylinder { x: x + k as f32 * 1.5, y, radius: 0.08, z0: 0.0, z1: 0.9 },
                                material: Material::Plain { color: [0.6, 0.6, 0.58], reflectivity: 0.5, grain: 0.1 },
                            });
                        }
                    }
                }
            }
            x += self.rng.random_range(10.0..40.0) / self.clutter.max(0.3);
        }
    }

    fn parked_cars(&mut self, side: f32, x0: f32, x1: f32) {
        let lane_y = side * (self.curb_y() - 1.1);
        let mut x = x0;
        while x < x1 {
            let length: f32 = self.rng.random_range(3.8..4.9);
            let occupied = self.rng.random_bool((0.45 * self.clutter as f64).clamp(0.0, 0.95));
            if occupied && !self.in_side_street(x, x + length, 2.0) {
                let jitter = self.rng.random_range(-0.2..0.2);
                self.car(x + length * 0.5, lane_y + jitter, length);
            }
            x += length + self.rng.random_range(0.6..3.0) + if self.rng.random_bool(0.15) { self.rng.random_range(5.0..20.0) } else { 0.0 };
        }
    }

    fn car(&mut self, x: f32, y: f32, length: f32) {
        let color = self.pick(self.colors.cars);
        let yaw = self.rng.random_range(-0.05..0.05);
        let width = self.rng.random_range(1.7..1.95);
        let body_h = self.rng.random_range(0.65..0.9);
        let material = Material::Car { color };
        self.push_box(V3::new(x, y, 0.3 + body_h * 0.5), V3::new(length * 0.5, width * 0.5, body_h * 0.5), yaw, material);
        let cabin_h = self.rng.random_range(0.5..0.75);
        let cabin_len = length * self.rng.random_range(0.45..0.6);
        let offset = self.rng.random_range(-0.3..0.1) * length * 0.2;
        let (c, s) = (yaw.cos(), yaw.sin());
        self.push_box(
            V3::new(x + c * offset, y + s * offset, 0.3 + body_h + cabin_h * 0.5),
            V3::new(cabin_len * 0.5, width * 0.45, cabin_h * 0.5),
            yaw,
            material,
        );
        let tyre = Material::Plain { color: [0.03, 0.03, 0.03], reflectivity: 0.08, grain: 0.0 };
        for (fx, fy) in [(0.33, 0.5), (0.33, -0.5), (-0.33, 0.5), (-0.33, -0.5)] {
            let (lx, ly) = (fx * length, fy * (width - 0.2));
            self.push_box(V3::new(x + c * lx - s * ly, y + s * lx + c * ly, 0.32), V3::new(0.32, 0.11, 0.32), yaw, tyre);
        }
    }
}
