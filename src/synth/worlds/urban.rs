//! Urban canyon: today's street (box buildings with facades, sidewalks, street furniture,
//! parked cars, side streets) with traffic in the oncoming lane, people and cyclists, tree
//! crowns made of many blobs, and a road that curves gently, climbs a little and banks.

use rand::Rng;
use rand_chacha::ChaCha8Rng;

use super::super::paint::{Median, Verge};
use super::super::street::Street;
use super::super::style::{Colors, Style};
use super::super::terrain::{RoadShape, Roadside};
use super::classic::{draw_street, street_primitives, Extras};
use super::kit::Kit;
use super::Layout;

pub fn layout(rng: &mut ChaCha8Rng, colors: &Colors, x0: f32, x1: f32) -> (Layout, Street) {
    let street = draw_street(rng, x0, x1, colors);
    let mut paint = super::base_paint(rng, colors);
    paint.parking_m = if street.parking { 2.2 } else { 0.0 };
    paint.lane_width_m = street.road_half_width - paint.parking_m;
    paint.median = Median::Paint;
    paint.sidewalk_m = street.sidewalk_width;
    paint.verge = [Verge::Lot, Verge::Lot];
    paint.junctions = street.side_streets.clone();
    paint.crossings = street.crossings.clone();
    paint.asphalt = street.asphalt;
    let (bank_mean, bank_wave) = super::bank(rng, 0.03);
    let shape = RoadShape {
        curve: super::curve(rng, 0.0..0.5),
        profile: super::profile(rng, 0.0..0.05),
        bank_mean,
        bank_wave,
        road_half_width_m: street.road_half_width,
        kerb_m: rng.random_range(0.1..0.17),
        sides: [Roadside::default(); 2],
        junctions: street.side_streets.clone(),
    };
    (Layout { paint, shape, ego_lane: 0 }, street)
}

pub fn populate(kit: &mut Kit, style: &Style, street: &Street) {
    let (x0, x1) = kit.range;
    let colors = style.palette.colors();
    let extras = Extras { no_sidewalk_boxes: true, irregular_trees: true };
    let mut out = street_primitives(kit.rng, style, &colors, street, x0, x1, extras);
    kit.out.append(&mut out);
    kit.traffic(0, 2.0, 0.15);
    let from = street.road_half_width + 0.4;
    kit.people(from, from + street.sidewalk_width - 0.8, 6.0, 1.5);
}
