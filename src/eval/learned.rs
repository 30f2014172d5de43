//! The learned methods, sharing one model backend and one map embedding per case:
//! - the CMR agent, through the server's own step loop (`maps::prepare_map`,
//!   `agent::prepare_image`, `agent::localize`), with the configured multi-start search and,
//!   when that has more than one start, also alone from the given start (the paper's protocol);
//! - the one-shot baseline on the same embeddings: points the frustum head predicts in view,
//!   mutual-nearest-neighbour feature matches against the image feature grid, then the
//!   ground-plane 2-point RANSAC solver (`pnp`).

use std::collections::BTreeMap;
use std::time::Instant;

use anyhow::Result;
use serde_json::json;

use std::sync::Arc;

use crate::agent::{self, SearchConfig, ms};
use crate::geometry::{Pose, PoseError};
use crate::maps::{PreparedMap, prepare_map};
use crate::model::{Backend, Calibration, Points};

use super::matching::{MatchStrategy, cell_centre, find_matches};
use super::methods::{EvalCase, Method, MethodRun};
use super::pnp::{Correspondence, GroundPnp, RansacOptions};

/// The agent as served: the configured number of starts.
pub const AGENT: &str = "cmr-agent";
/// The agent from the given start only: the paper's single trajectory.
pub const AGENT_SINGLE_START: &str = "cmr-agent, single start";
pub const BASELINE: &str = "one-shot matching + RANSAC";

pub struct Learned {
    backend: Box<dyn Backend>,
    /// The model set's calibrator at its own threshold: the verdict the server gives.
    calibration: Calibration,
    /// Run the one-shot baseline too.
    baseline: bool,
    /// The agent's search as served; K = `search.max_iterations`.
    search: SearchConfig,
    ransac: RansacOptions,
    matching: MatchStrategy,
    /// Every hypothesis's trajectory in the notes (`hypothesis_trajectories`).
    record_hypotheses: bool,
}

impl Learned {
    /// `baseline`: run the one-shot baseline as well as the agent.
    pub fn new(backend: Box<dyn Backend>, search: SearchConfig, ransac: RansacOptions, matching: MatchStrategy, record_hypotheses: bool, baseline: bool) -> Self {
        let calibration = Calibration::new(backend.manifest().calibrator.as_ref(), None);
        Learned { backend, calibration, baseline, search, ransac, matching, record_hypotheses }
    }

    /// Parameters each method runs: the agent all four graphs, the baseline all but the agent.
    pub fn parameters(graphs: &BTreeMap<String, u64>) -> BTreeMap<String, u64> {
        let sum = |names: &[&str]| names.iter().filter_map(|n| graphs.get(*n)).sum::<u64>();
        let encoders = ["point_encoder", "image_encoder", "frustum_head"];
        let agent = sum(&[&encoders[..], &["agent"]].concat());
        BTreeMap::from([(AGENT.to_string(), agent), (AGENT_SINGLE_START.to_string(), agent), (BASELINE.to_string(), sum(&encoders))])
    }

    fn run_agent(&mut self, case: &EvalCase, map: &Arc<PreparedMap>, method: &str, search: SearchConfig) -> Result<MethodRun> {
        let start = Instant::now();
        let manifest = self.backend.manifest().clone();
        let (tensor, crop_intrinsics) = agent::prepare_image(&case.image, &case.intrinsics, &manifest)?;
        let views = if search.judges() { agent::prepare_views(&case.image, &case.intrinsics, &manifest, search.judge_zoom)? } else { Vec::new() };
        let image_ms = ms(start);
        let k = search.max_iterations;
        let start = agent::Start { maps: vec![map.clone()], image_tensor: tensor.clone(), intrinsics: crop_intrinsics, prior: case.initial, search, views };
        let mut loc = agent::localize_start(self.backend.as_mut(), start)?;
        // The server's verdict (`serving::Localizer` does the same after its search).
        let signals = loc.signals();
        loc.verdict = self.calibration.judge(&signals);
        let t = loc.timings;
        // localize reports one total for all steps, so the time to reach step k is the time before
        // the loop plus k equal shares of it. Once hypotheses stop (merged, converged) later steps
        // have fewer rows, so this understates the first steps' times a little.
        let before_loop = image_ms + t.image_encoder_ms + t.frustum_head_ms;
        let per_step = t.agent_steps_ms / loc.iterations().max(1) as f64;
        // The answer had the search stopped after k steps (a stopped trajectory keeps its pose).
        let poses = (1..=k).map(|i| loc.pose_after(i)).collect();
        let elapsed_ms = (1..=k).map(|i| before_loop + per_step * i.min(loc.iterations()) as f64).collect();
        let best = loc.best();
        let mut notes = json!({
            "iterations_run": best.steps.len(),
            "converged": best.converged,
            "confidence": loc.confidence.score,
            "chosen_start_yaw_offset_deg": best.start_yaw_offset_deg,
            "chosen_start_axis_shift_m": best.start_axis_shift_m,
            "kept_prior": loc.kept_prior,
            // The answer (polished, when the search polished) and the truth, camera_from_map,
            // map frame, row-major 3x4: for error breakdowns (along the heading, sideways, up).
            "answer_camera_from_map": loc.camera_from_map().to_row_major_3x4(),
            "truth_camera_from_map": case.truth.to_row_major_3x4(),
            // Steps of the chosen start that led to the answer (fewer than it ran when a prior
            // bound answered with a pose it passed).
            "answer_steps": loc.answer_steps().len(),
            "alignment": loc.hypotheses.iter().map(|h| h.alignment()).collect::<Vec<_>>(),
            // Policy rows this case cost: the steps over all hypotheses that asked the policy (a
            // repeated step of a cycle costs none; the search's price).
            "policy_rows": loc.hypotheses.iter().flat_map(|h| &h.steps).filter(|s| !s.repeated).count(),
            // The calibrated verdict (null / false without a calibrator) and what it read.
            "p_registered": loc.verdict.p_registered,
            "localized": loc.verdict.localized,
            "signals": signals,
            // The judge's views (null when the search does not judge): the starts' agreement with
            // the served search's answer, and whether the views were read (`--judge-gate`).
            "judge": loc.judge.map(|j| json!({"agreement": j.agreement, "read_views": j.read_views})),
        });
        if self.record_hypotheses && method == AGENT {
            // The frustum head again (the search keeps its answers to itself), for the IoU of
            // every visited pose: a judge tried offline (scripts/pose-judges.py).
            let m = manifest.points.num_state_points.min(map.points.len());
            let image_features = self.backend.encode_image(&tensor)?;
            let logits = self.backend.frustum_logits(&map.features[..m * manifest.features.dim], &image_features)?;
            let probs: Vec<f32> = logits.iter().map(|l| agent::state::sigmoid(*l)).collect();
            let layout = agent::StateLayout::from_manifest(&manifest);
            let iou = |pose: &Pose| agent::episode::frustum_iou(&map.points[..m], &probs, &crop_intrinsics, &layout, pose);
            notes["hypotheses"] = hypothesis_trajectories(&loc, &case.truth, &iou);
        }
        Ok(MethodRun {
            method: method.into(),
            poses,
            elapsed_ms,
            phases_ms: vec![
                ("image preprocessing".into(), image_ms),
                ("image encoder".into(), t.image_encoder_ms),
                ("frustum head".into(), t.frustum_head_ms),
                ("agent steps".into(), t.agent_steps_ms),
                ("agent steps: state building".into(), t.state_build_ms),
                ("agent steps: polish".into(), t.polish_ms),
                ("agent steps: judge's views".into(), t.judge_ms),
            ],
            notes,
        })
    }

    fn run_baseline(&mut self, case: &EvalCase, map: &PreparedMap) -> Result<MethodRun> {
        let start = Instant::now();
        let manifest = self.backend.manifest().clone();
        let (tensor, crop_intrinsics) = agent::prepare_image(&case.image, &case.intrinsics, &manifest)?;
        let image_ms = ms(start);
        let t = Instant::now();
        let image_features = self.backend.encode_image(&tensor)?;
        let encoder_ms = ms(t);
        let t = Instant::now();
        let logits = self.backend.frustum_logits(&map.features, &image_features)?;
        let frustum_ms = ms(t);
        let t = Instant::now();
        let grid = FeatureGrid { dim: manifest.features.dim, stride: manifest.features.stride, grid_width: manifest.features.grid_width };
        let (in_view, correspondences) = one_shot_correspondences(&map.points, &map.features, &logits, &image_features, grid, self.matching);
        let matching_ms = ms(t);
        let t = Instant::now();
        let solution = GroundPnp::new(case.initial, crop_intrinsics).solve_ransac(&correspondences, &self.ransac);
        let ransac_ms = ms(t);
        // No solution: the method answers with the initial pose (and so fails the case).
        let pose = solution.map_or(case.initial, |s| s.camera_from_map);
        Ok(MethodRun {
            method: BASELINE.into(),
            poses: vec![pose],
            elapsed_ms: vec![ms(start)],
            phases_ms: vec![
                ("image preprocessing".into(), image_ms),
                ("image encoder".into(), encoder_ms),
                ("frustum head".into(), frustum_ms),
                ("matching".into(), matching_ms),
                ("RANSAC + refinement".into(), ransac_ms),
            ],
            notes: json!({
                "predicted_in_view": in_view,
                "matches": correspondences.len(),
                "inliers": solution.map_or(0, |s| s.inliers),
                "solved": solution.is_some(),
            }),
        })
    }
}

/// The shape of the image feature grid, from the manifest.
#[derive(Debug, Clone, Copy)]
pub struct FeatureGrid {
    pub dim: usize,
    pub stride: usize,
    pub grid_width: usize,
}

/// The baseline's matching stage: the points the frustum head predicts in view (logit > 0),
/// matched to image cells by `strategy`, each match as (map point, cell-centre
/// pixel in the model's crop). Returns the number of predicted-in-view points and the matches.
pub fn one_shot_correspondences(
    points: &[[f32; 3]],
    point_features: &[f32],
    frustum_logits: &[f32],
    image_features: &[f32],
    grid: FeatureGrid,
    strategy: MatchStrategy,
) -> (usize, Vec<Correspondence>) {
    let in_view: Vec<usize> = (0..frustum_logits.len().min(points.len())).filter(|&i| frustum_logits[i] > 0.0).collect();
    let matches = find_matches(point_features, grid.dim, &in_view, image_features, grid.grid_width, strategy);
    let correspondences = matches
        .iter()
        .map(|m| {
            let p = points[m.point];
            Correspondence {
                point: nalgebra::Point3::new(p[0] as f64, p[1] as f64, p[2] as f64),
                pixel: cell_centre(m.cell, grid.grid_width, grid.stride),
            }
        })
        .collect();
    (in_view.len(), correspondences)
}

impl Method for Learned {
    fn names(&self) -> Vec<String> {
        let mut names = vec![AGENT.to_string()];
        if self.search.hypotheses > 1 {
            names.push(AGENT_SINGLE_START.into());
        }
        if self.baseline {
            names.push(BASELINE.into());
        }
        names
    }

    fn run(&mut self, case: &EvalCase) -> Result<Vec<MethodRun>> {
        let t = Instant::now();
        let map = Arc::new(prepare_map(self.backend.as_mut(), Points::new(&case.map_cloud, case.map_intensity.as_deref()))?);
        let prepare_ms = ms(t);
        let mut runs = vec![self.run_agent(case, &map, AGENT, self.search)?];
        // Once per map (the server caches it), so it is reported apart from per-request times.
        runs[0].notes["map_prepare_ms"] = json!(prepare_ms);
        if self.search.hypotheses > 1 {
            runs.push(self.run_agent(case, &map, AGENT_SINGLE_START, SearchConfig::single(self.search.max_iterations))?);
        }
        if self.baseline {
            runs.push(self.run_baseline(case, &map)?);
        }
        Ok(runs)
    }
}

/// Every hypothesis of a search as JSON: its start, and after each step the pose
/// (camera_from_map, row-major 3×4), the alignment score, the frustum IoU (`frustum_iou`, as
/// `Confidence::frustum_iou`) and the errors against `truth`, with the policy's outputs
/// (`policy_step`); how it stopped. What `scripts/search-rules.py` and `scripts/pose-judges.py`
/// read.
fn hypothesis_trajectories(loc: &agent::Localization, truth: &Pose, frustum_iou: &dyn Fn(&Pose) -> f32) -> serde_json::Value {
    let at = |pose: &Pose, alignment: f32| {
        let e = PoseError::between(pose, truth);
        json!({
            "frustum_iou": frustum_iou(pose),
            "camera_from_map": pose.to_row_major_3x4(),
            "alignment": alignment,
            "rte_m": e.rte_m,
            "rre_geodesic_deg": e.rre_geodesic_deg,
            "rre_euler_deg": e.rre_euler_deg,
        })
    };
    loc.hypotheses
        .iter()
        .map(|h| {
            json!({
                "start_yaw_offset_deg": h.start_yaw_offset_deg,
                "start_axis_shift_m": h.start_axis_shift_m,
                "refinement": h.refinement,
                "start": at(&h.start, h.start_alignment),
                "steps": h.steps.iter().map(|s| policy_step(at(&s.camera_from_map, s.alignment), s)).collect::<Vec<_>>(),
                "converged": h.converged,
                "dropped": h.dropped,
            })
        })
        .collect()
}

/// A recorded step with what the policy said at the pose before it (the step's own outputs):
/// the critic's `value`, its certainty, the per-DoF softmax `probabilities` [3][actions] (rows
/// yaw, tx, tz; columns the action set's steps, ascending) and the chosen `action_indices`.
/// What an offline judge of poses is tried on (docs/evaluation.md, "Which pose to answer with").
fn policy_step(mut record: serde_json::Value, step: &agent::Step) -> serde_json::Value {
    record["value"] = json!(step.value);
    record["policy_certainty"] = json!(step.confidence);
    record["probabilities"] = json!(step.probabilities);
    record["action_indices"] = json!(step.action.indices);
    record["repeated"] = json!(step.repeated);
    record
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::agent::StateLayout;
    use crate::eval::methods::tests::case;
    use crate::geometry::{Intrinsics, PoseError};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// With embeddings that are perfect up to noise (each point carries the random feature of
    /// the cell it truly projects to), the baseline's glue — frustum selection, cell indexing,
    /// crop intrinsics, map frame, rig — must recover the ground truth to cell precision.
    #[test]
    fn ideal_embeddings_give_the_true_pose() {
        let c = case(-140.0, 7.0, -6.0);
        let layout = StateLayout {
            dim: 64,
            stride: 4,
            grid_height: 40,
            grid_width: 128,
            image_width: 512,
            image_height: 160,
            num_state_points: 16,
            xyz_scale_m: 10.0,
            form: crate::agent::Form2d::Features,
        };
        let k = Intrinsics { fx: 359.0, fy: 359.0, cx: 255.5, cy: 79.5 };
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let unit = |rng: &mut ChaCha8Rng| {
            let v: Vec<f32> = (0..64).map(|_| rng.random_range(-1.0f32..1.0)).collect();
            let n = v.iter().map(|x| x * x).sum::<f32>().sqrt();
            v.into_iter().map(|x| x / n).collect::<Vec<f32>>()
        };
        let cells = layout.cells();
        let cell_features: Vec<Vec<f32>> = (0..cells).map(|_| unit(&mut rng)).collect();
        let mut image = vec![0f32; 64 * cells];
        for (cell, f) in cell_features.iter().enumerate() {
            for (ch, v) in f.iter().enumerate() {
                image[ch * cells + cell] = *v;
            }
        }
        // Dense points in front of the true camera, so many cells are hit.
        let inverse = c.truth.inverse();
        let mut points = Vec::new();
        for _ in 0..3000 {
            let p_cam = k.back_project(rng.random_range(0.0..511.0), rng.random_range(0.0..159.0), rng.random_range(4.0..30.0));
            let p = inverse.transform(&p_cam);
            points.push([p.x as f32, p.y as f32, p.z as f32]);
        }
        points.extend(c.map_points.iter().copied()); // plus the case's own cloud, mostly out of view
        let mut features = Vec::with_capacity(points.len() * 64);
        let mut logits = Vec::with_capacity(points.len());
        for p in &points {
            let p_cam = c.truth.transform(&nalgebra::Point3::new(p[0] as f64, p[1] as f64, p[2] as f64));
            match layout.cell_of(&k, &p_cam) {
                Some(cell) => {
                    features.extend(cell_features[cell].iter().map(|v| v + rng.random_range(-0.02..0.02)));
                    logits.push(3.0);
                }
                None => {
                    features.extend(unit(&mut rng));
                    logits.push(-3.0);
                }
            }
        }
        let grid = FeatureGrid { dim: 64, stride: 4, grid_width: 128 };
        for strategy in [MatchStrategy::Mutual, MatchStrategy::Ratio] {
            let (in_view, matches) = one_shot_correspondences(&points, &features, &logits, &image, grid, strategy);
            assert!(in_view >= 3000 && matches.len() > 500, "{strategy:?}: {in_view} {}", matches.len());
            let solution = GroundPnp::new(c.initial, k).solve_ransac(&matches, &RansacOptions::default()).unwrap();
            let e = PoseError::between(&solution.camera_from_map, &c.truth);
            assert!(e.rte_m < 0.1 && e.rre_geodesic_deg < 0.2, "{strategy:?}: {e:?}");
        }
    }
}
