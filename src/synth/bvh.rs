//! A bounding-volume hierarchy over the scene's shapes: what makes ray casting a whole street
//! (hundreds of shapes, ~10⁶ rays per frame) affordable.

use super::shapes::{Aabb, Shape, ShapeHit, V3};

const LEAF_SIZE: usize = 4;

#[derive(Debug, Clone, Copy)]
struct Node {
    bounds: Aabb,
    /// Leaf: index of the first shape; inner: index of the left child (right = left + 1).
    first: u32,
    /// Number of shapes in a leaf; 0 for inner nodes.
    count: u32,
}

/// Built once per scene; shapes are reordered so each leaf's shapes are contiguous.
#[derive(Debug, Clone)]
pub struct Bvh {
    nodes: Vec<Node>,
    /// Shape indices in leaf order.
    order: Vec<u32>,
}

impl Bvh {
    /// Median split along the longest axis of the centroids' bounds (cheap to build, and good
    /// enough for a street of a few thousand shapes).
    pub fn build(shapes: &[Shape]) -> Self {
        let bounds: Vec<Aabb> = shapes.iter().map(Shape::bounds).collect();
        let mut order: Vec<u32> = (0..shapes.len() as u32).collect();
        let mut nodes = vec![Node { bounds: Aabb::empty(), first: 0, count: 0 }];
        if !shapes.is_empty() {
            build_node(&mut nodes, 0, &mut order, 0, &bounds);
        }
        Bvh { nodes, order }
    }

    /// The closest hit with t < `t_max`: (shape index, hit).
    pub fn closest(&self, shapes: &[Shape], origin: &V3, dir: &V3, t_max: f32) -> Option<(u32, ShapeHit)> {
        if self.order.is_empty() {
            return None;
        }
        let inv = V3::new(1.0 / dir.x, 1.0 / dir.y, 1.0 / dir.z);
        let mut best: Option<(u32, ShapeHit)> = None;
        let mut limit = t_max;
        self.nodes[0].bounds.hit(origin, &inv, limit)?;
        let mut stack = [0u32; 64];
        let mut top = 1usize;
        while top > 0 {
            top -= 1;
            let node = &self.nodes[stack[top] as usize];
            if node.count > 0 {
                for &shape_index in &self.order[node.first as usize..(node.first + node.count) as usize] {
                    if let Some(hit) = shapes[shape_index as usize].intersect(origin, dir, limit) {
                        limit = hit.t;
                        best = Some((shape_index, hit));
                    }
                }
                continue;
            }
            let (left, right) = (node.first, node.first + 1);
            let tl = self.nodes[left as usize].bounds.hit(origin, &inv, limit);
            let tr = self.nodes[right as usize].bounds.hit(origin, &inv, limit);
            // Push the farther child first so the nearer one is searched first and shrinks `limit`.
            match (tl, tr) {
                (Some(a), Some(b)) => {
                    let (near, far) = if a <= b { (left, right) } else { (right, left) };
                    stack[top] = far;
                    stack[top + 1] = near;
                    top += 2;
                }
                (Some(_), None) => {
                    stack[top] = left;
                    top += 1;
                }
                (None, Some(_)) => {
                    stack[top] = right;
                    top += 1;
                }
                (None, None) => {}
            }
        }
        best
    }

    /// Whether anything blocks the segment (0, t_max): shadow rays stop at the first blocker.
    pub fn any_hit(&self, shapes: &[Shape], origin: &V3, dir: &V3, t_max: f32) -> bool {
        if self.order.is_empty() {
            return false;
        }
        let inv = V3::new(1.0 / dir.x, 1.0 / dir.y, 1.0 / dir.z);
        let mut stack = [0u32; 64];
        let mut top = 1usize;
        while top > 0 {
            top -= 1;
            let node = &self.nodes[stack[top] as usize];
            if node.bounds.hit(origin, &inv, t_max).is_none() {
                continue;
            }
            if node.count > 0 {
                let leaf = &self.order[node.first as usize..(node.first + node.count) as usize];
                if leaf.iter().any(|&i| shapes[i as usize].intersect(origin, dir, t_max).is_some()) {
                    return true;
                }
            } else {
                stack[top] = node.first;
                stack[top + 1] = node.first + 1;
                top += 2;
            }
        }
        false
    }
}

fn build_node(nodes: &mut Vec<Node>, node_index: usize, order: &mut [u32], first: usize, bounds: &[Aabb]) {
    let node_bounds = order.iter().fold(Aabb::empty(), |acc, &i| acc.union(&bounds[i as usize]));
    nodes[node_index].bounds = node_bounds;
    if order.len() <= LEAF_SIZE {
        nodes[node_index].first = first as u32;
        nodes[node_index].count = order.len() as u32;
        return;
    }
    let centroid_bounds = order.iter().fold(Aabb::empty(), |acc, &i| {
        let c = bounds[i as usize].centroid();
        acc.union(&Aabb { min: c, max: c })
    });
    let extent = centroid_bounds.max - centroid_bounds.min;
    let axis = if extent.x >= extent.y && extent.x >= extent.z { 0 } else if extent.y >= extent.z { 1 } else { 2 };
    let mid = order.len() / 2;
    order.select_nth_unstable_by(mid, |&a, &b| {
        let ca = bounds[a as usize].centroid()[axis];
        let cb = bounds[b as usize].centroid()[axis];
        ca.total_cmp(&cb).then(a.cmp(&b))
    });
    let left = nodes.len();
    nodes.push(Node { bounds: Aabb::empty(), first: 0, count: 0 });
    nodes.push(Node { bounds: Aabb::empty(), first: 0, count: 0 });
    nodes[node_index].first = left as u32;
    nodes[node_index].count = 0;
    let (lo, hi) = order.split_at_mut(mid);
    build_node(nodes, left, lo, first, bounds);
    build_node(nodes, left + 1, hi, first + mid, bounds);
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// The hierarchy must return exactly what testing every shape returns.
    #[test]
    fn matches_brute_force() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let shapes: Vec<Shape> = (0..300)
            .map(|i| {
                let c = V3::new(rng.random_range(-50.0..50.0), rng.random_range(-50.0..50.0), rng.random_range(0.0..5.0));
                match i % 3 {
                    0 => {
                        let yaw: f32 = rng.random_range(-1.0..1.0);
                        Shape::Box { center: c, half: V3::new(1.0, 2.0, 1.5), cos: yaw.cos(), sin: yaw.sin() }
                    }
                    1 => Shape::Cylinder { x: c.x, y: c.y, radius: 0.4, z0: 0.0, z1: c.z + 1.0 },
                    _ => Shape::Ellipsoid { center: c, radii: V3::new(1.5, 1.0, 2.0) },
                }
            })
            .collect();
        let bvh = Bvh::build(&shapes);
        for _ in 0..2000 {
            let o = V3::new(rng.random_range(-60.0..60.0), rng.random_range(-60.0..60.0), rng.random_range(0.0..4.0));
            let d = V3::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-0.2..0.2));
            let brute = shapes
                .iter()
                .enumerate()
                .filter_map(|(i, s)| s.intersect(&o, &d, 200.0).map(|h| (i as u32, h)))
                .min_by(|a, b| a.1.t.total_cmp(&b.1.t));
            let fast = bvh.closest(&shapes, &o, &d, 200.0);
            assert_eq!(brute.map(|b| b.0), fast.map(|f| f.0));
            assert_eq!(brute.is_some(), bvh.any_hit(&shapes, &o, &d, 200.0));
        }
        let empty = Bvh::build(&[]);
        assert!(empty.closest(&[], &V3::zeros(), &V3::x(), 10.0).is_none());
        assert!(!empty.any_hit(&[], &V3::zeros(), &V3::x(), 10.0));
    }
}
