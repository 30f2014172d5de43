//! A scene: the shapes with their materials and semantic classes, the ground (a flat street or
//! a road on terrain) and its painted layout, and the queries both sensors use (closest hit,
//! shadow test, surface colour and LiDAR reflectivity, class).
//!
//! Scene frame: z up, x along the road's general direction; the flat street's ground is z = 0.

use std::sync::Arc;

use serde::Serialize;

use super::bvh::Bvh;
use super::look::Textures;
use super::materials::Material;
use super::paint::RoadPaint;
use super::shapes::{Shape, ShapeHit, V3, T_EPSILON};
use super::street::Street;
use super::terrain::Terrain;

/// What a surface is, for statistics of where LiDAR points land.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Class {
    Ground,
    Building,
    Vegetation,
    Vehicle,
    Person,
    /// Poles, signs, fences, rails, barriers, wires, gantries, street furniture.
    Structure,
}

impl Class {
    pub const ALL: [Class; 6] = [Class::Ground, Class::Building, Class::Vegetation, Class::Vehicle, Class::Person, Class::Structure];

    /// The usual class of a material (builders may say otherwise).
    pub fn of(material: &Material) -> Class {
        match material {
            Material::Facade(_) | Material::Corrugated { .. } => Class::Building,
            Material::Foliage { .. } => Class::Vegetation,
            Material::Car { .. } => Class::Vehicle,
            Material::Pavement { .. } => Class::Ground,
            Material::Plain { .. } | Material::Sign { .. } => Class::Structure,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Class::Ground => "ground",
            Class::Building => "building",
            Class::Vegetation => "vegetation",
            Class::Vehicle => "vehicle",
            Class::Person => "person",
            Class::Structure => "structure",
        }
    }
}

#[derive(Debug, Clone, Copy)]
pub struct Primitive {
    pub shape: Shape,
    pub material: Material,
    pub class: Class,
}

impl Primitive {
    /// A primitive whose class follows from its material.
    pub fn new(shape: Shape, material: Material) -> Self {
        Primitive { shape, material, class: Class::of(&material) }
    }
}

/// Colour and LiDAR reflectivity at a surface point.
#[derive(Debug, Clone, Copy)]
pub struct Surface {
    pub albedo: [f32; 3],
    pub reflectivity: f32,
}

/// Index used in hits for the ground.
pub const GROUND: u32 = u32::MAX;

#[derive(Debug, Clone, Copy)]
pub struct Hit {
    pub t: f32,
    pub normal: V3,
    pub uv: [f32; 2],
    pub primitive: u32,
}

/// The ground's painted layout.
#[derive(Debug, Clone)]
pub enum Ground {
    /// Today's flat, straight street (the `classic` world).
    Street(Street),
    /// A road of any world family, painted in road coordinates (x, ŷ).
    Road(RoadPaint),
}

pub struct Scene {
    pub ground: Ground,
    /// `None`: the flat ground plane z = 0.
    pub terrain: Option<Arc<Terrain>>,
    pub shapes: Vec<Shape>,
    pub materials: Vec<Material>,
    pub classes: Vec<Class>,
    bvh: Bvh,
    /// The x range the trajectory may use (the scene extends beyond it by the LiDAR range).
    pub drive_range: (f32, f32),
    /// Appearance randomisation of every surface (`None`: materials as built).
    pub textures: Option<Textures>,
}

impl Scene {
    pub fn new(ground: Ground, terrain: Option<Arc<Terrain>>, primitives: Vec<Primitive>, drive_range: (f32, f32)) -> Self {
        let shapes: Vec<Shape> = primitives.iter().map(|p| p.shape).collect();
        let materials = primitives.iter().map(|p| p.material).collect();
        let classes = primitives.iter().map(|p| p.class).collect();
        let bvh = Bvh::build(&shapes);
        Scene { ground, terrain, shapes, materials, classes, bvh, drive_range, textures: None }
    }

    pub fn len(&self) -> usize {
        self.shapes.len()
    }

    pub fn is_empty(&self) -> bool {
        self.shapes.is_empty()
    }

    /// Ground height at (x, y).
    pub fn ground_height(&self, x: f32, y: f32) -> f32 {
        self.terrain.as_ref().map_or(0.0, |t| t.height(x, y))
    }

    /// The closest surface along the ray (shapes and the ground).
    pub fn intersect(&self, origin: &V3, dir: &V3, t_max: f32) -> Option<Hit> {
        if let Some(terrain) = &self.terrain {
            let shape_hit = self.bvh.closest(&self.shapes, origin, dir, t_max);
            let limit = shape_hit.as_ref().map_or(t_max, |(_, h)| h.t);
            if let Some(t) = terrain.intersect(origin, dir, limit) {
                let p = origin + dir * t;
                return Some(Hit { t, normal: terrain.normal(p.x, p.y), uv: [p.x, p.y], primitive: GROUND });
            }
            return shape_hit.map(|(index, ShapeHit { t, normal, uv })| Hit { t, normal, uv, primitive: index });
        }
        let mut limit = t_max;
        let mut best = None;
        if dir.z < 0.0 && origin.z > 0.0 {
            let t = -origin.z / dir.z;
            if t > T_EPSILON && t < limit {
                limit = t;
                let p = origin + dir * t;
                best = Some(Hit { t, normal: V3::z(), uv: [p.x, p.y], primitive: GROUND });
            }
        }
        if let Some((index, ShapeHit { t, normal, uv })) = self.bvh.closest(&self.shapes, origin, dir, limit) {
            best = Some(Hit { t, normal, uv, primitive: index });
        }
        best
    }

    /// Whether the segment from `origin` along `dir` up to `t_max` is blocked (shadow rays).
    /// Only shapes cast shadows; the ground does not.
    pub fn occluded(&self, origin: &V3, dir: &V3, t_max: f32) -> bool {
        self.bvh.any_hit(&self.shapes, origin, dir, t_max)
    }

    pub fn class_of(&self, hit: &Hit) -> Class {
        if hit.primitive == GROUND { Class::Ground } else { self.classes[hit.primitive as usize] }
    }

    /// Surface colour (linear RGB) and LiDAR reflectivity at `point` on `hit`.
    pub fn surface(&self, hit: &Hit, point: &V3) -> Surface {
        let surface = if hit.primitive == GROUND {
            match &self.ground {
                Ground::Street(street) => street.ground(point.x, point.y),
                Ground::Road(paint) => {
                    let along = self.terrain.as_ref().map(|t| t.along(point.x));
                    paint.surface(point.x, point.y - along.map_or(0.0, |a| a.centre))
                }
            }
        } else {
            self.materials[hit.primitive as usize].surface(hit, point)
        };
        match &self.textures {
            Some(textures) => textures.apply(surface, self.class_of(hit), hit, point),
            None => surface,
        }
    }
}
