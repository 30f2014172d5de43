//! The agent loop: observation building, policy steps and pose updates.
//!
//! The synchronous API below (`prepare_map`, `prepare_image`, `localize`) is what the evaluator
//! and the CLI use; the server's workers (`scheduler`) drive the same `Episode` logic with many
//! requests batched into each policy call.

pub mod episode;
pub mod input;
pub mod scheduler;
pub mod state;

use std::time::Instant;

use anyhow::{Result, bail};
use nalgebra::Point3;

use crate::geometry::{Intrinsics, Pose};
use crate::model::{Backend, Manifest};

pub use episode::{Confidence, Episode, Step};
pub use input::{prepare_image, sample_points};
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

/// The result of one localization.
#[derive(Debug, Clone)]
pub struct Localization {
    pub prior: Pose,
    /// The final estimate of camera_from_map.
    pub camera_from_map: Pose,
    pub steps: Vec<Step>,
    /// The agent chose all-zero steps before running out of iterations.
    pub converged: bool,
    pub confidence: Confidence,
    pub timings: Timings,
}

impl Localization {
    pub fn iterations(&self) -> usize {
        self.steps.len()
    }
}

/// Runs the image encoder and the frustum head: everything per request that precedes the loop.
pub fn start_episode(
    backend: &mut Backend,
    map: &PreparedMap,
    image_tensor: &[f32],
    intrinsics: Intrinsics,
    prior: Pose,
    max_iterations: usize,
) -> Result<(Episode, Timings)> {
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
    let episode = Episode::new(image_features, &logits, intrinsics, prior, max_iterations);
    Ok((episode, Timings { image_encoder_ms, frustum_head_ms, ..Default::default() }))
}

/// Localizes one image in a prepared map, synchronously, starting from `prior`.
/// `image_tensor` and `intrinsics` come from `prepare_image`.
pub fn localize(
    backend: &mut Backend,
    map: &PreparedMap,
    image_tensor: &[f32],
    intrinsics: Intrinsics,
    prior: Pose,
    max_iterations: usize,
) -> Result<Localization> {
    let manifest: std::sync::Arc<Manifest> = backend.manifest().clone();
    let layout = StateLayout::from_manifest(&manifest);
    let actions = manifest.action_set();
    let (mut episode, mut timings) = start_episode(backend, map, image_tensor, intrinsics, prior, max_iterations)?;
    let mut scratch = ScatterScratch::default();
    let mut state_2d = vec![0f32; layout.state_2d_len()];
    let mut state_3d = vec![0f32; layout.state_3d_len()];
    let t = Instant::now();
    while !episode.is_done() {
        let ts = Instant::now();
        episode.write_state(map, &layout, &mut scratch, &mut state_2d, &mut state_3d);
        timings.state_build_ms += ms(ts);
        let out = backend.agent_step(&state_2d, &state_3d, 1)?;
        episode.advance(map, &actions, &out.policy_logits, out.value[0]);
    }
    timings.agent_steps_ms = ms(t);
    Ok(finish(episode, map, &layout, timings))
}

/// Turns a finished episode into its result.
pub fn finish(episode: Episode, map: &PreparedMap, layout: &StateLayout, timings: Timings) -> Localization {
    let confidence = episode.confidence(map, layout);
    Localization {
        prior: episode.prior,
        camera_from_map: episode.pose,
        converged: episode.converged,
        steps: episode.steps,
        confidence,
        timings,
    }
}

pub fn ms(since: Instant) -> f64 {
    since.elapsed().as_secs_f64() * 1000.0
}
