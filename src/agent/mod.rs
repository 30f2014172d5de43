//! The agent: observation building, one trajectory (episode), the multi-start search, and the
//! step loop that drives them (`batch`), with a synchronous entry point ([`localize`]) for the
//! evaluator and tests. Scheduling requests onto workers is `serving`'s job, not this module's.

pub mod batch;
pub mod episode;
pub mod input;
pub mod search;
pub mod state;

use std::sync::Arc;
use std::time::Instant;

use anyhow::Result;

use crate::geometry::{Intrinsics, Pose};
use crate::maps::PreparedMap;
use crate::model::Backend;

pub use batch::{Batch, Start, StepError};
pub use episode::{Confidence, Episode, ImageEvidence, Step};
pub use input::prepare_image;
pub use search::{DEFAULT_HYPOTHESES, Hypothesis, MAX_HYPOTHESES, MAX_ITERATIONS, Search, SearchConfig, SearchTuning, best_of, prior_wins, start_yaw_offsets};
pub use state::{Form2d, ImageGrid, ScatterScratch, Shifts, StateLayout};

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
    /// The hypothesis whose final pose has the best alignment score: the answer (0 when the
    /// prior was kept).
    pub chosen: usize,
    /// The answer is the prior itself, unmoved: it outscored every final pose
    /// (`SearchConfig::keep_prior`).
    pub kept_prior: bool,
    /// Whether the prior competed with the final poses (`SearchConfig::keep_prior`).
    pub prior_competes: bool,
    /// Of the answer (the chosen hypothesis's final pose, or the prior).
    pub confidence: Confidence,
    pub timings: Timings,
}

impl Localization {
    pub fn best(&self) -> &Hypothesis {
        &self.hypotheses[self.chosen]
    }

    /// The final estimate of camera_from_map.
    pub fn camera_from_map(&self) -> Pose {
        if self.kept_prior { self.prior } else { self.best().camera_from_map() }
    }

    /// The steps that led to the answer: the chosen hypothesis's, none when the prior was kept.
    pub fn answer_steps(&self) -> &[Step] {
        if self.kept_prior { &[] } else { &self.best().steps }
    }

    /// The answer had the search stopped after `iterations` steps: the best-scoring pose over
    /// all hypotheses at that point, or the prior when it competes and scores higher (the
    /// evaluator's per-iteration figures; after the last step, `camera_from_map`).
    pub fn pose_after(&self, iterations: usize) -> Pose {
        let at: Vec<(Pose, f32)> = self.hypotheses.iter().map(|h| h.pose_after(iterations)).collect();
        let best = &at[best_of(at.iter().map(|(_, score)| *score))];
        let prior_alignment = self.hypotheses.first().map_or(f32::NAN, |h| h.start_alignment);
        if self.prior_competes && search::prior_wins(prior_alignment, best.1) { self.prior } else { best.0 }
    }

    /// Applies `f` to every pose it holds (prior, starts, steps): how serving moves a result from
    /// the region's local frame to the map frame (`geometry::LocalFrame`).
    pub fn map_poses(&mut self, f: impl Fn(&Pose) -> Pose) {
        self.prior = f(&self.prior);
        for h in &mut self.hypotheses {
            h.start = f(&h.start);
            for s in &mut h.steps {
                s.camera_from_map = f(&s.camera_from_map);
            }
        }
    }

    /// Steps taken by the longest hypothesis.
    pub fn iterations(&self) -> usize {
        self.hypotheses.iter().map(|h| h.steps.len()).max().unwrap_or(0)
    }
}

/// Localizes one image in a prepared map, synchronously, starting from `prior`: a batch of
/// one request through the same step loop as the server's workers. `image_tensor` and
/// `intrinsics` come from `prepare_image`.
pub fn localize(
    backend: &mut dyn Backend,
    map: &Arc<PreparedMap>,
    image_tensor: &[f32],
    intrinsics: Intrinsics,
    prior: Pose,
    config: SearchConfig,
) -> Result<Localization> {
    let mut batch = Batch::new(backend.manifest());
    let start = Start { map: map.clone(), image_tensor: image_tensor.to_vec(), intrinsics, prior, search: config };
    batch.admit(backend, start, ()).map_err(|(_, e)| anyhow::Error::new(e))?;
    loop {
        batch.step(backend);
        if let Some(((), result)) = batch.retire().pop() {
            return result.map_err(anyhow::Error::new);
        }
    }
}

pub fn ms(since: Instant) -> f64 {
    since.elapsed().as_secs_f64() * 1000.0
}
