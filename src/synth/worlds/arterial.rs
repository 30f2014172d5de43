//! Vegetation-lined arterial, like most KITTI frames: two lanes each way, a median with tram
//! tracks under overhead wires (or grass with trees), kerbs and sidewalks, then dense irregular
//! foliage on both sides (rows of trees over hedges and bushes) with buildings behind it.

use rand::Rng;
use rand_chacha::ChaCha8Rng;

use super::super::materials::Material;
use super::super::paint::{Median, Verge};
use super::super::style::Colors;
use super::super::terrain::{RoadShape, Roadside};
use super::kit::Kit;
use super::Layout;

pub fn layout(rng: &mut ChaCha8Rng, colors: &Colors, x0: f32, x1: f32) -> Layout {
    let mut paint = super::base_paint(rng, colors);
    paint.lanes_each_way = if rng.random_bool(0.75) { 2 } else { 1 };
    paint.lane_width_m = rng.random_range(3.0..3.6);
    let tram = rng.random_bool(0.6);
    paint.median = if tram { Median::Tram } else if rng.random_bool(0.5) { Median::Grass } else { Median::Paint };
    paint.median_m = match paint.median {
        Median::Tram => rng.random_range(6.2..7.2),
        Median::Grass => rng.random_range(2.5..5.0),
        _ => 0.3,
    };
    paint.parking_m = if rng.random_bool(0.3) { 2.1 } else { 0.0 };
    paint.sidewalk_m = rng.random_range(2.0..4.0);
    paint.verge = [Verge::Grass, Verge::Grass];
    paint.junctions = super::junctions(rng, x0, x1, (80.0, 200.0), 0.5, (4.0, 7.0));
    paint.crossings = paint.junctions.iter().filter(|_| rng.random_bool(0.5)).map(|(x, hw)| x - hw - 3.0).collect();
    let (bank_mean, bank_wave) = super::bank(rng, 0.025);
    let shape = RoadShape {
        curve: super::curve(rng, 0.0..0.6),
        profile: super::profile(rng, 0.0..0.05),
        bank_mean,
        bank_wave,
        road_half_width_m: paint.half_width(),
        kerb_m: rng.random_range(0.1..0.17),
        sides: [0, 1].map(|_| Roadside {
            slope_start_m: rng.random_range(6.0..14.0),
            slope_width_m: rng.random_range(6.0..12.0),
            slope_rise_m: rng.random_range(-1.0..2.5),
            ..Roadside::default()
        }),
        junctions: paint.junctions.clone(),
    };
    let ego_lane = rng.random_range(0..paint.lanes_each_way);
    Layout { paint, shape, ego_lane }
}

pub fn populate(kit: &mut Kit, ego_lane: u32) {
    let paint = kit.paint;
    let (x0, x1) = kit.range;
    let edge = paint.half_width();
    let green = edge + paint.sidewalk_m;
    for side in [1.0f32, -1.0] {
        // Tree row along the kerb, hedges and bushes behind, more trees further back.
        let mut x = x0 + kit.rng.random_range(0.0..6.0);
        while x < x1 {
            if kit.free(x - 2.0, x + 2.0, 1.0) && kit.rng.random_bool(0.85) {
                let a1 = kit.rng.random_range(0.3..0.7);
                let a2 = kit.rng.random_range(0.9..1.5);
                kit.tree(x, side * (edge + paint.sidewalk_m * a1), a2);
            }
            x += kit.rng.random_range(4.0..8.0) / kit.clutter.max(0.5);
        }
        let mut x = x0;
        while x < x1 {
            let run = kit.rng.random_range(10.0..50.0);
            if kit.free(x, x + run, 1.0) && kit.rng.random_bool(0.9) {
                let a1 = kit.rng.random_range(0.5..2.0);
                let a2 = kit.rng.random_range(1.2..3.0);
                let a3 = kit.rng.random_range(1.0..2.2);
                kit.hedge(x, x + run, side * (green + a1), a2, a3);
            }
            x += run + kit.rng.random_range(0.0..8.0);
        }
        let mut x = x0 + kit.rng.random_range(0.0..8.0);
        while x < x1 {
            if kit.free(x - 3.0, x + 3.0, 1.0) {
                let y = side * (green + kit.rng.random_range(2.0..11.0));
                if kit.rng.random_bool(0.6) {
                    let a1 = kit.rng.random_range(1.0..1.8);
                    kit.tree(x, y, a1);
                } else {
                    let a1 = kit.rng.random_range(0.8..2.0);
                    kit.bush(x, y, a1);
                }
            }
            x += kit.rng.random_range(2.0..6.0) / kit.clutter.max(0.5);
        }
        // Buildings far behind the green band.
        let mut x = x0;
        while x < x1 {
            let w = kit.rng.random_range(15.0..45.0);
            if kit.rng.random_bool(0.6) && kit.free(x, x + w, 2.0) {
                let floors = kit.rng.random_range(2.0f32..8.0).round();
                let a1 = kit.rng.random_range(2.9..3.5);
                let facade = kit.facade(a1);
                let h = floors * facade.floor_height + 0.5;
                let a1 = kit.rng.random_range(12.0..25.0);
                let a2 = kit.rng.random_range(10.0..18.0);
                kit.building(x + w * 0.5, green + a1, side, w, a2, h, Material::Facade(facade));
            }
            x += w + kit.rng.random_range(3.0..20.0);
        }
        let mut x = x0 + kit.rng.random_range(0.0..25.0);
        while x < x1 {
            if kit.free(x - 1.0, x + 1.0, 0.5) {
                let a1 = kit.rng.random_range(7.0..10.0);
                kit.street_light(x, side * (edge + 0.5), side, a1);
            }
            x += kit.rng.random_range(25.0..40.0);
        }
    }
    if paint.median == Median::Tram {
        // Catenary: poles on the median's centre every ~30 m, a wire above each track.
        let mut x = x0 + kit.rng.random_range(0.0..30.0);
        while x < x1 {
            if kit.free(x - 0.5, x + 0.5, 0.0) {
                kit.pole(x, 0.0, 7.5, 0.12, [0.35, 0.38, 0.36]);
                kit.block(x, 0.0, 6.8, [0.1, paint.median_m * 0.75, 0.1], 0.0, Material::Plain { color: [0.35, 0.38, 0.36], reflectivity: 0.45, grain: 0.2 }, super::super::scene::Class::Structure);
            }
            x += kit.rng.random_range(26.0..34.0);
        }
        for s in [1.0, -1.0] {
            kit.wire(x0, x1, s * paint.median_m * 0.25, 6.2);
        }
    } else if paint.median == Median::Grass {
        let mut x = x0 + kit.rng.random_range(0.0..10.0);
        while x < x1 {
            if kit.free(x - 2.0, x + 2.0, 1.0) {
                let a1 = kit.rng.random_range(-0.3..0.3);
                let a2 = kit.rng.random_range(0.8..1.3);
                kit.tree(x, a1, a2);
            }
            x += kit.rng.random_range(8.0..16.0);
        }
    }
    kit.parked(0.5);
    kit.traffic(ego_lane, 2.0, 0.15);
    kit.people(edge + 0.3, green - 0.3, 4.0, 2.0);
}
