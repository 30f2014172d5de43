//! Puts primitives built in the straight road frame onto the terrain: x stays, y follows the
//! curving centreline (y + c(x)), boxes turn with the road's heading, and everything is lifted
//! to the local ground height; shapes standing on the ground reach down to its lowest point
//! under their footprint, so nothing floats on a slope.

use super::super::scene::Primitive;
use super::super::shapes::{Shape, V3};
use super::super::terrain::Terrain;

/// Shapes whose bottom is this close to the ground are treated as standing on it.
const STANDING_M: f32 = 0.05;
/// How far standing shapes reach below the lowest ground point under them.
const SINK_M: f32 = 0.08;

pub fn onto(terrain: &Terrain, primitives: Vec<Primitive>) -> Vec<Primitive> {
    primitives.into_iter().map(|p| Primitive { shape: bend(terrain, p.shape), ..p }).collect()
}

fn bend(terrain: &Terrain, shape: Shape) -> Shape {
    match shape {
        Shape::Box { center, half, cos, sin } => {
            let along = terrain.along(center.x);
            let turn = along.centre_slope.atan();
            let yaw = sin.atan2(cos) + turn;
            let (c, s) = (yaw.cos(), yaw.sin());
            let (x, y) = (center.x, center.y + along.centre);
            let ground = terrain.height(x, y);
            let bottom = center.z - half.z;
            let top = center.z + half.z + ground;
            let new_bottom = if bottom < STANDING_M {
                let corners = [(1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0)];
                let lowest = corners
                    .iter()
                    .map(|(fx, fy)| terrain.height(x + c * fx * half.x - s * fy * half.y, y + s * fx * half.x + c * fy * half.y))
                    .fold(ground, f32::min);
                lowest - SINK_M + bottom.max(0.0)
            } else {
                bottom + ground
            };
            let half_z = (top - new_bottom) * 0.5;
            Shape::Box { center: V3::new(x, y, new_bottom + half_z), half: V3::new(half.x, half.y, half_z), cos: c, sin: s }
        }
        Shape::Cylinder { x, y, radius, z0, z1 } => {
            let wy = y + terrain.along(x).centre;
            let ground = terrain.height(x, wy);
            let z0 = if z0 < STANDING_M { ground - SINK_M - radius * 0.5 } else { z0 + ground };
            Shape::Cylinder { x, y: wy, radius, z0, z1: z1 + ground }
        }
        Shape::Ellipsoid { center, radii } => {
            let wy = center.y + terrain.along(center.x).centre;
            Shape::Ellipsoid { center: V3::new(center.x, wy, center.z + terrain.height(center.x, wy)), radii }
        }
    }
}
