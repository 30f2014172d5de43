//! Suburban street: one lane each way, low kerbs, a grass strip and a sidewalk, houses set back
//! in yards with hedges, fences, driveways with cars in them, garden trees and bushes.

use rand::Rng;
use rand_chacha::ChaCha8Rng;

use super::super::paint::Verge;
use super::super::style::Colors;
use super::super::terrain::{RoadShape, Roadside};
use super::kit::{Kit, Vehicle};
use super::Layout;

pub fn layout(rng: &mut ChaCha8Rng, colors: &Colors, x0: f32, x1: f32) -> Layout {
    let mut paint = super::base_paint(rng, colors);
    paint.lane_width_m = rng.random_range(2.9..3.5);
    paint.parking_m = if rng.random_bool(0.5) { 2.1 } else { 0.0 };
    paint.edge_lines = rng.random_bool(0.4);
    paint.sidewalk_m = rng.random_range(1.2..2.2);
    paint.verge = [Verge::Grass, Verge::Grass];
    paint.junctions = super::junctions(rng, x0, x1, (60.0, 150.0), 0.6, (3.5, 5.0));
    let half = paint.half_width();
    // Driveways: one per house plot, drawn here so the paint knows them.
    for side in [1.0f32, -1.0] {
        let mut x = x0 + rng.random_range(0.0..10.0);
        while x < x1 {
            let plot = rng.random_range(14.0..24.0);
            if rng.random_bool(0.7) && !paint.in_junction(x, 6.0) {
                paint.driveways.push((x + rng.random_range(-3.0..3.0), rng.random_range(2.6..3.6), side, rng.random_range(8.0..14.0)));
            }
            x += plot;
        }
    }
    let (bank_mean, bank_wave) = super::bank(rng, 0.03);
    let shape = RoadShape {
        curve: super::curve(rng, 0.1..0.8),
        profile: super::profile(rng, 0.01..0.07),
        bank_mean,
        bank_wave,
        road_half_width_m: half,
        kerb_m: rng.random_range(0.05..0.12),
        sides: [0, 1].map(|_| Roadside {
            slope_start_m: rng.random_range(4.0..10.0),
            slope_width_m: rng.random_range(6.0..14.0),
            slope_rise_m: rng.random_range(-1.5..2.0),
            ..Roadside::default()
        }),
        junctions: paint.junctions.clone(),
    };
    Layout { paint, shape, ego_lane: 0 }
}

pub fn populate(kit: &mut Kit, ego_lane: u32) {
    let paint = kit.paint;
    let (x0, x1) = kit.range;
    let front = paint.half_width() + paint.sidewalk_m;
    for side in [1.0f32, -1.0] {
        // Plots along the road: a house, its yard boundary, trees and bushes.
        let mut x = x0;
        while x < x1 {
            let plot = kit.rng.random_range(14.0..24.0);
            if kit.free(x, x + plot, 1.0) {
                let setback = kit.rng.random_range(5.0..12.0);
                let width = (plot - kit.rng.random_range(3.0..7.0)).max(6.0);
                let depth = kit.rng.random_range(7.0..12.0);
                kit.house(x + plot * 0.5, front + setback, side, width, depth);
                let driveway = paint.driveways.iter().any(|d| d.2 == side && d.0 > x - 2.0 && d.0 < x + plot + 2.0);
                match if driveway { 2 } else { kit.rng.random_range(0..4) % 3 } {
                    0 => {
                        let (h, d) = (kit.rng.random_range(1.0..2.2), kit.rng.random_range(0.7..1.4));
                        kit.hedge(x + 0.5, x + plot - 0.5, side * (front + 0.6), h, d)
                    }
                    1 => kit.fence(x + 0.5, x + plot - 0.5, side * (front + 0.3)),
                    _ => {}
                }
                for _ in 0..kit.rng.random_range(0..3) {
                    let tx = x + kit.rng.random_range(0.0..plot);
                    let a1 = kit.rng.random_range(1.5..setback + depth + 4.0);
                    let a2 = kit.rng.random_range(0.7..1.2);
                    kit.tree(tx, side * (front + a1), a2);
                }
                for _ in 0..kit.rng.random_range(0..4) {
                    let bx = x + kit.rng.random_range(0.0..plot);
                    let a1 = kit.rng.random_range(1.0..setback);
                    let a2 = kit.rng.random_range(0.4..1.1);
                    kit.bush(bx, side * (front + a1), a2);
                }
                // Mailbox.
                if kit.rng.random_bool(0.4) {
                    kit.pole(x + 1.0, side * (front - 0.3), 1.1, 0.04, [0.2, 0.2, 0.2]);
                }
            }
            x += plot;
        }
    }
    // Cars standing in driveways, facing the road or away.
    for &(dx, _, side, len) in &paint.driveways.clone() {
        if kit.rng.random_bool(0.5) {
            let y = side * (paint.half_width() + len * kit.rng.random_range(0.45..0.7));
            let yaw = std::f32::consts::FRAC_PI_2 * if kit.rng.random_bool(0.5) { 1.0 } else { -1.0 };
            let kind = if kit.rng.random_bool(0.2) { Vehicle::Van } else { Vehicle::Car };
            kit.vehicle(dx, y, yaw, kind);
        }
    }
    // Street trees on the grass between the kerb and the sidewalk's far edge.
    for side in [1.0f32, -1.0] {
        let mut x = x0 + kit.rng.random_range(0.0..10.0);
        while x < x1 {
            if kit.free(x - 2.0, x + 2.0, 1.0) && kit.rng.random_bool((0.7 * kit.clutter as f64).min(1.0)) {
                let size = kit.rng.random_range(0.8..1.4);
                kit.tree(x, side * (front + 0.8), size);
            }
            x += kit.rng.random_range(8.0..18.0);
        }
    }
    kit.parked(0.4);
    kit.traffic(ego_lane, 1.0, 0.1);
    let mut x = x0 + kit.rng.random_range(0.0..30.0);
    while x < x1 {
        if kit.free(x - 1.0, x + 1.0, 0.5) {
            let side = if kit.rng.random_bool(0.5) { 1.0 } else { -1.0 };
            let a1 = kit.rng.random_range(5.5..7.5);
            kit.street_light(x, side * (paint.half_width() + 0.4), side, a1);
        }
        x += kit.rng.random_range(30.0..50.0);
    }
    kit.people(paint.half_width() + 0.3, front - 0.3, 3.0, 1.0);
}
