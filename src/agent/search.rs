//! Multi-start search: one request runs the agent from several starts and answers with the
//! hypothesis whose pose best explains the image.
//!
//! Why: the policy recovers any ground-plane offset but only part of the yaw circle: nearly all
//! of its failures start more than 60° off in yaw and settle far from the truth. The map and the
//! image embeddings give an independent judge, the alignment score (`state::alignment`), which
//! ranks the true pose above wrong ones. So the search starts H trajectories from the prior
//! turned by H evenly spaced yaws (about the map pivot, in the model's action frame, like the
//! agent's own rotation steps),
//! runs them side by side in the same batched policy calls, and keeps the best-scoring one.
//! With H = 1 it is the paper's single trajectory.
//!
//! Most of the search's cost is policy rows of hypotheses that add nothing. Two ways to save them:
//! - `merge_duplicates`: a hypothesis that comes within [`DUPLICATE_RTE_M`] / [`DUPLICATE_RRE_DEG`]
//!   of an earlier one (usually because both found the same answer) stops, since from there on
//!   it would repeat that one's work;
//! - `narrow_after`: once every start has taken that many steps, only the best-scoring one goes
//!   on.
//!
//! Stopped hypotheses keep their last pose and still compete at the end.
//!
//! A request may also bound its prior ([`PriorBound`]: the truth is within so many degrees and
//! metres of it, as a fleet's odometry or GNSS can say). Then the starts spread over that bound
//! instead of the whole circle, turned about the prior's camera centre, and the answer is the
//! best-scoring pose that any start *visited* inside the bound (the prior included): on real
//! frames the trajectories pass near the truth more often than they end there, and the bound
//! removes the street seen backwards that makes "best visited pose" fail without one
//! (docs/evaluation.md, "A bounded prior").
//!
//! Without a bound, a prior still says something: a fleet's odometry or GNSS puts it within some
//! 30° / 5 m of the truth, and the search's commonest real-image mistake is a pose far from it
//! (the street seen backwards). With `prior_margin` (the default), a pose within [`PRIOR_NEAR`] of
//! the prior competes with that much added to its alignment score: a pose away from the prior
//! answers only when it outscores every pose near it by more than the margin, so strong evidence
//! still moves a wrong prior, and a random start (the paper's protocol) loses next to nothing
//! (docs/evaluation.md, "A margin for the prior").
//!
//! With `refine` (the default; multi-start searches without a prior bound), once the first round is done a second,
//! short one runs: [`REFINE_STARTS`] starts within [`REFINE_BOUND`] of the first round's answer
//! and as many around that answer turned by 180° (the street seen the other way, the first
//! round's most common mistake), [`REFINE_ITERATIONS`] steps each; each group answers like a
//! bounded search around its base, and the best-scoring of the first round's answer and the
//! groups' answers wins (the first round's on a draw) (docs/evaluation.md, "A refinement round").
//!
//! With [`AxisStarts`] (off by default; `track`'s small searches use it), the first round runs
//! its starts also from the prior moved forward and back along its optical axis, each such
//! prior searched as a request of its own would be, and answers with the best of their answers
//! ([`first_round_answer`]): one image encoding and batched steps where `track` once ran a
//! request per shifted prior (docs/tracking.md, "Starts along the optical axis").

use std::sync::Arc;

use nalgebra::Point3;
use rayon::prelude::*;

use crate::geometry::{ActionFrame, Pose, PoseError};
use crate::geometry::actions::apply_motion;

use crate::maps::PreparedMap;

use super::batch::StepError;
use super::episode::{Episode, ImageEvidence, Step, ViewEvidence, judged_alignment};
use super::input::ViewInput;
use super::polish;
use super::state::{self, ScatterScratch, ScratchPool, StateLayout};
use super::{Localization, Timings};

/// Most starts one request may ask for.
pub const MAX_HYPOTHESES: usize = 16;

/// The hard upper bound of `max_iterations` in a request.
pub const MAX_ITERATIONS: u32 = 50;

/// Starts per request unless the request or `--default-hypotheses` says otherwise: the number
/// chosen on the validation set (docs/evaluation.md, "Multi-start search").
pub const DEFAULT_HYPOTHESES: u32 = 4;

/// What the client knows about its prior: the true camera_from_map is within `rotation_deg`
/// (geodesic angle) and `translation_m` (distance between the camera positions in the map) of
/// it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PriorBound {
    pub rotation_deg: f64,
    pub translation_m: f64,
}

impl PriorBound {
    /// Whether `pose` lies within the bound of `prior`: inclusive, with [`BOUND_SLACK`] for
    /// rounding, since the bounded starts lie exactly on its edge and must count as inside in
    /// any frame (the server works in a region's local frame, the evaluator in the map's).
    pub fn contains(&self, prior: &Pose, pose: &Pose) -> bool {
        let (angle_deg, distance_m) = offset_between(prior, pose);
        angle_deg <= self.rotation_deg + BOUND_SLACK && distance_m <= self.translation_m + BOUND_SLACK
    }
}

/// How far `b` is from `a` in a bound's terms: the geodesic angle between their rotations
/// (degrees) and the distance between their camera centres in the map (metres).
pub fn offset_between(a: &Pose, b: &Pose) -> (f64, f64) {
    (PoseError::between(a, b).rre_geodesic_deg, (a.camera_position_in_map() - b.camera_position_in_map()).norm())
}

/// What [`PriorBound::contains`] adds to both limits (degrees, metres).
pub const BOUND_SLACK: f64 = 1e-6;

/// Where a pose agrees with the prior for `prior_margin`: within 40° and 10 m of it, what a
/// fleet-grade prior (30° / 5 m off) and a registered answer (10° / 5 m off) allow together.
pub const PRIOR_NEAR: PriorBound = PriorBound { rotation_deg: 40.0, translation_m: 10.0 };

/// How the poses of a search compete for its answer, besides the prior they are judged against.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct AnswerRules {
    /// The request's bound: the best pose *visited* inside it answers ([`answer_at`]).
    pub bound: Option<PriorBound>,
    /// The prior competes with the answers (and wins a draw).
    pub prior_competes: bool,
    /// Without a bound: added to the alignment score of every pose within [`PRIOR_NEAR`] of the
    /// prior (the prior included) when the answer is chosen (0 = off).
    pub prior_margin: f32,
}

impl AnswerRules {
    /// The score `pose` competes with: `alignment`, plus the margin when it applies.
    pub fn score(&self, prior: &Pose, pose: &Pose, alignment: f32) -> f32 {
        if self.prior_margin > 0.0 && self.bound.is_none() && PRIOR_NEAR.contains(prior, pose) { alignment + self.prior_margin } else { alignment }
    }
}

/// How far one request searches.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SearchConfig {
    /// Starts (yaw offsets of the prior; of each prior along the axis with `axis`); 1 = the
    /// paper's single trajectory.
    pub hypotheses: usize,
    /// Policy steps per hypothesis.
    pub max_iterations: usize,
    /// After this many steps only the best-scoring hypothesis goes on (`None`: all run to the end).
    pub narrow_after: Option<usize>,
    /// Stop a hypothesis once it comes within the duplicate distance of an earlier one.
    pub merge_duplicates: bool,
    /// The prior itself competes with the hypotheses' final poses: when its alignment score is
    /// higher than every final pose's, the answer is the prior, unmoved.
    pub keep_prior: bool,
    /// The request's bound on its prior's error: starts within it, and the answer is the best
    /// pose visited inside it (the module's docs). `None`: the whole circle, final poses only.
    pub prior_bound: Option<PriorBound>,
    /// A refinement round after the first (the module's docs); ignored with a prior bound or a
    /// single start.
    pub refine: bool,
    /// Polish the answer on the alignment score (`super::polish`), inside the prior bound if any,
    /// choosing among it and the final poses apart from it by their polished scores
    /// ([`polish_candidates`]); ignored by a single start without a bound (`track`'s small searches, the paper's
    /// trajectory).
    pub polish: bool,
    /// Without a bound, what a pose that agrees with the prior (within [`PRIOR_NEAR`] of it)
    /// adds to its alignment score when the search chooses its answer: a pose away from the
    /// prior must outscore the best one near it by more than this (0 = off; the module's docs).
    pub prior_margin: f32,
    /// Starts along the prior's optical axis ([`AxisStarts`]; `each_way` 0 = none).
    pub axis: AxisStarts,
    /// The zoom of the judge's views (`input::prepare_views`; 0 = the served view alone): the
    /// answer is chosen among every pose the search visited by the alignment score averaged over
    /// the served view and those views (`Search::judged_answer`), and the polished choice
    /// compares its candidates' peaks by that average ([`SearchConfig::judges`]).
    pub judge_zoom: f64,
    /// When the search reads the judge's views (`Search::finish`): only when at most this share
    /// of the other starts ended where the served search answers ([`start_agreement`], in
    /// [0, 1]); otherwise the views are never encoded and the served view's score judges alone.
    /// 1: always.
    pub judge_gate: f64,
}

/// Starts along the prior's optical axis: besides the prior, the prior with the camera moved
/// ±k·`step_m` along its own optical axis, k = 1..=`each_way` ([`AxisStarts::priors`]). Each
/// such prior is searched as a request of its own would be (its `hypotheses` starts turned about
/// the map pivot, its own start competing with `keep_prior`, the prior's margin judged against
/// it), and the first round answers with the best of their answers by alignment score, the
/// unmoved prior's with `margin` added ([`first_round_answer`]; with a prior bound, the best pose
/// any start visited inside the bound around the request's prior). Why: the policy corrects heading
/// and sideways errors but hardly moves the camera along its optical axis, while the alignment
/// score does peak there (docs/tracking.md, "Starts along the optical axis"); a tracked frame's
/// constant-velocity prediction and a fleet prior are off exactly there.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AxisStarts {
    /// Shifted priors each way (0: the prior alone).
    pub each_way: usize,
    /// Their spacing, metres.
    pub step_m: f64,
    /// What the unmoved prior's answer adds to its alignment score when the answers are
    /// compared (alignment-score units, 0..=1).
    pub margin: f32,
}

impl AxisStarts {
    /// The prior alone.
    pub const NONE: AxisStarts = AxisStarts { each_way: 0, step_m: 0.0, margin: 0.0 };

    /// The priors searched, each with its shift along the optical axis (metres, forward
    /// positive): `prior` (camera_from_map, 0, unchanged to the bit), then the camera moved along
    /// its own optical axis (camera z) by +k·`step_m` and −k·`step_m` for k = 1..=`each_way`.
    pub fn priors(&self, prior: &Pose) -> Vec<(f64, Pose)> {
        let mut priors = vec![(0.0, *prior)];
        for k in 1..=self.each_way {
            let d = k as f64 * self.step_m;
            priors.extend([(d, Self::along_axis(prior, d)), (-d, Self::along_axis(prior, -d))]);
        }
        priors
    }

    /// `pose` (camera_from_map) with the camera moved `d` metres along its own optical axis
    /// (camera z, forward positive), the rotation kept; `pose` itself, to the bit, for 0.
    pub fn along_axis(pose: &Pose, d: f64) -> Pose {
        if d == 0.0 { *pose } else { Pose::from_rt(nalgebra::Matrix3::identity(), nalgebra::Vector3::new(0.0, 0.0, -d)).compose(pose) }
    }

    /// How many priors are searched: 2·`each_way` + 1.
    pub fn groups(&self) -> usize {
        2 * self.each_way + 1
    }
}

impl SearchConfig {
    /// The most policy rows this search steps at once: its starts ([`SearchConfig::starts`]),
    /// or the refinement round's when that is larger (a worker reserves them when it admits the
    /// request).
    pub fn peak_rows(&self) -> usize {
        let refinement = if self.refines() { REFINE_ROWS } else { 0 };
        self.starts().max(refinement)
    }

    /// The first round's starts: `hypotheses` (at most [`MAX_HYPOTHESES`]) for each prior along
    /// the axis ([`AxisStarts::groups`]; one without axis starts).
    pub fn starts(&self) -> usize {
        self.hypotheses.clamp(1, MAX_HYPOTHESES) * self.axis.groups()
    }

    /// Whether the refinement round runs: `refine`, for a multi-start search (the paper's single
    /// trajectory stays as it is) without a prior bound.
    pub fn refines(&self) -> bool {
        self.refine && self.hypotheses > 1 && self.prior_bound.is_none()
    }

    /// Whether the answer is polished: `polish`, for a multi-start or bounded search (`track`'s
    /// single-start searches drift when polished: docs/evaluation.md, "A continuous polish").
    pub fn polishes(&self) -> bool {
        self.polish && (self.hypotheses > 1 || self.prior_bound.is_some())
    }

    /// Whether the answer is chosen by the judge's views (`judge_zoom` > 0), for a multi-start or
    /// bounded search, as the polish: a single trajectory answers with its last pose.
    pub fn judges(&self) -> bool {
        self.judge_zoom > 0.0 && (self.hypotheses > 1 || self.prior_bound.is_some())
    }

    /// The paper's procedure: one trajectory from the prior, answered with its last pose.
    pub fn single(max_iterations: usize) -> Self {
        Self { hypotheses: 1, max_iterations, narrow_after: None, merge_duplicates: false, keep_prior: false, prior_bound: None, refine: false, polish: false, prior_margin: 0.0, axis: AxisStarts::NONE, judge_zoom: 0.0, judge_gate: 1.0 }
    }

    /// How its poses compete for the answer: the prior competes with `keep_prior` or a bound; the
    /// margin applies without a bound.
    pub fn answer_rules(&self) -> AnswerRules {
        AnswerRules { bound: self.prior_bound, prior_competes: self.keep_prior || self.prior_bound.is_some(), prior_margin: self.prior_margin }
    }
}

/// The refinement round's bound around each of its bases.
pub const REFINE_BOUND: PriorBound = PriorBound { rotation_deg: 30.0, translation_m: 5.0 };
/// Starts per base of the refinement round (`bounded_start_yaw_offsets` within the bound).
pub const REFINE_STARTS: usize = 4;
/// Policy steps per start of the refinement round.
pub const REFINE_ITERATIONS: usize = 3;
/// The refinement round's bases: the first round's answer turned by these yaws (about its
/// camera centre).
pub const REFINE_TURNS_DEG: [f64; 2] = [0.0, 180.0];
/// Hypotheses (policy rows at its first step) of the refinement round.
pub const REFINE_ROWS: usize = REFINE_STARTS * REFINE_TURNS_DEG.len();

/// The search settings besides the number of starts: one set of flags for `serve`, `localize`
/// and `eval`, so that all three run the same search. Defaults chosen on the validation set
/// (docs/evaluation.md, "Multi-start search").
#[derive(Debug, Clone, Copy, PartialEq, clap::Args)]
pub struct SearchTuning {
    /// Once every start has taken this many steps, only the best-scoring one goes on (0 = all
    /// run to the end). Cuts the search's cost at some accuracy.
    #[arg(long, env = "CMR_NARROW_AFTER", default_value_t = 0)]
    pub narrow_after: u32,
    /// Stop a hypothesis once it comes within 4 m / 20° of an earlier one (`true`/`false`).
    #[arg(long, env = "CMR_MERGE_DUPLICATES", default_value_t = true, action = clap::ArgAction::Set)]
    pub merge_duplicates: bool,
    /// Answer with the prior, unmoved, when its alignment score beats every hypothesis's final
    /// pose (`true`/`false`): the search does no harm to a good (fleet-grade) prior that nothing
    /// explains better. On by default since model v7: on the held-out real-train drives it costs
    /// no case under the paper's protocol and gains 6 points from fleet-grade priors
    /// (docs/evaluation.md, "Keeping the prior"); `false` gives the search's answer always.
    #[arg(long, env = "CMR_KEEP_PRIOR", default_value_t = true, action = clap::ArgAction::Set)]
    pub keep_prior: bool,
    /// After the search, a short second round around its answer and around the answer turned
    /// by 180° (4 starts within 30° / 5 m of each, 3 steps), keeping whichever pose scores best
    /// (`true`/`false`; single-start requests and requests with a `prior_bound` never refine). On by default: on the
    /// held-out real-train drives it registers 51.0 % of the protocol cases instead of 43.75 %,
    /// for about 70 % more policy rows (docs/evaluation.md, "A refinement round").
    #[arg(long, env = "CMR_REFINE", default_value_t = true, action = clap::ArgAction::Set)]
    pub refine: bool,
    /// After a multi-start or bounded search, polish its answer on the alignment score: turns
    /// about the camera centre and sideways shifts from 1° / 0.5 m down to 0.125° / 0.0625 m, then
    /// turns from 8° down to 1° to look beyond that peak (and the fine steps again when they
    /// found a higher one), at most 80 poses scored, within 20° / 3 m of the answer and a
    /// request's `prior_bound`; the fine steps first also climb the final poses of up to 6 other
    /// hypotheses apart from the answer, and the highest peak answers (`true`/`false`). On by
    /// default: it registers more cases from every regime on the held-out real-train drives and
    /// cuts the heading error of registered answers (docs/evaluation.md, "A continuous polish",
    /// "A wider turn for the polish", "A polished choice").
    #[arg(long, env = "CMR_POLISH", default_value_t = true, action = clap::ArgAction::Set)]
    pub polish: bool,
    /// Without a `prior_bound`, a pose within 40° / 10 m of the prior competes for the answer
    /// with this much added to its alignment score, so a pose far from the prior must outscore
    /// the poses near it by more than this (0 = off). The default was chosen on the held-out
    /// real-train drives (docs/evaluation.md, "A margin for the prior"): from fleet-grade priors
    /// it keeps answers that the street seen backwards would otherwise take.
    #[arg(long, env = "CMR_PRIOR_MARGIN", default_value_t = DEFAULT_PRIOR_MARGIN, value_parser = parse_margin)]
    pub prior_margin: f32,
    /// Also search from the prior moved this many times each way along its optical axis,
    /// `--axis-step-m` apart, and answer with the best of those searches'
    /// answers (`AxisStarts`; a request's `axis_starts` replaces all three settings). 0 = off,
    /// the default: measured on `track`'s small searches (docs/tracking.md, "Starts along the
    /// optical axis"), not chosen for the full search. Starts × (2·this + 1) may not exceed 16.
    #[arg(long, env = "CMR_AXIS_STARTS", default_value_t = 0, value_parser = clap::value_parser!(u32).range(0..=MAX_AXIS_STARTS as i64))]
    pub axis_starts: u32,
    /// The spacing of `--axis-starts`, metres (0.1..=10).
    #[arg(long, env = "CMR_AXIS_STEP_M", default_value_t = DEFAULT_AXIS_STEP_M, value_parser = parse_axis_step)]
    pub axis_step_m: f64,
    /// With `--axis-starts`, a shifted prior's answer must outscore the unmoved prior's by more
    /// than this (alignment-score units, 0..=1).
    #[arg(long, env = "CMR_AXIS_MARGIN", default_value_t = DEFAULT_AXIS_MARGIN, value_parser = parse_margin)]
    pub axis_margin: f32,
    /// The judge's views: besides the served crop, the image encoder also reads three crops of
    /// the image resized this many times more (at its left edge, centre and right edge), and a
    /// multi-start or bounded search answers with the pose it visited whose alignment score,
    /// averaged over the four views, is highest; with `--polish`, that answer and up to 6 other
    /// final poses climb the served view's score and the highest peak by the four-view average
    /// answers. 0 = the served view alone; otherwise 1..=3.
    #[arg(long, env = "CMR_JUDGE_ZOOM", default_value_t = DEFAULT_JUDGE_ZOOM, value_parser = parse_judge_zoom)]
    pub judge_zoom: f64,
    /// With `--judge-zoom`, read the views only when the starts disagree: when at most this
    /// share of the other starts ended within 4 m / 20° of the served search's answer (0..=1);
    /// otherwise the three views are never encoded and the served crop's score chooses among
    /// the visited poses alone. 1 reads them for every multi-start or bounded request.
    #[arg(long, env = "CMR_JUDGE_GATE", default_value_t = DEFAULT_JUDGE_GATE, value_parser = parse_share)]
    pub judge_gate: f64,
}

/// A share: a finite number from 0 to 1.
fn parse_share(s: &str) -> Result<f64, String> {
    let v: f64 = s.parse().map_err(|e| format!("{e}"))?;
    if v.is_finite() && (0.0..=1.0).contains(&v) { Ok(v) } else { Err(format!("{v} is not within 0..=1")) }
}

/// `--judge-zoom`: 0, or within `input::JUDGE_ZOOM_RANGE`.
fn parse_judge_zoom(s: &str) -> Result<f64, String> {
    let v: f64 = s.parse().map_err(|e| format!("{e}"))?;
    if v == 0.0 || super::input::JUDGE_ZOOM_RANGE.contains(&v) { Ok(v) } else { Err(format!("{v} is neither 0 nor within {:?}", super::input::JUDGE_ZOOM_RANGE)) }
}

/// Most shifted priors each way along the optical axis ([`AxisStarts::each_way`]).
pub const MAX_AXIS_STARTS: usize = 7;
/// The range of [`AxisStarts::step_m`], metres.
pub const AXIS_STEP_RANGE_M: std::ops::RangeInclusive<f64> = 0.1..=10.0;
/// `--axis-step-m`'s default: the spacing `track` measured (docs/tracking.md).
pub const DEFAULT_AXIS_STEP_M: f64 = 1.25;
/// `--axis-margin`'s default: the margin `track` measured (docs/tracking.md).
pub const DEFAULT_AXIS_MARGIN: f32 = 0.005;

/// A spacing along the optical axis within [`AXIS_STEP_RANGE_M`].
fn parse_axis_step(s: &str) -> Result<f64, String> {
    let v: f64 = s.parse().map_err(|e| format!("{e}"))?;
    if v.is_finite() && AXIS_STEP_RANGE_M.contains(&v) { Ok(v) } else { Err(format!("{v} is not within {:?} m", AXIS_STEP_RANGE_M)) }
}

/// `--prior-margin`'s default (alignment-score units): 0.025 for the served view's score (chosen
/// 2026-12-05), 0.015 since the judge's views average it (chosen on the development files of
/// docs/evaluation.md, "The judge's views in the server").
pub const DEFAULT_PRIOR_MARGIN: f32 = 0.015;

/// Where the served view's score chooses again around the judge's pose
/// (`Search::judged_answer`): poses within 5° and 3 m of it.
pub const JUDGE_LOCAL: PriorBound = PriorBound { rotation_deg: 5.0, translation_m: 3.0 };

/// `--judge-zoom`'s default: the judge's views at ×1.5 (docs/evaluation.md, "The judge's views in
/// the server").
pub const DEFAULT_JUDGE_ZOOM: f64 = 1.5;

/// `--judge-gate`'s default.
pub const DEFAULT_JUDGE_GATE: f64 = 1.0;

/// A margin: a finite number from 0 to 1 (the alignment score is a mean cosine, within ±1).
fn parse_margin(s: &str) -> Result<f32, String> {
    let v: f32 = s.parse().map_err(|e| format!("{e}"))?;
    if v.is_finite() && (0.0..=1.0).contains(&v) { Ok(v) } else { Err(format!("{v} is not within 0..=1")) }
}

impl Default for SearchTuning {
    /// The flags' defaults (what `serve`, `localize` and `eval` run with no search flag given).
    fn default() -> Self {
        #[derive(clap::Parser)]
        struct Flags {
            #[command(flatten)]
            tuning: SearchTuning,
        }
        <Flags as clap::Parser>::parse_from(["defaults"]).tuning
    }
}

impl SearchTuning {
    /// Whether a search of `hypotheses` starts with these settings stays within
    /// [`MAX_HYPOTHESES`] starts (`hypotheses` × (2·`axis_starts` + 1)); the error says why not.
    /// `serve`, `localize`, `track` and `eval` check their defaults with it before they start.
    pub fn check(&self, hypotheses: u32) -> Result<(), String> {
        let starts = self.search(hypotheses as usize, 1).starts();
        if hypotheses as usize > MAX_HYPOTHESES || starts > MAX_HYPOTHESES {
            return Err(format!("{hypotheses} hypotheses × (2·{} axis starts + 1) = {} starts: at most {MAX_HYPOTHESES}", self.axis_starts, hypotheses as usize * (2 * self.axis_starts as usize + 1)));
        }
        Ok(())
    }

    pub fn search(&self, hypotheses: usize, max_iterations: usize) -> SearchConfig {
        SearchConfig {
            hypotheses,
            max_iterations,
            narrow_after: (self.narrow_after > 0).then_some(self.narrow_after as usize),
            merge_duplicates: self.merge_duplicates,
            keep_prior: self.keep_prior,
            prior_bound: None,
            refine: self.refine,
            polish: self.polish,
            prior_margin: self.prior_margin,
            axis: AxisStarts { each_way: self.axis_starts as usize, step_m: self.axis_step_m, margin: self.axis_margin },
            judge_zoom: self.judge_zoom,
            judge_gate: self.judge_gate,
        }
    }
}

/// Two hypotheses closer than this (translation of camera_from_map, metres; and geodesic
/// rotation, degrees) count as duplicates: the later one would most likely walk into the same
/// answer (the starts are 90° apart; the policy's coarsest steps are 8.1 m and 62.5°). Chosen by
/// replaying recorded searches (`scripts/search-rules.py`, docs/evaluation.md "Trying search
/// rules offline"): 1 m / 5° until 2026-12; 4 m / 20° costs about a fifth fewer policy rows on
/// synthetic validation for one case of 240, and on real-dev stops starts that the agent would
/// otherwise walk away from a good pose.
pub const DUPLICATE_RTE_M: f64 = 4.0;
pub const DUPLICATE_RRE_DEG: f64 = 20.0;

/// Whether `b` is within the duplicate distance of `a` (`PoseError::between(b, a)` below
/// [`DUPLICATE_RTE_M`] and [`DUPLICATE_RRE_DEG`]).
pub fn within_duplicate_radius(b: &Pose, a: &Pose) -> bool {
    let e = PoseError::between(b, a);
    e.rte_m < DUPLICATE_RTE_M && e.rre_geodesic_deg < DUPLICATE_RRE_DEG
}

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

/// The yaw offsets of H starts within a bound of ±`bound_deg`: the prior first, then the bound's
/// ends, then points halfway, a quarter of the way, ... alternating sides
/// (0, +b, −b, +b/2, −b/2, +b/4, ...); `bound_deg` above 180° counts as 180°.
pub fn bounded_start_yaw_offsets(hypotheses: usize, bound_deg: f64) -> Vec<f64> {
    let bound = bound_deg.min(180.0);
    (0..hypotheses)
        .map(|k| {
            if k == 0 {
                return 0.0;
            }
            let level = (k - 1) / 2; // 0: the ends, 1: halfway, 2: a quarter, ...
            let sign = if k % 2 == 1 { 1.0 } else { -1.0 };
            sign * bound / f64::powi(2.0, level as i32)
        })
        .collect()
}

/// Which pose of a search answers after `iterations` steps: `None` for the prior itself, else
/// (hypothesis, steps taken to reach the pose; 0 = its start).
///
/// Without a bound: the best-scoring final pose over the hypotheses (the first one on ties),
/// or the prior when `rules.prior_competes` and it scores strictly higher; scores are
/// [`AnswerRules::score`]'s (the prior's margin included). With a bound: the best-scoring pose
/// visited within the bound of `prior` (each hypothesis's start and every step up to
/// `iterations`), the prior first so that it wins a draw; NaN scores never win.
pub fn answer_at(hypotheses: &[Hypothesis], prior: &Pose, rules: AnswerRules, iterations: usize) -> Option<(usize, usize)> {
    let Some(bound) = rules.bound else {
        let finals: Vec<f32> = hypotheses.iter().map(|h| h.pose_after(iterations)).map(|(pose, a)| rules.score(prior, &pose, a)).collect();
        let best = best_of(finals.iter().copied());
        let prior_score = hypotheses.first().map_or(f32::NAN, |h| rules.score(prior, prior, h.start_alignment));
        if rules.prior_competes && outscores(prior_score, finals[best]) {
            return None;
        }
        return Some((best, iterations.min(hypotheses[best].steps.len())));
    };
    let mut best: (Option<(usize, usize)>, f32) = (None, hypotheses.first().map_or(f32::NAN, |h| h.start_alignment));
    if best.1.is_nan() {
        best.1 = f32::NEG_INFINITY;
    }
    for (h, hypothesis) in hypotheses.iter().enumerate() {
        for k in 0..=iterations.min(hypothesis.steps.len()) {
            if h == 0 && k == 0 {
                continue; // the prior, already the incumbent
            }
            let (pose, score) = hypothesis.pose_after(k);
            if score > best.1 && bound.contains(prior, &pose) {
                best = (Some((h, k)), score);
            }
        }
    }
    best.0
}

/// One finished trajectory of a search.
#[derive(Debug, Clone)]
pub struct Hypothesis {
    /// The turn applied to its base (the prior, moved along its optical axis by
    /// `start_axis_shift_m`; in the refinement round, the first round's answer or that answer
    /// turned by 180°) to get this start.
    pub start_yaw_offset_deg: f64,
    /// Where its base lies along the prior's optical axis (metres, forward positive;
    /// [`AxisStarts::priors`]): 0 without axis starts; in the refinement round, the shift of the
    /// first round's answer (whose map it searches).
    pub start_axis_shift_m: f64,
    /// A start of the refinement round.
    pub refinement: bool,
    pub start: Pose,
    pub start_alignment: f32,
    /// Every step, each with the alignment score of the pose it reached.
    pub steps: Vec<Step>,
    pub converged: bool,
    /// Stopped early: it duplicated an earlier hypothesis, or another scored better (`narrow_after`).
    pub dropped: bool,
}

impl Hypothesis {
    /// The pose after `iterations` steps (the last one if the trajectory stopped earlier).
    pub fn pose_after(&self, iterations: usize) -> (Pose, f32) {
        super::episode::pose_after(&self.start, self.start_alignment, &self.steps, iterations)
    }

    pub fn camera_from_map(&self) -> Pose {
        self.pose_after(self.steps.len()).0
    }

    pub fn alignment(&self) -> f32 {
        self.pose_after(self.steps.len()).1
    }
}

/// Whether a challenger's alignment score beats the incumbent's: strictly (a draw keeps the
/// incumbent), and NaN never wins (a NaN incumbent loses to any number). How the prior competes
/// with the search's answer, and a refinement group with the first round's.
pub fn outscores(challenger: f32, incumbent: f32) -> bool {
    challenger > incumbent || (incumbent.is_nan() && !challenger.is_nan())
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

/// Which pose answers a search: hypothesis `hypothesis` after `steps` steps. `kept`: the start of
/// a group of the first round answered unmoved because it outscored every pose its group reached
/// (`keep_prior`; `hypothesis` is then the group's first, `steps` 0): the request's prior for the
/// first group.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Answer {
    pub hypothesis: usize,
    pub steps: usize,
    pub kept: bool,
}

impl Answer {
    /// Hypothesis `hypothesis` after `steps` steps.
    pub fn at(hypothesis: usize, steps: usize) -> Self {
        Self { hypothesis, steps, kept: false }
    }

    /// The start of the group whose first hypothesis is `hypothesis`, kept unmoved.
    pub fn kept(hypothesis: usize) -> Self {
        Self { hypothesis, steps: 0, kept: true }
    }

    /// The answer's pose and alignment score.
    pub fn pose(&self, hypotheses: &[Hypothesis]) -> (Pose, f32) {
        hypotheses[self.hypothesis].pose_after(self.steps)
    }
}

/// How [`Search::finish`] has the judge's views encoded when it reads them (`Batch::retire`
/// passes the backend's image encoder); an error fails the request.
pub type ReadViews<'a> = dyn FnMut(&[ViewInput]) -> Result<Vec<ViewEvidence>, StepError> + 'a;

/// What the judge's views did for one search ([`Search::finish`]), kept with its answer.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct JudgeRecord {
    /// [`start_agreement`] of the served search's own answer ([`search_answer`]), in [0, 1].
    pub agreement: f64,
    /// The views were encoded and judged ([`SearchConfig::judge_gate`]); without them the
    /// served view's score judges alone.
    pub read_views: bool,
}

/// Share of the other starts of the answer's group in the first round (its prior along the axis;
/// the chosen one excluded unless the prior was kept) whose final pose lies within the duplicate
/// radius ([`within_duplicate_radius`]) of `answer_pose`, in [0, 1] (0 with none): starts a
/// quarter turn apart that end at the same place. `chosen`, `kept`: the answer's hypothesis and
/// whether the prior was kept (`Localization::chosen`, `kept_prior`).
pub fn start_agreement(hypotheses: &[Hypothesis], chosen: usize, kept: bool, answer_pose: &Pose) -> f64 {
    let first = &hypotheses[..first_round_len(hypotheses)];
    let shift = hypotheses[chosen].start_axis_shift_m;
    let group = axis_groups(first).into_iter().find(|g| first[g.start].start_axis_shift_m == shift).unwrap_or(0..first.len());
    let others: Vec<&Hypothesis> = group.clone().filter(|&h| kept || h != chosen).map(|h| &first[h]).collect();
    if others.is_empty() {
        return 0.0;
    }
    others.iter().filter(|h| within_duplicate_radius(&h.camera_from_map(), answer_pose)).count() as f64 / others.len() as f64
}

/// The groups of a first round: runs of consecutive hypotheses with the same
/// `start_axis_shift_m`, one per prior along the optical axis ([`AxisStarts`]); the whole round
/// without axis starts.
pub fn axis_groups(first: &[Hypothesis]) -> Vec<std::ops::Range<usize>> {
    let mut groups: Vec<std::ops::Range<usize>> = Vec::new();
    for (h, hypothesis) in first.iter().enumerate() {
        match groups.last_mut() {
            Some(g) if first[g.start].start_axis_shift_m == hypothesis.start_axis_shift_m => g.end = h + 1,
            _ => groups.push(h..h + 1),
        }
    }
    groups
}

/// The first round's answer after `iterations` steps: each group's ([`axis_groups`];
/// [`answer_at`] with the group's first start, its prior along the axis, as the prior), then the
/// group whose answer scores highest (alignment, the first group's with `axis_margin` added; the
/// earlier group on a draw). Without axis starts, the one group's answer. With a bound
/// (`rules.bound`), every start of every group competes as one search does: the best pose visited
/// inside the bound around the request's `prior`, the prior winning a draw.
pub fn first_round_answer(first: &[Hypothesis], prior: &Pose, rules: AnswerRules, axis_margin: f32, iterations: usize) -> Answer {
    if rules.bound.is_some() {
        return match answer_at(first, prior, rules, iterations) {
            None => Answer::kept(0),
            Some((h, k)) => Answer::at(h, k),
        };
    }
    let mut best: Option<(Answer, f32)> = None;
    for group in axis_groups(first) {
        let hypotheses = &first[group.clone()];
        let answer = match answer_at(hypotheses, &hypotheses[0].start, rules, iterations) {
            None => Answer::kept(group.start),
            Some((h, k)) => Answer::at(group.start + h, k),
        };
        let judged = answer.pose(first).1 + if group.start == 0 { axis_margin } else { 0.0 };
        if best.is_none_or(|(_, b)| outscores(judged, b)) {
            best = Some((answer, judged));
        }
    }
    best.expect("a search has a start").0
}

/// The answer of a whole search after `iterations` steps: the first round's
/// ([`first_round_answer`] over the hypotheses that are not `refinement` ones), then, when
/// `with_refinement`, each refinement group's ([`REFINE_STARTS`] consecutive hypotheses;
/// [`answer_at`] within [`REFINE_BOUND`] of the group's first start, which competes) when it
/// scores strictly higher, by [`AnswerRules::score`] against the request's prior.
pub fn search_answer(hypotheses: &[Hypothesis], prior: &Pose, rules: AnswerRules, axis_margin: f32, iterations: usize, with_refinement: bool) -> Answer {
    let first = first_round_len(hypotheses);
    let score = |a: Answer| {
        let (pose, alignment) = a.pose(hypotheses);
        rules.score(prior, &pose, alignment)
    };
    let mut best = first_round_answer(&hypotheses[..first], prior, rules, axis_margin, iterations);
    if !with_refinement {
        return best;
    }
    let mut best_score = score(best);
    for (g, group) in hypotheses[first..].chunks(REFINE_STARTS).enumerate() {
        let offset = first + g * REFINE_STARTS;
        let base = group[0].start;
        let group_rules = AnswerRules { bound: Some(REFINE_BOUND), prior_competes: true, prior_margin: 0.0 };
        let answer = match answer_at(group, &base, group_rules, REFINE_ITERATIONS) {
            None => Answer::at(offset, 0),
            Some((h, k)) => Answer::at(offset + h, k),
        };
        let s = score(answer);
        if outscores(s, best_score) {
            (best, best_score) = (answer, s);
        }
    }
    best
}

/// Most hypotheses the polished choice (`polish::choose`) compares with the search's answer.
/// Measured on the real-train validation split's three regimes (288 cases, model v11): 1 / 2 / 6
/// such hypotheses polished on at once register 201 / 206 / 209 (the answer alone: 200), and
/// with only the fine pass for choosing, 6 register 212; more than 6 apart seldom exist (12
/// gives what 6 does). docs/evaluation.md, "A polished choice".
pub const POLISH_CANDIDATES: usize = 6;

/// The poses the polished choice compares: the search's answer first (`answer`: hypothesis and
/// steps, as [`search_answer`] gives it, (group's first, 0) for a kept start), then the final poses of
/// other hypotheses, best first by [`AnswerRules::score`] against `prior` (hypothesis order on a
/// draw; NaN scores left out), each beyond the polish's reach ([`polish::REACH`]) of every pose
/// taken before it (within it, that pose's polish covers it) and, with a bound, inside it: at
/// most [`POLISH_CANDIDATES`] besides the answer. (hypothesis, steps) pairs.
pub fn polish_candidates(hypotheses: &[Hypothesis], prior: &Pose, rules: AnswerRules, answer: (usize, usize)) -> Vec<(usize, usize)> {
    let mut picked = vec![(answer, hypotheses[answer.0].pose_after(answer.1).0)];
    let mut others: Vec<(usize, Pose, f32)> = hypotheses
        .iter()
        .enumerate()
        .map(|(h, hyp)| {
            let (pose, alignment) = hyp.pose_after(hyp.steps.len());
            (h, pose, rules.score(prior, &pose, alignment))
        })
        .filter(|(_, pose, s)| !s.is_nan() && rules.bound.is_none_or(|b| b.contains(prior, pose)))
        .collect();
    others.sort_by(|a, b| b.2.total_cmp(&a.2));
    for (h, pose, _) in others {
        if picked.len() > POLISH_CANDIDATES {
            break;
        }
        if picked.iter().all(|(_, taken)| !polish::REACH.contains(taken, &pose)) {
            picked.push(((h, hypotheses[h].steps.len()), pose));
        }
    }
    picked.into_iter().map(|(a, _)| a).collect()
}

/// How many of `hypotheses` belong to the first round (the refinement round's come after).
pub fn first_round_len(hypotheses: &[Hypothesis]) -> usize {
    hypotheses.iter().take_while(|h| !h.refinement).count()
}

/// The hypotheses of one request in progress.
pub struct Search {
    pub prior: Pose,
    pub episodes: Vec<Episode>,
    /// The maps the episodes localize in: one shared by all (a whole region), or in a tiled
    /// region one per prior along the optical axis, each cut around its own prior as a request
    /// from it would be.
    pub maps: Vec<Arc<PreparedMap>>,
    /// Each episode's map: an index into `maps`.
    pub scenes: Vec<usize>,
    /// What the image says against each map (`maps[i]`'s frustum probabilities).
    evidence: Vec<Arc<ImageEvidence>>,
    offsets: Vec<f64>,
    /// Each episode's shift along the prior's optical axis (the refinement round's: its base's).
    shifts: Vec<f64>,
    /// Episodes of the first round (the rest, once started, are the refinement round's).
    first_round: usize,
    /// Starts per prior along the axis: the first round's groups are this long.
    group_len: usize,
    /// The refinement round is still to start (the first round is running).
    refine_pending: bool,
    frame: ActionFrame,
    max_iterations: usize,
    /// Steps after which only the best-scoring hypothesis of each group goes on; `None` once
    /// done (or never).
    narrow_after: Option<usize>,
    merge_duplicates: bool,
    rules: AnswerRules,
    axis_margin: f32,
    polish: bool,
    /// The answer is chosen with the judge's views (`SearchConfig::judges`).
    judges: bool,
    judge_gate: f64,
    /// The judge's views, prepared but not yet encoded ([`Search::with_views`]).
    view_inputs: Vec<ViewInput>,
}

impl Search {
    /// `maps`, each with its `evidence`: one, or one per prior along the axis (in
    /// `AxisStarts::priors` order). `frame`: the model's action
    /// frame, which the starts' turns follow.
    pub fn new(evidence: Vec<ImageEvidence>, maps: Vec<Arc<PreparedMap>>, prior: Pose, config: SearchConfig, frame: ActionFrame) -> Self {
        assert!(!maps.is_empty() && evidence.len() == maps.len(), "one evidence per map");
        let evidence: Vec<Arc<ImageEvidence>> = evidence.into_iter().map(Arc::new).collect();
        let max_iterations = config.max_iterations;
        let hypotheses = config.hypotheses.clamp(1, MAX_HYPOTHESES);
        let bases = config.axis.priors(&prior);
        assert!(maps.len() == 1 || maps.len() == bases.len(), "one map, or one per prior along the axis");
        let (mut episodes, mut offsets, mut shifts, mut scenes) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        let mut yaws_per_group = 0;
        for (g, (shift, base)) in bases.into_iter().enumerate() {
            let m = if maps.len() == 1 { 0 } else { g };
            // Unbounded, the starts turn about the map's pivot (like the agent's own steps);
            // within a bound, about the prior's camera centre, so that every start lies inside it.
            let (yaws, pivot) = match config.prior_bound {
                None => (start_yaw_offsets(hypotheses), maps[m].pivot),
                Some(b) => (bounded_start_yaw_offsets(hypotheses, b.rotation_deg), Point3::from(base.camera_position_in_map())),
            };
            yaws_per_group = yaws.len();
            for yaw_deg in yaws {
                let start = if yaw_deg == 0.0 { base } else { apply_motion(frame, &base, &pivot, yaw_deg, 0.0, 0.0) };
                episodes.push(Episode::new(evidence[m].clone(), start, max_iterations));
                offsets.push(yaw_deg);
                shifts.push(shift);
                scenes.push(m);
            }
        }
        let narrow_after = config.narrow_after.filter(|_| yaws_per_group > 1);
        Self {
            prior,
            episodes,
            maps,
            scenes,
            evidence,
            first_round: offsets.len(),
            group_len: yaws_per_group,
            offsets,
            shifts,
            refine_pending: config.refines(),
            frame,
            max_iterations,
            narrow_after,
            merge_duplicates: config.merge_duplicates,
            rules: config.answer_rules(),
            axis_margin: config.axis.margin,
            polish: config.polishes(),
            judges: config.judges(),
            judge_gate: config.judge_gate,
            view_inputs: Vec::new(),
        }
    }

    /// The judge's views of the request's image (`input::prepare_views`), kept until
    /// [`Search::finish`] decides whether to encode them.
    pub fn with_views(mut self, views: Vec<ViewInput>) -> Self {
        self.view_inputs = views;
        self
    }

    /// Every episode, in order, with the map it localizes in.
    pub fn episodes_with_maps(&mut self) -> impl Iterator<Item = (&mut Episode, &PreparedMap)> {
        let (maps, scenes) = (&self.maps, &self.scenes);
        self.episodes.iter_mut().zip(scenes).map(move |(episode, &m)| (episode, &*maps[m]))
    }

    /// Scores the last pose of each of the first `count` episodes that has not been scored yet.
    fn settle(&mut self, count: usize, layout: &StateLayout, scratch: &mut ScatterScratch) {
        for (episode, map) in self.episodes_with_maps().take(count) {
            episode.settle(map, layout, scratch);
        }
    }

    /// Call after every batched step: stops duplicates (within each group of the first round and
    /// of the refinement round) and narrows, as configured, and starts the refinement round once
    /// the first is done.
    pub fn after_step(&mut self, layout: &StateLayout, scratch: &mut ScatterScratch) {
        if self.merge_duplicates {
            for g in (0..self.first_round).step_by(self.group_len) {
                self.drop_duplicates(g..g + self.group_len);
            }
            for g in (self.first_round..self.episodes.len()).step_by(REFINE_STARTS) {
                self.drop_duplicates(g..(g + REFINE_STARTS).min(self.episodes.len()));
            }
        }
        self.narrow(layout, scratch);
        if self.refine_pending && self.episodes.iter().all(Episode::is_done) {
            self.start_refinement(layout, scratch);
        }
    }

    /// Stops every running hypothesis of `group` that is within the duplicate distance of an
    /// earlier one of the group that was not itself dropped.
    fn drop_duplicates(&mut self, group: std::ops::Range<usize>) {
        for j in group.clone().skip(1) {
            if self.episodes[j].is_done() {
                continue;
            }
            let duplicate = (group.start..j).any(|i| {
                let (a, b) = (&self.episodes[i], &self.episodes[j]);
                !a.dropped && within_duplicate_radius(&b.pose, &a.pose)
            });
            self.episodes[j].dropped |= duplicate;
        }
    }

    /// Once every first-round hypothesis has taken `narrow_after` steps (or stopped), all but the
    /// best-scoring one of each group stop.
    fn narrow(&mut self, layout: &StateLayout, scratch: &mut ScatterScratch) {
        let Some(after) = self.narrow_after else { return };
        let first = &self.episodes[..self.first_round];
        if !first.iter().all(|e| e.is_done() || e.steps.len() >= after) {
            return;
        }
        self.narrow_after = None;
        self.settle(self.first_round, layout, scratch);
        for group in self.episodes[..self.first_round].chunks_mut(self.group_len) {
            let leader = best_of(group.iter().map(Episode::alignment));
            for (h, episode) in group.iter_mut().enumerate() {
                episode.dropped |= h != leader && !episode.is_done();
            }
        }
    }

    /// The refinement round's starts: around the first round's answer and that answer turned by
    /// [`REFINE_TURNS_DEG`] (about its camera centre), [`REFINE_STARTS`] each within
    /// [`REFINE_BOUND`], in the answer's map.
    fn start_refinement(&mut self, layout: &StateLayout, scratch: &mut ScatterScratch) {
        self.refine_pending = false;
        self.settle(self.episodes.len(), layout, scratch);
        let hypotheses: Vec<Hypothesis> = (0..self.episodes.len()).map(|h| self.hypothesis(h, false, self.episodes[h].steps.clone())).collect();
        let chosen = first_round_answer(&hypotheses, &self.prior, self.rules, self.axis_margin, self.max_iterations);
        let answer = chosen.pose(&hypotheses).0;
        let (m, shift) = (self.scenes[chosen.hypothesis], self.shifts[chosen.hypothesis]);
        let centre = Point3::from(answer.camera_position_in_map());
        for turn in REFINE_TURNS_DEG {
            let base = if turn == 0.0 { answer } else { apply_motion(self.frame, &answer, &centre, turn, 0.0, 0.0) };
            let base_centre = Point3::from(base.camera_position_in_map());
            for yaw_deg in bounded_start_yaw_offsets(REFINE_STARTS, REFINE_BOUND.rotation_deg) {
                let start = if yaw_deg == 0.0 { base } else { apply_motion(self.frame, &base, &base_centre, yaw_deg, 0.0, 0.0) };
                self.episodes.push(Episode::new(self.evidence[m].clone(), start, REFINE_ITERATIONS));
                self.offsets.push(yaw_deg);
                self.shifts.push(shift);
                self.scenes.push(m);
            }
        }
    }

    pub fn is_done(&self) -> bool {
        !self.refine_pending && self.episodes.iter().all(Episode::is_done)
    }

    /// Rows this search holds in a batch: those that step next, or the refinement round's while
    /// it is still to start (reserved, so that a batch never grows past its bound when it does).
    pub fn reserved_rows(&self) -> usize {
        let running = self.running().count();
        if self.refine_pending { running.max(REFINE_ROWS) } else { running }
    }

    /// The hypotheses whose next step is asked of the policy (one row each).
    pub fn running(&self) -> impl Iterator<Item = usize> + '_ {
        (0..self.episodes.len()).filter(|&h| self.episodes[h].needs_policy())
    }

    /// Takes the next step of every hypothesis that repeats a cycle (`Episode::replay`): call
    /// once per batched step, before the policy's rows are advanced, so that every hypothesis
    /// moves one step per iteration.
    pub fn replay(&mut self) {
        for episode in self.episodes.iter_mut().filter(|e| e.is_replaying()) {
            episode.replay();
        }
    }

    /// Scores every final pose, chooses the answer ([`search_answer`] after the last step: the
    /// best first-round hypothesis, or the prior with `keep_prior` when it scores higher still;
    /// within a bound, the best pose visited inside it; then the refinement round's groups when
    /// one scores higher; with the judge's views, [`Search::judged_answer`] instead); with the
    /// polish, the polished choice between that answer and the final poses apart from it
    /// ([`polish_candidates`], `polish::choose`, climbing the judge's score); and turns the
    /// search into its result.
    /// The polished choice's candidates climb on several threads (scatter buffers from `pool`);
    /// every pose and score is the same whatever the threads.
    ///
    /// With the judge's views (`SearchConfig::judges`), `read_views` encodes them when the served
    /// view's choice is in doubt (`SearchConfig::judge_gate`); its error fails the request.
    pub fn finish(mut self, layout: &StateLayout, pool: &ScratchPool, mut timings: Timings, read_views: &mut ReadViews<'_>) -> Result<Localization, StepError> {
        pool.with(|scratch| self.settle(self.episodes.len(), layout, scratch));
        let hypotheses: Vec<Hypothesis> = (0..self.episodes.len())
            .map(|h| {
                let steps = std::mem::take(&mut self.episodes[h].steps);
                self.hypothesis(h, h >= self.first_round, steps)
            })
            .collect();
        let mut views: Vec<ViewEvidence> = Vec::new();
        let mut judge = None;
        // The served search's own answer: with the judge's views, where most starts ended there
        // the views are not read and the served view judges alone.
        let served = search_answer(&hypotheses, &self.prior, self.rules, self.axis_margin, self.max_iterations, true);
        let answer = if self.judges {
            let agreement = start_agreement(&hypotheses, served.hypothesis, served.kept, &served.pose(&hypotheses).0);
            let read = agreement <= self.judge_gate;
            judge = Some(JudgeRecord { agreement, read_views: read });
            if read {
                let started = std::time::Instant::now();
                views = read_views(&self.view_inputs)?;
                timings.image_encoder_ms += super::ms(started);
            }
            let started = std::time::Instant::now();
            let answer = self.judged_answer(&hypotheses, &self.visited(&hypotheses), &views, layout, pool).unwrap_or(served);
            timings.judge_ms = super::ms(started);
            timings.agent_steps_ms += timings.judge_ms;
            answer
        } else {
            served
        };
        let (mut chosen, mut answer_steps, mut kept_prior) = (answer.hypothesis, answer.steps, answer.kept);
        let polish = self.polish.then(|| {
            let started = std::time::Instant::now();
            let bound = self.rules.bound.map(|b| (&self.prior, b));
            let picked = polish_candidates(&hypotheses, &self.prior, self.rules, (chosen, answer_steps));
            let candidates: Vec<(Pose, f32)> = picked.iter().map(|&(h, k)| hypotheses[h].pose_after(k)).collect();
            // Each candidate climbs in its own hypothesis's map, on the served view's score (the
            // judge's views compare the peaks). Every pose a candidate's polish scores lies
            // within its reach: only the points seen from there are projected (the same scores).
            let scenes: Vec<usize> = picked.iter().map(|&(h, _)| self.scenes[h]).collect();
            let reach = polish::REACH;
            let near: Vec<state::NearView> = candidates
                .par_iter()
                .zip(&scenes)
                .map(|((p, _), &m)| state::NearView::new(layout, &self.evidence[m].intrinsics, &self.maps[m].points, p, reach.rotation_deg, reach.translation_m))
                .collect();
            let score = |c: usize, p: &Pose| {
                let (map, e) = (&self.maps[scenes[c]], &self.evidence[scenes[c]]);
                pool.with(|scratch| state::alignment_near(layout, &near[c], &map.features, &e.image_features, &e.intrinsics, p, scratch))
            };
            // A peak competes with the judge's score there (the served one without views).
            let judge = |c: usize, pose: &Pose, alignment: f32| {
                let judged = pool.with(|scratch| judged_alignment(&views, &self.maps[scenes[c]], layout, pose, alignment, scratch));
                self.rules.score(&self.prior, pose, judged)
            };
            let (c, p) = polish::choose(self.frame, &candidates, bound, judge, score).expect("the search's answer is a candidate");
            if c > 0 {
                (chosen, answer_steps, kept_prior) = (picked[c].0, picked[c].1, false);
            }
            timings.polish_ms = super::ms(started);
            timings.agent_steps_ms += timings.polish_ms;
            p
        });
        // The policy's certainty at the answer: of the decision taken there (the last one when
        // the answer is a trajectory's end).
        let best = &hypotheses[chosen];
        let (pose, alignment) = best.pose_after(answer_steps);
        let certainty = best.steps.get(answer_steps).or(best.steps.last()).map_or(0.0, |s| s.confidence);
        let confidence = self.episodes[chosen].confidence_of(&self.maps[self.scenes[chosen]], layout, &pose, certainty, alignment);
        Ok(Localization {
            prior: self.prior,
            hypotheses,
            chosen,
            answer_steps,
            kept_prior,
            rules: self.rules,
            axis_margin: self.axis_margin,
            confidence,
            max_iterations: self.max_iterations,
            timings,
            verdict: Default::default(),
            polish,
            judge,
        })
    }

    /// Every pose the search visited that may answer: each hypothesis's start and the pose after
    /// each of its steps (a step that stayed or repeated a cycle adding none), with a bound those
    /// inside it, the prior only when it competes; as (hypothesis, steps, pose, served view's
    /// alignment score).
    fn visited(&self, hypotheses: &[Hypothesis]) -> Vec<(usize, usize, Pose, f32)> {
        let mut visited = Vec::new();
        for (h, hypothesis) in hypotheses.iter().enumerate() {
            for k in 0..=hypothesis.steps.len() {
                if k > 0 && (hypothesis.steps[k - 1].repeated || hypothesis.steps[k - 1].action.is_zero()) {
                    continue;
                }
                if (h, k) == (0, 0) && !self.rules.prior_competes {
                    continue;
                }
                let (pose, served) = hypothesis.pose_after(k);
                if self.rules.bound.is_none_or(|b| b.contains(&self.prior, &pose)) {
                    visited.push((h, k, pose, served));
                }
            }
        }
        visited
    }

    /// Hypothesis `h` after `k` steps as the answer: a start of the first round (yaw offset 0)
    /// is kept unmoved ([`Answer::kept`]).
    fn visited_answer(&self, hypotheses: &[Hypothesis], h: usize, k: usize) -> Answer {
        let hypothesis = &hypotheses[h];
        if k == 0 && !hypothesis.refinement && hypothesis.start_yaw_offset_deg == 0.0 { Answer::kept(h) } else { Answer::at(h, k) }
    }

    /// The answer chosen by the judge's views: among the `visited` poses ([`Search::visited`]) the
    /// one whose score ([`judged_alignment`] over `views`, judged by [`AnswerRules::score`]
    /// against the prior) is highest, the earliest on a draw, NaN never (`None` when every score
    /// is NaN); a start of the first round (yaw offset 0) that wins is kept unmoved. Without views
    /// (the gate shut them out) that is the served view's best visited pose.
    ///
    /// Then, among the visited poses within [`JUDGE_LOCAL`] of that pose, the one the served
    /// view's score ranks highest answers (the same rules).
    ///
    /// Why: averaged over zoomed crops the learned score tells the right pose from a wrong one
    /// better than the served crop alone, and the right pose is more often one the search passed
    /// than one it stopped at (docs/evaluation.md, "Zoomed views as the choice's judge"); but among
    /// poses that differ by a step along the optical axis the average prefers the camera behind
    /// the truth, by about a metre on real frames, where the served view's score does much less
    /// (docs/evaluation.md, "The judge's views in the server").
    fn judged_answer(&self, hypotheses: &[Hypothesis], visited: &[(usize, usize, Pose, f32)], views: &[ViewEvidence], layout: &StateLayout, pool: &ScratchPool) -> Option<Answer> {
        let judged: Vec<f32> = visited
            .par_iter()
            .map(|&(h, _, pose, served)| {
                let m = self.scenes[h];
                let score = pool.with(|scratch| judged_alignment(views, &self.maps[m], layout, &pose, served, scratch));
                self.rules.score(&self.prior, &pose, score)
            })
            .collect();
        let i = best_of(judged.iter().copied());
        if judged.get(i).is_none_or(|s| s.is_nan()) {
            return None;
        }
        // Where the judge's pose lies, the served view's score places the answer (poses beyond
        // `JUDGE_LOCAL` of it do not compete).
        let judged_pose = visited[i].2;
        let near = visited.iter().map(|&(_, _, pose, served)| if JUDGE_LOCAL.contains(&judged_pose, &pose) { self.rules.score(&self.prior, &pose, served) } else { f32::NAN });
        let (h, k, _, _) = visited[best_of(near)];
        Some(self.visited_answer(hypotheses, h, k))
    }
}

impl Search {
    /// Episode `h`, finished (or, for choosing the refinement's bases, settled), as a
    /// [`Hypothesis`] with `steps`.
    fn hypothesis(&self, h: usize, refinement: bool, steps: Vec<Step>) -> Hypothesis {
        let e = &self.episodes[h];
        Hypothesis {
            start_yaw_offset_deg: self.offsets[h],
            start_axis_shift_m: self.shifts[h],
            refinement,
            start: e.start,
            start_alignment: e.start_alignment,
            steps,
            converged: e.converged,
            dropped: e.dropped,
        }
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
    fn a_hypothesis_that_reaches_an_earlier_one_stops() {
        use crate::geometry::Intrinsics;
        use nalgebra::Vector3;
        let map = PreparedMap { points: vec![[0.0, 0.0, 5.0]], features: vec![0.0; 64], pivot: Point3::new(0.0, 0.0, 5.0), source_points: 1, intensity: None };
        let evidence = ImageEvidence { image_features: Default::default(), frustum_probs: vec![0.5], intrinsics: Intrinsics { fx: 100.0, fy: 100.0, cx: 50.0, cy: 50.0 } };
        let config = SearchConfig { hypotheses: 4, max_iterations: 10, narrow_after: None, merge_duplicates: true, keep_prior: false, prior_bound: None, refine: false, polish: false, prior_margin: 0.0, axis: AxisStarts::NONE, judge_zoom: 0.0, judge_gate: 1.0 };
        let mut search = Search::new(vec![evidence], vec![Arc::new(map.clone())], Pose::identity(), config, ActionFrame::CameraY);
        let shifted = |dx: f64| Pose::from_rt(nalgebra::Matrix3::identity(), Vector3::new(dx * DUPLICATE_RTE_M, 0.0, 0.0));
        // 0 and 1 meet (half the radius apart); 2 is within the radius of 1 but 1.2 radii from 0;
        // 3 is far from all.
        search.episodes[0].pose = shifted(0.0);
        search.episodes[1].pose = shifted(0.5);
        search.episodes[2].pose = shifted(1.2);
        search.episodes[3].pose = shifted(9.0);
        let (layout, mut scratch) = (StateLayout { dim: 64, stride: 4, grid_height: 1, grid_width: 1, image_width: 4, image_height: 4, num_state_points: 1, xyz_scale_m: 1.0, form: crate::agent::state::Form2d::Features }, ScatterScratch::default());
        search.after_step(&layout, &mut scratch);
        let dropped: Vec<bool> = search.episodes.iter().map(|e| e.dropped).collect();
        assert_eq!(dropped, vec![false, true, false, false], "a dropped hypothesis drops nobody");
        // A turn of 1.2 times the angle is not a duplicate, 0.8 times is (about the pivot, 5 m
        // away, which also moves it well within the distance); a stopped (converged) leader
        // still counts.
        search.episodes[0].converged = true;
        search.episodes[3].pose = apply_motion(ActionFrame::CameraY, &shifted(0.0), &map.pivot, 0.8 * DUPLICATE_RRE_DEG, 0.0, 0.0);
        search.episodes[2].pose = apply_motion(ActionFrame::CameraY, &shifted(0.0), &Point3::origin(), 1.2 * DUPLICATE_RRE_DEG, 0.0, 0.0);
        search.after_step(&layout, &mut scratch);
        let dropped: Vec<bool> = search.episodes.iter().map(|e| e.dropped).collect();
        assert_eq!(dropped, vec![false, true, false, true]);
    }

    #[test]
    fn bounded_starts_spread_over_the_bound() {
        assert_eq!(bounded_start_yaw_offsets(1, 30.0), vec![0.0]);
        assert_eq!(bounded_start_yaw_offsets(3, 30.0), vec![0.0, 30.0, -30.0]);
        assert_eq!(bounded_start_yaw_offsets(6, 40.0), vec![0.0, 40.0, -40.0, 20.0, -20.0, 10.0]);
        assert_eq!(bounded_start_yaw_offsets(3, 270.0), vec![0.0, 180.0, -180.0]);
    }

    #[test]
    fn a_bound_contains_rotations_and_positions_up_to_its_edges() {
        use nalgebra::Vector3;
        let bound = PriorBound { rotation_deg: 30.0, translation_m: 5.0 };
        let prior = Pose::level_camera_along_x(Vector3::new(10.0, -4.0, 1.5));
        let at = |yaw: f64, dx: f64| apply_motion(ActionFrame::MapZ, &prior, &Point3::from(prior.camera_position_in_map()), yaw, dx, 0.0);
        assert!(bound.contains(&prior, &prior));
        assert!(bound.contains(&prior, &at(29.9, 0.0)) && bound.contains(&prior, &at(-29.9, 4.9)));
        assert!(!bound.contains(&prior, &at(30.1, 0.0)) && !bound.contains(&prior, &at(0.0, 5.1)));
        // A turn about the camera centre does not move the camera.
        assert!((at(25.0, 0.0).camera_position_in_map() - prior.camera_position_in_map()).norm() < 1e-9);
    }

    /// A pose `x_m` along camera_from_map's translation x, unrotated.
    fn shifted(x_m: f64) -> Pose {
        Pose::from_rt(nalgebra::Matrix3::identity(), nalgebra::Vector3::new(x_m, 0.0, 0.0))
    }

    /// A step that reached `shifted(x_m)`, scoring `alignment` there.
    fn step_to(x_m: f64, alignment: f32) -> Step {
        Step {
            iteration: 1,
            camera_from_map: shifted(x_m),
            action: crate::geometry::ActionSet::default().action([5, 5, 5]),
            probabilities: [vec![1.0], vec![1.0], vec![1.0]],
            confidence: 0.5,
            value: 0.0,
            alignment,
            repeated: false,
        }
    }

    /// A trajectory from `start` (scoring `start_alignment`) through `steps`.
    fn trajectory(start: Pose, start_alignment: f32, steps: Vec<Step>, refinement: bool) -> Hypothesis {
        Hypothesis { start_yaw_offset_deg: 0.0, start_axis_shift_m: 0.0, refinement, start, start_alignment, steps, converged: false, dropped: false }
    }

    /// Unbounded: the best final pose (or the prior when it competes and wins). Bounded: the
    /// best visited pose inside the bound, the prior winning a draw.
    #[test]
    fn the_answer_follows_the_bound() {
        let prior = Pose::identity();
        let (step, hypothesis) = (step_to, |start, start_alignment, steps| trajectory(start, start_alignment, steps, false));
        // Start 0 (the prior, 0.5) passes 0.8 at 2 m, ends at 0.6 at 4 m; start 1 ends at 0.9,
        // 12 m away.
        let hs = vec![
            hypothesis(prior, 0.5, vec![step(2.0, 0.8), step(4.0, 0.6)]),
            hypothesis(shifted(9.0), 0.1, vec![step(12.0, 0.9)]),
        ];
        let rules = |bound, prior_competes| AnswerRules { bound, prior_competes, prior_margin: 0.0 };
        assert_eq!(answer_at(&hs, &prior, rules(None, false), 2), Some((1, 1)));
        assert_eq!(answer_at(&hs, &prior, rules(None, true), 2), Some((1, 1)));
        let bound = Some(PriorBound { rotation_deg: 30.0, translation_m: 5.0 });
        assert_eq!(answer_at(&hs, &prior, rules(bound, true), 2), Some((0, 1)));
        assert_eq!(answer_at(&hs, &prior, rules(bound, true), 0), None, "after no steps only the starts compete");
        let wide = Some(PriorBound { rotation_deg: 30.0, translation_m: 20.0 });
        assert_eq!(answer_at(&hs, &prior, rules(wide, true), 2), Some((1, 1)));
        // A draw with the prior keeps the prior; a NaN never wins.
        let draw = vec![hypothesis(prior, 0.8, vec![step(2.0, 0.8), step(3.0, f32::NAN)])];
        assert_eq!(answer_at(&draw, &prior, rules(bound, true), 2), None);
    }

    /// The refinement groups answer within their bound around their first start, and win only
    /// by scoring strictly higher than the first round's answer; before the last step they do
    /// not count.
    #[test]
    fn the_refinement_round_wins_only_by_scoring_higher() {
        let step = step_to;
        let h = |start: f64, start_alignment: f32, steps: Vec<Step>, refinement: bool| trajectory(shifted(start), start_alignment, steps, refinement);
        let prior = shifted(0.0);
        let rules = AnswerRules { bound: None, prior_competes: true, prior_margin: 0.0 };
        // First round: one start ending at 10 m, 0.5. Refinement: a group around 10 m whose
        // second start passes 0.7 at 12 m and ends 20 m away (outside the bound) at 0.9; a group
        // around the flip that only scores 0.4.
        let mut hs = vec![h(0.0, 0.1, vec![step(10.0, 0.5)], false)];
        hs.push(h(10.0, 0.5, vec![], true));
        hs.push(h(10.0, 0.45, vec![step(12.0, 0.7), step(30.0, 0.9)], true));
        hs.extend((0..REFINE_STARTS - 2).map(|_| h(10.0, 0.3, vec![], true)));
        hs.extend((0..REFINE_STARTS).map(|_| h(10.0, 0.4, vec![], true)));
        assert_eq!(search_answer(&hs, &prior, rules, 0.0, 1, false), Answer::at(0, 1));
        assert_eq!(search_answer(&hs, &prior, rules, 0.0, 1, true), Answer::at(2, 1));
        // A draw keeps the first round's answer.
        hs[2].steps[0].alignment = 0.5;
        assert_eq!(search_answer(&hs, &prior, rules, 0.0, 1, true), Answer::at(0, 1));
    }

    /// The polished choice's candidates: the answer first, then the best-scoring final poses
    /// each beyond the polish's reach of those taken, inside a bound, at most POLISH_CANDIDATES
    /// besides the answer.
    #[test]
    fn the_polished_choice_compares_the_answer_with_distant_final_poses() {
        let prior = Pose::identity();
        let hypothesis = |end: f64, alignment: f32| trajectory(prior, 0.1, vec![step_to(end, alignment)], false);
        let rules = AnswerRules { bound: None, prior_competes: true, prior_margin: 0.0 };
        // 0 answers (10 m); 1 ends 1 m from it (within reach: left out); 2 and 3 at 20 and 40 m,
        // 3 scoring higher; 4 scores NaN.
        let hs = vec![hypothesis(10.0, 0.6), hypothesis(11.0, 0.55), hypothesis(20.0, 0.3), hypothesis(40.0, 0.5), hypothesis(60.0, f32::NAN)];
        assert_eq!(polish_candidates(&hs, &prior, rules, (0, 1)), vec![(0, 1), (3, 1), (2, 1)]);
        // The kept prior answers as (0, 0): hypothesis 0's own end is then a candidate too.
        assert_eq!(polish_candidates(&hs, &prior, rules, (0, 0)), vec![(0, 0), (0, 1), (3, 1), (2, 1)]);
        // A bound leaves out what lies outside it.
        let bounded = AnswerRules { bound: Some(PriorBound { rotation_deg: 30.0, translation_m: 25.0 }), ..rules };
        assert_eq!(polish_candidates(&hs, &prior, bounded, (0, 1)), vec![(0, 1), (2, 1)]);
        // At most POLISH_CANDIDATES besides the answer, the best first.
        let many: Vec<Hypothesis> = (0..POLISH_CANDIDATES + 4).map(|i| hypothesis(10.0 * (i + 1) as f64, 0.1 * i as f32)).collect();
        let picked = polish_candidates(&many, &prior, rules, (0, 1));
        assert_eq!(picked.len(), POLISH_CANDIDATES + 1);
        assert_eq!(picked[1], (POLISH_CANDIDATES + 3, 1));
    }

    /// Without a bound, poses within PRIOR_NEAR of the prior compete with the margin added: a far
    /// pose answers only when it outscores them by more than the margin; a bound ignores it.
    #[test]
    fn the_prior_margin_keeps_near_poses_unless_far_ones_clearly_win() {
        let prior = Pose::identity();
        let hypothesis = |start, start_alignment, steps| trajectory(start, start_alignment, steps, false);
        // Start 0 ends 3 m from the prior at 0.60; start 1 ends 20 m away at 0.62.
        let hs = vec![hypothesis(prior, 0.5, vec![step_to(3.0, 0.60)]), hypothesis(shifted(15.0), 0.1, vec![step_to(20.0, 0.62)])];
        let rules = |prior_margin, prior_competes| AnswerRules { bound: None, prior_competes, prior_margin };
        assert_eq!(answer_at(&hs, &prior, rules(0.0, true), 1), Some((1, 1)), "no margin: the best score");
        assert_eq!(answer_at(&hs, &prior, rules(0.03, true), 1), Some((0, 1)), "0.62 does not beat 0.60 + 0.03");
        assert_eq!(answer_at(&hs, &prior, rules(0.01, true), 1), Some((1, 1)), "0.62 beats 0.60 + 0.01");
        // The prior itself is near: with the margin it still wins only by scoring higher than the near poses.
        let kept = vec![hypothesis(prior, 0.61, vec![step_to(3.0, 0.60)]), hs[1].clone()];
        assert_eq!(answer_at(&kept, &prior, rules(0.03, true), 1), None);
        assert_eq!(answer_at(&kept, &prior, rules(0.03, false), 1), Some((0, 1)));
        // A bound decides by itself.
        let bounded = AnswerRules { bound: Some(PriorBound { rotation_deg: 30.0, translation_m: 25.0 }), prior_competes: true, prior_margin: 0.03 };
        assert_eq!(answer_at(&hs, &prior, bounded, 1), Some((1, 1)));
        // In the whole search, a refinement group far from the prior needs the margin too.
        let mut search = vec![hypothesis(prior, 0.5, vec![step_to(3.0, 0.60)])];
        search.extend((0..REFINE_STARTS).map(|k| trajectory(shifted(20.0), if k == 0 { 0.62 } else { 0.1 }, vec![], true)));
        search.extend((0..REFINE_STARTS).map(|_| trajectory(shifted(3.0), 0.1, vec![], true)));
        assert_eq!(search_answer(&search, &prior, rules(0.0, true), 0.0, 1, true), Answer::at(1, 0));
        assert_eq!(search_answer(&search, &prior, rules(0.03, true), 0.0, 1, true), Answer::at(0, 1));
    }

    #[test]
    fn axis_priors_move_the_camera_along_its_optical_axis() {
        let r = nalgebra::Rotation3::from_euler_angles(0.1, -0.4, 1.2).into_inner();
        let prior = Pose::from_rt(r, nalgebra::Vector3::new(3.0, -2.0, 0.5));
        let priors = AxisStarts { each_way: 2, step_m: 1.25, margin: 0.0 }.priors(&prior);
        let shifts: Vec<f64> = priors.iter().map(|(d, _)| *d).collect();
        assert_eq!(shifts, [0.0, 1.25, -1.25, 2.5, -2.5]);
        assert_eq!(priors[0].1, prior);
        let axis = prior.rotation().transpose() * nalgebra::Vector3::z();
        for (d, moved) in &priors[1..] {
            let step = moved.camera_position_in_map() - prior.camera_position_in_map();
            assert!((step - *d * axis).norm() < 1e-12, "{step:?} for {d}");
            assert_eq!(moved.rotation(), prior.rotation());
        }
        assert_eq!(AxisStarts::NONE.priors(&prior), vec![(0.0, prior)]);
        assert_eq!(AxisStarts::NONE.groups(), 1);
    }

    /// Each prior along the axis answers as a search of its own (its start kept when it
    /// outscores its trajectory); the groups' answers compete by alignment, the unmoved prior's
    /// with the margin.
    #[test]
    fn the_first_round_answers_with_the_best_group() {
        let rules = AnswerRules { bound: None, prior_competes: true, prior_margin: 0.0 };
        let group = |shift: f64, start_alignment: f32, end_alignment: f32| Hypothesis {
            start_axis_shift_m: shift,
            ..trajectory(shifted(shift), start_alignment, vec![step_to(shift + 1.0, end_alignment)], false)
        };
        // The prior's group ends at 0.5; the group 1.25 m ahead keeps its start (0.6 over 0.4);
        // the group behind ends at 0.55.
        let first = vec![group(0.0, 0.3, 0.5), group(1.25, 0.6, 0.4), group(-1.25, 0.2, 0.55)];
        assert_eq!(axis_groups(&first), vec![0..1, 1..2, 2..3]);
        assert_eq!(first_round_answer(&first, &shifted(0.0), rules, 0.0, 1), Answer::kept(1));
        assert_eq!(first_round_answer(&first, &shifted(0.0), rules, 0.25, 1), Answer::at(0, 1), "0.6 does not beat 0.5 + 0.25");
        assert_eq!(first_round_answer(&first, &shifted(0.0), rules, 0.0, 0), Answer::at(1, 0), "after no steps the starts compete");
        // One group: the answer as before (the prior kept, or its trajectory's end).
        assert_eq!(first_round_answer(&first[..1], &shifted(0.0), rules, 0.0, 1), Answer::at(0, 1));
        let kept = vec![group(0.0, 0.7, 0.5)];
        assert_eq!(first_round_answer(&kept, &shifted(0.0), rules, 0.0, 1), Answer::kept(0));
        assert_eq!(search_answer(&kept, &shifted(0.0), rules, 0.0, 1, true), Answer::kept(0));
        // With a bound, every visited pose of every group inside it competes: the start 1.25 m
        // ahead (0.6) answers, as a pose, not as a kept prior; a larger score outside the bound
        // does not.
        let bounded = AnswerRules { bound: Some(PriorBound { rotation_deg: 30.0, translation_m: 5.0 }), ..rules };
        assert_eq!(first_round_answer(&first, &shifted(0.0), bounded, 0.0, 1), Answer::at(1, 0));
        let mut far = first.clone();
        far[2].steps[0] = step_to(9.0, 0.9);
        assert_eq!(first_round_answer(&far, &shifted(0.0), bounded, 0.0, 1), Answer::at(1, 0));
    }

    #[test]
    fn the_tuning_defaults_are_the_flags_defaults() {
        let t = SearchTuning::default();
        assert_eq!((t.narrow_after, t.merge_duplicates, t.keep_prior, t.refine, t.polish, t.prior_margin, t.judge_zoom), (0, true, true, true, true, DEFAULT_PRIOR_MARGIN, DEFAULT_JUDGE_ZOOM));
    }

    #[test]
    fn a_challenger_wins_only_by_scoring_strictly_higher() {
        assert!(outscores(0.5, 0.4));
        assert!(!outscores(0.4, 0.4), "a draw keeps the incumbent");
        assert!(!outscores(0.3, 0.4));
        assert!(!outscores(f32::NAN, 0.4));
        assert!(outscores(0.1, f32::NAN));
    }

    #[test]
    fn the_best_score_wins_and_ties_go_to_the_earlier_start() {
        assert_eq!(best_of([0.2, 0.7, 0.5]), 1);
        assert_eq!(best_of([0.7, 0.7, 0.5]), 0);
        assert_eq!(best_of([f32::NAN, 0.1]), 1);
        assert_eq!(best_of([-1.0]), 0);
    }
}
