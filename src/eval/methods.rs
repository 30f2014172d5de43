//! What the evaluator compares: every method turns one case into a pose per iteration.

use std::time::Instant;

use anyhow::Result;
use image::RgbImage;
use nalgebra::Point3;

use crate::geometry::{ActionSet, Intrinsics, Pose};

use super::perturbations::Perturbation;

/// The greedy expert's method name.
pub const EXPERT: &str = "expert (oracle)";

/// One evaluated frame under its frozen perturbation, as every method sees it.
pub struct EvalCase {
    pub perturbation: Perturbation,
    /// The whole map cloud (Q·scan, finite points), map frame: what a user would upload.
    pub map_cloud: Vec<[f32; 3]>,
    /// The raw intensity of each point of `map_cloud` (the scan's 4th float), which a model
    /// that reads intensity is given with the points; `None` when the case has none.
    pub map_intensity: Option<Vec<f32>>,
    /// Its N sampled points (the contract's ChaCha8 seed-0 sampling), map frame.
    pub map_points: Vec<[f32; 3]>,
    /// The pivot of rotation steps: the mean of `map_points`.
    pub pivot: Point3<f64>,
    /// The full camera image and its intrinsics (methods crop it themselves).
    pub image: RgbImage,
    pub intrinsics: Intrinsics,
    /// The starting pose: the rig's camera_from_lidar.
    pub initial: Pose,
    /// Ground truth camera_from_map = camera_from_lidar · Q⁻¹.
    pub truth: Pose,
}

/// One method's answer for one case.
#[derive(Debug, Clone, PartialEq)]
pub struct MethodRun {
    pub method: String,
    /// The estimate after iterations 1..=K; one entry for one-shot methods. A trajectory that
    /// stopped early repeats its last pose up to K.
    pub poses: Vec<Pose>,
    /// Milliseconds from the method's start until `poses[k]` was known (for the per-iteration table).
    pub elapsed_ms: Vec<f64>,
    /// Time per named phase (e.g. image encoder, matching, RANSAC).
    pub phases_ms: Vec<(String, f64)>,
    /// Method-specific notes for the per-case JSON (e.g. inliers, early stop).
    pub notes: serde_json::Value,
}

/// A method, or a group of methods that share expensive inputs (the learned ones share the
/// map embeddings), returning one run per method name.
pub trait Method {
    fn names(&self) -> Vec<String>;
    fn run(&mut self, case: &EvalCase) -> Result<Vec<MethodRun>>;
}

/// The initial pose, unchanged: the error a localizer starts from.
pub struct NoOp;

impl Method for NoOp {
    fn names(&self) -> Vec<String> {
        vec!["no-op".into()]
    }

    fn run(&mut self, case: &EvalCase) -> Result<Vec<MethodRun>> {
        Ok(vec![MethodRun {
            method: "no-op".into(),
            poses: vec![case.initial],
            elapsed_ms: vec![0.0],
            phases_ms: vec![],
            notes: serde_json::Value::Null,
        }])
    }
}

/// The greedy expert with ground truth: per DoF the step nearest to the needed motion. Its
/// error after K steps is the ceiling the discrete action set allows in K iterations.
pub struct Expert {
    pub actions: ActionSet,
    pub iterations: usize,
}

impl Method for Expert {
    fn names(&self) -> Vec<String> {
        vec![EXPERT.into()]
    }

    fn run(&mut self, case: &EvalCase) -> Result<Vec<MethodRun>> {
        let start = Instant::now();
        let mut pose = case.initial;
        let mut poses = Vec::with_capacity(self.iterations);
        let mut elapsed_ms = Vec::with_capacity(self.iterations);
        for _ in 0..self.iterations {
            let action = self.actions.expert(&pose, &case.truth, &case.pivot);
            pose = self.actions.apply(&pose, &case.pivot, &action);
            poses.push(pose);
            elapsed_ms.push(start.elapsed().as_secs_f64() * 1e3);
        }
        Ok(vec![MethodRun { method: self.names().remove(0), poses, elapsed_ms, phases_ms: vec![], notes: serde_json::Value::Null }])
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::geometry::PoseError;
    use nalgebra::{Matrix3, Vector3};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    pub(crate) fn rig() -> Pose {
        let r = Matrix3::new(0.0, -1.0, 0.0, 0.0, 0.0, -1.0, 1.0, 0.0, 0.0);
        Pose::from_rt(r, Vector3::new(0.06, -0.08, -0.27))
    }

    /// A case with a random street-like cloud and the given perturbation (no image content).
    pub(crate) fn case(yaw_deg: f64, dx_m: f64, dy_m: f64) -> EvalCase {
        let perturbation = Perturbation { sequence: "00".into(), frame: 0, yaw_deg, dx_m, dy_m };
        let q = perturbation.map_from_lidar();
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let map_points: Vec<[f32; 3]> = (0..500)
            .map(|_| {
                let p = nalgebra::Point3::new(rng.random_range(-30.0..30.0), rng.random_range(-30.0..30.0), rng.random_range(-1.8..3.0));
                let m = q.transform(&p);
                [m.x as f32, m.y as f32, m.z as f32]
            })
            .collect();
        let n = map_points.len() as f64;
        let sum = map_points.iter().fold(Vector3::zeros(), |acc, p| acc + Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64));
        EvalCase {
            pivot: Point3::from(sum / n),
            map_cloud: map_points.clone(),
            map_intensity: None,
            map_points,
            image: RgbImage::new(4, 4),
            intrinsics: Intrinsics { fx: 700.0, fy: 700.0, cx: 620.0, cy: 187.0 },
            initial: rig(),
            truth: perturbation.truth(&rig()),
            perturbation,
        }
    }

    #[test]
    fn no_op_error_is_the_perturbation() {
        let c = case(-123.0, 6.0, -8.0);
        let run = NoOp.run(&c).unwrap().remove(0);
        let e = PoseError::between(&run.poses[0], &c.truth);
        assert!((e.rte_m - 10.0).abs() < 1e-9, "{e:?}");
        assert!((e.rre_geodesic_deg - 123.0).abs() < 1e-9 && (e.rre_euler_deg - 123.0).abs() < 1e-9, "{e:?}");
    }

    #[test]
    fn the_expert_reaches_near_zero_error_from_any_perturbation() {
        let mut expert = Expert { actions: ActionSet::default(), iterations: 10 };
        for (yaw, dx, dy) in [(179.9, 10.0, -10.0), (-180.0, -9.0, 4.0), (3.3, 0.05, 0.0), (-47.0, 2.2, 7.7)] {
            let c = case(yaw, dx, dy);
            let run = expert.run(&c).unwrap().remove(0);
            assert_eq!(run.poses.len(), 10);
            let start = PoseError::between(&c.initial, &c.truth);
            let last = PoseError::between(&run.poses[9], &c.truth);
            assert!(last.rte_m < 0.06 && last.rre_geodesic_deg < 0.06, "{yaw} {dx} {dy}: {last:?}");
            assert!(last.rte_m < start.rte_m || start.rte_m < 0.06);
        }
    }
}
