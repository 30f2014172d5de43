//! Industrial estate or port: wide lanes, concrete yards behind mesh fences, big ribbed sheds,
//! stacks of shipping containers, parked trucks and vans, tall light masts, few plants.

use rand::Rng;
use rand_chacha::ChaCha8Rng;

use super::super::materials::Material;
use super::super::paint::Verge;
use super::super::scene::Class;
use super::super::style::Colors;
use super::super::terrain::{RoadShape, Roadside};
use super::kit::{Kit, Vehicle};
use super::Layout;

pub fn layout(rng: &mut ChaCha8Rng, colors: &Colors, x0: f32, x1: f32) -> Layout {
    let mut paint = super::base_paint(rng, colors);
    paint.lanes_each_way = if rng.random_bool(0.6) { 1 } else { 2 };
    paint.lane_width_m = rng.random_range(3.5..4.2);
    paint.edge_lines = rng.random_bool(0.5);
    paint.shoulder_m = rng.random_range(0.0..1.5);
    paint.sidewalk_m = if rng.random_bool(0.5) { rng.random_range(1.5..2.5) } else { 0.0 };
    paint.verge = [0, 1].map(|_| if rng.random_bool(0.7) { Verge::Concrete } else { Verge::Gravel });
    paint.junctions = super::junctions(rng, x0, x1, (80.0, 220.0), 0.5, (5.0, 9.0));
    let (bank_mean, bank_wave) = super::bank(rng, 0.02);
    let shape = RoadShape {
        curve: super::curve(rng, 0.0..0.4),
        profile: super::profile(rng, 0.0..0.02),
        bank_mean,
        bank_wave,
        road_half_width_m: paint.half_width(),
        kerb_m: if paint.sidewalk_m > 0.0 { rng.random_range(0.1..0.16) } else { 0.0 },
        sides: [Roadside::default(); 2],
        junctions: paint.junctions.clone(),
    };
    let ego_lane = rng.random_range(0..paint.lanes_each_way);
    Layout { paint, shape, ego_lane }
}

const CONTAINER: [f32; 3] = [12.19, 2.44, 2.59];

pub fn populate(kit: &mut Kit, ego_lane: u32) {
    let paint = kit.paint;
    let (x0, x1) = kit.range;
    let edge = paint.half_width() + paint.sidewalk_m;
    for side in [1.0f32, -1.0] {
        let fence_y = side * (edge + kit.rng.random_range(1.0..4.0));
        kit.fence(x0, x1, fence_y);
        let yard = fence_y.abs() + 2.0;
        let mut x = x0;
        while x < x1 {
            let w = kit.rng.random_range(20.0..60.0);
            if kit.free(x, x + w, 2.0) {
                match kit.rng.random_range(0..3) {
                    0 => {
                        let color = kit.pick(&[[0.6, 0.6, 0.58], [0.2, 0.3, 0.45], [0.55, 0.2, 0.12], [0.3, 0.4, 0.3], [0.75, 0.72, 0.6]]);
                        let depth = kit.rng.random_range(15.0..40.0);
                        let h = kit.rng.random_range(6.0..14.0);
                        let a1 = kit.rng.random_range(4.0..20.0);
                        let a2 = kit.rng.random_range(0.15..0.4);
                        kit.building(x + w * 0.5, yard + a1, side, w * 0.9, depth, h, Material::Corrugated { color, pitch: a2 });
                    }
                    1 => {
                        // Container stacks in rows, long side along the road or across it.
                        let across = kit.rng.random_bool(0.4);
                        let rows = kit.rng.random_range(1..4);
                        let per_row = (w / if across { 2.6 } else { 12.5 }) as usize;
                        for r in 0..rows {
                            let y = side * (yard + 3.0 + r as f32 * if across { 13.0 } else { 2.6 } + if across { 6.1 } else { 1.2 });
                            for k in 0..per_row {
                                let cx = x + (k as f32 + 0.5) * if across { 2.6 } else { 12.5 };
                                let tiers = kit.rng.random_range(0..5);
                                for t in 0..tiers {
                                    let color = kit.pick(&[[0.6, 0.12, 0.08], [0.1, 0.25, 0.5], [0.15, 0.4, 0.2], [0.75, 0.55, 0.1], [0.5, 0.5, 0.5], [0.8, 0.8, 0.78], [0.4, 0.2, 0.3]]);
                                    let yaw = if across { std::f32::consts::FRAC_PI_2 } else { 0.0 } + kit.rng.random_range(-0.02..0.02);
                                    kit.block(cx, y, t as f32 * CONTAINER[2], CONTAINER, yaw, Material::Corrugated { color, pitch: 0.3 }, Class::Structure);
                                }
                            }
                        }
                    }
                    _ => {
                        // Yard with parked trucks and vans.
                        for _ in 0..kit.rng.random_range(1..5) {
                            let kind = if kit.rng.random_bool(0.6) { Vehicle::Truck } else { Vehicle::Van };
                            let yaw = kit.rng.random_range(0.0..std::f32::consts::TAU);
                            let a1 = kit.rng.random_range(0.0..w);
                            let a2 = kit.rng.random_range(4.0..20.0);
                            kit.vehicle(x + a1, side * (yard + a2), yaw, kind);
                        }
                    }
                }
            }
            x += w + kit.rng.random_range(2.0..15.0);
        }
        let mut x = x0 + kit.rng.random_range(0.0..60.0);
        while x < x1 {
            let a1 = kit.rng.random_range(12.0..20.0);
            kit.pole(x, fence_y - side * 0.5, a1, 0.2, [0.5, 0.5, 0.5]);
            x += kit.rng.random_range(50.0..90.0);
        }
        let mut x = x0 + kit.rng.random_range(0.0..40.0);
        while x < x1 {
            if kit.free(x - 1.0, x + 1.0, 1.0) {
                let a1 = kit.rng.random_range(0.5..1.2);
                kit.bush(x, fence_y - side * 0.8, a1);
            }
            x += kit.rng.random_range(15.0..70.0) / kit.clutter.max(0.3);
        }
    }
    kit.traffic(ego_lane, 1.2, 0.5);
    kit.people(paint.half_width() + 0.3, edge.max(paint.half_width() + 1.0), 0.8, 0.3);
}
