//! World families: what kind of place a sequence drives through. `classic` is today's flat,
//! straight street, byte for byte; the others are drawn per sequence when `--world` is not
//! given. Each family draws a road layout (lanes, median, kerbs, verges, junctions) and a road
//! shape (curves, grade, bank, ditches, embankments, cuttings), then places its objects in the
//! straight road frame with the shared `kit`; `bend` puts them onto the terrain.

pub mod arterial;
pub mod bend;
pub mod classic;
pub mod highway;
pub mod industrial;
pub mod kit;
pub mod rural;
pub mod suburban;
pub mod urban;

use std::sync::Arc;

use rand::Rng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::paint::RoadPaint;
use super::scene::{Ground, Scene};
use super::style::{Colors, Style};
use super::terrain::{RoadShape, Terrain, Waves};
use kit::Kit;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum WorldKind {
    /// Today's street exactly: flat, straight, box buildings, parked cars (never drawn at random).
    Classic,
    /// Urban canyon: today's street plus traffic, people, cyclists, irregular trees, gentle curves and slopes.
    Urban,
    /// Houses in yards, hedges, driveways, parked cars, low kerbs.
    Suburban,
    /// No kerbs: ditches, fields, fences, guard rails, sparse trees, hills.
    Rural,
    /// Multi-lane road lined with dense foliage, tram tracks, overhead wires, poles.
    Arterial,
    /// Barriers, gantries, embankments and cuttings, heavy traffic.
    Highway,
    /// Sheds, container stacks, fenced yards, trucks.
    Industrial,
}

/// The families drawn when `--world` is not given.
pub const DRAWN: [WorldKind; 6] = [WorldKind::Urban, WorldKind::Suburban, WorldKind::Rural, WorldKind::Arterial, WorldKind::Highway, WorldKind::Industrial];

impl WorldKind {
    pub fn name(self) -> &'static str {
        match self {
            WorldKind::Classic => "classic",
            WorldKind::Urban => "urban",
            WorldKind::Suburban => "suburban",
            WorldKind::Rural => "rural",
            WorldKind::Arterial => "arterial",
            WorldKind::Highway => "highway",
            WorldKind::Industrial => "industrial",
        }
    }
}

/// A built world: the scene and where the vehicle drives in it.
pub struct Built {
    pub scene: Scene,
    /// Lateral lane position (scene y for classic, road ŷ otherwise), metres.
    pub lane_y: f64,
    /// Largest weave amplitude that keeps the vehicle in its lane, metres.
    pub weave_limit_m: f64,
}

/// A family's road: its paint, its shape and which of our lanes the vehicle uses.
pub struct Layout {
    pub paint: RoadPaint,
    pub shape: RoadShape,
    pub ego_lane: u32,
}

/// Builds a world covering the drive range plus `margin` metres each way.
pub fn build(kind: WorldKind, rng: &mut ChaCha8Rng, drive_range: (f32, f32), margin: f32, style: &Style) -> Built {
    let (x0, x1) = (drive_range.0 - margin, drive_range.1 + margin);
    if kind == WorldKind::Classic {
        let scene = classic::build_street(rng, drive_range, margin, style);
        let Ground::Street(street) = &scene.ground else { unreachable!("classic builds a street") };
        let road = street.road_half_width as f64;
        let driving_edge = if street.parking { road - 2.2 } else { road };
        return Built { scene, lane_y: -driving_edge * 0.5, weave_limit_m: (driving_edge * 0.5 - 1.1).clamp(0.0, 0.9) };
    }
    let colors = style.palette.colors();
    let (layout, street) = match kind {
        WorldKind::Urban => {
            let (layout, street) = urban::layout(rng, &colors, x0, x1);
            (layout, Some(street))
        }
        WorldKind::Suburban => (suburban::layout(rng, &colors, x0, x1), None),
        WorldKind::Rural => (rural::layout(rng, &colors, x0, x1), None),
        WorldKind::Arterial => (arterial::layout(rng, &colors, x0, x1), None),
        WorldKind::Highway => (highway::layout(rng, &colors, x0, x1), None),
        WorldKind::Industrial => (industrial::layout(rng, &colors, x0, x1), None),
        WorldKind::Classic => unreachable!(),
    };
    let terrain = Arc::new(Terrain::new(layout.shape.clone(), x0 - 20.0, x1 + 20.0));
    let mut kit = Kit { rng, colors: style.palette.colors(), clutter: style.clutter, paint: &layout.paint, range: (x0, x1), drive: drive_range, out: Vec::new() };
    match kind {
        WorldKind::Urban => urban::populate(&mut kit, style, street.as_ref().expect("urban street")),
        WorldKind::Suburban => suburban::populate(&mut kit, layout.ego_lane),
        WorldKind::Rural => rural::populate(&mut kit, &layout.shape, layout.ego_lane),
        WorldKind::Arterial => arterial::populate(&mut kit, layout.ego_lane),
        WorldKind::Highway => highway::populate(&mut kit, &layout.shape, layout.ego_lane),
        WorldKind::Industrial => industrial::populate(&mut kit, layout.ego_lane),
        WorldKind::Classic => unreachable!(),
    }
    let primitives = bend::onto(&terrain, kit.out);
    let lane_y = layout.paint.lane_centre(-1.0, layout.ego_lane) as f64;
    let weave_limit_m = ((layout.paint.lane_width_m as f64) * 0.5 - 1.1).clamp(0.0, 0.35);
    let scene = Scene::new(Ground::Road(layout.paint), Some(terrain), primitives, drive_range);
    Built { scene, lane_y, weave_limit_m }
}

/// Curves: `curviness` (drawn from the range) 0..1 scales the heading swing up to ~12°.
pub fn curve(rng: &mut ChaCha8Rng, curviness: std::ops::Range<f32>) -> Waves {
    let curviness = rng.random_range(curviness);
    let l1 = rng.random_range(300.0..700.0);
    let l2 = rng.random_range(120.0..260.0);
    [
        [curviness * 0.03 * l1 * rng.random_range(0.2..1.0), l1, rng.random_range(0.0..std::f32::consts::TAU)],
        [curviness * 0.008 * l2 * rng.random_range(0.0..1.0), l2, rng.random_range(0.0..std::f32::consts::TAU)],
    ]
}

/// Grade: the steepest slope reaches about `grade` (drawn from the range) (a tangent, 0.06 = 6 %).
pub fn profile(rng: &mut ChaCha8Rng, grade: std::ops::Range<f32>) -> Waves {
    let grade = rng.random_range(grade);
    let l1 = rng.random_range(250.0..600.0);
    let l2 = rng.random_range(90.0..200.0);
    let g1 = grade * rng.random_range(0.3..0.85);
    let g2 = grade * rng.random_range(0.0..0.3);
    [
        [g1 * l1 / std::f32::consts::TAU, l1, rng.random_range(0.0..std::f32::consts::TAU)],
        [g2 * l2 / std::f32::consts::TAU, l2, rng.random_range(0.0..std::f32::consts::TAU)],
    ]
}

/// Bank: a mean cross slope and a slow wave, the sum within ±`max` (a tangent).
pub fn bank(rng: &mut ChaCha8Rng, max: f32) -> (f32, [f32; 3]) {
    let mean = rng.random_range(-0.5..0.5) * max;
    (mean, [rng.random_range(0.0..0.5) * max, rng.random_range(100.0..300.0), rng.random_range(0.0..std::f32::consts::TAU)])
}

/// Crossing roads every `spacing` metres (x centre, half width), each present with `p`.
pub fn junctions(rng: &mut ChaCha8Rng, x0: f32, x1: f32, spacing: (f32, f32), p: f64, half_width: (f32, f32)) -> Vec<(f32, f32)> {
    let mut out = Vec::new();
    let mut x = x0 + rng.random_range(10.0..spacing.1);
    while x < x1 {
        if rng.random_bool(p) {
            out.push((x, rng.random_range(half_width.0..half_width.1)));
        }
        x += rng.random_range(spacing.0..spacing.1);
    }
    out
}

/// A plain road paint to start from (one lane each way, no median, no kerb).
pub fn base_paint(rng: &mut ChaCha8Rng, colors: &Colors) -> RoadPaint {
    use super::paint::{Median, Verge};
    RoadPaint {
        lanes_each_way: 1,
        lane_width_m: 3.3,
        median_m: 0.0,
        median: Median::Paint,
        solid_centre: rng.random_bool(0.3),
        yellow_centre: rng.random_bool(0.2),
        parking_m: 0.0,
        shoulder_m: 0.0,
        edge_lines: true,
        sidewalk_m: 0.0,
        verge: [Verge::Grass, Verge::Grass],
        junctions: Vec::new(),
        crossings: Vec::new(),
        driveways: Vec::new(),
        asphalt: colors.asphalt,
        verge_color: colors.lot,
        pavement: colors.pavement,
        seed: rng.random(),
    }
}
