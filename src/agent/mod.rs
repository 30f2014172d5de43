//! The agent: observation building, one trajectory (episode), the multi-start search, and the
//! step loop that drives them (`batch`), with a synchronous entry point ([`localize`]) for the
//! evaluator and tests. Scheduling requests onto workers is `serving`'s job, not this module's.

pub mod batch;
pub mod episode;
pub mod input;
pub mod polish;
pub mod search;
pub mod state;

use std::sync::Arc;
use std::time::Instant;

use anyhow::Result;

use crate::geometry::{Intrinsics, Pose, PoseError};
use crate::maps::PreparedMap;
use crate::model::{Backend, Signals, Verdict};

pub use batch::{Batch, Start, StepError};
pub use episode::{Confidence, Episode, ImageEvidence, Step, ViewEvidence, judged_alignment};
pub use input::{ViewInput, prepare_image, prepare_views};
pub use search::{AnswerRules, AxisStarts, DEFAULT_HYPOTHESES, Hypothesis, JudgeRecord, MAX_HYPOTHESES, MAX_ITERATIONS, PriorBound, Search, SearchConfig, SearchTuning, best_of, outscores, start_yaw_offsets};
pub use state::{Form2d, ImageGrid, ScatterScratch, ScratchPool, Shifts, StateLayout};

/// Milliseconds spent per phase of one localization.
#[derive(Debug, Clone, Copy, Default)]
pub struct Timings {
    pub image_encoder_ms: f64,
    pub frustum_head_ms: f64,
    /// State building + policy calls + pose updates, all steps.
    pub agent_steps_ms: f64,
    /// The part of `agent_steps_ms` spent building this request's observations (Rust).
    pub state_build_ms: f64,
    /// The part of `agent_steps_ms` spent on the continuous polish (`polish`).
    pub polish_ms: f64,
    /// The part of `agent_steps_ms` spent scoring the visited poses in the judge's views
    /// (`SearchConfig::judge_zoom`; 0 without them).
    pub judge_ms: f64,
}

/// The result of one localization: every hypothesis of the search, and which one answers.
#[derive(Debug, Clone)]
pub struct Localization {
    pub prior: Pose,
    /// One per start, in the order of `start_yaw_offsets`; the first starts at the prior.
    pub hypotheses: Vec<Hypothesis>,
    /// The hypothesis whose pose answers (0 when the prior was kept): the best-scoring final
    /// pose, or within a prior bound the best-scoring pose visited inside it
    /// (`search::answer_at`).
    pub chosen: usize,
    /// Steps of the chosen hypothesis that led to the answer: all of them without a prior bound,
    /// possibly fewer with one (0 when the prior was kept).
    pub answer_steps: usize,
    /// The search's answer is the prior itself, unmoved: it outscored every final pose
    /// (`SearchConfig::keep_prior`); with starts along the axis, the start of the chosen group
    /// (the prior moved by the chosen hypothesis's `start_axis_shift_m`); the polish may still
    /// move it (`polish`).
    pub kept_prior: bool,
    /// How the poses competed for the answer (`SearchConfig::answer_rules`: the request's bound
    /// on the prior's error, whether the prior competed, the prior's margin).
    pub rules: search::AnswerRules,
    /// What the unmoved prior's group added to its score against the groups along the optical
    /// axis (`search::AxisStarts::margin`; irrelevant without axis starts).
    pub axis_margin: f32,
    /// Of the answer (the chosen hypothesis's final pose, or the prior).
    pub confidence: Confidence,
    /// The request's policy steps per hypothesis.
    pub max_iterations: usize,
    pub timings: Timings,
    /// The calibrated verdict on the answer: uncalibrated (`p_registered: None, localized:
    /// false`) as the search leaves it; set from [`Localization::signals`] by whoever holds the
    /// model set's [`crate::model::Calibration`] (`serving::Localizer`, `cmr-agent eval`).
    pub verdict: Verdict,
    /// The continuous polish of the answer (`polish`), when the search ran it.
    pub polish: Option<polish::Polish>,
    /// What the judge's views did (`search::JudgeRecord`), when the search judges
    /// (`SearchConfig::judges`).
    pub judge: Option<search::JudgeRecord>,
}

impl Localization {
    pub fn best(&self) -> &Hypothesis {
        &self.hypotheses[self.chosen]
    }

    /// The final estimate of camera_from_map: the search's answer ([`Localization::search_answer`]),
    /// polished when the search ran the polish.
    pub fn camera_from_map(&self) -> Pose {
        self.polish.map_or_else(|| self.search_answer(), |p| p.camera_from_map)
    }

    /// The search's own answer, before any polish: the chosen hypothesis's pose after
    /// `answer_steps` (its start, the prior or a prior along the axis, when it was kept).
    pub fn search_answer(&self) -> Pose {
        self.best().pose_after(self.answer_steps).0
    }

    /// The steps that led to the answer: the chosen hypothesis's up to the answer, none when the
    /// prior was kept.
    pub fn answer_steps(&self) -> &[Step] {
        if self.kept_prior { &[] } else { &self.best().steps[..self.answer_steps] }
    }

    /// Whether the answer is where the chosen trajectory stopped by choosing the zero step.
    pub fn converged(&self) -> bool {
        !self.kept_prior && self.best().converged && self.answer_steps == self.best().steps.len()
    }

    /// The answer had the search stopped after `iterations` steps: the first round's by the same
    /// rule before the request's `max_iterations`, the whole search's (refinement included) from
    /// there (`search::search_answer`; the evaluator's per-iteration figures; after the last step,
    /// `camera_from_map`, polish included).
    pub fn pose_after(&self, iterations: usize) -> Pose {
        if iterations >= self.max_iterations {
            return self.camera_from_map();
        }
        search::search_answer(&self.hypotheses, &self.prior, self.rules, self.axis_margin, iterations, false).pose(&self.hypotheses).0
    }

    /// The hypotheses of the first round (before any refinement round's).
    pub fn first_round(&self) -> &[Hypothesis] {
        &self.hypotheses[..search::first_round_len(&self.hypotheses)]
    }

    /// Applies `f` to every pose it holds (prior, starts, steps): how serving moves a result from
    /// the region's local frame to the map frame (`geometry::LocalFrame`).
    pub fn map_poses(&mut self, f: impl Fn(&Pose) -> Pose) {
        self.prior = f(&self.prior);
        if let Some(p) = &mut self.polish {
            (p.from, p.camera_from_map) = (f(&p.from), f(&p.camera_from_map));
        }
        for h in &mut self.hypotheses {
            h.start = f(&h.start);
            for s in &mut h.steps {
                s.camera_from_map = f(&s.camera_from_map);
            }
        }
    }

    /// What the calibrator reads (`model::calibrator::Signals`; its fields say what each is), of
    /// the search's answer before any polish (the chosen hypothesis's pose, or its start when it
    /// was kept: what the calibrator was fitted on; the polish moves it in steps of at most 1° or
    /// 0.5 m, and only ever to a pose that scores higher). The search's context is its first
    /// round's (the starts the calibrator was fitted on): every first-round hypothesis but the
    /// chosen one is an "other" one; "agreeing" starts end within the search's duplicate radius
    /// of the answer. With starts along the optical axis, the context is the chosen hypothesis's
    /// group (`search::axis_groups`; a refinement hypothesis's: the group of the first round's
    /// answer it refined), as if its prior had been a request of its own: the signals are then
    /// those that request would have had.
    pub fn signals(&self) -> Signals {
        let answer = self.search_answer();
        let alignment = self.confidence.alignment;
        let first = self.first_round();
        let shift = self.best().start_axis_shift_m;
        let context = search::axis_groups(first).into_iter().find(|g| first[g.start].start_axis_shift_m == shift).unwrap_or(0..first.len());
        let group = &first[context.clone()];
        let others = group.iter().enumerate().filter(|(h, _)| self.kept_prior || context.start + h != self.chosen);
        let runner_up = others.map(|(_, h)| h.alignment()).fold(f32::NEG_INFINITY, f32::max);
        let margin = if runner_up == f32::NEG_INFINITY { 0.0 } else { (alignment - runner_up) as f64 };
        let agreement = search::start_agreement(&self.hypotheses, self.chosen, self.kept_prior, &answer);
        let start_mean = group.iter().map(|h| h.start_alignment as f64).sum::<f64>() / group.len().max(1) as f64;
        let searched = group.iter().chain(&self.hypotheses[first.len()..]);
        let visited = searched.flat_map(|h| std::iter::once(h.start).chain(h.steps.iter().map(|s| s.camera_from_map)));
        let (near, all) = visited.fold((0usize, 0usize), |(near, all), p| (near + PoseError::between(&p, &answer).is_registered() as usize, all + 1));
        let converged = self.converged();
        Signals {
            alignment: alignment as f64,
            alignment_gain: alignment as f64 - start_mean,
            alignment_margin: margin,
            agreement,
            frustum_iou: self.confidence.frustum_iou as f64,
            policy_certainty: self.confidence.policy_certainty as f64,
            converged: if converged { 1.0 } else { 0.0 },
            steps_fraction: self.answer_steps().len() as f64 / self.max_iterations.max(1) as f64,
            in_view: self.confidence.in_view as f64,
            log2_starts: (group.len().max(1) as f64).log2(),
            bounded: if self.rules.bound.is_some() { 1.0 } else { 0.0 },
            visit_share: near as f64 / all.max(1) as f64,
            peak_margin: self.polish.and_then(|p| Some((p.alignment - p.runner_up_alignment?) as f64)).unwrap_or(0.0),
        }
    }

    /// Batched policy calls the search made: the longest first-round hypothesis's steps, plus the
    /// longest refinement hypothesis's.
    pub fn iterations(&self) -> usize {
        let longest = |refinement: bool| self.hypotheses.iter().filter(|h| h.refinement == refinement).map(|h| h.steps.len()).max().unwrap_or(0);
        longest(false) + longest(true)
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
    localize_start(backend, Start { maps: vec![map.clone()], image_tensor: image_tensor.to_vec(), intrinsics, prior, search: config, views: Vec::new() })
}

/// [`localize`] of a whole [`Start`] (the judge's views with it).
pub fn localize_start(backend: &mut dyn Backend, start: Start) -> Result<Localization> {
    let mut batch = Batch::new(backend.manifest());
    batch.admit(backend, start, ()).map_err(|(_, e)| anyhow::Error::new(e))?;
    loop {
        batch.step(backend);
        if let Some(((), result)) = batch.retire(backend).pop() {
            return result.map_err(anyhow::Error::new);
        }
    }
}

pub fn ms(since: Instant) -> f64 {
    since.elapsed().as_secs_f64() * 1000.0
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Matrix3, Vector3};

    fn hypothesis(x_m: f64, alignment: f32) -> Hypothesis {
        Hypothesis {
            start_yaw_offset_deg: 0.0,
            start_axis_shift_m: 0.0,
            refinement: false,
            start: Pose::from_rt(Matrix3::identity(), Vector3::new(x_m, 0.0, 0.0)),
            start_alignment: alignment,
            steps: Vec::new(),
            converged: true,
            dropped: false,
        }
    }

    fn localization(hypotheses: Vec<Hypothesis>, chosen: usize) -> Localization {
        let confidence = Confidence { frustum_iou: 0.25, policy_certainty: 0.5, score: 0.3, alignment: hypotheses[chosen].alignment(), in_view: 0.125 };
        let answer_steps = hypotheses[chosen].steps.len();
        Localization {
            prior: Pose::identity(),
            hypotheses,
            chosen,
            answer_steps,
            kept_prior: false,
            rules: Default::default(),
            axis_margin: 0.0,
            confidence,
            max_iterations: 10,
            timings: Timings::default(),
            verdict: Verdict::default(),
            polish: None,
            judge: None,
        }
    }

    /// The margin is over the best other start; agreement counts the others within the
    /// duplicate radius of the answer; one start has neither.
    #[test]
    fn signals_read_the_search() {
        let near = search::DUPLICATE_RTE_M / 2.0;
        let far = search::DUPLICATE_RTE_M * 3.0;
        let loc = localization(vec![hypothesis(0.0, 0.5), hypothesis(near, 0.75), hypothesis(far, 0.625), hypothesis(-far, 0.25)], 1);
        let s = loc.signals();
        assert_eq!((s.alignment, s.alignment_margin), (0.75, 0.125));
        // Every test hypothesis is its own start: the starts' mean is (0.5 + 0.75 + 0.625 + 0.25) / 4.
        assert!((s.alignment_gain - (0.75 - 0.53125)).abs() < 1e-12, "{}", s.alignment_gain);
        assert!((s.agreement - 1.0 / 3.0).abs() < 1e-12, "{}", s.agreement);
        assert_eq!((s.frustum_iou, s.policy_certainty, s.in_view), (0.25, 0.5, 0.125));
        assert_eq!((s.converged, s.steps_fraction, s.log2_starts), (1.0, 0.0, 2.0));
        // Four poses visited (the starts), two within 10° / 5 m of the answer: itself and the one
        // half a duplicate radius away.
        assert_eq!(s.visit_share, 0.5);
        let single = localization(vec![hypothesis(0.0, 0.5)], 0).signals();
        assert_eq!((single.alignment_margin, single.agreement, single.log2_starts), (0.0, 0.0, 0.0));
        // The peak margin: the polished answer over the best other candidate's peak; 0 without
        // a polish or with one candidate.
        assert_eq!(s.peak_margin, 0.0);
        let mut polished = localization(vec![hypothesis(0.0, 0.5), hypothesis(far, 0.75)], 1);
        let p = polish::Polish { from: Pose::identity(), from_alignment: 0.75, camera_from_map: Pose::identity(), alignment: 0.875, scores: 9, candidates: 2, runner_up_alignment: Some(0.625) };
        polished.polish = Some(p);
        assert_eq!(polished.signals().peak_margin, 0.25);
        polished.polish = Some(polish::Polish { candidates: 1, runner_up_alignment: None, ..p });
        assert_eq!(polished.signals().peak_margin, 0.0);
    }

    /// A kept prior is the answer: its own score, every start counts as another, no steps.
    #[test]
    fn signals_of_a_kept_prior_are_the_priors() {
        let near = search::DUPLICATE_RTE_M / 2.0;
        let far = search::DUPLICATE_RTE_M * 3.0;
        let mut first = hypothesis(far, 0.25);
        first.start = Pose::identity(); // the first start is the prior, scoring 0.875 there
        first.start_alignment = 0.875;
        first.steps.push(Step {
            iteration: 1,
            camera_from_map: Pose::from_rt(Matrix3::identity(), Vector3::new(far, 0.0, 0.0)),
            action: crate::geometry::ActionSet::default().action([5, 5, 5]),
            probabilities: [vec![1.0], vec![1.0], vec![1.0]],
            confidence: 0.5,
            value: 0.0,
            alignment: 0.25,
            repeated: false,
        });
        let mut loc = localization(vec![first, hypothesis(near, 0.75), hypothesis(-far, 0.5)], 0);
        (loc.kept_prior, loc.answer_steps, loc.rules.prior_competes, loc.confidence.alignment) = (true, 0, true, 0.875);
        assert_eq!(loc.camera_from_map(), Pose::identity());
        let s = loc.signals();
        assert_eq!((s.alignment, s.alignment_margin), (0.875, 0.125));
        // Of the three final poses only the second is near the prior.
        assert!((s.agreement - 1.0 / 3.0).abs() < 1e-12, "{}", s.agreement);
        assert_eq!((s.converged, s.steps_fraction), (0.0, 0.0));
        assert!((s.alignment_gain - (0.875 - (0.875 + 0.75 + 0.5) / 3.0)).abs() < 1e-12);
        // Visited: the prior (the first start), its step far away, the near start, the far one.
        assert_eq!(s.visit_share, 0.5);
    }

    /// With starts along the optical axis, the signals read the chosen hypothesis's group alone:
    /// those its prior would have had as a request of its own.
    #[test]
    fn signals_of_an_axis_group_are_those_of_its_own_search() {
        let far = search::DUPLICATE_RTE_M * 3.0;
        let in_group = |x_m: f64, alignment: f32, shift: f64| Hypothesis { start_axis_shift_m: shift, ..hypothesis(x_m, alignment) };
        // Two groups of two starts (shifts 0 and +1.25 m); the second group's first start answers.
        let grouped = localization(vec![in_group(0.0, 0.5, 0.0), in_group(far, 0.875, 0.0), in_group(1.0, 0.75, 1.25), in_group(-far, 0.25, 1.25)], 2);
        let alone = localization(vec![hypothesis(1.0, 0.75), hypothesis(-far, 0.25)], 0);
        assert_eq!(grouped.signals(), alone.signals());
        assert_eq!(grouped.signals().alignment_margin, 0.5, "over its group's other start, not the other group's 0.875");
    }
}
