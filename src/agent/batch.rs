//! The step loop, once: a batch of requests whose running hypotheses step together in ONE policy
//! call per iteration. The synchronous [`super::localize`] runs a batch of one request; the
//! server's workers (`serving::scheduler`) admit requests into a batch and retire them at step
//! boundaries (iteration-level batching).
//!
//! A row that goes wrong fails only its own request: a pose that is no longer finite (or leaves
//! the coordinate bound) is caught before its state is built, and policy outputs are checked row
//! by row after the call. A failing policy call as a whole fails the requests that were in it.

use std::sync::Arc;
use std::time::Instant;

use rayon::prelude::*;

use crate::geometry::{ActionSet, Intrinsics, Pose};
use crate::maps::PreparedMap;
use crate::model::{Backend, Manifest};

use super::episode::{ImageEvidence, ViewEvidence};
use super::input::{JUDGE_ANCHORS, ViewInput};
use super::search::Search;
use super::state::{self, ScratchPool, StateLayout};
use super::{Localization, SearchConfig, Timings, ms};

/// Why a request left the batch without a localization.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StepError {
    /// The request's own numbers went out of range (a pose, its state, the policy's answer to it).
    #[error("{0}")]
    NonFinite(String),
    /// A model call failed for a reason that is not this request's input.
    #[error("inference failed: {0}")]
    Inference(String),
}

/// What a request brings to the batch: everything `prepare_image` and the map store made.
pub struct Start {
    /// The map: one, or (a tiled region with starts along the optical axis) one per prior along
    /// the axis, each cut around its own prior (`search::Search::new`).
    pub maps: Vec<Arc<PreparedMap>>,
    /// [3, H, W] per the manifest, from `prepare_image`.
    pub image_tensor: Vec<f32>,
    /// The crop's intrinsics, from `prepare_image`.
    pub intrinsics: Intrinsics,
    /// The judge's views, from `prepare_views` with `search.judge_zoom` (read when
    /// `search.judges()`; may be empty otherwise).
    pub views: Vec<ViewInput>,
    /// camera_from_map to start from.
    pub prior: Pose,
    pub search: SearchConfig,
}

struct Running<T> {
    tag: T,
    search: Search,
    timings: Timings,
    steps_started: Instant,
    failed: Option<StepError>,
}

/// The requests a worker is stepping, with the buffers the steps reuse.
pub struct Batch<T> {
    running: Vec<Running<T>>,
    layout: StateLayout,
    actions: ActionSet,
    /// Scatter buffers, one per thread building states or polishing at once.
    scratch: ScratchPool,
    state_2d: Vec<f32>,
    state_3d: Vec<f32>,
}

impl<T: Send> Batch<T> {
    pub fn new(manifest: &Manifest) -> Self {
        Self {
            running: Vec::new(),
            layout: StateLayout::from_manifest(manifest),
            actions: manifest.action_set(),
            scratch: ScratchPool::default(),
            state_2d: Vec::new(),
            state_3d: Vec::new(),
        }
    }

    /// Requests in the batch.
    pub fn len(&self) -> usize {
        self.running.len()
    }

    pub fn is_empty(&self) -> bool {
        self.running.is_empty()
    }

    /// Rows the batch holds: hypotheses that will take a step in the next policy call, and the
    /// refinement rounds still to start (`Search::reserved_rows`).
    pub fn rows(&self) -> usize {
        self.running.iter().filter(|r| r.failed.is_none()).map(|r| r.search.reserved_rows()).sum()
    }

    /// Runs the per-request graphs (image encoder, frustum head) and adds the request. On error
    /// the tag comes back with the reason.
    pub fn admit(&mut self, backend: &mut dyn Backend, start: Start, tag: T) -> Result<(), (T, StepError)> {
        match begin(backend, start, &self.layout) {
            Ok((search, timings)) => {
                self.running.push(Running { tag, search, timings, steps_started: Instant::now(), failed: None });
                Ok(())
            }
            Err(e) => Err((tag, e)),
        }
    }

    /// One step of every running hypothesis of every request: one batched policy call for those
    /// that need the policy, a replayed step for those that repeat a cycle (`Search::replay`);
    /// returns the policy rows (0 when no hypothesis needed the policy).
    pub fn step(&mut self, backend: &mut dyn Backend) -> usize {
        // Rows whose pose is unusable fail their request here, before any state is built.
        for r in self.running.iter_mut().filter(|r| r.failed.is_none()) {
            if let Some(h) = r.search.running().find(|&h| !r.search.episodes[h].pose.is_sane()) {
                r.failed = Some(StepError::NonFinite(format!("hypothesis {h} reached a pose that is not finite or beyond the coordinate bound")));
            }
        }
        // Hypotheses that repeat a cycle take their step without the policy.
        for r in self.running.iter_mut().filter(|r| r.failed.is_none()) {
            r.search.replay();
        }
        let rows: Vec<(usize, usize)> = self
            .running
            .iter()
            .enumerate()
            .filter(|(_, r)| r.failed.is_none())
            .flat_map(|(i, r)| r.search.running().map(move |h| (i, h)))
            .collect();
        if !rows.is_empty() {
            self.ask_policy(backend, &rows);
        }
        // Every request still running ends its iteration here, those that only replayed too.
        let (running, layout) = (&mut self.running, &self.layout);
        self.scratch.with(|scratch| {
            for r in running.iter_mut().filter(|r| r.failed.is_none()) {
                r.search.after_step(layout, scratch);
            }
        });
        rows.len()
    }

    /// One batched policy call for `rows` ((request, hypothesis), in slot order), each row's
    /// hypothesis advanced by its answer. A failed call fails every request that had a row in
    /// it; a non-finite answer fails its own request.
    fn ask_policy(&mut self, backend: &mut dyn Backend, rows: &[(usize, usize)]) {
        let (l2, l3) = (self.layout.state_2d_len(), self.layout.state_3d_len());
        self.state_2d.resize(rows.len() * l2, 0.0);
        self.state_3d.resize(rows.len() * l3, 0.0);
        self.build_states(rows);
        let output = match backend.agent_step(&self.state_2d, &self.state_3d, rows.len()) {
            Ok(output) => output,
            Err(e) => {
                let e = StepError::Inference(format!("{e:#}"));
                tracing::error!("policy call failed for {} rows: {e}", rows.len());
                for &(i, _) in rows {
                    self.running[i].failed = Some(e.clone());
                }
                return;
            }
        };
        let per = 3 * self.actions.num_actions();
        for (slot, &(i, h)) in rows.iter().enumerate() {
            let r = &mut self.running[i];
            if r.failed.is_some() {
                continue;
            }
            let logits = &output.policy_logits[slot * per..(slot + 1) * per];
            if !(logits.iter().all(|v| v.is_finite()) && output.value[slot].is_finite()) {
                r.failed = Some(StepError::NonFinite(format!("the policy answered non-finite values for hypothesis {h}")));
                continue;
            }
            let (episode, map) = r.search.episodes_with_maps().nth(h).expect("a running hypothesis");
            episode.advance(map, &self.actions, logits, output.value[slot]);
        }
    }

    /// Builds the observation of every row into the state buffers, rows in parallel (each with a
    /// scratch buffer from the pool): rows are independent, so the result does not depend on the
    /// threads. `rows` lists (request, hypothesis) in slot order.
    fn build_states(&mut self, rows: &[(usize, usize)]) {
        let (l2, l3) = (self.layout.state_2d_len(), self.layout.state_3d_len());
        let mut slots_2d = self.state_2d[..rows.len() * l2].chunks_mut(l2);
        let mut slots_3d = self.state_3d[..rows.len() * l3].chunks_mut(l3);
        let mut jobs = Vec::with_capacity(rows.len());
        for (i, r) in self.running.iter_mut().enumerate() {
            let wanted: Vec<usize> = rows.iter().filter(|(j, _)| *j == i).map(|(_, h)| *h).collect();
            for (h, (episode, map)) in r.search.episodes_with_maps().enumerate() {
                if wanted.contains(&h) {
                    let (s2, s3) = (slots_2d.next().expect("one slot per row"), slots_3d.next().expect("one slot per row"));
                    jobs.push((i, map, episode, s2, s3));
                }
            }
        }
        let (layout, pool) = (&self.layout, &self.scratch);
        let spent: Vec<(usize, f64)> = jobs
            .into_par_iter()
            .map(|(i, map, episode, s2, s3)| {
                let t = Instant::now();
                pool.with(|scratch| episode.write_state(map, layout, scratch, s2, s3));
                (i, ms(t))
            })
            .collect();
        for (i, t) in spent {
            self.running[i].timings.state_build_ms += t;
        }
    }

    /// Fails every request still in the batch with `error` (used when a step panicked).
    pub fn fail_all(&mut self, error: StepError) {
        for r in &mut self.running {
            r.failed = Some(error.clone());
        }
    }

    /// Removes the requests whose tag matches `cancel` (deadline passed, client gone), unanswered.
    pub fn cancel(&mut self, mut cancel: impl FnMut(&T) -> bool) -> Vec<T> {
        let mut out = Vec::new();
        let mut i = 0;
        while i < self.running.len() {
            if cancel(&self.running[i].tag) {
                out.push(self.running.swap_remove(i).tag);
            } else {
                i += 1;
            }
        }
        out
    }

    /// Removes and answers every request that is done or failed. A finishing search whose
    /// judge needs its views has them encoded here (`Search::finish`).
    pub fn retire(&mut self, backend: &mut dyn Backend) -> Vec<(T, Result<Localization, StepError>)> {
        let mut out = Vec::new();
        let mut i = 0;
        while i < self.running.len() {
            let r = &self.running[i];
            if r.failed.is_none() && !r.search.is_done() {
                i += 1;
                continue;
            }
            let mut r = self.running.swap_remove(i);
            let result = match r.failed.take() {
                Some(e) => Err(e),
                None => {
                    r.timings.agent_steps_ms = ms(r.steps_started);
                    let layout = &self.layout;
                    let mut read_views = |views: &[ViewInput]| encode_views(backend, layout, views);
                    r.search.finish(layout, &self.scratch, r.timings, &mut read_views)
                }
            };
            out.push((r.tag, result));
        }
        out
    }
}

/// Runs the image encoder and the frustum head (once per map; everything per request that
/// precedes the loop) and sets up the search's hypotheses.
fn begin(backend: &mut dyn Backend, start: Start, layout: &StateLayout) -> Result<(Search, Timings), StepError> {
    let manifest = backend.manifest().clone();
    let fits = |map: &PreparedMap| map.features.len() == map.points.len() * manifest.features.dim && map.points.len() >= manifest.points.num_state_points;
    if start.maps.is_empty() || !start.maps.iter().all(|m| fits(m)) {
        return Err(StepError::Inference("the prepared map does not match this model (feature dimension or point count)".into()));
    }
    if !start.prior.is_sane() {
        return Err(StepError::NonFinite("the prior is not finite or beyond the coordinate bound".into()));
    }
    let t = Instant::now();
    let encode = |backend: &mut dyn Backend, tensor: &[f32]| backend.encode_image(tensor).map_err(|e| StepError::Inference(format!("image encoder: {e:#}")));
    let image_features = encode(backend, &start.image_tensor)?;
    // The judge's views are encoded when the search finishes, and only if it needs them.
    if start.search.judges() && start.views.len() != JUDGE_ANCHORS.len() {
        return Err(StepError::Inference(format!("the search judges with {} views, the request brought {}", JUDGE_ANCHORS.len(), start.views.len())));
    }
    let image_encoder_ms = ms(t);
    // The frustum head's answers are read for the state points only (the 3D state and the
    // confidence), so it runs on those: M of the N points, a twentieth of the work.
    let t = Instant::now();
    let mut frustum_probs = Vec::with_capacity(start.maps.len());
    for map in &start.maps {
        let state_features = &map.features[..manifest.points.num_state_points * manifest.features.dim];
        let logits = backend.frustum_logits(state_features, &image_features).map_err(|e| StepError::Inference(format!("frustum head: {e:#}")))?;
        frustum_probs.push(logits.iter().map(|l| state::sigmoid(*l)).collect::<Vec<f32>>());
    }
    let frustum_head_ms = ms(t);
    let image_features = Arc::new(state::ImageGrid::new(layout, image_features));
    let evidence = frustum_probs.into_iter().map(|frustum_probs| ImageEvidence { image_features: image_features.clone(), frustum_probs, intrinsics: start.intrinsics }).collect();
    let views = if start.search.judges() { start.views } else { Vec::new() };
    let search = Search::new(evidence, start.maps, start.prior, start.search, manifest.action_frame()).with_views(views);
    Ok((search, Timings { image_encoder_ms, frustum_head_ms, ..Default::default() }))
}

/// The image encoder's reading of each of the judge's views.
fn encode_views(backend: &mut dyn Backend, layout: &StateLayout, views: &[ViewInput]) -> Result<Vec<ViewEvidence>, StepError> {
    views
        .iter()
        .map(|v| {
            let features = backend.encode_image(&v.tensor).map_err(|e| StepError::Inference(format!("image encoder (a judge's view): {e:#}")))?;
            Ok(ViewEvidence { image_features: state::ImageGrid::new(layout, features), intrinsics: v.intrinsics })
        })
        .collect()
}
