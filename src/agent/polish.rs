//! The continuous polish: after the search has chosen its answer, a pattern search on the
//! alignment score (`state::alignment`) around it, in steps finer than the policy's.
//!
//! Why: the policy moves in discrete steps and stops where its own reading of the observation
//! says, and the alignment score around that stop is sharper in heading than the policy is (and
//! sideways too on synthetic frames; on real ones the sideways moves win cases but do not reduce
//! the mean position error). Moves: turns about the camera's own centre (map vertical, or camera y for a
//! `camera_y` model) and shifts along the action frame's sideways axis (`tx`). Three passes of one
//! pattern search, where a move is kept when it scores strictly higher (first improvement, in the
//! order +yaw, −yaw, +lateral, −lateral) and, when none does, the steps halve:
//! 1. the fine pass climbs the nearest peak: [`YAW_DEG`] and [`LATERAL_M`] at first, halving
//!    [`HALVINGS`] times;
//! 2. the wide pass looks beyond it in heading, turns only: [`WIDE_YAW_DEG`] at first, halving
//!    [`WIDE_HALVINGS`] times. Real answers are often short of the right heading by more than the
//!    fine steps reach; started wide instead, the search leaves a near peak for a far one that a
//!    first wide step happens to outscore, and loses heading accuracy on synthetic frames;
//! 3. when the wide pass moved, the fine pass again from there.
//!
//! At most [`MAX_SCORES`] poses are scored, never more than [`REACH`] from the search's answer.
//! Along the optical axis it does not move: on real frames the alignment score is nearly flat
//! there, and polishing forward made the answers worse (docs/evaluation.md, "A continuous
//! polish"). With a prior bound the polish stays inside it.
//!
//! The search polishes more than its answer: [`choose`] lets the answer and the final poses of
//! other hypotheses apart from it (`search::polish_candidates`) each climb their nearest peak
//! with the fine pass, and polishes on the one whose peak scores highest (with the judge's views,
//! `SearchConfig::judge_zoom`, by the score averaged over the views). The candidates climb in
//! parallel (rayon); each climb is sequential, so the poses scored and the answer do not depend on
//! the threads.

use nalgebra::Point3;
use rayon::prelude::*;

use crate::geometry::actions::apply_motion;
use crate::geometry::{ActionFrame, Pose};

use super::search::{PriorBound, outscores};

/// The fine pass's first turn, degrees.
pub const YAW_DEG: f64 = 1.0;
/// The fine pass's first sideways shift, metres.
pub const LATERAL_M: f64 = 0.5;
/// How many times the fine pass's steps halve (the last ones: 0.125° and 0.0625 m).
pub const HALVINGS: u32 = 3;
/// The wide pass's first turn, degrees (turns only).
pub const WIDE_YAW_DEG: f64 = 8.0;
/// How many times the wide pass's turn halves (the last one: 1°).
pub const WIDE_HALVINGS: u32 = 3;
/// Most poses scored by the polish of one pose, all passes together (the polished choice climbs
/// each candidate within its own budget).
pub const MAX_SCORES: usize = 80;

/// How far the polish may move the answer (geodesic angle, camera centre distance): a local
/// refinement, not a search. Chosen on the real-train validation split's three regimes (288
/// cases, model v11): 20° / 3 m with the wide pass registers 200, as many as 35°; the fine pass
/// alone within 10° / 3 m registers 195 (docs/evaluation.md, "A continuous polish" and "A wider
/// turn for the polish").
pub const REACH: PriorBound = PriorBound { rotation_deg: 20.0, translation_m: 3.0 };

/// What the polish did to an answer.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Polish {
    /// The pose polished (the search's answer, or the hypothesis the polished choice took
    /// instead), and its alignment score.
    pub from: Pose,
    pub from_alignment: f32,
    /// The polished answer and its alignment score (`from` and `from_alignment` when no move
    /// scored higher).
    pub camera_from_map: Pose,
    pub alignment: f32,
    /// Poses scored, every candidate's together.
    pub scores: usize,
    /// Poses polished to choose the answer ([`choose`]; 1 for [`polish`]).
    pub candidates: usize,
    /// The highest alignment score another candidate's peak reached (the fine pass), `None` with
    /// one candidate: how clearly the answer's peak won the choice (the calibrator's
    /// `peak_margin`).
    pub runner_up_alignment: Option<f32>,
}

/// Polishes `from` (camera_from_map, scoring `from_alignment`) on `score`, turning and shifting in
/// `frame`'s axes; every pose it moves to lies within `bound` (the prior and its bound) when one
/// is given. A NaN score never wins.
/// [`choose`] with the one candidate.
pub fn polish(frame: ActionFrame, from: Pose, from_alignment: f32, bound: Option<(&Pose, PriorBound)>, score: impl Fn(&Pose) -> f32 + Sync) -> Polish {
    let (_, polished) = choose(frame, &[(from, from_alignment)], bound, |_, _, alignment| alignment, |_, p| score(p)).expect("one candidate");
    polished
}

/// The polished choice: every candidate (camera_from_map and its alignment score; the search's
/// own answer first) climbs its nearest peak (the fine pass, within its own [`REACH`] and
/// `bound`); the one whose peak scores highest by `judge` (candidate, pose, alignment; the first on a draw,
/// never a NaN) goes on with the wide pass (and the fine pass again if that moved), as
/// [`polish`] would. `score(c, pose)` scores a pose near candidate `c`, called from several
/// threads at once (the candidates climb in parallel). Returns the candidate chosen and its
/// polish (`scores` counts every candidate's).
///
/// Why: the search ranks its hypotheses by their final poses' scores, and a final pose is often
/// short of its own peak by more than the peaks differ; compared at their peaks, the hypothesis
/// near the truth wins more often on real frames (docs/evaluation.md, "A polished choice").
pub fn choose(
    frame: ActionFrame,
    candidates: &[(Pose, f32)],
    bound: Option<(&Pose, PriorBound)>,
    judge: impl Fn(usize, &Pose, f32) -> f32,
    score: impl Fn(usize, &Pose) -> f32 + Sync,
) -> Option<(usize, Polish)> {
    let climbs: Vec<Climb> = candidates
        .par_iter()
        .enumerate()
        .map(|(c, &(from, from_alignment))| {
            let mut climb = Climb::new(frame, from, from_alignment, bound);
            climb.run(YAW_DEG, LATERAL_M, HALVINGS, &mut |p: &Pose| score(c, p));
            climb
        })
        .collect();
    let scores: usize = climbs.iter().map(|climb| climb.scores).sum();
    let peaks: Vec<f32> = climbs.iter().map(|climb| climb.best).collect();
    let mut best: Option<(usize, Climb, f32)> = None;
    for (c, climb) in climbs.into_iter().enumerate() {
        let judged = judge(c, &climb.pose, climb.best);
        if best.as_ref().is_none_or(|(_, _, b)| outscores(judged, *b)) {
            best = Some((c, climb, judged));
        }
    }
    let (c, mut climb, _) = best?;
    let before = climb.scores;
    climb.widen(&mut |p: &Pose| score(c, p));
    let runner_up = peaks.iter().enumerate().filter(|&(i, _)| i != c).map(|(_, &a)| a).reduce(|a, b| if outscores(b, a) { b } else { a });
    Some((c, climb.result(candidates.len(), scores + climb.scores - before, runner_up)))
}

/// The polish's pattern search: the pose reached, its score, and the poses scored so far.
struct Climb<'a> {
    frame: ActionFrame,
    /// The pose polished, the centre of [`REACH`].
    from: Pose,
    from_alignment: f32,
    pose: Pose,
    best: f32,
    scores: usize,
    bound: Option<(&'a Pose, PriorBound)>,
}

impl<'a> Climb<'a> {
    fn new(frame: ActionFrame, from: Pose, from_alignment: f32, bound: Option<(&'a Pose, PriorBound)>) -> Self {
        Self { frame, from, from_alignment, pose: from, best: from_alignment, scores: 0, bound }
    }

    /// From the fine pass's peak: the wide pass, and the fine pass again when it moved.
    fn widen(&mut self, score: &mut impl FnMut(&Pose) -> f32) {
        let peak = self.pose;
        self.run(WIDE_YAW_DEG, 0.0, WIDE_HALVINGS, score);
        if self.pose != peak {
            self.run(YAW_DEG, LATERAL_M, HALVINGS, score);
        }
    }

    fn result(&self, candidates: usize, scores: usize, runner_up_alignment: Option<f32>) -> Polish {
        Polish { from: self.from, from_alignment: self.from_alignment, camera_from_map: self.pose, alignment: self.best, scores, candidates, runner_up_alignment }
    }

    /// Climbs from the pose reached: turns of `yaw_deg` and, unless `lateral_m` is 0, sideways
    /// shifts of `lateral_m`; a move is kept when it scores strictly higher (first improvement);
    /// when none does, both steps halve, `halvings` times.
    fn run(&mut self, mut yaw_deg: f64, mut lateral_m: f64, halvings: u32, score: &mut impl FnMut(&Pose) -> f32) {
        let mut level = 0;
        while level <= halvings && self.scores < MAX_SCORES {
            let mut improved = false;
            let moves = [(yaw_deg, 0.0), (-yaw_deg, 0.0), (0.0, lateral_m), (0.0, -lateral_m)];
            for (turn, shift) in &moves[..if lateral_m > 0.0 { 4 } else { 2 }] {
                if self.scores >= MAX_SCORES {
                    break;
                }
                let centre = Point3::from(self.pose.camera_position_in_map());
                let candidate = apply_motion(self.frame, &self.pose, &centre, *turn, *shift, 0.0);
                if !REACH.contains(&self.from, &candidate) || self.bound.is_some_and(|(prior, b)| !b.contains(prior, &candidate)) {
                    continue;
                }
                self.scores += 1;
                let s = score(&candidate);
                if outscores(s, self.best) {
                    (self.pose, self.best, improved) = (candidate, s, true);
                }
            }
            if !improved {
                (yaw_deg, lateral_m) = (yaw_deg / 2.0, lateral_m / 2.0);
                level += 1;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::PoseError;
    use nalgebra::{Matrix3, Vector3};

    /// A level camera (y = map down, looking along map +x) at `x_m`, `y_m`, turned by `yaw_deg`.
    fn camera(x_m: f64, y_m: f64, yaw_deg: f64) -> Pose {
        let level = Pose::from_rt(Matrix3::new(0.0, -1.0, 0.0, 0.0, 0.0, -1.0, 1.0, 0.0, 0.0), Vector3::zeros());
        let r = apply_motion(ActionFrame::MapZ, &level, &Point3::origin(), yaw_deg, 0.0, 0.0).rotation();
        Pose::from_rt(r, -(r * Vector3::new(x_m, y_m, 0.0)))
    }

    /// A smooth score peaking at `truth`, flat along the heading like a real frame's.
    fn score_near(truth: Pose) -> impl Fn(&Pose) -> f32 + Sync {
        move |p: &Pose| {
            let e = PoseError::between(p, &truth);
            let (right, _) = crate::geometry::actions::ground_heading(&truth);
            let sideways = (p.camera_position_in_map() - truth.camera_position_in_map()).dot(&right);
            (1.0 / (1.0 + (e.rre_geodesic_deg / 2.0).powi(2) + (sideways / 0.5).powi(2))) as f32
        }
    }

    #[test]
    fn climbs_to_the_peak_in_heading_and_sideways() {
        let truth = camera(3.0, -2.0, 20.0);
        // 1.7° and 0.8 m sideways off (about the camera's own centre).
        let start = apply_motion(ActionFrame::MapZ, &truth, &Point3::from(truth.camera_position_in_map()), 1.7, 0.8, 0.0);
        let f = score_near(truth);
        let s0 = f(&start);
        let p = polish(ActionFrame::MapZ, start, s0, None, score_near(truth));
        let angle = PoseError::between(&p.camera_from_map, &truth).rre_geodesic_deg;
        let distance = (p.camera_from_map.camera_position_in_map() - truth.camera_position_in_map()).norm();
        assert!(p.alignment > s0 && p.scores <= MAX_SCORES);
        assert!(angle < 0.2 && distance < 0.1, "{angle} deg, {distance} m");
        assert_eq!((p.from, p.from_alignment), (start, s0));
    }

    #[test]
    fn keeps_the_answer_when_nothing_scores_higher_and_stays_inside_a_bound() {
        let truth = camera(0.0, 0.0, 0.0);
        let p = polish(ActionFrame::MapZ, truth, 1.0, None, score_near(truth));
        assert_eq!((p.camera_from_map, p.alignment), (truth, 1.0));
        // The peak lies 3° outside a 10° bound around the prior: the polish stops at the edge.
        let prior = camera(0.0, 0.0, -10.0);
        let peak = camera(0.0, 0.0, 3.0);
        let bound = PriorBound { rotation_deg: 10.0, translation_m: 5.0 };
        let f = score_near(peak);
        let p = polish(ActionFrame::MapZ, prior, f(&prior), Some((&prior, bound)), score_near(peak));
        assert!(bound.contains(&prior, &p.camera_from_map));
        assert!(PoseError::between(&p.camera_from_map, &prior).rre_geodesic_deg > 9.0);
    }

    #[test]
    fn a_nan_score_never_wins() {
        let start = camera(0.0, 0.0, 0.0);
        let p = polish(ActionFrame::MapZ, start, 0.5, None, |_| f32::NAN);
        assert_eq!(p.camera_from_map, start);
        // The fine pass's four moves and the wide pass's two turns at every level, nothing more.
        assert_eq!(p.scores, 4 * (HALVINGS as usize + 1) + 2 * (WIDE_HALVINGS as usize + 1));
    }

    /// Peaks in heading: the highest of `score_near` each, scaled by its height.
    fn peaks(peaks: Vec<(Pose, f32)>) -> impl Fn(&Pose) -> f32 + Sync {
        move |p: &Pose| peaks.iter().map(|&(peak, height)| height * score_near(peak)(p)).fold(f32::MIN, f32::max)
    }

    #[test]
    fn the_wide_pass_turns_to_a_higher_peak_beyond_the_local_one() {
        // The answer sits 0.5° off a local peak; the higher one lies 8.5° further round.
        let (near, far) = (camera(0.0, 0.0, 0.0), camera(0.0, 0.0, 8.5));
        let start = camera(0.0, 0.0, -0.5);
        let s0 = peaks(vec![(near, 0.8), (far, 1.0)])(&start);
        let p = polish(ActionFrame::MapZ, start, s0, None, peaks(vec![(near, 0.8), (far, 1.0)]));
        let angle = PoseError::between(&p.camera_from_map, &far).rre_geodesic_deg;
        assert!(angle < 0.2 && p.scores <= MAX_SCORES, "{angle} deg from the higher peak, {} poses", p.scores);
    }

    #[test]
    fn never_turns_beyond_the_reach() {
        // A score that keeps rising as the view turns away (from a heading 90° behind).
        let away = camera(0.0, 0.0, -90.0);
        let rising = move |p: &Pose| PoseError::between(p, &away).rre_geodesic_deg as f32;
        let start = camera(0.0, 0.0, 0.0);
        let p = polish(ActionFrame::MapZ, start, rising(&start), None, rising);
        let turned = PoseError::between(&p.camera_from_map, &start).rre_geodesic_deg;
        assert!(turned <= REACH.rotation_deg && turned > REACH.rotation_deg - 1.0, "turned {turned} deg");
    }

    #[test]
    fn the_wide_pass_keeps_a_local_peak_that_scores_highest() {
        // The answer sits 1.5° off the highest peak; a lower one lies 8° beyond the answer, where
        // a wide first turn would land and climb. Climbing the near peak first keeps it there.
        let (near, far) = (camera(0.0, 0.0, 0.0), camera(0.0, 0.0, 9.5));
        let start = camera(0.0, 0.0, 1.5);
        let s0 = peaks(vec![(near, 1.0), (far, 0.9)])(&start);
        let p = polish(ActionFrame::MapZ, start, s0, None, peaks(vec![(near, 1.0), (far, 0.9)]));
        assert!(PoseError::between(&p.camera_from_map, &near).rre_geodesic_deg < 0.2);
    }

    #[test]
    fn the_choice_takes_the_candidate_whose_peak_scores_highest() {
        // The answer (candidate 0) scores higher where it stands, 5° off a peak of 0.8; the other
        // candidate stands 6° off a peak of 1.0, 90° round.
        let (low, high) = (camera(0.0, 0.0, 0.0), camera(0.0, 0.0, 90.0));
        let two = || peaks(vec![(low, 0.8), (high, 1.0)]);
        let candidates = [camera(0.0, 0.0, 1.0), camera(0.0, 0.0, 96.0)];
        let scored: Vec<(Pose, f32)> = candidates.iter().map(|p| (*p, two()(p))).collect();
        assert!(scored[0].1 > scored[1].1);
        let fs = [two(), two()];
        let (c, p) = choose(ActionFrame::MapZ, &scored, None, |_, _, a| a, |c, pose| fs[c](pose)).unwrap();
        assert_eq!((c, p.candidates, p.from), (1, 2, candidates[1]));
        assert!(PoseError::between(&p.camera_from_map, &high).rre_geodesic_deg < 0.2);
        // The scores of both candidates' climbs are counted.
        let alone = polish(ActionFrame::MapZ, candidates[1], scored[1].1, None, two());
        assert!(p.scores > alone.scores && p.alignment == alone.alignment && p.camera_from_map == alone.camera_from_map);
        // The runner-up is the other candidate's peak (0.8, reached from 1° off), not its start.
        let runner_up = p.runner_up_alignment.unwrap();
        assert!(runner_up > scored[0].1 && (runner_up - 0.8).abs() < 0.01, "{runner_up}");
        assert_eq!(alone.runner_up_alignment, None);
        // The judge decides: a margin for the first candidate keeps it.
        let (c, p) = choose(ActionFrame::MapZ, &scored, None, |_, pose, a| a + if PoseError::between(pose, &low).rre_geodesic_deg < 30.0 { 0.5 } else { 0.0 }, |c, pose| fs[c](pose)).unwrap();
        assert_eq!((c, p.from), (0, candidates[0]));
        assert!(PoseError::between(&p.camera_from_map, &low).rre_geodesic_deg < 0.2);
    }

    #[test]
    fn the_choice_is_the_same_on_one_thread_and_on_several() {
        // Five candidates near three peaks of different heights: the climbs run in parallel, the
        // choice and every count must not depend on which finishes first.
        let f = peaks(vec![(camera(0.0, 0.0, 0.0), 0.8), (camera(0.0, 0.0, 95.0), 1.0), (camera(0.0, 0.0, -60.0), 0.9)]);
        let candidates: Vec<(Pose, f32)> = [1.5, 40.0, 92.0, 170.0, -57.0].iter().map(|&yaw| camera(0.3, -0.2, yaw)).map(|p| (p, f(&p))).collect();
        let on = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| choose(ActionFrame::MapZ, &candidates, None, |_, _, a| a, |_, p| f(p)))
        };
        let one = on(1).unwrap();
        assert_eq!(one.0, 2, "the highest peak's candidate");
        for threads in [2, 5] {
            assert_eq!(on(threads).unwrap(), one);
        }
    }

    #[test]
    fn the_choice_keeps_the_answer_on_a_draw_and_never_takes_a_nan() {
        let (a, b) = (camera(0.0, 0.0, 0.0), camera(0.0, 0.0, 120.0));
        let (c, p) = choose(ActionFrame::MapZ, &[(a, 0.5), (b, 0.5)], None, |_, _, s| s, |_, _| 0.5).unwrap();
        assert_eq!((c, p.camera_from_map, p.candidates), (0, a, 2));
        let (c, _) = choose(ActionFrame::MapZ, &[(a, 0.5), (b, f32::NAN)], None, |_, _, s| s, |c, _| if c == 0 { 0.5 } else { f32::NAN }).unwrap();
        assert_eq!(c, 0);
        let (_, p) = choose(ActionFrame::MapZ, &[(a, 0.5), (b, 0.25), (a, f32::NAN)], None, |_, _, s| s, |c, _| [0.5, 0.25, f32::NAN][c]).unwrap();
        assert_eq!(p.runner_up_alignment, Some(0.25), "a NaN peak is never the runner-up over a number");
        assert!(choose(ActionFrame::MapZ, &[], None, |_, _, s| s, |_, _| 0.5).is_none());
    }
}
