//! The agent loop: observation building, policy steps and pose updates.
//!
//! The synchronous API below (`prepare_map`, `prepare_image`, `localize`) is what the evaluator
//! and the CLI use; the server's workers (`scheduler`) drive the same `Search` logic with many
//! requests batched into each policy call.

pub mod episode;
pub mod input;
pub mod scheduler;
pub mod search;
pub mod state;

use std::time::Instant;

use anyhow::{Result, bail};
use nalgebra::Point3;

use crate::geometry::{Intrinsics, Pose};
use crate::model::{Backend, Manifest};

pub use episode::{Confidence, Episode, ImageEvidence, Step};
pub use input::{prepare_image, sample_points};
pub use search::{Hypothesis, Search, best_of, start_yaw_offsets};
pub use state::{ScatterScratch, StateLayout};

/// A map region ready for localization: the N sampled points and their embeddings. It does not
/// depend on any image, so it is computed once per map and model and cached.
#[derive(Debug, Clone)]
pub struct PreparedMap {
    /// The N sampled points, map frame.
    pub points: Vec<[f32; 3]>,
    /// Point features [N, D], row-major.
    pub features: Vec<f32>,
    /// Centroid of the sampled points (map frame): the pivot of every rotation step.
    pub pivot: Point3<f64>,
    /// How many finite points the source cloud had.
    pub source_points: usize,
}

impl PreparedMap {
    /// Memory held, for the cache's byte budget.
    pub fn size_bytes(&self) -> usize {
        self.points.len() * 12 + self.features.len() * 4 + std::mem::size_of::<Self>()
    }
}

/// Samples N points from a cloud (map frame) and runs the point encoder on them.
pub fn prepare_map(backend: &mut Backend, cloud: &[[f32; 3]]) -> Result<PreparedMap> {
    let n = backend.manifest().points.num_points;
    let points = sample_points(cloud, n)?;
    let features = backend.encode_points(&points)?;
    let pivot = centroid(&points);
    let source_points = cloud.iter().filter(|p| p.iter().all(|v| v.is_finite())).count();
    Ok(PreparedMap { points, features, pivot, source_points })
}

pub fn centroid(points: &[[f32; 3]]) -> Point3<f64> {
    let mut sum = [0f64; 3];
    for p in points {
        for c in 0..3 {
            sum[c] += p[c] as f64;
        }
    }
    let n = points.len().max(1) as f64;
    Point3::new(sum[0] / n, sum[1] / n, sum[2] / n)
}

/// Milliseconds spent per phase of one localization.
#[derive(Debug, Clone, Copy, Default)]
pub struct Timings {
    pub image_encoder_ms: f64,
    pub frustum_head_ms: f64,
    /// State building + policy calls + pose updates, all steps.
    pub agent_steps_ms: f64,
    /// The part of `agent_steps_ms` spent building this request's observations (Rust).
    pub state_build_ms: f64,
}

/// The result of one localization: every hypothesis of the search, and which one answers.
#[derive(Debug, Clone)]
pub struct Localization {
    pub prior: Pose,
    /// One per start, in the order of `start_yaw_offsets`; the first starts at the prior.
    pub hypotheses: Vec<Hypothesis>,
    /// The hypothesis whose final pose has the best alignment score: the answer.
    pub chosen: usize,
    /// Of the chosen hypothesis.
    pub confidence: Confidence,
    pub timings: Timings,
}

impl Localization {
    pub fn best(&self) -> &Hypothesis {
        &self.hypotheses[self.chosen]
    }

    /// The final estimate of camera_from_map.
    pub fn camera_from_map(&self) -> Pose {
        self.best().camera_from_map()
    }

    /// The answer had the search stopped after `iterations` steps: the best-scoring pose over
    /// all hypotheses at that point (the evaluator's per-iteration figures).
    pub fn pose_after(&self, iterations: usize) -> Pose {
        let at: Vec<(Pose, f32)> = self.hypotheses.iter().map(|h| h.pose_after(iterations)).collect();
        at[best_of(at.iter().map(|(_, score)| *score))].0
    }

    /// Steps taken by the longest hypothesis.
    pub fn iterations(&self) -> usize {
        self.hypotheses.iter().map(|h| h.steps.len()).max().unwrap_or(0)
    }
}

/// Runs the image encoder and the frustum head (everything per request that precedes the loop)
/// and sets up the search's hypotheses.
pub fn start_search(
    backend: &mut Backend,
    map: &PreparedMap,
    image_tensor: &[f32],
    intrinsics: Intrinsics,
    prior: Pose,
    search: SearchConfig,
) -> Result<(Search, Timings)> {
    if map.features.len() != map.points.len() * backend.manifest().features.dim {
        bail!("prepared map does not match this model's feature dimension");
    }
    if map.points.len() < backend.manifest().points.num_state_points {
        bail!("prepared map has fewer points than the model's state points");
    }
    let t = Instant::now();
    let image_features = backend.encode_image(image_tensor)?;
    let image_encoder_ms = ms(t);
    let t = Instant::now();
    let logits = backend.frustum_logits(&map.features, &image_features)?;
    let frustum_head_ms = ms(t);
    let evidence = ImageEvidence { image_features, frustum_probs: logits.iter().map(|l| state::sigmoid(*l)).collect(), intrinsics };
    let search = Search::new(evidence, map, prior, search);
    Ok((search, Timings { image_encoder_ms, frustum_head_ms, ..Default::default() }))
}

/// How far one request searches.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SearchConfig {
    /// Starts (yaw offsets of the prior); 1 = the paper's single trajectory.
    pub hypotheses: usize,
    /// Policy steps per hypothesis.
    pub max_iterations: usize,
    /// After this many steps only the best-scoring hypothesis goes on (`None`: all run to the end).
    pub narrow_after: Option<usize>,
    /// Stop a hypothesis once it comes within the duplicate distance of an earlier one.
    pub merge_duplicates: bool,
}

impl SearchConfig {
    /// The paper's procedure: one trajectory from the prior.
    pub fn single(max_iterations: usize) -> Self {
        Self { hypotheses: 1, max_iterations, narrow_after: None, merge_duplicates: false }
    }
}

/// Localizes one image in a prepared map, synchronously, starting from `prior`.
/// `image_tensor` and `intrinsics` come from `prepare_image`. All hypotheses step together in
/// one batched policy call per iteration, as in the server.
pub fn localize(
    backend: &mut Backend,
    map: &PreparedMap,
    image_tensor: &[f32],
    intrinsics: Intrinsics,
    prior: Pose,
    config: SearchConfig,
) -> Result<Localization> {
    let manifest: std::sync::Arc<Manifest> = backend.manifest().clone();
    let layout = StateLayout::from_manifest(&manifest);
    let actions = manifest.action_set();
    let (mut search, mut timings) = start_search(backend, map, image_tensor, intrinsics, prior, config)?;
    let mut scratch = ScatterScratch::default();
    let (l2, l3) = (layout.state_2d_len(), layout.state_3d_len());
    let (mut state_2d, mut state_3d) = (Vec::new(), Vec::new());
    let t = Instant::now();
    while !search.is_done() {
        let running: Vec<usize> = search.running().collect();
        state_2d.resize(running.len() * l2, 0.0);
        state_3d.resize(running.len() * l3, 0.0);
        let ts = Instant::now();
        for (slot, &h) in running.iter().enumerate() {
            let (s2, s3) = (&mut state_2d[slot * l2..(slot + 1) * l2], &mut state_3d[slot * l3..(slot + 1) * l3]);
            search.episodes[h].write_state(map, &layout, &mut scratch, s2, s3);
        }
        timings.state_build_ms += ms(ts);
        let out = backend.agent_step(&state_2d, &state_3d, running.len())?;
        let per = 3 * actions.num_actions();
        for (slot, &h) in running.iter().enumerate() {
            search.episodes[h].advance(map, &actions, &out.policy_logits[slot * per..(slot + 1) * per], out.value[slot]);
        }
        search.after_step(map, &layout, &mut scratch);
    }
    timings.agent_steps_ms = ms(t);
    Ok(search.finish(map, &layout, &mut scratch, timings))
}

pub fn ms(since: Instant) -> f64 {
    since.elapsed().as_secs_f64() * 1000.0
}
