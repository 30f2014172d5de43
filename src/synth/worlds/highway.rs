//! Highway: two or three wide lanes each way, a concrete barrier in the median, paved
//! shoulders, guard rails, embankments and cuttings, noise walls, sign gantries, light poles,
//! heavy traffic at every distance; wide curves with bank.

use rand::Rng;
use rand_chacha::ChaCha8Rng;

use super::super::materials::Material;
use super::super::paint::{Median, Verge};
use super::super::scene::Class;
use super::super::style::Colors;
use super::super::terrain::{RoadShape, Roadside};
use super::kit::Kit;
use super::Layout;

pub fn layout(rng: &mut ChaCha8Rng, colors: &Colors, x0: f32, x1: f32) -> Layout {
    let mut paint = super::base_paint(rng, colors);
    paint.lanes_each_way = rng.random_range(2..=3);
    paint.lane_width_m = rng.random_range(3.5..3.8);
    paint.median = Median::Concrete;
    paint.median_m = rng.random_range(1.5..4.0);
    paint.shoulder_m = rng.random_range(2.0..3.2);
    paint.solid_centre = true;
    paint.verge = [0, 1].map(|_| if rng.random_bool(0.5) { Verge::Grass } else { Verge::Gravel });
    let _ = (x0, x1);
    let (bank_mean, bank_wave) = super::bank(rng, 0.05);
    let sides = [0, 1].map(|_| {
        let embankment = rng.random_bool(0.5);
        Roadside {
            ditch_start_m: 1.0,
            ditch_width_m: rng.random_range(2.0..3.0),
            ditch_depth_m: if embankment { 0.0 } else { rng.random_range(0.2..0.6) },
            slope_start_m: rng.random_range(1.5..4.0),
            slope_width_m: rng.random_range(6.0..14.0),
            slope_rise_m: if embankment { -rng.random_range(2.0..6.0) } else { rng.random_range(1.0..6.0) },
        }
    });
    let shape = RoadShape {
        curve: super::curve(rng, 0.2..0.7),
        profile: super::profile(rng, 0.0..0.04),
        bank_mean,
        bank_wave,
        road_half_width_m: paint.half_width(),
        kerb_m: 0.0,
        sides,
        junctions: Vec::new(),
    };
    let ego_lane = rng.random_range(0..paint.lanes_each_way);
    Layout { paint, shape, ego_lane }
}

pub fn populate(kit: &mut Kit, shape: &RoadShape, ego_lane: u32) {
    let paint = kit.paint;
    let (x0, x1) = kit.range;
    let edge = paint.half_width();
    let a1 = kit.rng.random_range(0.8..1.1);
    kit.barrier(x0, x1, 0.0, a1);
    for (i, side) in [1.0f32, -1.0].into_iter().enumerate() {
        let roadside = shape.sides[i];
        kit.guard_rail(x0, x1, side * (edge + 0.4));
        if roadside.slope_rise_m > 0.0 && kit.rng.random_bool(0.3) {
            // Noise wall on top of the cutting's edge.
            let wall = Material::Plain { color: kit.pick(&[[0.45, 0.42, 0.38], [0.25, 0.35, 0.3], [0.5, 0.3, 0.2]]), reflectivity: 0.35, grain: 0.5 };
            let y = side * (edge + roadside.slope_start_m + roadside.slope_width_m + 1.0);
            let h = kit.rng.random_range(3.0..5.0);
            let mut x = x0;
            while x < x1 {
                kit.block(x + 4.0, y, 0.0, [8.0, 0.3, h], 0.0, wall, Class::Structure);
                x += 8.0;
            }
        }
        let far = edge + roadside.slope_start_m + roadside.slope_width_m;
        let mut x = x0 + kit.rng.random_range(0.0..40.0);
        while x < x1 {
            let y = side * (far + kit.rng.random_range(1.0..20.0));
            if kit.rng.random_bool(0.5) {
                let a1 = kit.rng.random_range(0.8..1.5);
                kit.tree(x, y, a1);
            } else {
                let a1 = kit.rng.random_range(0.8..1.8);
                kit.bush(x, y, a1);
            }
            x += kit.rng.random_range(8.0..40.0) / kit.clutter.max(0.3);
        }
    }
    // Light poles on the barrier.
    let mut x = x0 + kit.rng.random_range(0.0..40.0);
    while x < x1 {
        kit.pole(x, 0.0, 10.0, 0.14, [0.5, 0.5, 0.5]);
        for s in [1.0f32, -1.0] {
            kit.block(x, s * 1.0, 9.8, [0.15, 2.0, 0.12], 0.0, Material::Plain { color: [0.5, 0.5, 0.5], reflectivity: 0.45, grain: 0.1 }, Class::Structure);
        }
        x += kit.rng.random_range(40.0..60.0);
    }
    // Sign gantries spanning our carriageway.
    let mut x = x0 + kit.rng.random_range(20.0..150.0);
    while x < x1 {
        let steel = Material::Plain { color: [0.55, 0.56, 0.57], reflectivity: 0.6, grain: 0.2 };
        let span = edge + 1.0;
        for y in [-span, -0.6] {
            kit.block(x, y, 0.0, [0.5, 0.5, 7.0], 0.0, steel, Class::Structure);
        }
        kit.block(x, -span * 0.5 - 0.3, 6.2, [0.8, span + 0.6, 0.8], 0.0, steel, Class::Structure);
        let color = kit.pick(&[[0.05, 0.3, 0.12], [0.05, 0.15, 0.5]]);
        for lane in 0..paint.lanes_each_way {
            if kit.rng.random_bool(0.7) {
                let y = paint.lane_centre(-1.0, lane);
                kit.block(x - 0.5, y, 5.0, [0.1, paint.lane_width_m * 0.85, 1.6], 0.0, Material::Sign { color }, Class::Structure);
            }
        }
        x += kit.rng.random_range(150.0..350.0);
    }
    kit.traffic(ego_lane, 3.0, 0.3);
}
