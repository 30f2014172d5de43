//! Rural road: no kerbs, a gravel shoulder, ditches, fields behind fences, guard rails where
//! the road runs on an embankment, sparse trees and bush clumps, utility poles with wires,
//! the odd farm shed; hills and curves.

use rand::Rng;
use rand_chacha::ChaCha8Rng;

use super::super::materials::Material;
use super::super::paint::Verge;
use super::super::style::Colors;
use super::super::terrain::{RoadShape, Roadside};
use super::kit::Kit;
use super::Layout;

pub fn layout(rng: &mut ChaCha8Rng, colors: &Colors, x0: f32, x1: f32) -> Layout {
    let mut paint = super::base_paint(rng, colors);
    paint.lane_width_m = rng.random_range(2.8..3.4);
    paint.shoulder_m = rng.random_range(0.2..0.8);
    paint.edge_lines = rng.random_bool(0.6);
    paint.verge = [0, 1].map(|_| if rng.random_bool(0.6) { Verge::Field } else { Verge::Grass });
    paint.junctions = super::junctions(rng, x0, x1, (150.0, 400.0), 0.4, (2.8, 4.0));
    let (bank_mean, bank_wave) = super::bank(rng, 0.04);
    let sides = [0, 1].map(|_| {
        let embankment = rng.random_bool(0.35);
        Roadside {
            ditch_start_m: rng.random_range(0.5..1.5),
            ditch_width_m: rng.random_range(1.5..3.0),
            ditch_depth_m: if embankment { 0.0 } else { rng.random_range(0.3..0.9) },
            slope_start_m: rng.random_range(3.5..6.0),
            slope_width_m: rng.random_range(5.0..12.0),
            slope_rise_m: if embankment { -rng.random_range(1.0..3.5) } else { rng.random_range(-0.5..3.0) },
        }
    });
    let shape = RoadShape {
        curve: super::curve(rng, 0.3..1.0),
        profile: super::profile(rng, 0.02..0.08),
        bank_mean,
        bank_wave,
        road_half_width_m: paint.half_width(),
        kerb_m: 0.0,
        sides,
        junctions: paint.junctions.clone(),
    };
    Layout { paint, shape, ego_lane: 0 }
}

pub fn populate(kit: &mut Kit, shape: &RoadShape, ego_lane: u32) {
    let paint = kit.paint;
    let (x0, x1) = kit.range;
    let edge = paint.half_width();
    for (i, side) in [1.0f32, -1.0].into_iter().enumerate() {
        let roadside = shape.sides[i];
        let beyond_ditch = edge + roadside.ditch_start_m + roadside.ditch_width_m + 0.5;
        if roadside.slope_rise_m < -0.8 {
            kit.guard_rail(x0, x1, side * (edge + 0.5));
        }
        if kit.rng.random_bool(0.6) {
            let y = side * (beyond_ditch + kit.rng.random_range(0.0..2.0));
            kit.fence(x0, x1, y);
        }
        // A hedgerow along the field edge on some roads.
        if kit.rng.random_bool(0.45) {
            let y = side * (beyond_ditch + kit.rng.random_range(2.5..6.0));
            let (h, d) = (kit.rng.random_range(1.5..3.5), kit.rng.random_range(1.2..2.5));
            let mut x = x0;
            while x < x1 {
                let run = kit.rng.random_range(20.0..80.0);
                if kit.free(x, x + run, 2.0) {
                    kit.hedge(x, (x + run).min(x1), y, h, d);
                }
                x += run + kit.rng.random_range(3.0..25.0);
            }
        }
        // Sparse trees and clumps of bushes, in rows along field edges or scattered.
        let mut x = x0 + kit.rng.random_range(0.0..30.0);
        while x < x1 {
            let y = side * (beyond_ditch + kit.rng.random_range(1.0..25.0));
            if kit.rng.random_bool(0.6) {
                let a1 = kit.rng.random_range(0.8..1.5);
                kit.tree(x, y, a1);
            } else {
                for _ in 0..kit.rng.random_range(2..6) {
                    let (dx, dy) = (kit.rng.random_range(-3.0..3.0), kit.rng.random_range(-2.0..2.0));
                    let a1 = kit.rng.random_range(0.5..1.4);
                    kit.bush(x + dx, y + dy, a1);
                }
            }
            x += kit.rng.random_range(12.0..60.0) / kit.clutter.max(0.3);
        }
        // A farm shed now and then.
        if kit.rng.random_bool(0.4) {
            let x = kit.rng.random_range(x0..x1);
            if kit.free(x - 15.0, x + 15.0, 0.0) {
                let color = kit.pick(&[[0.45, 0.12, 0.08], [0.5, 0.5, 0.48], [0.25, 0.3, 0.22]]);
                let w = kit.rng.random_range(12.0..30.0);
                let a1 = kit.rng.random_range(8.0..30.0);
                let a2 = kit.rng.random_range(8.0..15.0);
                let a3 = kit.rng.random_range(4.0..8.0);
                kit.building(x, beyond_ditch + a1, side, w, a2, a3, Material::Corrugated { color, pitch: 0.2 });
            }
        }
    }
    // Utility poles with two wires on one side.
    let side = if kit.rng.random_bool(0.5) { 1.0 } else { -1.0 };
    let y = side * (edge + shape.sides[if side > 0.0 { 0 } else { 1 }].slope_start_m.max(2.5));
    let mut x = x0;
    let height = kit.rng.random_range(7.0..9.0);
    while x < x1 {
        kit.pole(x, y, height, 0.13, [0.3, 0.24, 0.18]);
        x += kit.rng.random_range(35.0..50.0);
    }
    kit.wire(x0, x1, y, height - 0.3);
    kit.wire(x0, x1, y + 0.5, height - 0.6);
    kit.traffic(ego_lane, 0.5, 0.25);
    kit.people(edge + 0.2, edge + 1.0, 0.3, 0.6);
}
