//! The continuous polish: after the search has chosen its answer, a pattern search on the
//! alignment score (`state::alignment`) around it, in steps finer than the policy's.
//!
//! Why: the policy moves in discrete steps and stops where its own reading of the observation
//! says, and the alignment score around that stop is sharper in heading than the policy is (and
//! sideways too on synthetic frames; on real ones the sideways moves win cases but do not reduce
//! the mean position error). Moves: turns about the camera's own centre (map vertical, or camera y for a
//! `camera_y` model) and shifts along the action frame's sideways axis (`tx`), of [`YAW_DEG`] and
//! [`LATERAL_M`] at first; a move is kept when it scores strictly higher (first improvement, in
//! the order +yaw, −yaw, +lateral, −lateral); when none does, both steps halve, [`HALVINGS`]
//! times; at most [`MAX_SCORES`] poses are scored. Along the optical axis it does not move: on
//! real frames the alignment score is nearly flat there, and polishing forward made the answers
//! worse (docs/evaluation.md, "A continuous polish"). With a prior bound the polish stays inside
//! it.

use nalgebra::Point3;

use crate::geometry::actions::apply_motion;
use crate::geometry::{ActionFrame, Pose};

use super::search::{PriorBound, outscores};

/// The first turn, degrees.
pub const YAW_DEG: f64 = 1.0;
/// The first sideways shift, metres.
pub const LATERAL_M: f64 = 0.5;
/// How many times both steps halve (the last ones: 0.125° and 0.0625 m).
pub const HALVINGS: u32 = 3;
/// Most poses scored by one polish.
pub const MAX_SCORES: usize = 60;

/// How far the polish may move the answer (geodesic angle, camera centre distance): a local
/// refinement, not a search. Chosen on the real-train validation split: 10° / 3 m registers one
/// case fewer of 288 than no limit, 5° / 1.5 m three fewer
/// (docs/evaluation.md, "A continuous polish").
pub const REACH: PriorBound = PriorBound { rotation_deg: 10.0, translation_m: 3.0 };

/// What the polish did to an answer.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Polish {
    /// The search's answer before the polish, and its alignment score.
    pub from: Pose,
    pub from_alignment: f32,
    /// The polished answer and its alignment score (`from` and `from_alignment` when no move
    /// scored higher).
    pub camera_from_map: Pose,
    pub alignment: f32,
    /// Poses scored.
    pub scores: usize,
}

/// Polishes `from` (camera_from_map, scoring `from_alignment`) on `score`, turning and shifting in
/// `frame`'s axes; every pose it moves to lies within `bound` (the prior and its bound) when one
/// is given. A NaN score never wins.
pub fn polish(frame: ActionFrame, from: Pose, from_alignment: f32, bound: Option<(&Pose, PriorBound)>, mut score: impl FnMut(&Pose) -> f32) -> Polish {
    let (mut yaw, mut lateral) = (YAW_DEG, LATERAL_M);
    let (mut pose, mut best) = (from, from_alignment);
    let mut scores = 0;
    let mut level = 0;
    while level <= HALVINGS && scores < MAX_SCORES {
        let mut improved = false;
        for (turn, shift) in [(yaw, 0.0), (-yaw, 0.0), (0.0, lateral), (0.0, -lateral)] {
            if scores >= MAX_SCORES {
                break;
            }
            let centre = Point3::from(pose.camera_position_in_map());
            let candidate = apply_motion(frame, &pose, &centre, turn, shift, 0.0);
            if !REACH.contains(&from, &candidate) || bound.is_some_and(|(prior, b)| !b.contains(prior, &candidate)) {
                continue;
            }
            scores += 1;
            let s = score(&candidate);
            if outscores(s, best) {
                (pose, best, improved) = (candidate, s, true);
            }
        }
        if !improved {
            (yaw, lateral) = (yaw / 2.0, lateral / 2.0);
            level += 1;
        }
    }
    Polish { from, from_alignment, camera_from_map: pose, alignment: best, scores }
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
    fn score_near(truth: Pose) -> impl FnMut(&Pose) -> f32 {
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
        let mut f = score_near(truth);
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
        let mut f = score_near(peak);
        let p = polish(ActionFrame::MapZ, prior, f(&prior), Some((&prior, bound)), score_near(peak));
        assert!(bound.contains(&prior, &p.camera_from_map));
        assert!(PoseError::between(&p.camera_from_map, &prior).rre_geodesic_deg > 9.0);
    }

    #[test]
    fn a_nan_score_never_wins() {
        let start = camera(0.0, 0.0, 0.0);
        let p = polish(ActionFrame::MapZ, start, 0.5, None, |_| f32::NAN);
        assert_eq!(p.camera_from_map, start);
        assert_eq!(p.scores, 4 * (HALVINGS as usize + 1));
    }
}
