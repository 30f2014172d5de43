//! The one-shot baseline's geometric solver: a ground-plane 2-point solver inside RANSAC, then
//! Gauss-Newton refinement of the reprojection error.
//!
//! The paper's protocol perturbs the map only by a rotation about the map's z axis and a
//! translation in the map's xy plane, and the rig calibration `camera_from_lidar` (C) is known.
//! So camera_from_map = C · G with G = (Rz(θ), (a, b, 0)): three unknowns. A correspondence
//! (map point p, pixel (u, v)) says the lidar-frame point G·p lies on the pixel's ray
//! o + λ d (o = camera centre, d = ray direction, both in the lidar frame), i.e.
//! (G·p − o) × d = 0. With x = (cos θ, sin θ, a, b, 1) each component of that cross product is
//! linear in x, so two correspondences (four independent equations) determine x; cos θ and
//! sin θ are then projected onto the unit circle and (a, b) refitted.

use nalgebra::{Isometry3, Matrix2, Matrix3, Matrix4, Point3, Translation3, UnitQuaternion, Vector2, Vector3, Vector4};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::geometry::{Intrinsics, Pose};

/// A 2D–3D match: a map-frame point and the pixel (u, v) it is believed to project to.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Correspondence {
    pub point: Point3<f64>,
    pub pixel: (f64, f64),
}

/// RANSAC settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RansacOptions {
    pub iterations: usize,
    /// A match is an inlier when it reprojects within this many pixels (and in front).
    pub inlier_px: f64,
    /// Fewer inliers than this and the solver gives up.
    pub min_inliers: usize,
    pub seed: u64,
}

impl Default for RansacOptions {
    fn default() -> Self {
        RansacOptions { iterations: 1000, inlier_px: 8.0, min_inliers: 6, seed: 0 }
    }
}

/// The solver's answer.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GroundPnpSolution {
    pub camera_from_map: Pose,
    /// Map-to-rig ground motion G: yaw θ (rad) about z and translation (a, b).
    pub yaw_rad: f64,
    pub translation_xy: (f64, f64),
    pub inliers: usize,
}

/// Solves camera_from_map = C · G for G a ground-plane motion, from 2D–3D matches.
pub struct GroundPnp {
    camera_from_lidar: Pose,
    intrinsics: Intrinsics,
    /// Camera centre in the lidar frame.
    origin: Vector3<f64>,
    /// Lidar-from-camera rotation, turning camera rays into lidar-frame directions.
    lidar_from_camera: Matrix3<f64>,
}

impl GroundPnp {
    pub fn new(camera_from_lidar: Pose, intrinsics: Intrinsics) -> Self {
        let lidar_from_camera = camera_from_lidar.rotation().transpose();
        let origin = camera_from_lidar.camera_position_in_map();
        GroundPnp { camera_from_lidar, intrinsics, origin, lidar_from_camera }
    }

    /// camera_from_map for the ground motion (θ, a, b).
    pub fn pose(&self, yaw_rad: f64, a: f64, b: f64) -> Pose {
        let g = Pose(Isometry3::from_parts(Translation3::new(a, b, 0.0), UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw_rad)));
        self.camera_from_lidar.compose(&g)
    }

    /// The three rows (over x = (c, s, a, b, 1)) of (G·p − o) × d for one correspondence.
    fn rows(&self, m: &Correspondence) -> [[f64; 5]; 3] {
        let k = &self.intrinsics;
        let ray = Vector3::new((m.pixel.0 - k.cx) / k.fx, (m.pixel.1 - k.cy) / k.fy, 1.0);
        let d = self.lidar_from_camera * ray;
        let (p, o) = (m.point, self.origin);
        let wx = [p.x, -p.y, 1.0, 0.0, -o.x];
        let wy = [p.y, p.x, 0.0, 1.0, -o.y];
        let wz = [0.0, 0.0, 0.0, 0.0, p.z - o.z];
        let combine = |a: &[f64; 5], fa: f64, b: &[f64; 5], fb: f64| -> [f64; 5] { std::array::from_fn(|i| a[i] * fa - b[i] * fb) };
        [combine(&wy, d.z, &wz, d.y), combine(&wz, d.x, &wx, d.z), combine(&wx, d.y, &wy, d.x)]
    }

    /// Least-squares (θ, a, b) from two or more correspondences; None when degenerate.
    pub fn solve_linear(&self, matches: &[Correspondence]) -> Option<(f64, f64, f64)> {
        let mut ata = Matrix4::<f64>::zeros();
        let mut atb = Vector4::<f64>::zeros();
        let mut rows_all = Vec::with_capacity(matches.len() * 3);
        for m in matches {
            for r in self.rows(m) {
                let a = Vector4::new(r[0], r[1], r[2], r[3]);
                ata += a * a.transpose();
                atb -= a * r[4];
                rows_all.push(r);
            }
        }
        let x = ata.try_inverse()? * atb;
        let norm = x[0].hypot(x[1]);
        if !norm.is_finite() || norm < 1e-9 {
            return None;
        }
        let (c, s) = (x[0] / norm, x[1] / norm);
        // Refit (a, b) with the rotation fixed on the unit circle.
        let mut n = Matrix2::<f64>::zeros();
        let mut rhs = Vector2::<f64>::zeros();
        for r in &rows_all {
            let a = Vector2::new(r[2], r[3]);
            n += a * a.transpose();
            rhs -= a * (r[0] * c + r[1] * s + r[4]);
        }
        let ab = n.try_inverse()? * rhs;
        let out = (s.atan2(c), ab[0], ab[1]);
        (out.0.is_finite() && out.1.is_finite() && out.2.is_finite()).then_some(out)
    }

    /// Squared reprojection error in pixels, or None when the point is behind the camera.
    fn residual(&self, pose: &Pose, m: &Correspondence) -> Option<(f64, f64)> {
        let p = pose.transform(&m.point);
        if p.z < crate::geometry::camera::MIN_DEPTH_M {
            return None;
        }
        let (u, v) = self.intrinsics.project(&p)?;
        Some((u - m.pixel.0, v - m.pixel.1))
    }

    fn inliers(&self, pose: &Pose, matches: &[Correspondence], max_px: f64) -> Vec<usize> {
        let max2 = max_px * max_px;
        (0..matches.len())
            .filter(|&i| self.residual(pose, &matches[i]).is_some_and(|(du, dv)| du * du + dv * dv < max2))
            .collect()
    }

    /// Gauss-Newton on the summed squared reprojection error over `matches` (numeric Jacobian).
    pub fn refine(&self, start: (f64, f64, f64), matches: &[Correspondence]) -> (f64, f64, f64) {
        let mut x = Vector3::new(start.0, start.1, start.2);
        let residuals = |x: &Vector3<f64>| -> Vec<f64> {
            let pose = self.pose(x[0], x[1], x[2]);
            matches
                .iter()
                .flat_map(|m| match self.residual(&pose, m) {
                    Some((du, dv)) => [du, dv],
                    None => [0.0, 0.0],
                })
                .collect()
        };
        for _ in 0..10 {
            let r0 = residuals(&x);
            let steps = [1e-6, 1e-5, 1e-5];
            let mut jtj = Matrix3::<f64>::zeros();
            let mut jtr = Vector3::<f64>::zeros();
            let columns: Vec<Vec<f64>> = (0..3)
                .map(|j| {
                    let mut xj = x;
                    xj[j] += steps[j];
                    residuals(&xj).iter().zip(&r0).map(|(a, b)| (a - b) / steps[j]).collect()
                })
                .collect();
            for i in 0..r0.len() {
                let row = Vector3::new(columns[0][i], columns[1][i], columns[2][i]);
                jtj += row * row.transpose();
                jtr += row * r0[i];
            }
            let Some(inv) = (jtj + Matrix3::identity() * 1e-9).try_inverse() else { break };
            let delta = inv * jtr;
            let candidate = x - delta;
            let cost = |r: &[f64]| r.iter().map(|v| v * v).sum::<f64>();
            if !candidate.iter().all(|v| v.is_finite()) || cost(&residuals(&candidate)) > cost(&r0) {
                break;
            }
            x = candidate;
            if delta.norm() < 1e-10 {
                break;
            }
        }
        (x[0], x[1], x[2])
    }

    /// RANSAC over 2-point samples, then refinement on the inliers (twice, re-selecting them).
    pub fn solve_ransac(&self, matches: &[Correspondence], options: &RansacOptions) -> Option<GroundPnpSolution> {
        if matches.len() < 2.max(options.min_inliers) {
            return None;
        }
        let mut rng = ChaCha8Rng::seed_from_u64(options.seed);
        let mut best: Option<((f64, f64, f64), usize)> = None;
        for _ in 0..options.iterations {
            let i = rng.random_range(0..matches.len());
            let j = rng.random_range(0..matches.len());
            if i == j {
                continue;
            }
            let Some(model) = self.solve_linear(&[matches[i], matches[j]]) else { continue };
            let count = self.inliers(&self.pose(model.0, model.1, model.2), matches, options.inlier_px).len();
            if best.is_none_or(|(_, c)| count > c) {
                best = Some((model, count));
            }
        }
        let (mut model, count) = best?;
        if count < options.min_inliers {
            return None;
        }
        let mut inliers = Vec::new();
        for _ in 0..2 {
            inliers = self.inliers(&self.pose(model.0, model.1, model.2), matches, options.inlier_px);
            if inliers.len() < options.min_inliers {
                return None;
            }
            let chosen: Vec<Correspondence> = inliers.iter().map(|&i| matches[i]).collect();
            model = self.refine(model, &chosen);
        }
        Some(GroundPnpSolution {
            camera_from_map: self.pose(model.0, model.1, model.2),
            yaw_rad: model.0,
            translation_xy: (model.1, model.2),
            inliers: inliers.len(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::PoseError;

    fn kitti_like_rig() -> Pose {
        let r = Matrix3::new(0.0, -1.0, 0.0, 0.0, 0.0, -1.0, 1.0, 0.0, 0.0);
        Pose::from_rt(r, Vector3::new(0.06, -0.08, -0.27))
    }

    /// Map points visible from the true pose, with their exact pixels.
    fn scene(truth: &Pose, k: &Intrinsics, count: usize, seed: u64) -> Vec<Correspondence> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let inverse = truth.inverse();
        let mut out = Vec::new();
        while out.len() < count {
            let (u, v, depth) = (rng.random_range(0.0..512.0), rng.random_range(0.0..160.0), rng.random_range(3.0..40.0));
            let point = inverse.transform(&k.back_project(u, v, depth));
            out.push(Correspondence { point, pixel: (u, v) });
        }
        out
    }

    #[test]
    fn two_exact_matches_determine_the_ground_motion() {
        let k = Intrinsics { fx: 359.0, fy: 359.0, cx: 255.5, cy: 79.5 };
        let pnp = GroundPnp::new(kitti_like_rig(), k);
        let truth = pnp.pose(2.4, -7.5, 3.25);
        let matches = scene(&truth, &k, 2, 1);
        let (yaw, a, b) = pnp.solve_linear(&matches).unwrap();
        assert!((yaw - 2.4).abs() < 1e-9 && (a + 7.5).abs() < 1e-8 && (b - 3.25).abs() < 1e-8, "{yaw} {a} {b}");
    }

    #[test]
    fn ransac_recovers_the_pose_exactly_despite_outliers() {
        let k = Intrinsics { fx: 359.0, fy: 359.0, cx: 255.5, cy: 79.5 };
        let pnp = GroundPnp::new(kitti_like_rig(), k);
        let truth = pnp.pose(-1.3, 4.0, -9.0);
        let mut matches = scene(&truth, &k, 60, 2);
        // 40% outliers: the same points with shuffled pixels.
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for m in matches.iter_mut().take(24) {
            m.pixel = (rng.random_range(0.0..512.0), rng.random_range(0.0..160.0));
        }
        let solution = pnp.solve_ransac(&matches, &RansacOptions::default()).unwrap();
        let e = PoseError::between(&solution.camera_from_map, &truth);
        assert!(e.rte_m < 1e-6 && e.rre_geodesic_deg < 1e-6, "{e:?}");
        assert!(solution.inliers >= 36);
    }

    #[test]
    fn too_few_or_degenerate_matches_give_no_answer() {
        let k = Intrinsics { fx: 359.0, fy: 359.0, cx: 255.5, cy: 79.5 };
        let pnp = GroundPnp::new(kitti_like_rig(), k);
        let m = Correspondence { point: Point3::new(10.0, 0.0, 0.0), pixel: (255.5, 79.5) };
        assert!(pnp.solve_linear(&[m, m]).is_none());
        assert!(pnp.solve_ransac(&[m; 3], &RansacOptions::default()).is_none());
    }
}
