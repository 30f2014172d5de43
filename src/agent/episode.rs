//! One trajectory in progress (one hypothesis of a search): the current pose, the steps taken so
//! far, and how to build the next observation. Kept separate from the inference calls so the
//! synchronous `localize` and the batching workers drive exactly the same logic.

use std::sync::Arc;

use crate::geometry::{ActionSet, AgentAction, Intrinsics, Pose};

use super::state::{ImageGrid, ScatterScratch, StateLayout, alignment, write_state};
use crate::maps::PreparedMap;

/// One policy step: the action chosen at the pose before it, and the pose after it.
#[derive(Debug, Clone)]
pub struct Step {
    /// 1-based iteration number.
    pub iteration: usize,
    pub camera_from_map: Pose,
    pub action: AgentAction,
    /// Softmax of the policy per DoF (rows yaw, tx, tz; columns ascending steps).
    pub probabilities: [Vec<f32>; 3],
    /// The policy's certainty: the mean over DoF of the chosen step's probability.
    pub confidence: f32,
    pub value: f32,
    /// Alignment score of `camera_from_map` (see `state::alignment`). It is read off the next
    /// observation, so it is NaN until that observation is built or the episode is settled.
    pub alignment: f32,
    /// Copied from the step taken at the same pose earlier in a cycle ([`Episode::replay`])
    /// instead of asked of the policy: it cost no policy row.
    pub repeated: bool,
}

/// How sure the result is, from two independent signals.
#[derive(Debug, Clone, Copy)]
pub struct Confidence {
    /// Intersection-over-union between the points the frustum head predicts in view (sigmoid > 0.5)
    /// and the points in view at the final pose, over the M state points (a random sample of the
    /// map's points): high when the pose explains what the image shows.
    pub frustum_iou: f32,
    /// The last step's policy certainty (mean over DoF of the argmax probability).
    pub policy_certainty: f32,
    /// sqrt(frustum_iou · policy_certainty), in [0, 1].
    pub score: f32,
    /// The final pose's alignment score (mean point/image feature agreement, in [−1, 1]).
    pub alignment: f32,
    /// Share of the M state points in the model input's frustum at the final pose, in [0, 1].
    pub in_view: f32,
}

/// What every hypothesis of one request that localizes in one map shares: computed once per
/// request and map, never copied (the image features are shared by the maps of one request).
#[derive(Debug)]
pub struct ImageEvidence {
    /// Image features [D, GH, GW] (and cell-major where the state needs them).
    pub image_features: Arc<ImageGrid>,
    /// sigmoid(frustum logit) of the first M sampled points of the map (the state points).
    pub frustum_probs: Vec<f32>,
    /// The crop's intrinsics.
    pub intrinsics: Intrinsics,
}

/// One of the judge's views of a request's image: its features and its crop's intrinsics.
#[derive(Debug)]
pub struct ViewEvidence {
    pub image_features: ImageGrid,
    pub intrinsics: Intrinsics,
}

/// The judge's score of `camera_from_map` in `map` (whose served-view alignment score is
/// `served`, `state::alignment`): the mean of `served` and the same score in each of the judge's
/// `views` (read from the same image, `input::prepare_views`); `served` itself without views.
pub fn judged_alignment(views: &[ViewEvidence], map: &PreparedMap, layout: &StateLayout, camera_from_map: &Pose, served: f32, scratch: &mut ScatterScratch) -> f32 {
    if views.is_empty() {
        return served;
    }
    let mut sum = served as f64;
    for view in views {
        sum += alignment(layout, &map.points, &map.features, &view.image_features, &view.intrinsics, camera_from_map, scratch) as f64;
    }
    (sum / (1 + views.len()) as f64) as f32
}

pub struct Episode {
    pub evidence: Arc<ImageEvidence>,
    /// Where this trajectory started.
    pub start: Pose,
    pub pose: Pose,
    pub max_iterations: usize,
    pub steps: Vec<Step>,
    pub converged: bool,
    /// Stopped by the search (a duplicate of another hypothesis, or narrowed away).
    pub dropped: bool,
    /// Alignment score of `start` (known once the first observation is built).
    pub start_alignment: f32,
    /// Set once the trajectory comes back to a pose it visited: see [`Episode::replay`].
    cycle: Option<Cycle>,
}

/// Where a trajectory's cycle lies: the pose after step `from` (0: the start) is the first pose
/// of the cycle, and `period` steps bring the trajectory back to it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Cycle {
    from: usize,
    period: usize,
}

/// Two poses whose entries differ by no more than this are one pose for [`Episode::replay`]: the
/// rounding of a step and its exact inverse (about 1e-14 on real frames' cycles), far below
/// anything that moves a point across a feature cell.
pub const SAME_POSE_TOLERANCE: f64 = 1e-12;

impl Episode {
    pub fn new(evidence: Arc<ImageEvidence>, start: Pose, max_iterations: usize) -> Self {
        Self {
            evidence,
            start,
            pose: start,
            max_iterations,
            steps: Vec::new(),
            converged: false,
            dropped: false,
            start_alignment: f32::NAN,
            cycle: None,
        }
    }

    /// Whether the next step must be asked of the policy: the episode goes on and has not come
    /// back to a pose it visited (then [`Episode::replay`] takes the step instead).
    pub fn needs_policy(&self) -> bool {
        !self.is_done() && self.cycle.is_none()
    }

    /// Whether the episode goes on by [`Episode::replay`] alone.
    pub fn is_replaying(&self) -> bool {
        !self.is_done() && self.cycle.is_some()
    }

    /// The pose after `k` steps (0: the start) and its alignment score.
    fn pose_at(&self, k: usize) -> (Pose, f32) {
        pose_after(&self.start, self.start_alignment, &self.steps, k)
    }

    /// Takes the next step of a trajectory that came back to a pose it had visited, without the
    /// policy. The observation is a function of the pose alone and the policy of the observation
    /// (its argmax per DoF), so from there on the trajectory repeats the same cycle of steps to
    /// the end of its budget: on real frames 16-38 % of the search's steps are such repeats,
    /// nearly all of a cycle of two (a large turn and its inverse; docs/evaluation.md, "Cycles"). Each repeated
    /// step is a copy of the one taken at the same pose before, so the trajectory, the answer
    /// and every signal are the ones the policy rows would give, and the search still advances
    /// all hypotheses in step (duplicates and the refinement round see the same poses at the
    /// same iterations). Panics when the episode is not [`Episode::is_replaying`].
    pub fn replay(&mut self) {
        let cycle = self.cycle.filter(|_| !self.is_done()).expect("a replaying episode");
        let taken = self.steps.len();
        let source = cycle.from + (taken - cycle.from) % cycle.period;
        let mut step = self.steps[source].clone();
        step.iteration = taken + 1;
        step.repeated = true;
        self.pose = step.camera_from_map;
        self.steps.push(step);
    }

    /// After a step: whether its pose is one the trajectory visited before (the step just taken
    /// is not the zero step). Then the pose takes that visit's alignment score, which its
    /// observation would give, and the episode replays from here on.
    fn find_cycle(&mut self) {
        let now = self.steps.len();
        let here = self.pose.matrix();
        let Some(from) = (0..now).rev().find(|&k| {
            let then = self.pose_at(k).0.matrix();
            here.iter().zip(then.iter()).all(|(a, b)| (a - b).abs() <= SAME_POSE_TOLERANCE)
        }) else {
            return;
        };
        self.steps[now - 1].alignment = self.pose_at(from).1;
        self.cycle = Some(Cycle { from, period: now - from });
    }

    /// Done when the agent chose all-zero steps, used its iteration budget or was dropped.
    pub fn is_done(&self) -> bool {
        self.converged || self.dropped || self.steps.len() >= self.max_iterations
    }

    /// Builds the observation at the current pose, and records that pose's alignment score.
    pub fn write_state(&mut self, map: &PreparedMap, layout: &StateLayout, scratch: &mut ScatterScratch, state_2d: &mut [f32], state_3d: &mut [f32]) {
        let e = &self.evidence;
        let score = write_state(
            layout,
            &map.points,
            &map.features,
            &e.frustum_probs,
            &e.image_features,
            &e.intrinsics,
            &self.pose,
            scratch,
            state_2d,
            state_3d,
        );
        self.record_alignment(score);
    }

    /// Scores the current pose if no observation has yet (the pose after the last step), so
    /// every step carries its alignment. Call once the episode is done.
    pub fn settle(&mut self, map: &PreparedMap, layout: &StateLayout, scratch: &mut ScatterScratch) {
        if self.alignment().is_nan() {
            let e = &self.evidence;
            let score = alignment(layout, &map.points, &map.features, &e.image_features, &e.intrinsics, &self.pose, scratch);
            self.record_alignment(score);
        }
    }

    fn record_alignment(&mut self, score: f32) {
        match self.steps.last_mut() {
            Some(step) => step.alignment = score,
            None => self.start_alignment = score,
        }
    }

    /// The current pose's alignment score (NaN when not yet known).
    pub fn alignment(&self) -> f32 {
        self.steps.last().map_or(self.start_alignment, |s| s.alignment)
    }

    /// Applies the policy's choice: argmax per DoF, then the disentangled update about the pivot
    /// in the action set's frame (the model's `actions.frame`).
    pub fn advance(&mut self, map: &PreparedMap, actions: &ActionSet, policy_logits: &[f32], value: f32) {
        let a = actions.num_actions();
        let probabilities: [Vec<f32>; 3] = std::array::from_fn(|dof| softmax(&policy_logits[dof * a..(dof + 1) * a]));
        let indices: [usize; 3] = std::array::from_fn(|dof| argmax(&probabilities[dof]));
        let confidence = (0..3).map(|dof| probabilities[dof][indices[dof]]).sum::<f32>() / 3.0;
        let action = actions.action(indices);
        // A zero step keeps the pose, whose score the observation just built gave.
        let alignment = if action.is_zero() { self.alignment() } else { f32::NAN };
        if action.is_zero() {
            self.converged = true;
        } else {
            self.pose = actions.apply(&self.pose, &map.pivot, &action);
        }
        self.steps.push(Step {
            iteration: self.steps.len() + 1,
            camera_from_map: self.pose,
            action,
            probabilities,
            confidence,
            value,
            alignment,
            repeated: false,
        });
        if !self.converged {
            self.find_cycle();
        }
    }

    /// How sure an answer at `pose` (one this trajectory visited) is: the frustum head's
    /// agreement there, with the policy's certainty and alignment score the search recorded.
    pub fn confidence_of(&self, map: &PreparedMap, layout: &StateLayout, pose: &Pose, policy_certainty: f32, alignment: f32) -> Confidence {
        let e = &self.evidence;
        let (frustum_iou, in_view) = frustum_overlap(&map.points, &e.frustum_probs, &e.intrinsics, layout, pose);
        Confidence { frustum_iou, policy_certainty, score: (frustum_iou * policy_certainty).sqrt(), alignment, in_view }
    }
}

/// Intersection-over-union between the points the frustum head predicts in view
/// (`frustum_probs[i]` > 0.5 for `points[i]`; only the points that have a probability count)
/// and the points in the model input's frustum at `camera_from_map` (crop intrinsics `k`,
/// `layout`'s image size); 0 when both sets are empty.
pub fn frustum_iou(points: &[[f32; 3]], frustum_probs: &[f32], k: &Intrinsics, layout: &StateLayout, camera_from_map: &Pose) -> f32 {
    frustum_overlap(points, frustum_probs, k, layout, camera_from_map).0
}

/// [`frustum_iou`], and the share of those points (the ones that have a probability) that are
/// in the frustum at `camera_from_map` (0 when there are none).
pub fn frustum_overlap(points: &[[f32; 3]], frustum_probs: &[f32], k: &Intrinsics, layout: &StateLayout, camera_from_map: &Pose) -> (f32, f32) {
    let (mut both, mut either, mut seen, mut total) = (0usize, 0usize, 0usize, 0usize);
    for (p, prob) in points.iter().zip(frustum_probs) {
        let p_cam = camera_from_map.0 * nalgebra::Point3::new(p[0] as f64, p[1] as f64, p[2] as f64);
        let in_view = k.in_frustum(&p_cam, layout.image_width, layout.image_height);
        let predicted = *prob > 0.5;
        both += (in_view && predicted) as usize;
        either += (in_view || predicted) as usize;
        seen += in_view as usize;
        total += 1;
    }
    let iou = if either == 0 { 0.0 } else { both as f32 / either as f32 };
    let share = if total == 0 { 0.0 } else { seen as f32 / total as f32 };
    (iou, share)
}

/// Where a trajectory from `start` (scoring `start_alignment`) stands after `k` of its `steps`
/// (0: the start; the last step's pose when it took fewer), and that pose's alignment score. One
/// reading for an episode in progress and a finished [`super::Hypothesis`].
pub fn pose_after(start: &Pose, start_alignment: f32, steps: &[Step], k: usize) -> (Pose, f32) {
    match k.min(steps.len()) {
        0 => (*start, start_alignment),
        k => (steps[k - 1].camera_from_map, steps[k - 1].alignment),
    }
}

pub fn softmax(logits: &[f32]) -> Vec<f32> {
    let max = logits.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let exps: Vec<f32> = logits.iter().map(|l| (l - max).exp()).collect();
    let total: f32 = exps.iter().sum();
    exps.into_iter().map(|e| e / total).collect()
}

/// Index of the largest value; the first one on ties.
pub fn argmax(values: &[f32]) -> usize {
    let mut best = 0;
    for (i, v) in values.iter().enumerate() {
        if *v > values[best] {
            best = i;
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::agent::state::sigmoid;
    use crate::model::{AgentOutput, Backend, FakeBackend, Manifest};
    use nalgebra::Point3;

    /// The fake encoders, and a policy that shifts the camera sideways by 0.9 m towards the
    /// state points' mean camera x (yaw and forward at zero): it settles into a cycle of two.
    fn centring(manifest: Arc<Manifest>) -> FakeBackend {
        let a = manifest.num_actions();
        let policy = Box::new(move |_: &[f32], state_3d: &[f32], batch: usize| {
            let l3 = state_3d.len() / batch;
            let mut policy_logits = vec![0f32; batch * 3 * a];
            for b in 0..batch {
                let x: f32 = state_3d[b * l3..(b + 1) * l3].chunks(5).map(|p| p[0]).sum();
                let row = &mut policy_logits[b * 3 * a..(b + 1) * 3 * a];
                row[a / 2] = 5.0;
                row[a + if x > 0.0 { a / 2 - 3 } else { a / 2 + 3 }] = 5.0;
                row[2 * a + a / 2] = 5.0;
            }
            Some(AgentOutput { policy_logits, value: vec![0.0; batch] })
        });
        FakeBackend::with_policy(manifest, policy)
    }

    /// One policy step of `episode` with `backend`, as the batch loop takes it.
    fn policy_step(episode: &mut Episode, backend: &mut FakeBackend, map: &PreparedMap, layout: &StateLayout) {
        let (mut s2, mut s3) = (vec![0f32; layout.state_2d_len()], vec![0f32; layout.state_3d_len()]);
        episode.write_state(map, layout, &mut ScatterScratch::default(), &mut s2, &mut s3);
        let out = backend.agent_step(&s2, &s3, 1).unwrap();
        episode.advance(map, &backend.manifest().action_set(), &out.policy_logits, out.value[0]);
    }

    /// A trajectory that comes back to a pose it visited repeats its cycle without the policy:
    /// the same steps (actions, poses, alignment scores, probabilities) as asking the policy
    /// every time, for fewer policy rows.
    #[test]
    fn a_cycle_is_replayed_without_the_policy_and_matches_it() {
        let manifest = Arc::new(Manifest::load(&std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/tiny-model")).unwrap());
        let mut backend = centring(manifest.clone());
        let cloud: Vec<[f32; 3]> = (0..5000).map(|i| [(i % 100) as f32 * 0.3 - 15.0, (i / 100) as f32 * 0.4 - 10.0, ((i * 7) % 13) as f32 * 0.2 - 1.7]).collect();
        let map = crate::maps::prepare_map(&mut backend, crate::model::Points::xyz(&cloud)).unwrap();
        let layout = StateLayout::from_manifest(&manifest);
        let image: Vec<f32> = (0..3 * layout.image_width as usize * layout.image_height as usize).map(|p| (p % 97) as f32 / 97.0).collect();
        let image_features = backend.encode_image(&image).unwrap();
        let state_features = &map.features[..manifest.points.num_state_points * manifest.features.dim];
        let logits = backend.frustum_logits(state_features, &image_features).unwrap();
        let evidence = Arc::new(ImageEvidence {
            image_features: Arc::new(ImageGrid::new(&layout, image_features)),
            frustum_probs: logits.iter().map(|l| sigmoid(*l)).collect(),
            intrinsics: Intrinsics { fx: 250.0, fy: 250.0, cx: 255.5, cy: 79.5 },
        });
        let rig = Pose::from_rt(nalgebra::Matrix3::new(0.0, -1.0, 0.0, 0.0, 0.0, -1.0, 1.0, 0.0, 0.0), nalgebra::Vector3::zeros());
        let start = rig.compose(&Pose::ground_motion(0.1, 1.0, 3.2));
        let iterations = 12;

        let mut asked = Episode::new(evidence.clone(), start, iterations);
        while !asked.is_done() {
            policy_step(&mut asked, &mut backend, &map, &layout);
        }
        asked.settle(&map, &layout, &mut ScatterScratch::default());
        let rows_asked = std::mem::take(&mut backend.rows);

        let mut replayed = Episode::new(evidence, start, iterations);
        while !replayed.is_done() {
            if replayed.is_replaying() {
                replayed.replay();
            } else {
                assert!(replayed.needs_policy());
                policy_step(&mut replayed, &mut backend, &map, &layout);
            }
        }
        replayed.settle(&map, &layout, &mut ScatterScratch::default());

        let repeats = replayed.steps.iter().filter(|s| s.repeated).count();
        assert!(repeats >= 4, "the policy should settle into a cycle early: {repeats} repeated steps");
        assert_eq!((rows_asked, backend.rows), (iterations, iterations - repeats));
        assert_eq!(replayed.steps.len(), asked.steps.len());
        for (r, a) in replayed.steps.iter().zip(&asked.steps) {
            assert_eq!((r.iteration, r.action, &r.probabilities), (a.iteration, a.action, &a.probabilities));
            let moved = r.camera_from_map.matrix() - a.camera_from_map.matrix();
            assert!(moved.amax() < 1e-9, "step {}: the poses differ by {}", r.iteration, moved.amax());
            assert!((r.alignment - a.alignment).abs() < 1e-6, "step {}: {} vs {}", r.iteration, r.alignment, a.alignment);
        }
        assert!(!replayed.steps[..iterations - repeats].iter().any(|s| s.repeated), "only the steps after the cycle closed repeat");
    }

    #[test]
    fn zero_action_converges_and_keeps_the_pose() {
        let map = PreparedMap {
            points: vec![[0.0, 0.0, 5.0]],
            features: vec![0.0; 64],
            pivot: Point3::new(0.0, 0.0, 5.0),
            source_points: 1,
            intensity: None,
        };
        let set = ActionSet::default();
        let k = Intrinsics { fx: 100.0, fy: 100.0, cx: 256.0, cy: 80.0 };
        let evidence = Arc::new(ImageEvidence { image_features: Default::default(), frustum_probs: vec![0.95], intrinsics: k });
        let mut ep = Episode::new(evidence, Pose::identity(), 5);
        let mut logits = vec![0f32; 33];
        logits[10] = 5.0; // yaw +62.5°
        logits[11 + 5] = 5.0;
        logits[22 + 5] = 5.0;
        ep.advance(&map, &set, &logits, 0.0);
        assert!(!ep.converged);
        assert_eq!(ep.steps[0].action.yaw_deg, 62.5);
        let moved = ep.pose;
        logits[10] = 0.0;
        logits[5] = 5.0;
        ep.advance(&map, &set, &logits, 0.0);
        assert!(ep.converged && ep.is_done());
        assert_eq!(ep.pose, moved);
        assert_eq!(ep.steps.len(), 2);
    }
}
