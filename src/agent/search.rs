//! Multi-start search: one request runs the agent from several starts and answers with the
//! hypothesis whose pose best explains the image.
//!
//! Why: the policy recovers any ground-plane offset but only part of the yaw circle: nearly all
//! of its failures start more than 60° off in yaw and settle far from the truth. The map and the
//! image embeddings give an independent judge, the alignment score (`state::alignment`), which
//! ranks the true pose above wrong ones. So the search starts H trajectories from the prior
//! turned by H evenly spaced yaws (about the map pivot, like the agent's own rotation steps),
//! runs them side by side in the same batched policy calls, and keeps the best-scoring one.
//! With H = 1 it is the paper's single trajectory.
//!
//! Most of the search's cost is the policy rows of hypotheses that will lose. Optionally
//! (`SearchConfig::narrow_after`) the search keeps only the best-scoring hypothesis once every
//! start has taken that many steps; the others stop where they are and still compete at the end.

use std::sync::Arc;

use crate::geometry::Pose;
use crate::geometry::actions::apply_motion;

use super::episode::{Episode, ImageEvidence, Step};
use super::state::{ScatterScratch, StateLayout};
use super::{Localization, PreparedMap, SearchConfig, Timings};

/// Most starts one request may ask for.
pub const MAX_HYPOTHESES: usize = 16;

/// The yaw offsets of H starts: k·360°/H for k = 0..H, wrapped into (−180°, 180°]; the prior
/// itself comes first. `training/cmr/geometry.py::start_yaw_offsets` is its twin, and
/// `fixtures/conventions.json` pins both.
pub fn start_yaw_offsets(hypotheses: usize) -> Vec<f64> {
    (0..hypotheses)
        .map(|k| {
            let offset = k as f64 * 360.0 / hypotheses as f64;
            if offset > 180.0 { offset - 360.0 } else { offset }
        })
        .collect()
}

/// One finished trajectory of a search.
#[derive(Debug, Clone)]
pub struct Hypothesis {
    /// The turn applied to the prior to get this start.
    pub start_yaw_offset_deg: f64,
    pub start: Pose,
    pub start_alignment: f32,
    /// Every step, each with the alignment score of the pose it reached.
    pub steps: Vec<Step>,
    pub converged: bool,
    /// Stopped early because another hypothesis scored better (`narrow_after`).
    pub dropped: bool,
}

impl Hypothesis {
    /// The pose after `iterations` steps (the last one if the trajectory stopped earlier).
    pub fn pose_after(&self, iterations: usize) -> (Pose, f32) {
        match iterations.min(self.steps.len()) {
            0 => (self.start, self.start_alignment),
            k => (self.steps[k - 1].camera_from_map, self.steps[k - 1].alignment),
        }
    }

    pub fn camera_from_map(&self) -> Pose {
        self.pose_after(self.steps.len()).0
    }

    pub fn alignment(&self) -> f32 {
        self.pose_after(self.steps.len()).1
    }
}

/// Index of the best-scoring candidate; the first one on ties (so the prior's own trajectory
/// wins a draw). NaN scores never win.
pub fn best_of(scores: impl IntoIterator<Item = f32>) -> usize {
    let mut best = (0, f32::NEG_INFINITY);
    for (i, s) in scores.into_iter().enumerate() {
        if s > best.1 {
            best = (i, s);
        }
    }
    best.0
}

/// The hypotheses of one request in progress.
pub struct Search {
    pub prior: Pose,
    pub episodes: Vec<Episode>,
    offsets: Vec<f64>,
    /// Steps after which only the best-scoring hypothesis goes on; `None` once done (or never).
    narrow_after: Option<usize>,
}

impl Search {
    pub fn new(evidence: ImageEvidence, map: &PreparedMap, prior: Pose, config: SearchConfig) -> Self {
        let evidence = Arc::new(evidence);
        let max_iterations = config.max_iterations;
        let offsets = start_yaw_offsets(config.hypotheses.clamp(1, MAX_HYPOTHESES));
        let episodes = offsets
            .iter()
            .map(|&yaw_deg| {
                let start = if yaw_deg == 0.0 { prior } else { apply_motion(&prior, &map.pivot, yaw_deg, 0.0, 0.0) };
                Episode::new(evidence.clone(), start, max_iterations)
            })
            .collect();
        let narrow_after = config.narrow_after.filter(|_| offsets.len() > 1);
        Self { prior, episodes, offsets, narrow_after }
    }

    /// Call after every batched step: once every hypothesis has taken `narrow_after` steps (or
    /// stopped), all but the best-scoring one stop.
    pub fn narrow(&mut self, map: &PreparedMap, layout: &StateLayout, scratch: &mut ScatterScratch) {
        let Some(after) = self.narrow_after else { return };
        if !self.episodes.iter().all(|e| e.is_done() || e.steps.len() >= after) {
            return;
        }
        self.narrow_after = None;
        for episode in &mut self.episodes {
            episode.settle(map, layout, scratch);
        }
        let leader = best_of(self.episodes.iter().map(Episode::alignment));
        for (h, episode) in self.episodes.iter_mut().enumerate() {
            episode.dropped |= h != leader && !episode.is_done();
        }
    }

    pub fn is_done(&self) -> bool {
        self.episodes.iter().all(Episode::is_done)
    }

    /// The hypotheses that still take steps.
    pub fn running(&self) -> impl Iterator<Item = usize> + '_ {
        (0..self.episodes.len()).filter(|&h| !self.episodes[h].is_done())
    }

    /// Scores every final pose, keeps the best hypothesis, and turns the search into its result.
    pub fn finish(mut self, map: &PreparedMap, layout: &StateLayout, scratch: &mut ScatterScratch, timings: Timings) -> Localization {
        for episode in &mut self.episodes {
            episode.settle(map, layout, scratch);
        }
        let chosen = best_of(self.episodes.iter().map(Episode::alignment));
        let confidence = self.episodes[chosen].confidence(map, layout);
        let hypotheses = self
            .episodes
            .into_iter()
            .zip(self.offsets)
            .map(|(e, start_yaw_offset_deg)| Hypothesis {
                start_yaw_offset_deg,
                start: e.start,
                start_alignment: e.start_alignment,
                steps: e.steps,
                converged: e.converged,
                dropped: e.dropped,
            })
            .collect();
        Localization { prior: self.prior, hypotheses, chosen, confidence, timings }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn starts_are_evenly_spaced_and_begin_at_the_prior() {
        assert_eq!(start_yaw_offsets(1), vec![0.0]);
        assert_eq!(start_yaw_offsets(2), vec![0.0, 180.0]);
        assert_eq!(start_yaw_offsets(4), vec![0.0, 90.0, 180.0, -90.0]);
        assert_eq!(start_yaw_offsets(8), vec![0.0, 45.0, 90.0, 135.0, 180.0, -135.0, -90.0, -45.0]);
    }

    #[test]
    fn the_best_score_wins_and_ties_go_to_the_earlier_start() {
        assert_eq!(best_of([0.2, 0.7, 0.5]), 1);
        assert_eq!(best_of([0.7, 0.7, 0.5]), 0);
        assert_eq!(best_of([f32::NAN, 0.1]), 1);
        assert_eq!(best_of([-1.0]), 0);
    }
}
