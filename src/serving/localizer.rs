//! The localize path, top to bottom, for every caller (the HTTP route and `cmr-agent localize`):
//!
//! 1. [`Localizer::admit`]: refuse at once when not ready, draining or full (a queue [`Slot`] is
//!    reserved BEFORE any work, so a 429 costs nothing); the request's deadline starts here.
//! 2. [`Localizer::localize`]: look up the map, validate the request against it
//!    ([`ValidLocalizeRequest`]), take a decode permit (bounded concurrent decodes), decode within
//!    the pixel budget, prepare the map (cached embeddings), submit to the scheduler in the
//!    reserved slot, and wait for the answer until the deadline.
//!    [`Localizer::localize_for_picture`] is the same path keeping the decoded image for the
//!    overlay; [`Localizer::picture_input`] stops before the agent (an explicit pose is drawn).

use std::sync::Arc;
use std::time::{Duration, Instant};

use tokio::sync::{Semaphore, oneshot};
use tracing::Instrument;

use crate::agent::{Localization, Start, ms};
use crate::maps::{CropEmbeddings, Maps, validate_id};
use crate::model::{Calibration, Manifest};

use image::RgbImage;

use crate::geometry::{Intrinsics, LocalFrame};
use crate::maps::PreparedMap;

use super::decode::{ImageLimits, ImagePayload, decode_payload, prepare_request_image};
use super::error::LocalizeError;
use super::lifecycle::{InFlight, Lifecycle};
use super::request::{LocalizeRequest, PriorSource, RequestDefaults, ValidLocalizeRequest};
use super::scheduler::{Job, Scheduler, Slot};

/// The localize path's settings (from `serve`'s flags).
#[derive(Debug, Clone, Copy)]
pub struct LocalizerConfig {
    pub image: ImageLimits,
    pub defaults: RequestDefaults,
    /// From admission to answer.
    pub request_timeout: Duration,
    /// Images decoded at once (each may hold up to `image.max_pixels` of RGB and a resize).
    pub decode_permits: usize,
    /// Replaces the manifest's `calibrator.threshold` for `localized` (`None`: the manifest's).
    pub localized_threshold: Option<f64>,
}

/// An admitted request: its place in the queue, its clock, and its count as in flight.
pub struct Admission {
    slot: Slot,
    started: Instant,
    _in_flight: InFlight,
}

/// A localization and the time it spent in each serving phase.
pub struct Localized {
    pub localization: Localization,
    /// Where `localization.prior` came from.
    pub prior_source: PriorSource,
    pub queue_ms: f64,
    pub decode_ms: f64,
    pub total_ms: f64,
}

/// What a picture of a request is drawn from: the decoded image at its own resolution, the
/// request's intrinsics (for that resolution, not the model's crop) and the region's prepared
/// map (its N sampled points, in the region's local `frame`: map-frame poses are drawn through
/// `frame.camera_from_local`).
pub struct PictureInput {
    pub image: RgbImage,
    pub intrinsics: Intrinsics,
    pub map: Arc<PreparedMap>,
    pub frame: LocalFrame,
}

pub struct Localizer {
    pub maps: Arc<Maps>,
    pub scheduler: Arc<Scheduler>,
    pub lifecycle: Arc<Lifecycle>,
    manifest: Arc<Manifest>,
    config: LocalizerConfig,
    decodes: Arc<Semaphore>,
    /// The model set's calibrator with the threshold in force: every answer's verdict.
    pub calibration: Calibration,
}

impl Localizer {
    pub fn new(maps: Arc<Maps>, scheduler: Arc<Scheduler>, lifecycle: Arc<Lifecycle>, manifest: Arc<Manifest>, config: LocalizerConfig) -> Self {
        let decodes = Arc::new(Semaphore::new(config.decode_permits.max(1)));
        let calibration = Calibration::new(manifest.calibrator.as_ref(), config.localized_threshold);
        Self { maps, scheduler, lifecycle, manifest, config, decodes, calibration }
    }

    /// Admission control: call before reading or decoding anything of the request.
    pub fn admit(&self) -> Result<Admission, LocalizeError> {
        if self.lifecycle.is_draining() {
            return Err(LocalizeError::Draining);
        }
        if !self.lifecycle.is_ready() {
            return Err(LocalizeError::NotReady("models are still loading; retry shortly".into()));
        }
        let slot = self.scheduler.reserve()?;
        Ok(Admission { slot, started: Instant::now(), _in_flight: self.lifecycle.enter() })
    }

    /// Localizes one admitted request against map `map_id`. `request.image` is ignored: the
    /// image comes as `image` (base64 from the JSON body, or raw bytes).
    pub async fn localize(&self, admission: Admission, map_id: &str, request: &LocalizeRequest, image: ImagePayload) -> Result<Localized, LocalizeError> {
        let span = tracing::info_span!("localize", map = map_id);
        let (done, _) = self.localize_in_span(admission, map_id, request, image, false, span.clone()).instrument(span).await?;
        Ok(done)
    }

    /// [`Localizer::localize`], keeping what a picture of the answer needs: the decoded image
    /// at its own resolution, its intrinsics and the region's prepared points.
    pub async fn localize_for_picture(
        &self,
        admission: Admission,
        map_id: &str,
        request: &LocalizeRequest,
        image: ImagePayload,
    ) -> Result<(Localized, PictureInput), LocalizeError> {
        let span = tracing::info_span!("localize", map = map_id, picture = true);
        let (done, picture) = self.localize_in_span(admission, map_id, request, image, true, span.clone()).instrument(span).await?;
        let picture = picture.ok_or_else(|| LocalizeError::Internal("the decoded image was not kept".into()))?;
        Ok((done, picture))
    }

    /// A picture's input without running the agent (an explicit pose is drawn): the same map
    /// lookup, validation (`request`'s intrinsics and every other field, as localize checks
    /// them), decode permit, pixel budget and deadline as [`Localizer::localize`].
    pub async fn picture_input(&self, admission: Admission, map_id: &str, request: &LocalizeRequest, image: ImagePayload) -> Result<PictureInput, LocalizeError> {
        let deadline = admission.started + self.config.request_timeout;
        let work = async {
            let valid = self.validate(map_id, request).await?;
            let permit = self.decodes.clone().acquire_owned().await.map_err(|_| LocalizeError::Draining)?;
            let (manifest, limits) = (self.manifest.clone(), self.config.image);
            let decoded = blocking(move || {
                let _permit = permit;
                decode_payload(image, &manifest, limits)
            })
            .await?;
            let map = self.prepared(&valid, false).await?.swap_remove(0);
            Ok(PictureInput { image: decoded, intrinsics: valid.intrinsics, map, frame: valid.frame })
        };
        let result = tokio::time::timeout_at(deadline.into(), work).await.map_err(|_| LocalizeError::DeadlineExceeded)?;
        drop(admission);
        result
    }

    async fn localize_in_span(
        &self,
        admission: Admission,
        map_id: &str,
        request: &LocalizeRequest,
        image: ImagePayload,
        keep_image: bool,
        span: tracing::Span,
    ) -> Result<(Localized, Option<PictureInput>), LocalizeError> {
        let deadline = admission.started + self.config.request_timeout;
        let valid = self.validate(map_id, request).await?;
        let permit = self.decodes.clone().acquire_owned().await.map_err(|_| LocalizeError::Draining)?;
        let t = Instant::now();
        let (manifest, limits, intrinsics) = (self.manifest.clone(), self.config.image, valid.intrinsics);
        let judge_zoom = if valid.search.judges() { valid.search.judge_zoom } else { 0.0 };
        let prepared = blocking(move || {
            let _permit = permit;
            prepare_request_image(image, &intrinsics, &manifest, limits, judge_zoom)
        })
        .await?;
        let (tensor, crop_k, views, decoded) = (prepared.tensor, prepared.intrinsics, prepared.views, prepared.image);
        // Held through the agent's run only when a picture will be drawn.
        let decoded = keep_image.then_some(decoded);
        let decode_ms = ms(t);
        metrics::histogram!("cmr_phase_seconds", "phase" => "decode").record(decode_ms / 1000.0);

        let maps = self.prepared(&valid, true).await?;
        let (reply, answer) = oneshot::channel();
        let picture = decoded.map(|image| PictureInput { image, intrinsics, map: maps[0].clone(), frame: valid.frame });
        let start = Start { maps, image_tensor: tensor, intrinsics: crop_k, prior: valid.prior, search: valid.search, views };
        self.scheduler.submit(Job { start, deadline, span, reply }, admission.slot)?;
        let wait = deadline.saturating_duration_since(Instant::now()) + Duration::from_millis(500);
        let finished = match tokio::time::timeout(wait, answer).await {
            Ok(Ok(result)) => result?,
            Ok(Err(_)) => return Err(LocalizeError::Internal("the worker dropped the request".into())),
            Err(_) => return Err(LocalizeError::DeadlineExceeded),
        };
        let mut localization = finished.localization;
        localization.verdict = self.calibration.judge(&localization.signals());
        if !valid.frame.is_identity() {
            localization.map_poses(|p| valid.frame.camera_from_map(p));
        }
        let done = Localized { localization, prior_source: valid.prior_source, queue_ms: finished.queue_ms, decode_ms, total_ms: ms(admission.started) };
        Ok((done, picture))
    }
}

impl Localizer {
    /// The map entry (404 when absent) and the request checked against it and the limits.
    async fn validate(&self, map_id: &str, request: &LocalizeRequest) -> Result<ValidLocalizeRequest, LocalizeError> {
        validate_id(map_id)?;
        let maps = self.maps.clone();
        let id = map_id.to_string();
        let entry = blocking(move || maps.store.get(&id).map_err(LocalizeError::from)).await?;
        let tiled = self.maps.is_tiled(entry.num_points);
        ValidLocalizeRequest::new(request, &self.config.defaults, entry, tiled)
    }

    /// The points and embeddings this request uses, in the region's local frame: a whole
    /// region's prepared sample (cache, else `<id>.emb`, else the point encoder), or a tiled
    /// region's crops (`ValidLocalizeRequest::crops`: around the prior, and with starts along the
    /// optical axis around each shifted prior; the first only unless `every_crop`); 422 when a
    /// crop holds fewer than the agent's M points.
    async fn prepared(&self, valid: &ValidLocalizeRequest, every_crop: bool) -> Result<Vec<Arc<PreparedMap>>, LocalizeError> {
        let maps = self.maps.clone();
        let entry = valid.map.clone();
        let crops = valid.crops[..if every_crop { valid.crops.len() } else { valid.crops.len().min(1) }].to_vec();
        let min_points = self.manifest.points.num_state_points;
        blocking(move || {
            let prepared = maps.prepared_for(&entry).map_err(LocalizeError::from)?;
            if crops.is_empty() {
                return Ok(vec![prepared.around([0.0; 3], 0.0, 0, true).map_err(|e| LocalizeError::Internal(e.to_string()))?]);
            }
            let stored = maps.config.crop_embeddings == CropEmbeddings::Stored;
            crops
                .iter()
                .enumerate()
                .map(|(g, c)| {
                    let field = if g == 0 { "prior_camera_from_map" } else { "axis_starts" };
                    let map = prepared.around(c.sensor, c.radius_m, min_points, stored).map_err(|e| LocalizeError::Invalid(format!("{field}: {e}")))?;
                    match maps.config.crop_embeddings {
                        CropEmbeddings::Stored => Ok(map),
                        CropEmbeddings::Encode => maps.reencode(&map).map(Arc::new).map_err(LocalizeError::from),
                    }
                })
                .collect()
        })
        .await
    }
}

/// Runs `work` on tokio's blocking pool (file I/O, decoding, point encoding).
async fn blocking<T: Send + 'static>(work: impl FnOnce() -> Result<T, LocalizeError> + Send + 'static) -> Result<T, LocalizeError> {
    tokio::task::spawn_blocking(work).await.map_err(|e| LocalizeError::Internal(e.to_string()))?
}
