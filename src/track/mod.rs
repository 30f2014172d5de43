//! Following a drive: localize the frames of a sequence in order, each from the previous
//! estimate moved by a constant-velocity prediction.
//!
//! - The first frame starts from a coarse prior (GNSS-like: [`coarse_prior`]) and runs the full
//!   multi-start search (a cold localize).
//! - Every later frame starts from the [`predict`]ed pose (the last estimate moved by the last
//!   measured motion per frame, [`last_motion`]: a step from a dead-reckoned frame, or into a
//!   fallback after a tracked frame, is a correction, not motion) and runs a small search (by default
//!   one start, three policy steps) from it and from it moved along its optical axis by
//!   ±k·[`TrackConfig::axis_step_m`], k = 1..=[`TrackConfig::axis_starts`], in one request
//!   (`agent::AxisStarts`: each shifted prior searched as a request of its own would be, the
//!   answer whose alignment score is highest kept, the prediction's own with
//!   [`TrackConfig::axis_margin`] added). Why: the small search corrects heading and sideways
//!   errors but does not move the camera along its optical axis, and a constant-velocity
//!   prediction is off exactly there (the speed is unknown at the second frame, and noisy
//!   after); the alignment score does peak along the axis where the policy does not move
//!   (docs/tracking.md, "Starts along the optical axis").
//! - That answer is kept when it is trusted: `localized` (the model set's calibrated verdict,
//!   `model::calibrator`) and its confidence score (`agent::Confidence::score` = sqrt(frustum
//!   IoU × the last step's policy certainty), in [0, 1]) at least
//!   [`TrackConfig::fallback_below`]. Otherwise the frame is localized again with the full search
//!   from the prior the small search's answer started from ([`Mode::Fallback`]); when that answer is
//!   not `localized` either, the frame is dead-reckoned: its estimate is the prediction
//!   ([`Mode::DeadReckoning`]).
//! - A model set without a calibrator gives no verdict (`p_registered: None`): then the score
//!   alone decides the small search, and the full search's answer is always kept (the loop as it
//!   was before the calibrator).
//! - With [`Odometry`] (a fleet's wheel or visual odometry: camera poses in a frame of its own),
//!   the prediction takes the camera's motion from it instead of repeating the last measured one,
//!   and a dead-reckoned frame follows it: the loop is otherwise the same.
//!
//! The loop does no I/O and knows nothing of HTTP or the server: a [`FrameLocalizer`] answers one
//! frame (`cmr-agent track` implements it with `serving::Localizer`, the path
//! `cmr-agent localize` and `POST /v1/maps/{id}/localize` share). Errors of the trajectory
//! ([`metrics`]) and the files written from it ([`output`], [`plot`]) live beside it.
//!
//! Poses are camera_from_map of image_2 (OpenCV camera frame; map frame z-up, see
//! `kitti::Sequence::map_from_lidar` for a KITTI-layout sequence's map frame), metres.

pub mod metrics;
pub mod output;
pub mod plot;

use nalgebra::{Rotation3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

use crate::agent::AxisStarts;
use crate::geometry::Pose;
use crate::model::Verdict;

/// How large one localization's search is: starts of the multi-start search and policy steps
/// per start (the localize request's `hypotheses` and `max_iterations`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct SearchSize {
    pub hypotheses: u32,
    pub max_iterations: u32,
}

/// The tracker's settings.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct TrackConfig {
    /// The search of a tracked frame (from the prediction).
    pub tracked: SearchSize,
    /// The search of the first frame and of a fallback.
    pub full: SearchSize,
    /// A tracked answer whose confidence score is below this (or that is not `localized`) falls
    /// back to the full search. Anything above 1 always does.
    pub fallback_below: f32,
    /// Starts of the small search from the prediction moved forward and back along its optical
    /// axis, each way (0: the prediction alone; `agent::AxisStarts::each_way`).
    pub axis_starts: u32,
    /// Their spacing, metres.
    pub axis_step_m: f64,
    /// What the prediction's own answer adds to its alignment score when the answers from the
    /// shifted priors are compared: a start along the axis must outscore it by more than this.
    pub axis_margin: f32,
}

impl TrackConfig {
    /// The small search's starts along the optical axis.
    pub fn axis(&self) -> AxisStarts {
        AxisStarts { each_way: self.axis_starts as usize, step_m: self.axis_step_m, margin: self.axis_margin }
    }
}

/// One frame's answer from a [`FrameLocalizer`].
#[derive(Debug, Clone, Copy)]
pub struct FrameAnswer {
    /// Estimated camera_from_map.
    pub camera_from_map: Pose,
    /// `agent::Confidence::score` of the answer, in [0, 1].
    pub confidence: f32,
    /// Its alignment score (`agent::state::alignment`): how a search with starts along the axis
    /// compares the answers from its shifted priors.
    pub alignment: f32,
    /// The calibrated verdict (`p_registered: None, localized: false` without a calibrator).
    pub verdict: Verdict,
    /// Steps of the chosen hypothesis.
    pub iterations: usize,
    /// Where the chosen hypothesis's prior lay along the optical axis of the prior asked for
    /// (metres, forward positive; 0 without axis starts).
    pub axis_shift_m: f64,
    /// Time the localization took as the caller sees it (the localize call, or the HTTP round
    /// trip), milliseconds; reading the frame from disk is not part of it.
    pub latency_ms: f64,
}

/// Localizes frame `position` (0-based position in the drive, not the file index) from `prior`
/// with a search of `search`'s size and `axis`'s starts along the optical axis (one request).
/// `Ok(None)`: the localizer refused the prior itself (the server's 422 for a request's values:
/// e.g. the prior, or a start along its axis, outside the mapped area or its crop too sparse),
/// which a drifting track can reach; the tracker goes on without that search. `Err`: anything
/// else (unreadable frame, model failure), which stops the drive.
pub trait FrameLocalizer {
    fn localize(&mut self, position: usize, prior: &Pose, search: SearchSize, axis: AxisStarts) -> anyhow::Result<Option<FrameAnswer>>;
}

/// How a frame was localized.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Mode {
    /// The first frame: the full search from the coarse prior.
    Cold,
    /// The small search from the prediction was confident enough.
    Tracked,
    /// The small search was not; the full search from the prediction answered.
    Fallback,
    /// Neither search was `localized`: the estimate is the prediction itself.
    DeadReckoning,
}

impl Mode {
    pub fn name(self) -> &'static str {
        match self {
            Mode::Cold => "cold",
            Mode::Tracked => "tracked",
            Mode::Fallback => "fallback",
            Mode::DeadReckoning => "dead_reckoning",
        }
    }
}

/// One frame of a tracked drive.
#[derive(Debug, Clone, Copy)]
pub struct TrackedFrame {
    /// Position in the drive (0-based).
    pub position: usize,
    pub mode: Mode,
    /// Where the search started (camera_from_map).
    pub prior: Pose,
    /// The answer kept (camera_from_map).
    pub estimate: Pose,
    /// Confidence score of the kept answer (of the full search's for a dead-reckoned frame).
    pub confidence: f32,
    /// Its calibrated verdict (the full search's for a dead-reckoned frame).
    pub verdict: Verdict,
    /// Confidence score of the small search, for every frame after the first.
    pub tracked_confidence: Option<f32>,
    /// Steps of the kept answer's chosen hypothesis.
    pub iterations: usize,
    /// Sum of the localizations' latencies for this frame (the small search, and the full one on
    /// a fallback), ms.
    pub latency_ms: f64,
    /// Where the small search's answer started along the prediction's optical axis (metres,
    /// forward positive; `agent::AxisStarts::priors`); `None` for the first frame.
    pub axis_shift_m: Option<f64>,
}

/// Constant-velocity prediction of the next camera_from_map: the last estimate moved again by
/// the camera's `motion` per frame (M = T_j·T_{j−1}⁻¹ on camera_from_map, in the camera's own
/// frame; [`last_motion`]): T_k = M·T_{k−1}. Without a measured motion the camera is predicted to
/// stand still.
pub fn predict(motion: Option<&Pose>, last: &Pose) -> Pose {
    match motion {
        // Renormalised: a dead-reckoned drive composes predictions of predictions, and the
        // rotation's rounding error grows with every one (after 30 frames RᵀR was 1.2e-3 off the
        // identity, beyond what a request's prior may be).
        Some(motion) => motion.compose(last).renormalized(),
        None => *last,
    }
}

/// The camera's motion per frame, T_j·T_{j−1}⁻¹, from the latest pair of consecutive frames whose
/// estimates both answer the image and whose step is motion, not a correction ([`measures_motion`]);
/// `None` before there is one (the camera is then predicted to stand still).
///
/// Why not simply the last two estimates: a dead-reckoned estimate is the prediction itself, so the
/// step from it to the next answer carries every error the prediction piled up; and a fallback
/// after a tracked frame is there because the prediction missed, so its step is mostly the
/// correction of the frame before. Repeated as a velocity, such a jump ran the tracker away from
/// the car (README drive seed 8: a 4.4 m correction became a 7.9 m miss the frame after, 20 m by
/// frame 8; seed 9: a 16 m, 30° fallback correction became a turn of 27° per frame;
/// docs/tracking.md, "A velocity from motion, not corrections").
pub fn last_motion(done: &[TrackedFrame]) -> Option<Pose> {
    done.windows(2)
        .rev()
        .find(|pair| measures_motion(pair[0].mode, pair[1].mode))
        .map(|pair| pair[1].estimate.compose(&pair[0].estimate.inverse()))
}

/// Whether the step between two consecutive frames (modes `earlier`, `later`) measures the
/// camera's motion: neither is dead-reckoned, and the later one is a tracked answer, or a
/// fallback after a frame that was itself answered by the full search (cold or fallback).
pub fn measures_motion(earlier: Mode, later: Mode) -> bool {
    match (earlier, later) {
        (Mode::DeadReckoning, _) | (_, Mode::DeadReckoning) | (_, Mode::Cold) => false,
        (_, Mode::Tracked) => true,
        (Mode::Cold | Mode::Fallback, Mode::Fallback) => true,
        (Mode::Tracked, Mode::Fallback) => false,
    }
}

/// A drive's odometry: one camera pose per drive position (camera_from_odom, in a frame of the
/// odometry's own, e.g. a wheel-odometry or visual-odometry track started anywhere); only the
/// motions between consecutive positions are read, so that frame need not be the map's.
#[derive(Debug, Clone, PartialEq)]
pub struct Odometry {
    poses: Vec<Pose>,
}

impl Odometry {
    /// `poses`: camera_from_odom of the same camera as the drive's images, one per position.
    pub fn new(poses: Vec<Pose>) -> Self {
        Self { poses }
    }

    /// Positions covered.
    pub fn len(&self) -> usize {
        self.poses.len()
    }

    pub fn is_empty(&self) -> bool {
        self.poses.is_empty()
    }

    /// The camera's motion into `position` from the position before, C_k·C_{k−1}⁻¹ (in the
    /// camera's own frame, as [`last_motion`]'s): the prediction T_k = motion·T_{k−1}.
    /// Panics for position 0 or beyond [`Odometry::len`].
    pub fn motion(&self, position: usize) -> Pose {
        self.poses[position].compose(&self.poses[position - 1].inverse())
    }

    /// The same odometry with every step's error a real one has, drawn from `seed`: the
    /// translation scaled by 1 + `noise_pct`/100 · n and the camera turned about its own y axis
    /// (the vertical of a level camera: a heading error) by `noise_deg` · n′ degrees, n and n′
    /// standard normal per step; the steps are then chained again from the first pose, so the
    /// errors pile up as odometry's drift does. Zero noise returns the poses unchanged.
    pub fn with_noise(&self, noise_pct: f64, noise_deg: f64, seed: u64) -> Self {
        if noise_pct == 0.0 && noise_deg == 0.0 {
            return self.clone();
        }
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut normal = || {
            // Box-Muller: one standard normal from two uniforms.
            let (u, v): (f64, f64) = (rng.random_range(f64::EPSILON..1.0), rng.random_range(0.0..1.0));
            (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
        };
        let mut poses = Vec::with_capacity(self.poses.len());
        for (k, pose) in self.poses.iter().enumerate() {
            if k == 0 {
                poses.push(*pose);
                continue;
            }
            let motion = self.motion(k);
            let scale = 1.0 + noise_pct / 100.0 * normal();
            let turn = Rotation3::from_axis_angle(&Vector3::y_axis(), (noise_deg * normal()).to_radians());
            let noisy = Pose::from_rt(turn.matrix() * motion.rotation(), motion.translation() * scale);
            poses.push(noisy.compose(&poses[k - 1]).renormalized());
        }
        Self { poses }
    }

    /// Odometry alone from `first` (camera_from_map at position 0): each later pose the one
    /// before moved by the odometry's motion, what a tracker that never registers would answer.
    pub fn dead_reckoned(&self, first: &Pose) -> Vec<Pose> {
        let mut poses = vec![*first];
        for position in 1..self.poses.len() {
            let next = predict(Some(&self.motion(position)), &poses[position - 1]);
            poses.push(next);
        }
        poses
    }
}

/// A GNSS-like prior: `truth` (camera_from_map) with the camera centre moved by exactly
/// `noise_m` metres in the map's ground plane (direction uniform) and its heading turned by
/// `noise_deg` degrees about the map's z axis through the camera centre (sign uniform); height,
/// pitch and roll are kept. Seeded: the same seed gives the same prior.
pub fn coarse_prior(truth: &Pose, noise_m: f64, noise_deg: f64, seed: u64) -> Pose {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let direction: f64 = rng.random_range(0.0..std::f64::consts::TAU);
    let yaw = if rng.random_bool(0.5) { noise_deg } else { -noise_deg }.to_radians();
    let centre = truth.camera_position_in_map();
    let moved = centre + Vector3::new(noise_m * direction.cos(), noise_m * direction.sin(), 0.0);
    // Q = T(moved) · Rz(yaw) · T(−centre) moves the camera in the map: map_from_camera' = Q · map_from_camera.
    let turn = Pose::ground_motion(yaw, 0.0, 0.0);
    let turned_centre = turn.rotation() * centre;
    let q = Pose::ground_motion(yaw, moved.x - turned_centre.x, moved.y - turned_centre.y);
    truth.compose(&q.inverse())
}

/// Follows a drive of `frames` frames: the first from `first_prior` with the full search, the
/// rest as the module doc says, each predicted with `odometry`'s motion when given (it must
/// cover the drive) and the constant-velocity one when not. `on_frame` sees each frame as soon
/// as it is done (progress). Errors: odometry shorter than the drive; the first error of
/// `localizer`, with the frame's position.
pub fn track(
    localizer: &mut dyn FrameLocalizer,
    frames: usize,
    first_prior: Pose,
    odometry: Option<&Odometry>,
    config: &TrackConfig,
    mut on_frame: impl FnMut(&TrackedFrame),
) -> anyhow::Result<Vec<TrackedFrame>> {
    use anyhow::Context;
    if let Some(odometry) = odometry.filter(|o| o.len() < frames) {
        anyhow::bail!("the odometry has {} poses for a drive of {frames} frames", odometry.len());
    }
    let mut done: Vec<TrackedFrame> = Vec::with_capacity(frames);
    for position in 0..frames {
        let at = || format!("frame {position} of the drive");
        let frame = if position == 0 {
            let answer = localizer
                .localize(0, &first_prior, config.full, AxisStarts::NONE)
                .with_context(at)?
                .ok_or_else(|| anyhow::anyhow!("the first frame's prior was refused (outside the mapped area?)"))
                .with_context(at)?;
            tracked_frame(0, Mode::Cold, first_prior, &answer, None, answer.latency_ms)
        } else {
            let motion = match odometry {
                Some(odometry) => Some(odometry.motion(position)),
                None => last_motion(&done),
            };
            let prior = predict(motion.as_ref(), &done[position - 1].estimate);
            let small = localizer.localize(position, &prior, config.tracked, config.axis()).with_context(at)?;
            let small_ms = small.map_or(0.0, |s| s.latency_ms);
            let tracked = small.map(|s| (s.confidence, s.axis_shift_m));
            // Where the answer's start lay: a fallback starts there too.
            let start = small.map_or(prior, |s| AxisStarts::along_axis(&prior, s.axis_shift_m));
            match small {
                Some(small) if small.confidence >= config.fallback_below && (small.verdict.localized || small.verdict.p_registered.is_none()) => {
                    tracked_frame(position, Mode::Tracked, start, &small, tracked, small_ms)
                }
                _ => {
                    let full = localizer.localize(position, &start, config.full, AxisStarts::NONE).with_context(at)?;
                    let latency_ms = small_ms + full.map_or(0.0, |f| f.latency_ms);
                    match full {
                        Some(full) if full.verdict.localized || full.verdict.p_registered.is_none() => {
                            tracked_frame(position, Mode::Fallback, start, &full, tracked, latency_ms)
                        }
                        _ => {
                            // Both searches unsure, or refused: the prediction, with the full search's
                            // confidence and verdict when it answered (none and not localized when not).
                            let refused = FrameAnswer { camera_from_map: prior, confidence: 0.0, alignment: f32::NAN, verdict: Verdict::default(), iterations: 0, axis_shift_m: 0.0, latency_ms };
                            let predicted = FrameAnswer { camera_from_map: prior, ..full.unwrap_or(refused) };
                            tracked_frame(position, Mode::DeadReckoning, prior, &predicted, tracked, latency_ms)
                        }
                    }
                }
            }
        };
        on_frame(&frame);
        done.push(frame);
    }
    Ok(done)
}

/// `small`: the small search's confidence score and its answer's start's shift along the axis
/// (`None` for the first frame).
fn tracked_frame(position: usize, mode: Mode, prior: Pose, answer: &FrameAnswer, small: Option<(f32, f64)>, latency_ms: f64) -> TrackedFrame {
    TrackedFrame {
        position,
        mode,
        prior,
        estimate: answer.camera_from_map,
        confidence: answer.confidence,
        verdict: answer.verdict,
        tracked_confidence: small.map(|(c, _)| c),
        iterations: answer.iterations,
        latency_ms,
        axis_shift_m: small.map(|(_, d)| d),
    }
}

/// One cold localization: the full search from a coarse prior, as a reference for the tracked
/// latency and accuracy.
#[derive(Debug, Clone, Copy)]
pub struct ColdFrame {
    pub position: usize,
    pub prior: Pose,
    pub answer: FrameAnswer,
}

/// Localizes each of `positions` cold: the full search from [`coarse_prior`] of that frame's
/// `truth`, seeded with `seed + position`.
pub fn cold_reference(
    localizer: &mut dyn FrameLocalizer,
    positions: &[usize],
    truth: &[Pose],
    noise_m: f64,
    noise_deg: f64,
    seed: u64,
    config: &TrackConfig,
) -> anyhow::Result<Vec<ColdFrame>> {
    positions
        .iter()
        .map(|&position| {
            let prior = coarse_prior(&truth[position], noise_m, noise_deg, seed.wrapping_add(position as u64));
            let answer = localizer
                .localize(position, &prior, config.full, AxisStarts::NONE)?
                .ok_or_else(|| anyhow::anyhow!("frame {position}: the coarse prior was refused (outside the mapped area?)"))?;
            Ok(ColdFrame { position, prior, answer })
        })
        .collect()
}

/// `count` positions spread evenly over `0..frames` (first and last included when count ≥ 2).
pub fn spread(frames: usize, count: usize) -> Vec<usize> {
    let count = count.min(frames);
    match count {
        0 => vec![],
        1 => vec![frames / 2],
        _ => (0..count).map(|i| i * (frames - 1) / (count - 1)).collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::PoseError;

    /// A drive at constant speed and turn rate (1 m and 0.5° per frame): camera_from_map truths.
    fn drive(frames: usize) -> Vec<Pose> {
        let rig = Pose::from_rt(
            nalgebra::Matrix3::new(0.0, -1.0, 0.0, 0.0, 0.0, -1.0, 1.0, 0.0, 0.0),
            Vector3::new(0.0, -0.08, -0.27),
        );
        let step = Pose::ground_motion(0.5f64.to_radians(), 1.0, 0.1);
        let mut map_from_lidar = Pose::identity();
        let mut truth = Vec::new();
        for _ in 0..frames {
            truth.push(rig.compose(&map_from_lidar.inverse()));
            map_from_lidar = map_from_lidar.compose(&step);
        }
        truth
    }

    /// A drive dead-reckoned for 200 frames (each prediction from the two before it) stays a
    /// pose a request accepts as its prior: rounding does not pile up in the rotation.
    #[test]
    fn a_long_chain_of_predictions_stays_a_rotation() {
        let truth = drive(2);
        let (motion, mut last) = (truth[1].compose(&truth[0].inverse()), truth[1]);
        for _ in 0..200 {
            last = predict(Some(&motion), &last);
        }
        Pose::from_matrix(&last.to_rows()).expect("a valid prior after 200 predictions");
    }

    /// Answers with the truth when the prior is within `reach_m` of it, else with the prior,
    /// whose confidence is then low: a stand-in for the agent with a basin of attraction.
    struct Basin {
        truth: Vec<Pose>,
        reach_m: f64,
        calls: Vec<(usize, SearchSize, usize)>,
        /// Gives a verdict (localized when it reached the truth); else none, like a model set
        /// without a calibrator.
        calibrated: bool,
        /// Refuses a search any of whose priors has its camera beyond this map x (`Ok(None)`,
        /// like the server's 422 for a prior outside the mapped area).
        map_x_max: Option<f64>,
    }

    impl Basin {
        /// One search from `prior`.
        fn answer(&self, position: usize, prior: &Pose, search: SearchSize) -> FrameAnswer {
            let truth = self.truth[position];
            let off = (prior.camera_position_in_map() - truth.camera_position_in_map()).norm();
            // The full search reaches 3 times as far.
            let reach = if search.hypotheses > 1 { 3.0 * self.reach_m } else { self.reach_m };
            let (pose, confidence) = if off <= reach { (truth, 0.9) } else { (*prior, 0.1) };
            let verdict = match self.calibrated {
                true => Verdict { p_registered: Some(confidence as f64), localized: confidence > 0.5 },
                false => Verdict::default(),
            };
            FrameAnswer { camera_from_map: pose, confidence, alignment: confidence, verdict, iterations: 3, axis_shift_m: 0.0, latency_ms: search.hypotheses as f64 }
        }
    }

    impl FrameLocalizer for Basin {
        /// With axis starts, one search from each shifted prior, the best alignment winning (the
        /// unmoved prior's with the margin), as `agent::search::first_round_answer` chooses; the
        /// latency counts every start.
        fn localize(&mut self, position: usize, prior: &Pose, search: SearchSize, axis: AxisStarts) -> anyhow::Result<Option<FrameAnswer>> {
            self.calls.push((position, search, axis.groups()));
            let off_map = |p: &Pose| self.map_x_max.is_some_and(|x| p.camera_position_in_map().x > x);
            if axis.priors(prior).iter().any(|(_, p)| off_map(p)) {
                return Ok(None);
            }
            let mut best: Option<(FrameAnswer, f32)> = None;
            for (d, start) in axis.priors(prior) {
                let answer = FrameAnswer { axis_shift_m: d, ..self.answer(position, &start, search) };
                let judged = answer.alignment + if d == 0.0 { axis.margin } else { 0.0 };
                if best.is_none_or(|(_, b)| judged > b) {
                    best = Some((answer, judged));
                }
            }
            let answer = best.expect("the prior is searched").0;
            Ok(Some(FrameAnswer { latency_ms: (search.hypotheses as usize * axis.groups()) as f64, ..answer }))
        }
    }

    const CONFIG: TrackConfig = TrackConfig {
        tracked: SearchSize { hypotheses: 1, max_iterations: 3 },
        full: SearchSize { hypotheses: 4, max_iterations: 10 },
        fallback_below: 0.5,
        axis_starts: 0,
        axis_step_m: 1.25,
        axis_margin: 0.0,
    };

    #[test]
    fn constant_velocity_continues_the_last_motion() {
        let truth = drive(4);
        let predicted = predict(Some(&truth[2].compose(&truth[1].inverse())), &truth[2]);
        // The drive's motion is constant, so the prediction is the next truth.
        let e = PoseError::between(&predicted, &truth[3]);
        assert!(e.rte_m < 1e-9 && e.rre_geodesic_deg < 1e-9, "{e:?}");
        assert_eq!(predict(None, &truth[2]), truth[2]);
    }

    /// The motion comes from the latest step between two answers that is not a correction: steps
    /// from or to a dead-reckoned frame and into a fallback after a tracked frame are passed over.
    #[test]
    fn the_motion_is_measured_between_answers_not_across_corrections() {
        let truth = drive(6);
        let frame = |position: usize, mode: Mode, estimate: Pose| TrackedFrame {
            position,
            mode,
            prior: estimate,
            estimate,
            confidence: 0.9,
            verdict: Verdict::default(),
            tracked_confidence: None,
            iterations: 3,
            latency_ms: 1.0,
            axis_shift_m: None,
        };
        let step = |a: &Pose, b: &Pose| b.compose(&a.inverse());
        let off = |pose: &Pose, metres: f64| pose.compose(&Pose::ground_motion(0.0, metres, 0.0).inverse());
        let mut done = vec![frame(0, Mode::Cold, truth[0])];
        assert_eq!(last_motion(&done), None, "one estimate: standing still");
        done.push(frame(1, Mode::Tracked, truth[1]));
        let walked = step(&truth[0], &truth[1]);
        assert_eq!(last_motion(&done), Some(walked));
        // A dead-reckoned frame 4 m off, then the fallback that corrects it: neither step is motion.
        done.push(frame(2, Mode::DeadReckoning, off(&truth[2], 4.0)));
        done.push(frame(3, Mode::Fallback, truth[3]));
        assert_eq!(last_motion(&done), Some(walked));
        done.push(frame(4, Mode::Tracked, truth[4]));
        assert_eq!(last_motion(&done), Some(step(&truth[3], &truth[4])));
        // A fallback after a tracked frame corrects it; fallbacks in a row are motion again.
        done.push(frame(5, Mode::Fallback, off(&truth[5], -3.0)));
        assert_eq!(last_motion(&done), Some(step(&truth[3], &truth[4])));
        assert!(measures_motion(Mode::Fallback, Mode::Fallback) && measures_motion(Mode::Cold, Mode::Fallback));
        assert!(!measures_motion(Mode::Tracked, Mode::Fallback) && !measures_motion(Mode::Fallback, Mode::DeadReckoning));
    }

    #[test]
    fn the_coarse_prior_is_exactly_as_far_off_as_asked_and_seeded() {
        let truth = drive(1)[0];
        let prior = coarse_prior(&truth, 5.0, 30.0, 7);
        let off = prior.camera_position_in_map() - truth.camera_position_in_map();
        assert!((off.norm() - 5.0).abs() < 1e-9 && off.z.abs() < 1e-9, "{off:?}");
        let turn = (prior.camera_heading_in_map_deg() - truth.camera_heading_in_map_deg()).abs();
        assert!((turn - 30.0).abs() < 1e-9, "{turn}");
        assert_eq!(prior, coarse_prior(&truth, 5.0, 30.0, 7));
        assert_ne!(prior, coarse_prior(&truth, 5.0, 30.0, 8));
    }

    #[test]
    fn tracks_with_small_searches_and_falls_back_when_unsure() {
        let truth = drive(6);
        // 1.5 m reach: every prediction is reached by the small search (frame 1's, standing
        // still, is 1 m behind; later ones are exact).
        let mut basin = Basin { truth: truth.clone(), reach_m: 1.5, calls: vec![], calibrated: false, map_x_max: None };
        let first = coarse_prior(&truth[0], 3.0, 0.0, 1);
        let frames = track(&mut basin, 6, first, None, &CONFIG, |_| {}).unwrap();
        assert_eq!(frames[0].mode, Mode::Cold);
        assert!(frames[1..].iter().all(|f| f.mode == Mode::Tracked));
        assert_eq!(basin.calls.len(), 6);
        assert_eq!((basin.calls[0].1, basin.calls[0].2), (CONFIG.full, 1));
        let e = PoseError::between(&frames[3].prior, &truth[3]);
        assert!(e.rte_m < 1e-9 && e.rre_geodesic_deg < 1e-9, "exact prediction from exact estimates: {e:?}");
        // 0.5 m reach (1.5 m for the full search): frame 1 (predicted standing still, 1 m off)
        // needs the full search.
        let mut basin = Basin { truth: truth.clone(), reach_m: 0.5, calls: vec![], calibrated: false, map_x_max: None };
        let first = coarse_prior(&truth[0], 1.0, 0.0, 1);
        let frames = track(&mut basin, 6, first, None, &CONFIG, |_| {}).unwrap();
        assert_eq!(frames[0].estimate, truth[0]);
        assert_eq!(frames[1].mode, Mode::Fallback);
        assert_eq!(frames[1].tracked_confidence, Some(0.1));
        assert_eq!(frames[1].estimate, truth[1]);
        assert_eq!(frames[1].latency_ms, 1.0 + 4.0, "both searches count");
        assert!(frames[2..].iter().all(|f| f.mode == Mode::Tracked));
        assert_eq!(basin.calls[1..3], [(1, CONFIG.tracked, 1), (1, CONFIG.full, 1)]);
    }

    /// With a verdict: an unlocalized small search falls back, and an unlocalized full search
    /// leaves the frame to dead reckoning (the prediction), counted as such.
    #[test]
    fn unlocalized_answers_fall_back_then_dead_reckon() {
        let truth = drive(5);
        // 0.5 m reach (1.5 m for the full search): frame 1's prediction (1 m off) needs the full
        // search; its answer is then exact, so later predictions are reached by the small one.
        let mut basin = Basin { truth: truth.clone(), reach_m: 0.5, calls: vec![], calibrated: true, map_x_max: None };
        let frames = track(&mut basin, 5, coarse_prior(&truth[0], 1.0, 0.0, 1), None, &CONFIG, |_| {}).unwrap();
        let modes: Vec<Mode> = frames.iter().map(|f| f.mode).collect();
        assert_eq!(modes, [Mode::Cold, Mode::Fallback, Mode::Tracked, Mode::Tracked, Mode::Tracked]);
        assert!(frames[1].verdict.localized && frames[1].verdict.p_registered == Some(0.9f32 as f64));
        // 0.2 m reach (0.6 m for the full search): frame 1 is out of both; it is dead-reckoned at
        // the prediction (the first estimate, standing still), and so is every later frame.
        let mut basin = Basin { truth: truth.clone(), reach_m: 0.2, calls: vec![], calibrated: true, map_x_max: None };
        let frames = track(&mut basin, 3, coarse_prior(&truth[0], 0.5, 0.0, 1), None, &CONFIG, |_| {}).unwrap();
        assert_eq!(frames[0].estimate, truth[0]);
        assert!(frames[1..].iter().all(|f| f.mode == Mode::DeadReckoning && f.estimate == f.prior && !f.verdict.localized));
        assert_eq!(frames[1].latency_ms, 1.0 + 4.0, "both searches count");
        assert_eq!(basin.calls.len(), 1 + 2 * 2);
        // Without a verdict the same drive keeps the full search's answers (as before the calibrator).
        let first = coarse_prior(&truth[0], 0.5, 0.0, 1);
        let mut basin = Basin { truth, reach_m: 0.2, calls: vec![], calibrated: false, map_x_max: None };
        let frames = track(&mut basin, 3, first, None, &CONFIG, |_| {}).unwrap();
        assert!(frames[1..].iter().all(|f| f.mode == Mode::Fallback));
    }

    /// Frame 1's prediction (standing still) is 1 m behind the truth: beyond a 0.5 m basin, so
    /// without starts along the axis the frame falls back; with one each way, the start 1 m ahead
    /// lands in the basin and wins on its alignment, and the frame is tracked.
    #[test]
    fn starts_along_the_axis_catch_an_unknown_speed() {
        let truth = drive(4);
        let axis = TrackConfig { axis_starts: 1, axis_step_m: 1.0, ..CONFIG };
        let mut basin = Basin { truth: truth.clone(), reach_m: 0.5, calls: vec![], calibrated: true, map_x_max: None };
        let frames = track(&mut basin, 4, coarse_prior(&truth[0], 1.0, 0.0, 1), None, &axis, |_| {}).unwrap();
        let modes: Vec<Mode> = frames.iter().map(|f| f.mode).collect();
        assert_eq!(modes, [Mode::Cold, Mode::Tracked, Mode::Tracked, Mode::Tracked]);
        assert_eq!(frames[1].estimate, truth[1]);
        let ahead = frames[1].prior.camera_position_in_map() - frames[0].estimate.camera_position_in_map();
        assert!((ahead.norm() - 1.0).abs() < 1e-9, "frame 1 started from the prediction moved 1 m: {ahead:?}");
        assert_eq!((frames[0].axis_shift_m, frames[1].axis_shift_m), (None, Some(1.0)));
        assert_eq!(frames[1].latency_ms, 3.0, "the three starts count");
        assert_eq!(basin.calls[1..], [(1, CONFIG.tracked, 3), (2, CONFIG.tracked, 3), (3, CONFIG.tracked, 3)], "one request per tracked frame");
        // A margin larger than the start ahead wins by (0.9 against 0.1) keeps the prediction's
        // answer, which then falls back.
        let wide = TrackConfig { axis_margin: 1.0, ..axis };
        let mut basin = Basin { truth: truth.clone(), reach_m: 0.5, calls: vec![], calibrated: true, map_x_max: None };
        let frames = track(&mut basin, 2, coarse_prior(&truth[0], 1.0, 0.0, 1), None, &wide, |_| {}).unwrap();
        assert_eq!((frames[1].mode, frames[1].prior), (Mode::Fallback, frames[0].estimate));
        // The same drive without them: frame 1 needs the full search.
        let first = coarse_prior(&truth[0], 1.0, 0.0, 1);
        let mut basin = Basin { truth, reach_m: 0.5, calls: vec![], calibrated: true, map_x_max: None };
        let frames = track(&mut basin, 2, first, None, &CONFIG, |_| {}).unwrap();
        assert_eq!(frames[1].mode, Mode::Fallback);
    }

    /// A drive that leaves the mapped area: a search the localizer refuses (a start along the
    /// axis beyond the map, then the prediction itself) does not stop the drive: the frame goes to
    /// the full search, then to dead reckoning. A refused first prior stops it, saying so.
    #[test]
    fn refused_priors_fall_back_then_dead_reckon_instead_of_stopping_the_drive() {
        let truth = drive(6);
        let axis = TrackConfig { axis_starts: 1, axis_step_m: 1.0, ..CONFIG };
        // Cameras at x ≈ 0.27 + k (frame k); the map ends at x = 3.5.
        let mut basin = Basin { truth: truth.clone(), reach_m: 0.5, calls: vec![], calibrated: true, map_x_max: Some(3.5) };
        let frames = track(&mut basin, 6, coarse_prior(&truth[0], 1.0, 0.0, 1), None, &axis, |_| {}).unwrap();
        let modes: Vec<Mode> = frames.iter().map(|f| f.mode).collect();
        assert_eq!(modes, [Mode::Cold, Mode::Tracked, Mode::Tracked, Mode::Fallback, Mode::DeadReckoning, Mode::DeadReckoning]);
        // Frame 3: its start 1 m ahead lies off the map, so the small search is refused; the full
        // search from the prediction (without axis starts) answers.
        assert_eq!((frames[3].tracked_confidence, frames[3].estimate, frames[3].latency_ms), (None, truth[3], 4.0));
        assert_eq!(basin.calls[3..5], [(3, CONFIG.tracked, 3), (3, CONFIG.full, 1)]);
        // Frames 4 and 5: the prediction itself is off the map; the estimate is the prediction.
        for f in &frames[4..] {
            assert!(f.estimate == f.prior && !f.verdict.localized && f.verdict.p_registered.is_none() && f.tracked_confidence.is_none(), "{f:?}");
        }
        let e = PoseError::between(&frames[4].estimate, &truth[4]);
        assert!(e.rte_m < 1e-9, "the motion before the fallback carries the prediction: {e:?}");
        let mut basin = Basin { truth: truth.clone(), reach_m: 0.5, calls: vec![], calibrated: true, map_x_max: Some(-1.0) };
        let e = track(&mut basin, 2, truth[0], None, &CONFIG, |_| {}).unwrap_err();
        assert!(format!("{e:#}").contains("frame 0 of the drive: the first frame's prior was refused"), "{e:#}");
    }

    /// The drive's poses in an odometry frame of its own (moved and turned against the map's).
    fn odometry_of(truth: &[Pose]) -> Odometry {
        let elsewhere = Pose::ground_motion(1.0, 40.0, -7.0);
        Odometry::new(truth.iter().map(|t| t.compose(&elsewhere)).collect())
    }

    /// Exact odometry predicts every frame exactly, frame 1 included (which the constant-velocity
    /// prediction has standing still), and its dead reckoning from the first truth is the drive.
    #[test]
    fn odometry_predicts_the_motion_from_the_second_frame_on() {
        let truth = drive(5);
        let odometry = odometry_of(&truth);
        // 0.5 m reach: frame 1's constant-velocity prediction (1 m behind) falls back; with odometry
        // every frame is tracked from an exact prediction.
        let mut basin = Basin { truth: truth.clone(), reach_m: 0.5, calls: vec![], calibrated: true, map_x_max: None };
        let frames = track(&mut basin, 5, coarse_prior(&truth[0], 1.0, 0.0, 1), Some(&odometry), &CONFIG, |_| {}).unwrap();
        assert!(frames[1..].iter().all(|f| f.mode == Mode::Tracked), "{:?}", frames.iter().map(|f| f.mode).collect::<Vec<_>>());
        for (f, t) in frames.iter().zip(&truth).skip(1) {
            let e = PoseError::between(&f.prior, t);
            assert!(e.rte_m < 1e-9 && e.rre_geodesic_deg < 1e-9, "frame {}: {e:?}", f.position);
        }
        for (est, t) in odometry.dead_reckoned(&truth[0]).iter().zip(&truth) {
            let e = PoseError::between(est, t);
            assert!(e.rte_m < 1e-9 && e.rre_geodesic_deg < 1e-9, "{e:?}");
        }
        let short = Odometry::new(odometry.poses[..4].to_vec());
        let e = track(&mut basin, 5, truth[0], Some(&short), &CONFIG, |_| {}).unwrap_err();
        assert!(e.to_string().contains("4 poses for a drive of 5 frames"), "{e}");
    }

    /// Neither search reaches the truth (a first answer 1 m off, 0.2 m reach): every frame is
    /// dead-reckoned, along the odometry's motion rather than standing still.
    #[test]
    fn dead_reckoning_follows_the_odometry() {
        let truth = drive(4);
        let odometry = odometry_of(&truth);
        let mut basin = Basin { truth: truth.clone(), reach_m: 0.2, calls: vec![], calibrated: true, map_x_max: None };
        let first = coarse_prior(&truth[0], 1.0, 0.0, 1);
        let frames = track(&mut basin, 4, first, Some(&odometry), &CONFIG, |_| {}).unwrap();
        assert!(frames[1..].iter().all(|f| f.mode == Mode::DeadReckoning), "{:?}", frames.iter().map(|f| f.mode).collect::<Vec<_>>());
        let estimates: Vec<Pose> = frames.iter().map(|f| f.estimate).collect();
        assert_eq!(estimates, odometry.dead_reckoned(&frames[0].estimate));
        for k in 1..4 {
            let moved = (estimates[k].camera_position_in_map() - estimates[k - 1].camera_position_in_map()).norm();
            assert!((moved - 1.0).abs() < 0.01, "frame {k} moved {moved} m: the drive's step");
        }
    }

    /// Noisy odometry is seeded, drifts by about the asked amount per step, and is the odometry
    /// itself without noise.
    #[test]
    fn noisy_odometry_is_seeded_and_drifts() {
        let truth = drive(200);
        let exact = odometry_of(&truth);
        assert_eq!(exact.with_noise(0.0, 0.0, 3), exact);
        let noisy = exact.with_noise(2.0, 0.5, 3);
        assert_eq!(noisy, exact.with_noise(2.0, 0.5, 3));
        assert_ne!(noisy, exact.with_noise(2.0, 0.5, 4));
        let (mut scale, mut turn) = (vec![], vec![]);
        for k in 1..200 {
            let (m, n) = (exact.motion(k), noisy.motion(k));
            scale.push(n.translation().norm() / m.translation().norm() - 1.0);
            turn.push(PoseError::between(&n, &m).rre_geodesic_deg);
        }
        let rms = |v: &[f64]| (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt();
        assert!((rms(&scale) - 0.02).abs() < 0.005, "scale error rms {}", rms(&scale));
        assert!((rms(&turn) - 0.5).abs() < 0.1, "turn rms {} deg", rms(&turn));
    }

    #[test]
    fn spread_covers_the_drive() {
        assert_eq!(spread(100, 5), vec![0, 24, 49, 74, 99]);
        assert_eq!(spread(3, 10), vec![0, 1, 2]);
        assert_eq!(spread(10, 1), vec![5]);
        assert!(spread(10, 0).is_empty());
    }
}
