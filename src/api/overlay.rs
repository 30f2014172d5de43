//! `POST /v1/maps/{id}/overlay`: the localize request answered with a picture (`image/png`)
//! instead of numbers: the region's points projected onto the image at the prior and at the
//! final pose (and, on request, at every iteration of the chosen start), or at one explicit
//! pose without running the agent. The request goes through the same `serving::Localizer` path
//! as localize (admission before the body is read, validation, decode budget, deadline), so its
//! refusals are localize's, with the same JSON errors; the drawing is `crate::render`'s.

use std::sync::Arc;
use std::time::Instant;

use axum::body::{Body, Bytes};
use axum::extract::State;
use axum::http::{HeaderMap, HeaderValue, header};
use axum::response::{IntoResponse, Response};
use serde::Deserialize;
use utoipa::ToSchema;

use crate::agent::Localization;
use crate::geometry::Pose;
use crate::geometry::pose::Matrix4x4;
use crate::render::{Overlay, PosePanel};
use crate::serving::{ImagePayload, IntrinsicsBody, LocalizeRequest, PictureInput, PriorSource};

use super::AppState;
use super::error::{ApiError, ErrorBody};
use super::extract::{MapId, MapIdParam};
use super::routes::{parse_json, read_body, serde_urlencoded_query};
use super::types::{BinaryBody, RawLocalizeParams};

/// The overlay's JSON body: localize's request, or an image, its intrinsics and an explicit
/// `camera_from_map` to draw without running the agent.
#[derive(Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct OverlayRequest {
    /// Base64 (standard alphabet) JPEG or PNG bytes.
    #[schema(min_length = 1, format = Byte)]
    pub image: String,
    /// Pinhole intrinsics of `image` in pixels.
    pub intrinsics: IntrinsicsBody,
    /// Starting pose (camera_from_map) of the agent; defaults as in localize.
    #[serde(default)]
    pub prior_camera_from_map: Option<Matrix4x4>,
    /// Policy steps per start, 1..=50 (as in localize).
    #[serde(default)]
    #[schema(minimum = 1, maximum = 50)]
    pub max_iterations: Option<u32>,
    /// Starts of the multi-start search, 1..=16 (as in localize).
    #[serde(default)]
    #[schema(minimum = 1, maximum = 16)]
    pub hypotheses: Option<u32>,
    /// Crop radius in a tiled region, metres (as in localize).
    #[serde(default)]
    #[schema(minimum = 1, maximum = 500)]
    pub radius_m: Option<f64>,
    /// How far the prior can be from the truth (as in localize).
    #[serde(default)]
    pub prior_bound: Option<crate::serving::request::PriorBoundBody>,
    /// Starts along the prior's optical axis (as in localize).
    #[serde(default)]
    pub axis_starts: Option<crate::serving::request::AxisStartsBody>,
    /// Draw this pose (a rigid camera_from_map within ±1e7 m, validated as the prior is) and do
    /// not run the agent; leave `prior_camera_from_map`, `max_iterations`, `hypotheses`,
    /// `prior_bound` and `axis_starts` out with it.
    #[serde(default)]
    pub camera_from_map: Option<Matrix4x4>,
}

/// Query of the overlay: localize's raw-image parameters, and `iterations`.
#[derive(Debug, Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub struct OverlayParams {
    /// Focal length along x, pixels (> 0). Required with a raw image body.
    #[param(exclusive_minimum = 0.0)]
    pub fx: Option<f64>,
    /// Focal length along y, pixels (> 0). Required with a raw image body.
    #[param(exclusive_minimum = 0.0)]
    pub fy: Option<f64>,
    /// Principal point x, pixels. Required with a raw image body.
    pub cx: Option<f64>,
    /// Principal point y, pixels. Required with a raw image body.
    pub cy: Option<f64>,
    /// 1..=50; with a raw image body (a JSON body names its own).
    #[param(minimum = 1, maximum = 50)]
    pub max_iterations: Option<u32>,
    /// Starts of the multi-start search, 1..=16; with a raw image body.
    #[param(minimum = 1, maximum = 16)]
    pub hypotheses: Option<u32>,
    /// Crop radius in a tiled region, metres; with a raw image body.
    #[param(minimum = 1, maximum = 500)]
    pub radius_m: Option<f64>,
    /// Also draw a strip of every iteration of the chosen start (small panels, 4 per row).
    #[serde(default)]
    pub iterations: Option<bool>,
}

/// What the body asked for: a localization to draw, or one explicit pose.
enum Wanted {
    Localize(LocalizeRequest),
    Pose(LocalizeRequest, Pose),
}

/// Draws the region's points on the request's image at the prior and at the final pose of a
/// localization (two panels, prior on top), coloured by camera-frame depth (red near, blue far),
/// the image at its own resolution scaled to at most 1600 pixels wide. The body is localize's
/// (JSON, or raw JPEG/PNG bytes with fx, fy, cx, cy in the query), with the same validation,
/// limits, admission and errors; `?iterations=true` adds every iteration of the chosen start. A
/// JSON body with `camera_from_map` draws that pose alone and does not run the agent. The
/// `x-camera-from-map` header carries the drawn final pose as 16 row-major numbers.
#[utoipa::path(post, path = "/v1/maps/{id}/overlay", params(MapIdParam, OverlayParams),
    request_body(content((OverlayRequest = "application/json"), (BinaryBody = "image/jpeg"), (BinaryBody = "image/png"))),
    responses((status = 200, content_type = "image/png", body = BinaryBody, description = "the picture"),
        (status = 400, body = ErrorBody), (status = 404, body = ErrorBody),
        (status = 408, body = ErrorBody), (status = 413, body = ErrorBody), (status = 415, body = ErrorBody), (status = 422, body = ErrorBody),
        (status = 429, body = ErrorBody), (status = 500, body = ErrorBody), (status = 503, body = ErrorBody)))]
pub async fn overlay(State(st): State<Arc<AppState>>, MapId(id): MapId, query: axum::extract::RawQuery, headers: HeaderMap, body: Body) -> Response {
    let started = Instant::now();
    let result = overlay_inner(&st, &id, query.0.as_deref(), &headers, body).await;
    let outcome = match &result {
        Ok(_) => "ok",
        Err(e) => e.error_type(),
    };
    metrics::counter!("cmr_requests_total", "endpoint" => "overlay", "outcome" => outcome).increment(1);
    metrics::histogram!("cmr_phase_seconds", "phase" => "overlay_total").record(started.elapsed().as_secs_f64());
    match result {
        Ok(r) => r,
        Err(e) => e.into_response(),
    }
}

async fn overlay_inner(st: &Arc<AppState>, id: &str, query: Option<&str>, headers: &HeaderMap, body: Body) -> Result<Response, ApiError> {
    let admission = st.localizer.admit()?;
    let body = read_body(body, st.config.max_body_bytes).await?;
    let params: OverlayParams = serde_urlencoded_query(query.unwrap_or(""))?;
    let strip = params.iterations.unwrap_or(false);
    let (wanted, payload) = read_overlay_request(&params, headers, body)?;
    let (panels, strip_panels, picture, drawn) = match wanted {
        Wanted::Localize(request) => {
            let (done, picture) = st.localizer.localize_for_picture(admission, id, &request, payload).await?;
            let loc = &done.localization;
            let strip_panels = if strip { iteration_panels(loc) } else { Vec::new() };
            (localization_panels(loc, done.prior_source), strip_panels, picture, loc.camera_from_map())
        }
        Wanted::Pose(request, pose) => {
            if strip {
                return Err(ApiError::Invalid("iterations: an explicit camera_from_map has no iterations to draw".into()));
            }
            let picture = st.localizer.picture_input(admission, id, &request, payload).await?;
            (vec![PosePanel::new("camera_from_map (as given)", pose)], Vec::new(), picture, pose)
        }
    };
    let png = tokio::task::spawn_blocking(move || draw(&picture, panels, strip_panels))
        .await
        .map_err(|e| ApiError::Internal(e.to_string()))??;
    let mut response = ([(header::CONTENT_TYPE, "image/png")], png).into_response();
    let pose_text = drawn.matrix().transpose().iter().map(|v| format!("{v:.6}")).collect::<Vec<_>>().join(",");
    if let Ok(v) = HeaderValue::from_str(&pose_text) {
        response.headers_mut().insert("x-camera-from-map", v);
    }
    Ok(response)
}

/// The two panels of a localization: the prior and the answer.
fn localization_panels(loc: &Localization, prior_source: PriorSource) -> Vec<PosePanel> {
    let verdict = match loc.verdict.p_registered {
        Some(p) if loc.verdict.localized => format!("localized (p {p:.2})"),
        Some(p) => format!("NOT localized (p {p:.2})"),
        None => "not localized (no calibrator)".to_string(),
    };
    let fin = if loc.kept_prior {
        format!("final: {verdict}, the prior, kept (no start explained the image better), confidence {:.2}", loc.confidence.score)
    } else {
        format!(
            "final: {verdict}, start {} of {}, {} steps{}, confidence {:.2}",
            loc.chosen + 1,
            loc.hypotheses.len(),
            loc.answer_steps().len(),
            if loc.converged() { ", converged" } else { "" },
            loc.confidence.score
        )
    };
    let prior = match prior_source {
        PriorSource::Request | PriorSource::Region => "prior",
        PriorSource::Default => "prior (default: level at the map's origin, along +x)",
    };
    vec![PosePanel::new(prior, loc.prior), PosePanel::new(fin, loc.camera_from_map())]
}

/// Every pose of the chosen start: its start and each step.
fn iteration_panels(loc: &Localization) -> Vec<PosePanel> {
    let best = loc.best();
    let start = format!("start ({:+.0}°)", best.start_yaw_offset_deg);
    std::iter::once(PosePanel::new(start, best.start))
        .chain(best.steps.iter().enumerate().map(|(i, s)| PosePanel::new(format!("step {}", i + 1), s.camera_from_map)))
        .collect()
}

fn draw(picture: &PictureInput, panels: Vec<PosePanel>, strip: Vec<PosePanel>) -> Result<Bytes, ApiError> {
    // The points are in the region's local frame; the panels' poses in the map frame.
    let local = |panels: Vec<PosePanel>| -> Vec<PosePanel> {
        panels.into_iter().map(|p| PosePanel { camera_from_map: picture.frame.camera_from_local(&p.camera_from_map), ..p }).collect()
    };
    let (panels, strip) = (local(panels), local(strip));
    let overlay = Overlay { image: &picture.image, intrinsics: picture.intrinsics, points: &picture.map.points, panels, strip };
    overlay.png().map(Bytes::from).map_err(|e| ApiError::Internal(format!("drawing the overlay: {e:#}")))
}

/// Reads either body variant: JSON (`OverlayRequest`) or raw image bytes with the query's
/// intrinsics, exactly as localize reads its own.
fn read_overlay_request(q: &OverlayParams, headers: &HeaderMap, body: Bytes) -> Result<(Wanted, ImagePayload), ApiError> {
    let ct = headers.get(header::CONTENT_TYPE).map(|v| v.to_str().unwrap_or("").to_ascii_lowercase()).unwrap_or_default();
    if ct.starts_with("image/jpeg") || ct.starts_with("image/png") {
        let raw = RawLocalizeParams { fx: q.fx, fy: q.fy, cx: q.cx, cy: q.cy, max_iterations: q.max_iterations, hypotheses: q.hypotheses, radius_m: q.radius_m };
        let request = raw.request()?;
        return Ok((Wanted::Localize(request), ImagePayload::Raw(body)));
    }
    if !(ct.is_empty() || ct.starts_with("application/json")) {
        return Err(ApiError::UnsupportedMediaType(format!("content-type must be application/json, image/jpeg or image/png, got {ct:?}")));
    }
    let r: OverlayRequest = parse_json(&body)?;
    let request = LocalizeRequest {
        image: String::new(),
        intrinsics: r.intrinsics,
        prior_camera_from_map: r.prior_camera_from_map,
        max_iterations: r.max_iterations,
        hypotheses: r.hypotheses,
        radius_m: r.radius_m,
        prior_bound: r.prior_bound,
        axis_starts: r.axis_starts,
    };
    let payload = ImagePayload::Base64(r.image);
    match r.camera_from_map {
        None => Ok((Wanted::Localize(request), payload)),
        Some(m) => {
            let search = request.max_iterations.is_some() || request.hypotheses.is_some() || request.prior_bound.is_some() || request.axis_starts.is_some();
            if request.prior_camera_from_map.is_some() || search {
                return Err(ApiError::Invalid(
                    "camera_from_map draws that pose without running the agent: leave out prior_camera_from_map, max_iterations, hypotheses, prior_bound and axis_starts".into(),
                ));
            }
            let pose = m.pose().map_err(|e| ApiError::Invalid(format!("camera_from_map: {e}")))?;
            // A tiled region draws the points around the drawn pose.
            let request = LocalizeRequest { prior_camera_from_map: Some(m), ..request };
            Ok((Wanted::Pose(request, pose), payload))
        }
    }
}
