//! Building blocks shared by the world families, placed in the straight road frame (x along
//! the road, y = ŷ across it, z = height above the local ground); `bend` later puts them onto
//! the curved, sloping road. Foliage is clusters of many small blobs, so a LiDAR sees it as
//! scattered points rather than one smooth shell.

use rand::Rng;
use rand_chacha::ChaCha8Rng;

use super::super::materials::{scale, Facade, Material};
use super::super::paint::RoadPaint;
use super::super::scene::{Class, Primitive};
use super::super::shapes::{Shape, V3};
use super::super::style::Colors;

/// A crown of `Foliage` blobs filling the ellipsoid (`center`, `radii`): 12–70 blobs of
/// 0.2–0.7 m, denser towards the outside like a real crown.
pub fn crown(rng: &mut ChaCha8Rng, out: &mut Vec<Primitive>, center: V3, radii: V3, color: [f32; 3], seed: u64) {
    let volume = radii.x * radii.y * radii.z;
    let blobs = (volume * 2.5).clamp(12.0, 70.0) as usize;
    let size = (radii.min() * 0.45).clamp(0.2, 0.7);
    for i in 0..blobs {
        // A direction on the unit sphere and a radius biased to the shell.
        let z: f32 = rng.random_range(-1.0..1.0);
        let phi: f32 = rng.random_range(0.0..std::f32::consts::TAU);
        let r = rng.random_range(0.35f32..1.0).sqrt() * 0.85;
        let s = (1.0 - z * z).sqrt();
        let offset = V3::new(s * phi.cos() * radii.x, s * phi.sin() * radii.y, z * radii.z) * r;
        let b = size * rng.random_range(0.6..1.3);
        let k = rng.random_range(0.8..1.15);
        out.push(Primitive::new(
            Shape::Ellipsoid { center: center + offset, radii: V3::new(b, b * rng.random_range(0.7..1.2), b * rng.random_range(0.6..1.0)) },
            Material::Foliage { color: scale(color, k), seed: seed ^ i as u64 },
        ));
    }
}

/// Vehicle body types.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Vehicle {
    Car,
    Van,
    Truck,
}

pub struct Kit<'a> {
    pub rng: &'a mut ChaCha8Rng,
    pub colors: Colors,
    /// Density multiplier of small objects (the style's clutter).
    pub clutter: f32,
    /// The road's painted layout (lanes, junctions).
    pub paint: &'a RoadPaint,
    /// x range covered by the scene and by the vehicle's path.
    pub range: (f32, f32),
    pub drive: (f32, f32),
    pub out: Vec<Primitive>,
}

impl Kit<'_> {
    pub fn pick(&mut self, list: &[[f32; 3]]) -> [f32; 3] {
        let c = list[self.rng.random_range(0..list.len())];
        scale(c, self.rng.random_range(0.85..1.15))
    }

    pub fn push(&mut self, shape: Shape, material: Material, class: Class) {
        self.out.push(Primitive { shape, material, class });
    }

    /// A box `size` (length along its yaw, width, height) with its bottom `z0` above ground.
    #[allow(clippy::too_many_arguments)]
    pub fn block(&mut self, x: f32, y: f32, z0: f32, size: [f32; 3], yaw: f32, material: Material, class: Class) {
        let half = V3::new(size[0] * 0.5, size[1] * 0.5, size[2] * 0.5);
        self.push(Shape::Box { center: V3::new(x, y, z0 + half.z), half, cos: yaw.cos(), sin: yaw.sin() }, material, class);
    }

    /// Whether [xa, xb] is clear of junctions (with `extra` metres to spare).
    pub fn free(&self, xa: f32, xb: f32, extra: f32) -> bool {
        !self.paint.junctions.iter().any(|(cx, hw)| xb > cx - hw - extra && xa < cx + hw + extra)
    }

    /// A metal or wooden pole from the ground.
    pub fn pole(&mut self, x: f32, y: f32, height: f32, radius: f32, color: [f32; 3]) {
        let m = Material::Plain { color, reflectivity: 0.45, grain: 0.3 };
        self.push(Shape::Cylinder { x, y, radius, z0: 0.0, z1: height }, m, Class::Structure);
    }

    pub fn tree(&mut self, x: f32, y: f32, size: f32) {
        let trunk_h = self.rng.random_range(1.5..3.2) * size;
        let bark = [0.22, 0.16, 0.11];
        let trunk = Material::Plain { color: bark, reflectivity: 0.35, grain: 0.4 };
        let radius = self.rng.random_range(0.1..0.3) * size.sqrt();
        self.push(Shape::Cylinder { x, y, radius, z0: 0.0, z1: trunk_h + 0.6 }, trunk, Class::Vegetation);
        let color = self.pick(self.colors.foliage);
        let seed = self.rng.random();
        if self.rng.random_bool(0.2) {
            // Conifer: blob layers shrinking upwards.
            let height = self.rng.random_range(5.0..11.0) * size;
            let layers = (height / 1.2) as usize;
            for l in 0..layers {
                let f = l as f32 / layers as f32;
                let r = (1.0 - f) * self.rng.random_range(1.4..2.4) * size + 0.3;
                let center = V3::new(x, y, trunk_h * 0.6 + f * height);
                crown(self.rng, &mut self.out, center, V3::new(r, r, 0.6), color, seed ^ l as u64);
            }
        } else {
            let r = self.rng.random_range(1.5..3.5) * size;
            let rz = r * self.rng.random_range(0.7..1.3);
            let radii = V3::new(r * self.rng.random_range(0.8..1.2), r * self.rng.random_range(0.8..1.2), rz);
            crown(self.rng, &mut self.out, V3::new(x, y, trunk_h + rz * 0.85), radii, color, seed);
        }
    }

    pub fn bush(&mut self, x: f32, y: f32, r: f32) {
        let color = self.pick(self.colors.foliage);
        let seed = self.rng.random();
        let ry = r * self.rng.random_range(0.7..1.2);
        crown(self.rng, &mut self.out, V3::new(x, y, r * 0.7), V3::new(r, ry, r * 0.8), color, seed);
    }

    /// A hedge from xa to xb at y: overlapping blobs, irregular in height and depth.
    pub fn hedge(&mut self, xa: f32, xb: f32, y: f32, height: f32, depth: f32) {
        let color = self.pick(self.colors.foliage);
        let seed: u64 = self.rng.random();
        let mut x = xa;
        let mut i = 0u64;
        while x < xb {
            for _ in 0..2 {
                let r = depth * 0.5 * self.rng.random_range(0.7..1.3);
                let z = self.rng.random_range(0.3..1.0) * (height - r).max(r);
                let c = V3::new(x + self.rng.random_range(-0.2..0.2), y + self.rng.random_range(-0.25..0.25) * depth, z);
                let m = Material::Foliage { color: scale(color, self.rng.random_range(0.85..1.15)), seed: seed ^ i };
                self.push(Shape::Ellipsoid { center: c, radii: V3::new(r * 1.1, r, r.max(height * 0.35)) }, m, Class::Vegetation);
                i += 1;
            }
            x += self.rng.random_range(0.4..0.8);
        }
    }

    /// A vehicle centred at (x, y), heading `yaw` (0 = along +x).
    pub fn vehicle(&mut self, x: f32, y: f32, yaw: f32, kind: Vehicle) {
        let color = self.pick(self.colors.cars);
        let (c, s) = (yaw.cos(), yaw.sin());
        let at = |lx: f32, ly: f32| (x + c * lx - s * ly, y + s * lx + c * ly);
        let (length, width, body_h, cabin_h, cabin_len, cabin_at) = match kind {
            Vehicle::Car => {
                let l = self.rng.random_range(3.8..4.9);
                (l, self.rng.random_range(1.7..1.95), self.rng.random_range(0.65..0.9), self.rng.random_range(0.5..0.75), l * self.rng.random_range(0.45..0.6), -0.05 * l)
            }
            Vehicle::Van => {
                let l = self.rng.random_range(4.8..5.8);
                (l, self.rng.random_range(1.9..2.05), self.rng.random_range(0.9..1.1), self.rng.random_range(0.9..1.2), l * 0.8, -0.08 * l)
            }
            Vehicle::Truck => {
                let l = self.rng.random_range(7.5..12.0);
                (l, 2.5, 0.9, 2.4, l - 2.4, -1.3)
            }
        };
        self.block(x, y, 0.3, [length, width, body_h], yaw, Material::Car { color, cabin: false }, Class::Vehicle);
        let (cx, cy) = at(cabin_at, 0.0);
        if kind == Vehicle::Truck {
            // Cargo box behind a cab with windows.
            let cargo = self.pick(&[[0.8, 0.8, 0.78], [0.6, 0.1, 0.08], [0.1, 0.2, 0.45], [0.75, 0.6, 0.1]]);
            self.block(cx, cy, 0.3 + body_h, [cabin_len, width, cabin_h], yaw, Material::Corrugated { color: cargo, pitch: 0.4 }, Class::Vehicle);
            let (hx, hy) = at(length * 0.5 - 1.1, 0.0);
            self.block(hx, hy, 0.3 + body_h, [2.0, width * 0.95, 1.3], yaw, Material::Car { color, cabin: true }, Class::Vehicle);
        } else {
            self.block(cx, cy, 0.3 + body_h, [cabin_len, width * 0.9, cabin_h], yaw, Material::Car { color, cabin: true }, Class::Vehicle);
        }
        let tyre = Material::Plain { color: [0.03, 0.03, 0.03], reflectivity: 0.08, grain: 0.0 };
        for (fx, fy) in [(0.33, 0.5), (0.33, -0.5), (-0.33, 0.5), (-0.33, -0.5)] {
            let (wx, wy) = at(fx * length, fy * (width - 0.2));
            self.block(wx, wy, 0.0, [0.64, 0.22, 0.64], yaw, tyre, Class::Vehicle);
        }
    }

    fn clothes(&mut self) -> [f32; 3] {
        self.pick(&[[0.05, 0.05, 0.06], [0.15, 0.15, 0.2], [0.3, 0.28, 0.25], [0.5, 0.08, 0.06], [0.1, 0.2, 0.45], [0.7, 0.7, 0.68], [0.6, 0.5, 0.1]])
    }

    /// A standing or walking person at (x, y).
    pub fn pedestrian(&mut self, x: f32, y: f32) {
        let k = self.rng.random_range(0.85..1.1);
        let legs = Material::Plain { color: self.clothes(), reflectivity: 0.25, grain: 0.2 };
        let top = Material::Plain { color: self.clothes(), reflectivity: 0.25, grain: 0.2 };
        let skin = Material::Plain { color: self.pick(&[[0.6, 0.42, 0.32], [0.35, 0.22, 0.15], [0.7, 0.55, 0.45]]), reflectivity: 0.3, grain: 0.1 };
        let stride = self.rng.random_range(0.0..0.25);
        let yaw: f32 = self.rng.random_range(0.0..std::f32::consts::TAU);
        for side in [-1.0f32, 1.0] {
            let (lx, ly) = (x + side * stride * yaw.cos() - side * 0.1 * yaw.sin(), y + side * stride * yaw.sin() + side * 0.1 * yaw.cos());
            self.push(Shape::Cylinder { x: lx, y: ly, radius: 0.075, z0: 0.0, z1: 0.88 * k }, legs, Class::Person);
        }
        self.block(x, y, 0.85 * k, [0.26, 0.42, 0.6 * k], yaw, top, Class::Person);
        self.push(Shape::Ellipsoid { center: V3::new(x, y, 1.6 * k), radii: V3::new(0.1, 0.1, 0.13) }, skin, Class::Person);
    }

    /// A person on a bicycle heading `yaw`.
    pub fn cyclist(&mut self, x: f32, y: f32, yaw: f32) {
        let (c, s) = (yaw.cos(), yaw.sin());
        let frame = Material::Plain { color: self.pick(&[[0.6, 0.05, 0.05], [0.05, 0.05, 0.05], [0.1, 0.3, 0.6], [0.8, 0.8, 0.8]]), reflectivity: 0.5, grain: 0.1 };
        let tyre = Material::Plain { color: [0.03, 0.03, 0.03], reflectivity: 0.1, grain: 0.0 };
        for f in [-0.52f32, 0.52] {
            self.block(x + c * f, y + s * f, 0.0, [0.68, 0.04, 0.68], yaw, tyre, Class::Person);
        }
        self.block(x, y, 0.45, [1.0, 0.05, 0.1], yaw, frame, Class::Person);
        let top = Material::Plain { color: self.clothes(), reflectivity: 0.25, grain: 0.2 };
        self.block(x - c * 0.1, y - s * 0.1, 0.95, [0.35, 0.38, 0.58], yaw, top, Class::Person);
        self.push(Shape::Cylinder { x: x - c * 0.05, y: y - s * 0.05, radius: 0.09, z0: 0.35, z1: 0.98 }, top, Class::Person);
        let skin = Material::Plain { color: [0.55, 0.4, 0.3], reflectivity: 0.3, grain: 0.1 };
        self.push(Shape::Ellipsoid { center: V3::new(x + c * 0.02, y + s * 0.02, 1.68), radii: V3::new(0.11, 0.1, 0.13) }, skin, Class::Person);
    }

    /// Posts every `spacing` metres with `rails` horizontal bars (a fence, a guard rail).
    #[allow(clippy::too_many_arguments)]
    pub fn railing(&mut self, xa: f32, xb: f32, y: f32, spacing: f32, post: [f32; 3], rails: &[(f32, f32)], rail_depth: f32, material: Material) {
        let mut x = xa;
        while x < xb {
            let next = (x + spacing).min(xb);
            if self.free(x, next, 0.5) {
                self.block(x, y, 0.0, post, 0.0, material, Class::Structure);
                for &(z, h) in rails {
                    self.block((x + next) * 0.5, y, z, [next - x, rail_depth, h], 0.0, material, Class::Structure);
                }
            }
            x = next;
        }
    }

    pub fn fence(&mut self, xa: f32, xb: f32, y: f32) {
        let (color, reflectivity, wire) = if self.rng.random_bool(0.5) { ([0.35, 0.25, 0.16], 0.3, false) } else { ([0.45, 0.46, 0.47], 0.5, true) };
        let h = self.rng.random_range(1.0..1.8);
        let rails: Vec<(f32, f32)> = if wire { vec![(h * 0.45, 0.02), (h - 0.05, 0.03)] } else { vec![(h * 0.3, 0.1), (h * 0.75, 0.1)] };
        let spacing = self.rng.random_range(2.5..3.5);
        self.railing(xa, xb, y, spacing, [0.1, 0.1, h], &rails, 0.04, Material::Plain { color, reflectivity, grain: 0.3 });
    }

    pub fn guard_rail(&mut self, xa: f32, xb: f32, y: f32) {
        let steel = Material::Plain { color: [0.55, 0.56, 0.57], reflectivity: 0.7, grain: 0.2 };
        self.railing(xa, xb, y, 2.0, [0.1, 0.15, 0.75], &[(0.45, 0.32)], 0.06, steel);
    }

    /// A concrete barrier in 6 m pieces.
    pub fn barrier(&mut self, xa: f32, xb: f32, y: f32, height: f32) {
        let concrete = Material::Plain { color: [0.55, 0.54, 0.5], reflectivity: 0.35, grain: 0.4 };
        let mut x = xa;
        while x < xb {
            let next = (x + 6.0).min(xb);
            if self.free(x, next, 0.0) {
                self.block((x + next) * 0.5, y, 0.0, [next - x, 0.55, height], 0.0, concrete, Class::Structure);
            }
            x = next;
        }
    }

    /// A thin overhead wire at height z, in 10 m pieces.
    pub fn wire(&mut self, xa: f32, xb: f32, y: f32, z: f32) {
        let m = Material::Plain { color: [0.08, 0.08, 0.08], reflectivity: 0.3, grain: 0.0 };
        let mut x = xa;
        while x < xb {
            let next = (x + 10.0).min(xb);
            self.block((x + next) * 0.5, y, z, [next - x, 0.025, 0.025], 0.0, m, Class::Structure);
            x = next;
        }
    }

    /// A street light on `side` (±1) at (x, y), its arm reaching over the road.
    pub fn street_light(&mut self, x: f32, y: f32, side: f32, height: f32) {
        let metal = Material::Plain { color: [0.32, 0.33, 0.34], reflectivity: 0.45, grain: 0.2 };
        self.push(Shape::Cylinder { x, y, radius: 0.1, z0: 0.0, z1: height }, metal, Class::Structure);
        let arm = self.rng.random_range(0.8..2.2);
        self.block(x, y - side * arm * 0.5, height - 0.15, [0.1, arm, 0.1], 0.0, metal, Class::Structure);
        let lamp = Material::Plain { color: [0.75, 0.74, 0.7], reflectivity: 0.5, grain: 0.0 };
        self.block(x, y - side * arm, height - 0.28, [0.5, 0.7, 0.16], 0.0, lamp, Class::Structure);
    }

    pub fn sign(&mut self, x: f32, y: f32) {
        let metal = Material::Plain { color: [0.32, 0.33, 0.34], reflectivity: 0.45, grain: 0.2 };
        let h = self.rng.random_range(2.0..2.8);
        self.push(Shape::Cylinder { x, y, radius: 0.04, z0: 0.0, z1: h }, metal, Class::Structure);
        let color = self.pick(&[[0.7, 0.05, 0.05], [0.05, 0.2, 0.6], [0.85, 0.7, 0.05], [0.9, 0.9, 0.9], [0.05, 0.45, 0.15]]);
        let size = self.rng.random_range(0.5..0.9);
        self.block(x, y, h, [0.04, size, size], 0.0, Material::Sign { color }, Class::Structure);
    }

    /// A facade material in the palette's colours with `floor` metres per storey.
    pub fn facade(&mut self, floor: f32) -> Facade {
        let bay_width = self.rng.random_range(2.2..4.2);
        Facade {
            base: self.pick(self.colors.facades),
            trim: self.pick(self.colors.trims),
            roof: self.pick(self.colors.roofs),
            floor_height: floor,
            bay_width,
            window_width: bay_width * self.rng.random_range(0.3..0.6),
            window_height: floor * self.rng.random_range(0.35..0.55),
            sill: self.rng.random_range(0.8..1.1),
            door_bay: self.rng.random_range(0..4),
            shop: None,
            banded: self.rng.random_bool(0.2),
            seed: self.rng.random(),
        }
    }

    /// A house whose front faces the road at |y| = `front` on `side`: walls plus a stepped
    /// (hipped-looking) roof.
    pub fn house(&mut self, x: f32, front: f32, side: f32, width: f32, depth: f32) {
        let floors = if self.rng.random_bool(0.6) { 1.0 } else { 2.0 };
        let floor = self.rng.random_range(2.7..3.1);
        let facade = self.facade(floor);
        let wall_h = floors * facade.floor_height + 0.3;
        let cy = side * (front + depth * 0.5);
        let yaw = self.rng.random_range(-0.08..0.08);
        self.block(x, cy, 0.0, [width, depth, wall_h], yaw, Material::Facade(facade), Class::Building);
        let roof = Material::Plain { color: facade.roof, reflectivity: 0.2, grain: 0.5 };
        let pitch = self.rng.random_range(0.35..0.8);
        for step in 0..4 {
            let inset = step as f32 * 0.25 * depth * 0.5;
            let (w, d) = (width + 0.6 - 2.0 * inset, depth + 0.6 - 2.0 * inset);
            if w < 0.6 || d < 0.6 {
                break;
            }
            let dz = 0.25 * depth * 0.5 * pitch;
            self.block(x, cy, wall_h + step as f32 * dz, [w, d, dz + 0.02], yaw, roof, Class::Building);
        }
    }

    /// A block of `height` metres with its front at |y| = `front`.
    #[allow(clippy::too_many_arguments)]
    pub fn building(&mut self, x: f32, front: f32, side: f32, width: f32, depth: f32, height: f32, material: Material) {
        self.block(x, side * (front + depth * 0.5), 0.0, [width, depth, height], 0.0, material, Class::Building);
    }

    /// Traffic on every lane except the vehicle's own within the driven stretch: oncoming lanes
    /// face −x. `per_100m` vehicles per lane per 100 m.
    pub fn traffic(&mut self, ego_lane: u32, per_100m: f32, heavy_share: f64) {
        let paint = self.paint;
        let (x0, x1) = self.range;
        for side in [-1.0f32, 1.0] {
            for lane in 0..paint.lanes_each_way {
                let y = paint.lane_centre(side, lane);
                let mut x = x0 + self.rng.random_range(0.0..30.0);
                while x < x1 {
                    let own = side < 0.0 && lane == ego_lane && x > self.drive.0 - 12.0 && x < self.drive.1 + 12.0;
                    if !own && !paint.in_junction(x, 3.0) {
                        let kind = if self.rng.random_bool(heavy_share) {
                            if self.rng.random_bool(0.5) { Vehicle::Van } else { Vehicle::Truck }
                        } else {
                            Vehicle::Car
                        };
                        let yaw = if side > 0.0 { std::f32::consts::PI } else { 0.0 } + self.rng.random_range(-0.03..0.03);
                        let dy = self.rng.random_range(-0.3..0.3);
                        self.vehicle(x, y + dy, yaw, kind);
                    }
                    x += self.rng.random_range(8.0..40.0) * 100.0 / (per_100m.max(0.1) * 25.0);
                }
            }
        }
    }

    /// Parked cars in the parking strips (both sides).
    pub fn parked(&mut self, occupancy: f64) {
        let paint = self.paint;
        if paint.parking_m < 1.8 {
            return;
        }
        let (x0, x1) = self.range;
        for side in [-1.0f32, 1.0] {
            let y = paint.parking_centre(side);
            let mut x = x0;
            while x < x1 {
                let l = self.rng.random_range(4.2..5.6);
                if self.rng.random_bool(occupancy) && !paint.in_junction(x, 3.0) {
                    let kind = if self.rng.random_bool(0.15) { Vehicle::Van } else { Vehicle::Car };
                    let yaw = if self.rng.random_bool(0.8) { 0.0 } else { std::f32::consts::PI } + self.rng.random_range(-0.04..0.04);
                    let dy = self.rng.random_range(-0.2..0.2);
                    self.vehicle(x + l * 0.5, y + dy, yaw, kind);
                }
                x += l + self.rng.random_range(0.5..3.0);
            }
        }
    }

    /// People along both roadsides between |y| = `from` and `to`, `per_100m` per side, and
    /// cyclists: on the oncoming edge of the road and on the roadside.
    pub fn people(&mut self, from: f32, to: f32, per_100m: f32, cyclists_per_100m: f32) {
        let (x0, x1) = self.range;
        let len = x1 - x0;
        for side in [-1.0f32, 1.0] {
            for _ in 0..(len / 100.0 * per_100m * self.clutter) as usize {
                let x = self.rng.random_range(x0..x1);
                let y = side * self.rng.random_range(from..to.max(from + 0.1));
                self.pedestrian(x, y);
            }
        }
        let edge = self.paint.half_width() - 0.7;
        for _ in 0..(len / 100.0 * cyclists_per_100m * self.clutter) as usize {
            let x = self.rng.random_range(x0..x1);
            if self.rng.random_bool(0.5) {
                let yaw = std::f32::consts::PI + self.rng.random_range(-0.1..0.1);
                self.cyclist(x, edge, yaw);
            } else {
                let side = if self.rng.random_bool(0.5) { 1.0 } else { -1.0 };
                let y = side * self.rng.random_range(from..to.max(from + 0.1));
                let yaw = if self.rng.random_bool(0.5) { 0.0 } else { std::f32::consts::PI };
                self.cyclist(x, y, yaw);
            }
        }
    }
}
