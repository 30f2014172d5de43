//! The two learned methods, sharing one model backend and one map embedding per case:
//! - the CMR agent, through the server's own synchronous path (`agent::prepare_map`,
//!   `agent::prepare_image`, `agent::localize`);
//! - the one-shot baseline on the same embeddings: points the frustum head predicts in view,
//!   mutual-nearest-neighbour feature matches against the image feature grid, then the
//!   ground-plane 2-point RANSAC solver (`pnp`).

use std::collections::BTreeMap;
use std::time::Instant;

use anyhow::Result;
use serde_json::json;

use crate::agent::{self, PreparedMap};
use crate::model::Backend;

use super::matching::{cell_centre, mutual_nearest};
use super::methods::{EvalCase, Method, MethodRun, pad_to};
use super::pnp::{Correspondence, GroundPnp, RansacOptions};

pub const AGENT: &str = "cmr-agent";
pub const BASELINE: &str = "one-shot matching + RANSAC";

pub struct Learned {
    backend: Backend,
    iterations: usize,
    ransac: RansacOptions,
}

impl Learned {
    pub fn new(backend: Backend, iterations: usize, ransac: RansacOptions) -> Self {
        Learned { backend, iterations, ransac }
    }

    /// Parameters each method runs: the agent all four graphs, the baseline all but the agent.
    pub fn parameters(graphs: &BTreeMap<String, u64>) -> BTreeMap<String, u64> {
        let sum = |names: &[&str]| names.iter().filter_map(|n| graphs.get(*n)).sum::<u64>();
        let encoders = ["point_encoder", "image_encoder", "frustum_head"];
        BTreeMap::from([(AGENT.to_string(), sum(&[&encoders[..], &["agent"]].concat())), (BASELINE.to_string(), sum(&encoders))])
    }

    fn run_agent(&mut self, case: &EvalCase, map: &PreparedMap) -> Result<MethodRun> {
        let start = Instant::now();
        let manifest = self.backend.manifest().clone();
        let (tensor, crop_intrinsics) = agent::prepare_image(&case.image, &case.intrinsics, &manifest)?;
        let image_ms = ms(start);
        let loc = agent::localize(&mut self.backend, map, &tensor, crop_intrinsics, case.initial, self.iterations)?;
        let t = loc.timings;
        // localize reports one total for all steps; each step does the same work, so the time to
        // reach step k is the time before the loop plus k equal shares of it.
        let before_loop = image_ms + t.image_encoder_ms + t.frustum_head_ms;
        let per_step = t.agent_steps_ms / loc.steps.len().max(1) as f64;
        let poses = loc.steps.iter().map(|s| s.camera_from_map).collect();
        let elapsed = (1..=loc.steps.len()).map(|k| before_loop + per_step * k as f64).collect();
        let (poses, elapsed_ms) = pad_to(poses, elapsed, self.iterations, case.initial);
        Ok(MethodRun {
            method: AGENT.into(),
            poses,
            elapsed_ms,
            phases_ms: vec![
                ("image preprocessing".into(), image_ms),
                ("image encoder".into(), t.image_encoder_ms),
                ("frustum head".into(), t.frustum_head_ms),
                ("agent steps".into(), t.agent_steps_ms),
            ],
            notes: json!({ "iterations_run": loc.steps.len(), "converged": loc.converged, "confidence": loc.confidence.score }),
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
        let in_view: Vec<usize> = (0..logits.len()).filter(|&i| logits[i] > 0.0).collect();
        let dim = manifest.features.dim;
        let matches = mutual_nearest(&map.features, dim, &in_view, &image_features);
        let (stride, grid_width) = (manifest.features.stride, manifest.features.grid_width);
        let correspondences: Vec<Correspondence> = matches
            .iter()
            .map(|m| {
                let p = map.points[m.point];
                Correspondence { point: nalgebra::Point3::new(p[0] as f64, p[1] as f64, p[2] as f64), pixel: cell_centre(m.cell, grid_width, stride) }
            })
            .collect();
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
                "predicted_in_view": in_view.len(),
                "matches": correspondences.len(),
                "inliers": solution.map_or(0, |s| s.inliers),
                "solved": solution.is_some(),
            }),
        })
    }
}

impl Method for Learned {
    fn names(&self) -> Vec<String> {
        vec![AGENT.into(), BASELINE.into()]
    }

    fn run(&mut self, case: &EvalCase) -> Result<Vec<MethodRun>> {
        let t = Instant::now();
        let map = agent::prepare_map(&mut self.backend, &case.map_cloud)?;
        let prepare_ms = ms(t);
        let mut agent_run = self.run_agent(case, &map)?;
        // Once per map (the server caches it), so it is reported apart from per-request times.
        agent_run.notes["map_prepare_ms"] = json!(prepare_ms);
        Ok(vec![agent_run, self.run_baseline(case, &map)?])
    }
}

fn ms(since: Instant) -> f64 {
    since.elapsed().as_secs_f64() * 1e3
}
