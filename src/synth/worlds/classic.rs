//! Today's street (the `classic` world, and the core of `urban`): a straight street with box
//! buildings, sidewalks, street furniture, trees and parked cars, drawn independently along x.
//! The draw order is frozen: `classic` must keep producing today's bytes.

use rand::Rng;
use rand_chacha::ChaCha8Rng;

use super::super::materials::{scale, Facade, Material};
use super::super::scene::{Class, Ground, Primitive, Scene};
use super::super::shapes::{Shape, V3};
use super::super::street::Street;
use super::super::style::{Colors, Style};

/// What the street's builder does beyond today's street.
#[derive(Debug, Clone, Copy, Default)]
pub struct Extras {
    /// Sidewalks are painted on a kerbed terrain instead of being raised boxes.
    pub no_sidewalk_boxes: bool,
    /// Tree crowns are clusters of small blobs instead of one ellipsoid.
    pub irregular_trees: bool,
}

/// Generates today's street covering x in `[x0, x1]` (the drive range plus the sensor range).
pub fn build_street(rng: &mut ChaCha8Rng, drive_range: (f32, f32), margin: f32, style: &Style) -> Scene {
    let colors = style.palette.colors();
    let (x0, x1) = (drive_range.0 - margin, drive_range.1 + margin);
    let street = draw_street(rng, x0, x1, &colors);
    let primitives = street_primitives(rng, style, &colors, &street, x0, x1, Extras::default());
    Scene::new(Ground::Street(street), None, primitives, drive_range)
}

/// The street's layout: widths, parking lanes, side streets, crossings.
pub fn draw_street(rng: &mut ChaCha8Rng, x0: f32, x1: f32, colors: &Colors) -> Street {
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
    Street {
        road_half_width,
        sidewalk_width,
        parking,
        crossings,
        side_streets,
        asphalt: colors.asphalt,
        lot: colors.lot,
        seed: rng.random(),
    }
}

/// Everything standing on the street, in the street frame (z = height above the ground).
pub fn street_primitives(rng: &mut ChaCha8Rng, style: &Style, colors: &Colors, street: &Street, x0: f32, x1: f32, extras: Extras) -> Vec<Primitive> {
    let mut builder = Builder { rng, colors, clutter: style.clutter, street, extras, out: Vec::new() };
    for side in [1.0f32, -1.0] {
        if !extras.no_sidewalk_boxes {
            builder.sidewalk(side, x0, x1);
        }
        builder.buildings(side, x0, x1);
        builder.street_furniture(side, x0, x1);
        if street.parking {
            builder.parked_cars(side, x0, x1);
        }
    }
    builder.out
}

struct Builder<'a> {
    rng: &'a mut ChaCha8Rng,
    colors: &'a Colors,
    clutter: f32,
    street: &'a Street,
    extras: Extras,
    out: Vec<Primitive>,
}

impl Builder<'_> {
    fn pick(&mut self, list: &'static [[f32; 3]]) -> [f32; 3] {
        let c = list[self.rng.random_range(0..list.len())];
        let k = self.rng.random_range(0.85..1.15);
        scale(c, k)
    }

    fn push_box(&mut self, center: V3, half: V3, yaw: f32, material: Material) {
        self.out.push(Primitive::new(Shape::Box { center, half, cos: yaw.cos(), sin: yaw.sin() }, material));
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
                        self.out.push(Primitive::new(
                            Shape::Ellipsoid { center: V3::new(bx, hy, r * 0.6), radii: V3::new(r, r * 0.9, r * 0.8) },
                            Material::Foliage { color, seed: self.rng.random() },
                        ));
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
            class: Class::Vegetation,
        });
        let r = self.rng.random_range(1.3..3.2);
        let color = self.pick(self.colors.foliage);
        let rz = r * self.rng.random_range(0.8..1.4);
        let center = V3::new(x, y, trunk_h + rz * 0.8);
        let radii = V3::new(r, r * self.rng.random_range(0.85..1.15), rz);
        let seed = self.rng.random();
        if self.extras.irregular_trees {
            super::kit::crown(self.rng, &mut self.out, center, radii, color, seed);
        } else {
            self.out.push(Primitive::new(Shape::Ellipsoid { center, radii }, Material::Foliage { color, seed }));
        }
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
                self.out.push(Primitive::new(Shape::Cylinder { x, y: py, radius: 0.1, z0: 0.0, z1: h }, metal));
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
                        self.out.push(Primitive::new(Shape::Cylinder { x, y, radius: 0.04, z0: 0.0, z1: h }, metal));
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
                            self.out.push(Primitive::new(
                                Shape::Cylinder { x: x + k as f32 * 1.5, y, radius: 0.08, z0: 0.0, z1: 0.9 },
                                Material::Plain { color: [0.6, 0.6, 0.58], reflectivity: 0.5, grain: 0.1 },
                            ));
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
        self.push_box(V3::new(x, y, 0.3 + body_h * 0.5), V3::new(length * 0.5, width * 0.5, body_h * 0.5), yaw, Material::Car { color, cabin: false });
        let cabin_h = self.rng.random_range(0.5..0.75);
        let cabin_len = length * self.rng.random_range(0.45..0.6);
        let offset = self.rng.random_range(-0.3..0.1) * length * 0.2;
        let (c, s) = (yaw.cos(), yaw.sin());
        self.push_box(
            V3::new(x + c * offset, y + s * offset, 0.3 + body_h + cabin_h * 0.5),
            V3::new(cabin_len * 0.5, width * 0.45, cabin_h * 0.5),
            yaw,
            Material::Car { color, cabin: true },
        );
        let tyre = Material::Plain { color: [0.03, 0.03, 0.03], reflectivity: 0.08, grain: 0.0 };
        for (fx, fy) in [(0.33, 0.5), (0.33, -0.5), (-0.33, 0.5), (-0.33, -0.5)] {
            let (lx, ly) = (fx * length, fy * (width - 0.2));
            let (center, half) = (V3::new(x + c * lx - s * ly, y + s * lx + c * ly, 0.32), V3::new(0.32, 0.11, 0.32));
            self.out.push(Primitive { shape: Shape::Box { center, half, cos: yaw.cos(), sin: yaw.sin() }, material: tyre, class: Class::Vehicle });
        }
    }
}
