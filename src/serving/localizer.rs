//! The localize path, top to bottom, for every caller (the HTTP route and `cmr-agent localize`):
//!
//! 1. [`Localizer::admit`]: refuse at once when not ready, draining or full (a queue [`Slot`] is
//!    reserved BEFORE any work, so a 429 costs nothing); the request's deadline starts here.
//! 2. [`Localizer::localize`]: look up the map, validate the request against it
//!    ([`ValidLocalizeRequest`]), take a decode permit (bounded concurrent decodes), decode within
//!    the pixel budget, prepare the map (cached embeddings), submit to the scheduler in the
//!    reserved slot, and wait for the answer until the deadline.

use std::sync::Arc;
use std::time::{Duration, Instant};

use tokio::sync::{Semaphore, oneshot};
use tracing::Instrument;

use crate::agent::{Localization, Start, ms};
use crate::maps::{Maps, validate_id};
use crate::model::Manifest;

use super::decode::{ImageLimits, ImagePayload, prepare_request_image};
use super::error::LocalizeError;
use super::lifecycle::{InFlight, Lifecycle};
use super::request::{LocalizeRequest, RequestDefaults, ValidLocalizeRequest};
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
}

/// An admitted request: its place in the queue, its clock, and its count as in flight.
pub struct Admission {
    slot: Slot,
    started: Instant,
    _in_flight: InFlight,
}

impl Admission {
    pub fn started(&self) -> Instant {
        self.started
    }
}

/// A localization and the time it spent in each serving phase.
pub struct Localized {
    pub localization: Localization,
    pub queue_ms: f64,
    pub decode_ms: f64,
    pub total_ms: f64,
}

pub struct Localizer {
    pub maps: Arc<Maps>,
    pub scheduler: Arc<Scheduler>,
    pub lifecycle: Arc<Lifecycle>,
    manifest: Arc<Manifest>,
    config: LocalizerConfig,
    decodes: Arc<Semaphore>,
}

impl Localizer {
    pub fn new(maps: Arc<Maps>, scheduler: Arc<Scheduler>, lifecycle: Arc<Lifecycle>, manifest: Arc<Manifest>, config: LocalizerConfig) -> Self {
        let decodes = Arc::new(Semaphore::new(config.decode_permits.max(1)));
        Self { maps, scheduler, lifecycle, manifest, config, decodes }
    }

    pub fn config(&self) -> &LocalizerConfig {
        &self.config
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
        self.localize_in_span(admission, map_id, request, image, span.clone()).instrument(span).await
    }

    async fn localize_in_span(
        &self,
        admission: Admission,
        map_id: &str,
        request: &LocalizeRequest,
        image: ImagePayload,
        span: tracing::Span,
    ) -> Result<Localized, LocalizeError> {
        let deadline = admission.started + self.config.request_timeout;
        validate_id(map_id)?;
        let maps = self.maps.clone();
        let id = map_id.to_string();
        let entry = blocking(move || maps.store.get(&id).map_err(LocalizeError::from)).await?;
        let valid = ValidLocalizeRequest::new(request, &self.config.defaults, entry)?;

        let permit = self.decodes.clone().acquire_owned().await.map_err(|_| LocalizeError::Draining)?;
        let t = Instant::now();
        let (manifest, limits, intrinsics) = (self.manifest.clone(), self.config.image, valid.intrinsics);
        let (tensor, crop_k) = blocking(move || {
            let _permit = permit;
            prepare_request_image(image, &intrinsics, &manifest, limits)
        })
        .await?;
        let decode_ms = ms(t);
        metrics::histogram!("cmr_phase_seconds", "phase" => "decode").record(decode_ms / 1000.0);

        let maps = self.maps.clone();
        let entry = valid.map.clone();
        let map = blocking(move || maps.prepared_for(&entry).map_err(LocalizeError::from)).await?;

        let (reply, answer) = oneshot::channel();
        let start = Start { map, image_tensor: tensor, intrinsics: crop_k, prior: valid.prior, search: valid.search };
        self.scheduler.submit(Job { start, deadline, span, reply }, admission.slot)?;
        let wait = deadline.saturating_duration_since(Instant::now()) + Duration::from_millis(500);
        let finished = match tokio::time::timeout(wait, answer).await {
            Ok(Ok(result)) => result?,
            Ok(Err(_)) => return Err(LocalizeError::Internal("the worker dropped the request".into())),
            Err(_) => return Err(LocalizeError::DeadlineExceeded),
        };
        Ok(Localized { localization: finished.localization, queue_ms: finished.queue_ms, decode_ms, total_ms: ms(admission.started) })
    }
}

/// Runs `work` on tokio's blocking pool (file I/O, decoding, point encoding).
async fn blocking<T: Send + 'static>(work: impl FnOnce() -> Result<T, LocalizeError> + Send + 'static) -> Result<T, LocalizeError> {
    tokio::task::spawn_blocking(work).await.map_err(|e| LocalizeError::Internal(e.to_string()))?
}
