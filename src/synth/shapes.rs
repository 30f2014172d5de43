//! The scene's primitive shapes and their ray intersections (f32: the renderer's hot path).
//!
//! Directions need not be unit length: the camera casts `(x/z, y/z, 1)` rays so that the hit
//! parameter `t` is the camera-frame depth directly; the LiDAR casts unit rays so `t` is range.

use nalgebra::Vector3;

pub type V3 = Vector3<f32>;

/// Ray hits closer than this (in ray-parameter units) are ignored, so shadow rays do not hit
/// the surface they start on.
pub const T_EPSILON: f32 = 1e-4;

#[derive(Debug, Clone, Copy)]
pub enum Shape {
    /// A box rotated by `yaw` about the world z axis (cos, sin stored).
    Box { center: V3, half: V3, cos: f32, sin: f32 },
    /// An upright cylinder with flat caps.
    Cylinder { x: f32, y: f32, radius: f32, z0: f32, z1: f32 },
    /// An axis-aligned ellipsoid (tree crowns, bushes).
    Ellipsoid { center: V3, radii: V3 },
}

/// Where a ray met a shape: ray parameter, outward unit normal, face coordinates in metres
/// (u along the face, v up from the shape's bottom; top faces: local x, y).
#[derive(Debug, Clone, Copy)]
pub struct ShapeHit {
    pub t: f32,
    pub normal: V3,
    pub uv: [f32; 2],
}

/// Axis-aligned bounds.
#[derive(Debug, Clone, Copy)]
pub struct Aabb {
    pub min: V3,
    pub max: V3,
}

impl Aabb {
    pub fn empty() -> Self {
        Aabb { min: V3::repeat(f32::INFINITY), max: V3::repeat(f32::NEG_INFINITY) }
    }
    pub fn union(&self, other: &Aabb) -> Aabb {
        Aabb { min: self.min.inf(&other.min), max: self.max.sup(&other.max) }
    }
    pub fn centroid(&self) -> V3 {
        (self.min + self.max) * 0.5
    }
    /// Slab test; returns the entry parameter when the ray meets the box within (0, t_max).
    #[inline]
    pub fn hit(&self, origin: &V3, inv_dir: &V3, t_max: f32) -> Option<f32> {
        let mut t0 = 0.0f32;
        let mut t1 = t_max;
        for axis in 0..3 {
            let a = (self.min[axis] - origin[axis]) * inv_dir[axis];
            let b = (self.max[axis] - origin[axis]) * inv_dir[axis];
            let (near, far) = if a < b { (a, b) } else { (b, a) };
            t0 = if near > t0 { near } else { t0 };
            t1 = if far < t1 { far } else { t1 };
        }
        (t0 <= t1).then_some(t0)
    }
}

impl Shape {
    pub fn bounds(&self) -> Aabb {
        match *self {
            Shape::Box { center, half, cos, sin } => {
                let ex = (cos * half.x).abs() + (sin * half.y).abs();
                let ey = (sin * half.x).abs() + (cos * half.y).abs();
                let e = V3::new(ex, ey, half.z);
                Aabb { min: center - e, max: center + e }
            }
            Shape::Cylinder { x, y, radius, z0, z1 } => Aabb {
                min: V3::new(x - radius, y - radius, z0),
                max: V3::new(x + radius, y + radius, z1),
            },
            Shape::Ellipsoid { center, radii } => Aabb { min: center - radii, max: center + radii },
        }
    }

    #[inline]
    pub fn intersect(&self, origin: &V3, dir: &V3, t_max: f32) -> Option<ShapeHit> {
        match *self {
            Shape::Box { center, half, cos, sin } => intersect_box(origin, dir, t_max, center, half, cos, sin),
            Shape::Cylinder { x, y, radius, z0, z1 } => intersect_cylinder(origin, dir, t_max, x, y, radius, z0, z1),
            Shape::Ellipsoid { center, radii } => intersect_ellipsoid(origin, dir, t_max, center, radii),
        }
    }
}

#[inline]
fn intersect_box(o: &V3, d: &V3, t_max: f32, c: V3, h: V3, cos: f32, sin: f32) -> Option<ShapeHit> {
    // Into the box frame: rotate by -yaw about z.
    let rel = o - c;
    let lo = V3::new(cos * rel.x + sin * rel.y, -sin * rel.x + cos * rel.y, rel.z);
    let ld = V3::new(cos * d.x + sin * d.y, -sin * d.x + cos * d.y, d.z);
    let mut t0 = f32::NEG_INFINITY;
    let mut t1 = f32::INFINITY;
    let mut axis0 = 0;
    for axis in 0..3 {
        let inv = 1.0 / ld[axis];
        let a = (-h[axis] - lo[axis]) * inv;
        let b = (h[axis] - lo[axis]) * inv;
        let (near, far) = if a < b { (a, b) } else { (b, a) };
        if near > t0 {
            t0 = near;
            axis0 = axis;
        }
        if far < t1 {
            t1 = far;
        }
    }
    if t0 > t1 || t0 < T_EPSILON || t0 >= t_max {
        return None;
    }
    let p = lo + ld * t0;
    let sign = if ld[axis0] > 0.0 { -1.0 } else { 1.0 };
    let mut local_n = V3::zeros();
    local_n[axis0] = sign;
    let normal = V3::new(cos * local_n.x - sin * local_n.y, sin * local_n.x + cos * local_n.y, local_n.z);
    let uv = match axis0 {
        0 => [p.y + h.y, p.z + h.z],
        1 => [p.x + h.x, p.z + h.z],
        _ => [p.x + h.x, p.y + h.y],
    };
    Some(ShapeHit { t: t0, normal, uv })
}

#[allow(clippy::too_many_arguments)]
#[inline]
fn intersect_cylinder(o: &V3, d: &V3, t_max: f32, x: f32, y: f32, r: f32, z0: f32, z1: f32) -> Option<ShapeHit> {
    let (ox, oy) = (o.x - x, o.y - y);
    let mut best: Option<ShapeHit> = None;
    let a = d.x * d.x + d.y * d.y;
    if a > 1e-12 {
        let b = ox * d.x + oy * d.y;
        let c = ox * ox + oy * oy - r * r;
        let disc = b * b - a * c;
        if disc >= 0.0 {
            let t = (-b - disc.sqrt()) / a;
            let z = o.z + d.z * t;
            if t > T_EPSILON && t < t_max && z >= z0 && z <= z1 {
                let nx = (ox + d.x * t) / r;
                let ny = (oy + d.y * t) / r;
                let angle = ny.atan2(nx);
                best = Some(ShapeHit { t, normal: V3::new(nx, ny, 0.0), uv: [angle * r, z - z0] });
            }
        }
    }
    if d.z.abs() > 1e-12 {
        for (cap_z, nz) in [(z1, 1.0f32), (z0, -1.0)] {
            let t = (cap_z - o.z) / d.z;
            let limit = best.map_or(t_max, |h| h.t);
            if t > T_EPSILON && t < limit {
                let (px, py) = (ox + d.x * t, oy + d.y * t);
                if px * px + py * py <= r * r {
                    best = Some(ShapeHit { t, normal: V3::new(0.0, 0.0, nz), uv: [px, py] });
                }
            }
        }
    }
    best
}

#[inline]
fn intersect_ellipsoid(o: &V3, d: &V3, t_max: f32, c: V3, radii: V3) -> Option<ShapeHit> {
    let so = (o - c).component_div(&radii);
    let sd = d.component_div(&radii);
    let a = sd.dot(&sd);
    let b = so.dot(&sd);
    let cc = so.dot(&so) - 1.0;
    let disc = b * b - a * cc;
    if disc < 0.0 {
        return None;
    }
    let t = (-b - disc.sqrt()) / a;
    if t <= T_EPSILON || t >= t_max {
        return None;
    }
    let unit = so + sd * t;
    let normal = unit.component_div(&radii).normalize();
    Some(ShapeHit { t, normal, uv: [unit.x.atan2(unit.y) * radii.x, (unit.z + 1.0) * radii.z] })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rotated_box_hit_distance_and_normal() {
        let yaw = 30f32.to_radians();
        let shape = Shape::Box { center: V3::new(10.0, 0.0, 1.0), half: V3::new(1.0, 2.0, 1.0), cos: yaw.cos(), sin: yaw.sin() };
        // Straight down onto the top face.
        let hit = shape.intersect(&V3::new(10.0, 0.0, 5.0), &V3::new(0.0, 0.0, -1.0), 100.0).unwrap();
        assert!((hit.t - 3.0).abs() < 1e-5 && (hit.normal.z - 1.0).abs() < 1e-6);
        // Along the box's own local x axis from outside: hits the face at local x = -1.
        let dir = V3::new(yaw.cos(), yaw.sin(), 0.0);
        let origin = V3::new(10.0, 0.0, 1.0) - dir * 5.0;
        let hit = shape.intersect(&origin, &dir, 100.0).unwrap();
        assert!((hit.t - 4.0).abs() < 1e-5);
        assert!((hit.normal + dir).norm() < 1e-5);
        let b = shape.bounds();
        assert!(b.min.x < 10.0 - 1.0 && b.max.y > 2.0 * yaw.cos());
    }

    #[test]
    fn cylinder_and_ellipsoid_hits() {
        let pole = Shape::Cylinder { x: 5.0, y: 0.0, radius: 0.5, z0: 0.0, z1: 3.0 };
        let hit = pole.intersect(&V3::new(0.0, 0.0, 1.0), &V3::new(2.0, 0.0, 0.0), 100.0).unwrap();
        assert!((hit.t - 2.25).abs() < 1e-5 && (hit.normal.x + 1.0).abs() < 1e-5);
        assert!(pole.intersect(&V3::new(0.0, 0.0, 3.5), &V3::new(1.0, 0.0, 0.0), 100.0).is_none());
        let top = pole.intersect(&V3::new(5.0, 0.1, 10.0), &V3::new(0.0, 0.0, -1.0), 100.0).unwrap();
        assert!((top.t - 7.0).abs() < 1e-5 && top.normal.z == 1.0);
        let crown = Shape::Ellipsoid { center: V3::new(0.0, 10.0, 4.0), radii: V3::new(2.0, 1.0, 3.0) };
        let hit = crown.intersect(&V3::new(0.0, 0.0, 4.0), &V3::new(0.0, 1.0, 0.0), 100.0).unwrap();
        assert!((hit.t - 9.0).abs() < 1e-5 && (hit.normal.y + 1.0).abs() < 1e-5);
    }
}
