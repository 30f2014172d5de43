//! HTTP handlers. Blocking work (decoding, point encoding, file I/O) runs on tokio's blocking
//! pool; model inference runs on the agent workers.

use std::sync::Arc;
use std::time::Instant;

use axum::Json;
use axum::body::{Body, Bytes};
use axum::extract::rejection::BytesRejection;
use axum::extract::{Query, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use crate::agent::search::{MAX_HYPOTHESES, MAX_ITERATIONS};
use crate::maps::formats::CloudFormat;
use crate::maps::{MapMetadata, Upload, UploadOptions, validate_id};
use crate::serving::{ImagePayload, LocalizeRequest};

use super::AppState;
use super::error::{ApiError, ErrorBody};
use super::extract::{Admin, MapId, MapIdParam};
use crate::agent::ms;
use super::types::*;

type Shared = State<Arc<AppState>>;

/// Runs `work` on tokio's blocking pool. Even a store lookup belongs there: it stats the region's
/// files, and re-reads and hashes a cloud that another replica has rewritten.
async fn blocking<T, E>(work: impl FnOnce() -> Result<T, E> + Send + 'static) -> Result<T, ApiError>
where
    T: Send + 'static,
    E: Into<ApiError> + Send + 'static,
{
    tokio::task::spawn_blocking(work).await.map_err(|e| ApiError::Internal(e.to_string()))?.map_err(Into::into)
}

/// Liveness: the process is up.
#[utoipa::path(get, path = "/health", responses((status = 200, body = Health)))]
pub async fn health() -> Json<Health> {
    Json(Health { status: "ok".into() })
}

/// Readiness: models loaded and warmed, maps prepared, not draining.
#[utoipa::path(get, path = "/ready", responses((status = 200, body = Readiness), (status = 503, body = Readiness)))]
pub async fn ready(State(st): Shared) -> Response {
    let ready = st.is_ready();
    let body = Readiness { ready, draining: st.lifecycle.is_draining(), workers: st.config.workers() };
    let status = if ready { StatusCode::OK } else { StatusCode::SERVICE_UNAVAILABLE };
    (status, Json(body)).into_response()
}

/// Prometheus metrics (text exposition format).
#[utoipa::path(get, path = "/metrics", responses((status = 200, body = String, content_type = "text/plain")))]
pub async fn metrics(State(st): Shared) -> Response {
    metrics::gauge!("cmr_queue_depth").set(st.scheduler.queue_depth() as f64);
    metrics::gauge!("cmr_active_requests").set(st.scheduler.active() as f64);
    metrics::gauge!("cmr_cache_bytes").set(st.maps.cache.weighted_bytes() as f64);
    ([(header::CONTENT_TYPE, "text/plain; version=0.0.4")], st.metrics.render()).into_response()
}

/// Model manifest, limits and version.
#[utoipa::path(get, path = "/v1/info", responses((status = 200, body = Info)))]
pub async fn info(State(st): Shared) -> Json<Info> {
    let c = &st.config.engine;
    let serve = &st.config;
    Json(Info {
        name: env!("CARGO_PKG_NAME").into(),
        version: env!("CARGO_PKG_VERSION").into(),
        manifest: serde_json::to_value(&*st.models.manifest).unwrap_or_default(),
        limits: Limits {
            max_body_bytes: serve.max_body_bytes,
            max_map_bytes: serve.max_map_bytes,
            max_image_side: c.max_image_side,
            max_iterations: MAX_ITERATIONS,
            default_max_iterations: c.default_max_iterations,
            max_hypotheses: MAX_HYPOTHESES as u32,
            default_hypotheses: c.default_hypotheses,
            narrow_after: c.search.narrow_after,
            merge_duplicates: c.search.merge_duplicates,
            keep_prior: c.search.keep_prior,
            refine: c.search.refine,
            polish: c.search.polish,
            prior_margin: c.search.prior_margin,
            judge_zoom: c.search.judge_zoom,
            judge_gate: c.search.judge_gate,
            queue_capacity: serve.queue_capacity,
            max_batch: c.max_batch,
            request_timeout_ms: c.request_timeout_ms,
            body_timeout_ms: serve.body_timeout_ms,
            cache_budget_bytes: st.maps.cache.budget_bytes(),
            max_map_points: c.max_map_points,
            tile_above_points: c.tile_above_points,
            default_radius_m: c.default_radius_m,
        },
        localized_threshold: st.localizer.calibration.threshold(),
        localized_threshold_bounded: st.localizer.calibration.bounded_threshold(),
        workers: serve.workers(),
        onnxruntime_library: crate::model::runtime::loaded_library().map(|p| p.display().to_string()),
    })
}

/// Lists the stored map regions.
#[utoipa::path(get, path = "/v1/maps", responses((status = 200, body = MapList)))]
pub async fn list_maps(State(st): Shared) -> Result<Json<MapList>, ApiError> {
    let maps = st.maps.clone();
    let summaries = blocking(move || Ok::<_, ApiError>(maps.store.list().into_iter().map(|e| MapSummary::new(e, &maps)).collect())).await?;
    Ok(Json(MapList { maps: summaries }))
}

/// One map region: its points, origin and extent (map frame), whether it is tiled, its tiles and
/// where its bytes are.
#[utoipa::path(get, path = "/v1/maps/{id}", params(MapIdParam),
    responses((status = 200, body = MapSummary), (status = 400, body = ErrorBody), (status = 404, body = ErrorBody)))]
pub async fn get_map(State(st): Shared, MapId(id): MapId) -> Result<Json<MapSummary>, ApiError> {
    let maps = st.maps.clone();
    let summary = blocking(move || maps.store.get(&id).map(|e| MapSummary::new(e, &maps))).await?;
    Ok(Json(summary))
}

/// Largest `max` of the points route, and its default.
pub const MAX_POINTS_QUERY: u32 = 100_000;
pub const DEFAULT_POINTS_QUERY: u32 = 20_000;

/// A compact sample of a region's points for drawing them client-side (the web page projects
/// them at every iteration): for a whole region the first `min(max, N)` points of its prepared
/// N-point sample (a seeded random permutation of the stored cloud, so any prefix is a uniform
/// subsample; the same points the agent and the overlay use), for a tiled region `max` points
/// spread over it. Body: `count` × 12 bytes, each point x, y, z as little-endian float32, metres,
/// relative to the region's origin (float32 cannot hold UTM-size coordinates to the centimetre):
/// p_map = p + origin, the origin given by `x-map-origin` as `x,y,z` (0,0,0 for most regions).
/// `x-point-count` gives `count`, `x-points-total` the stored cloud's finite points. At most
/// 100,000 × 12 bytes = 1.2 MB. Preparing a region that is not prepared yet runs the point
/// encoder once (as localize would).
#[utoipa::path(get, path = "/v1/maps/{id}/points", params(MapIdParam, PointsParams),
    responses((status = 200, content_type = "application/octet-stream", body = BinaryBody,
            description = "count × (x, y, z) little-endian float32, metres, relative to the region's origin (x-map-origin)",
            headers(("x-point-count" = u32, description = "points in the body"),
                ("x-points-total" = u64, description = "finite points of the stored cloud"),
                ("x-map-origin" = String, description = "the region's origin in the map frame, `x,y,z` metres: p_map = p + origin"))),
        (status = 400, body = ErrorBody), (status = 404, body = ErrorBody), (status = 422, body = ErrorBody),
        (status = 500, body = ErrorBody)))]
pub async fn map_points(State(st): Shared, MapId(id): MapId, query: axum::extract::RawQuery) -> Result<Response, ApiError> {
    let params: PointsParams = serde_urlencoded_query(query.0.as_deref().unwrap_or(""))?;
    let max = params.max.unwrap_or(DEFAULT_POINTS_QUERY);
    if !(1..=MAX_POINTS_QUERY).contains(&max) {
        return Err(ApiError::Invalid(format!("max must be 1..={MAX_POINTS_QUERY}, got {max}")));
    }
    let maps = st.maps.clone();
    let (points, total, origin) = blocking(move || {
        let entry = maps.store.get(&id)?;
        let (points, total) = maps.prepared_for(&entry)?.drawing_sample(max as usize);
        Ok::<_, crate::maps::MapError>((points, total, entry.origin))
    })
    .await?;
    let count = points.len();
    let mut body = Vec::with_capacity(count * 12);
    for v in points.iter().flatten() {
        body.extend_from_slice(&v.to_le_bytes());
    }
    let origin = HeaderValue::from_str(&format!("{},{},{}", origin[0], origin[1], origin[2])).expect("numbers are a valid header");
    let headers = [
        (header::CONTENT_TYPE, HeaderValue::from_static("application/octet-stream")),
        (header::CACHE_CONTROL, HeaderValue::from_static("no-cache")),
        (header::HeaderName::from_static("x-point-count"), HeaderValue::from(count as u64)),
        (header::HeaderName::from_static("x-points-total"), HeaderValue::from(total as u64)),
        (header::HeaderName::from_static("x-map-origin"), origin),
    ];
    Ok((headers, body).into_response())
}

/// Whether the body is gzip-compressed by `Content-Encoding` (`gzip`, `x-gzip` or `identity`;
/// anything else is 415).
fn gzip_encoded(headers: &HeaderMap) -> Result<bool, ApiError> {
    let Some(value) = headers.get(header::CONTENT_ENCODING) else { return Ok(false) };
    match value.to_str().unwrap_or("").trim().to_ascii_lowercase().as_str() {
        "" | "identity" => Ok(false),
        "gzip" | "x-gzip" => Ok(true),
        other => Err(ApiError::UnsupportedMediaType(format!("Content-Encoding {other:?} is not supported; send gzip or identity"))),
    }
}

/// Uploads (or replaces) a map region from raw point-cloud bytes: KITTI .bin, PCD, PLY or LAS
/// 1.0-1.4, optionally gzip-compressed (`Content-Encoding: gzip`, or a gzip body recognised by
/// its magic bytes; inflated size bounded by `max_map_bytes`). Coordinates must be finite-or-NaN
/// and within ±1e7 m (points with a NaN/infinite coordinate are dropped); they are read as float64
/// and stored as float32 relative to the region's `origin`, so UTM-size coordinates keep their
/// precision. At most `max_map_points` points (413 beyond); `voxel_m` downsamples before storing.
/// A region with more than `tile_above_points` points is tiled: its points are grouped into 20 m
/// ground cells here (2.5 M points: about 1 s), and, only for a server started with
/// `--crop-embeddings stored`, embedded tile by tile (2.5 M points: about 6 s more; the default
/// server encodes each request's crop instead). The previous region stays
/// intact unless the new one parses, encodes and is stored. With an admin token, the token is
/// checked before the body is read.
#[utoipa::path(put, path = "/v1/maps/{id}", params(MapIdParam, UploadParams,
        ("Content-Encoding" = Option<String>, Header, description = "`gzip` when the body is gzip-compressed (also recognised without it); `identity` or absent otherwise")),
    request_body(content = BinaryBody, content_type = "application/octet-stream",
        description = "The point-cloud file: KITTI .bin (float32 x, y, z, intensity), PCD (ascii, binary, binary_compressed), PLY (ascii, binary), LAS 1.0-1.4 and LAZ; optionally gzip-compressed"),
    responses((status = 201, body = RegisterResponse, description = "new region"), (status = 200, body = RegisterResponse, description = "region replaced"),
        (status = 400, body = ErrorBody, description = "invalid map id or unreadable body"),
        (status = 401, body = ErrorBody, description = "missing or wrong bearer token (checked before the body is read)"),
        (status = 408, body = ErrorBody, description = "the body did not arrive in time"),
        (status = 413, body = ErrorBody, description = "the body, or its gzip-inflated content, is larger than max_map_bytes, or the file holds more than max_map_points points"),
        (status = 415, body = ErrorBody, description = "recognised as something other than a point cloud this server reads (PNG/JPEG image, zip/7z/xz/zstd/bzip2 archive, gzip inside gzip, JSON/HTML/PDF) or an unsupported Content-Encoding; the message names what was received"),
        (status = 422, body = ErrorBody, description = "bytes of no known format, a cloud that does not parse, has a coordinate beyond ±1e7 m or no finite point, corrupt gzip, a body whose header contradicts `format`, or an `origin` or `voxel_m` out of range")),
    security(("bearer" = [])))]
pub async fn put_map(
    _admin: Admin,
    State(st): Shared,
    MapId(id): MapId,
    query: axum::extract::RawQuery,
    headers: HeaderMap,
    body: Result<Bytes, BytesRejection>,
) -> Result<Response, ApiError> {
    validate_id(&id)?;
    // Parsed here, not by axum's `Query`, so a bad parameter is a JSON 422 like every refusal.
    let params: UploadParams = serde_urlencoded_query(query.0.as_deref().unwrap_or(""))?;
    let gzip = gzip_encoded(&headers)?;
    let format = match params.format.as_deref() {
        None | Some("") => None,
        Some(name) => Some(name.parse::<CloudFormat>().map_err(ApiError::Invalid)?),
    };
    let options = UploadOptions { origin: params.origin()?, voxel_m: params.voxel_m };
    let body = body.map_err(ApiError::from_body)?;
    let t = Instant::now();
    let maps = st.maps.clone();
    let max_bytes = st.config.max_map_bytes;
    let (entry, timings, replaced) = blocking(move || {
        let existing = maps.store.get(&id).ok();
        let replaced = existing.is_some();
        let metadata = params.description.map(|d| {
            let mut m = existing.map(|e| e.metadata).unwrap_or_default();
            m.description = Some(d);
            m
        });
        let (entry, timings) = maps.register(&id, Upload { bytes: &body, format, gzip, max_bytes }, options, metadata)?;
        drop(body);
        Ok::<_, ApiError>((MapSummary::new(entry, &maps), timings, replaced))
    })
    .await?;
    let total = ms(t);
    metrics::histogram!("cmr_map_register_seconds").record(total / 1000.0);
    let status = if replaced { StatusCode::OK } else { StatusCode::CREATED };
    let body = RegisterResponse {
        map: entry,
        replaced,
        timings_ms: RegisterTimingsMs { parse: timings.parse_ms, point_encoder: timings.encode_ms, store: timings.store_ms, total },
    };
    Ok((status, Json(body)).into_response())
}

/// Replaces a region's metadata (description, initial_camera_from_map, source). The body must be a
/// JSON object with only those fields, each of its schema's type (else 422).
#[utoipa::path(put, path = "/v1/maps/{id}/metadata", params(MapIdParam),
    request_body = MapMetadata,
    responses((status = 200, body = MapSummary), (status = 400, body = ErrorBody), (status = 401, body = ErrorBody),
        (status = 404, body = ErrorBody), (status = 408, body = ErrorBody), (status = 413, body = ErrorBody), (status = 422, body = ErrorBody)),
    security(("bearer" = [])))]
pub async fn put_metadata(
    _admin: Admin,
    State(st): Shared,
    MapId(id): MapId,
    body: Result<Bytes, BytesRejection>,
) -> Result<Json<MapSummary>, ApiError> {
    validate_id(&id)?;
    let body = body.map_err(ApiError::from_body)?;
    let metadata = MapMetadata::from_json(parse_json(&body)?)?;
    let maps = st.maps.clone();
    let id2 = id.clone();
    let summary = blocking(move || maps.store.set_metadata(&id2, metadata).map(|e| MapSummary::new(e, &maps))).await?;
    Ok(Json(summary))
}

/// Deletes a region and its cached embeddings.
#[utoipa::path(delete, path = "/v1/maps/{id}", params(MapIdParam),
    responses((status = 204), (status = 400, body = ErrorBody), (status = 401, body = ErrorBody), (status = 404, body = ErrorBody)),
    security(("bearer" = [])))]
pub async fn delete_map(_admin: Admin, State(st): Shared, MapId(id): MapId) -> Result<StatusCode, ApiError> {
    let maps = st.maps.clone();
    blocking(move || maps.delete(&id)).await?;
    Ok(StatusCode::NO_CONTENT)
}

/// Localizes a camera image in a map region: the pose, the agent's trajectory, a confidence
/// signal and per-phase timings (also in the `Server-Timing` header). The body is either the JSON
/// request, or the raw JPEG/PNG bytes (`content-type: image/jpeg|image/png`) with the intrinsics
/// fx, fy, cx, cy in the query. Capacity is checked before the body is read: a 429 costs nothing.
#[utoipa::path(post, path = "/v1/maps/{id}/localize", params(MapIdParam, RawLocalizeParams),
    request_body(content((LocalizeRequest = "application/json"), (BinaryBody = "image/jpeg"), (BinaryBody = "image/png"))),
    responses((status = 200, body = LocalizeResponse), (status = 400, body = ErrorBody), (status = 404, body = ErrorBody),
        (status = 408, body = ErrorBody), (status = 413, body = ErrorBody), (status = 415, body = ErrorBody), (status = 422, body = ErrorBody),
        (status = 429, body = ErrorBody), (status = 500, body = ErrorBody), (status = 503, body = ErrorBody)))]
pub async fn localize(State(st): Shared, MapId(id): MapId, query: axum::extract::RawQuery, headers: HeaderMap, body: Body) -> Response {
    let started = Instant::now();
    let result = localize_inner(&st, &id, query.0.as_deref(), &headers, body).await;
    let outcome = match &result {
        Ok(_) => "ok",
        Err(e) => e.error_type(),
    };
    metrics::counter!("cmr_requests_total", "endpoint" => "localize", "outcome" => outcome).increment(1);
    metrics::histogram!("cmr_phase_seconds", "phase" => "total").record(started.elapsed().as_secs_f64());
    match result {
        Ok(r) => r,
        Err(e) => e.into_response(),
    }
}

/// Reads either request variant into one shape: the request and its image payload.
fn read_request(query: Option<&str>, headers: &HeaderMap, body: Bytes) -> Result<(LocalizeRequest, ImagePayload), ApiError> {
    let ct = headers.get(header::CONTENT_TYPE).map(|v| v.to_str().unwrap_or("").to_ascii_lowercase()).unwrap_or_default();
    if ct.starts_with("image/jpeg") || ct.starts_with("image/png") {
        let q: RawLocalizeParams = serde_urlencoded_query(query.unwrap_or(""))?;
        let request = q.request()?;
        return Ok((request, ImagePayload::Raw(body)));
    }
    if !(ct.is_empty() || ct.starts_with("application/json")) {
        return Err(ApiError::UnsupportedMediaType(format!("content-type must be application/json, image/jpeg or image/png, got {ct:?}")));
    }
    let mut request: LocalizeRequest = parse_json(&body)?;
    let image = std::mem::take(&mut request.image);
    Ok((request, ImagePayload::Base64(image)))
}

/// Query strings through the same deserializer axum's `Query` uses.
pub(super) fn serde_urlencoded_query<T: serde::de::DeserializeOwned>(query: &str) -> Result<T, ApiError> {
    let uri: axum::http::Uri = format!("/?{query}").parse().map_err(|_| ApiError::BadRequest("malformed query string".into()))?;
    Query::<T>::try_from_uri(&uri).map(|q| q.0).map_err(|e| ApiError::Invalid(format!("query: {}", e.body_text())))
}

async fn localize_inner(st: &Arc<AppState>, id: &str, query: Option<&str>, headers: &HeaderMap, body: Body) -> Result<Response, ApiError> {
    let admission = match st.localizer.admit() {
        Ok(admission) => admission,
        Err(e @ crate::serving::LocalizeError::QueueFull) => {
            tokio::time::sleep(std::time::Duration::from_millis(st.config.shed_delay_ms)).await;
            return Err(e.into());
        }
        Err(e) => return Err(e.into()),
    };
    let body = read_body(body, st.config.max_body_bytes).await?;
    let (request, payload) = read_request(query, headers, body)?;
    let done = st.localizer.localize(admission, id, &request, payload).await?;
    let loc = &done.localization;
    let timings = TimingsMs::new(done.queue_ms, done.decode_ms, &loc.timings, done.total_ms);
    metrics::histogram!("cmr_iterations").record(loc.iterations() as f64);
    let body = LocalizeResponse::new(id, loc, done.prior_source, timings);
    let mut response = Json(body).into_response();
    if let Ok(v) = HeaderValue::from_str(&timings.header()) {
        response.headers_mut().insert("server-timing", v);
    }
    Ok(response)
}

/// Reads a whole body of at most `limit` bytes (413 beyond), within the body deadline (408).
pub(super) async fn read_body(body: Body, limit: usize) -> Result<Bytes, ApiError> {
    axum::body::to_bytes(body, limit).await.map_err(|e| {
        if super::body_deadline::is_body_deadline(&e) {
            ApiError::BodyTimeout(format!("request body too slow: {e}"))
        } else if super::body_deadline::has_source::<http_body_util::LengthLimitError>(&e) {
            ApiError::PayloadTooLarge(format!("request body is larger than {limit} bytes"))
        } else {
            ApiError::BadRequest(format!("cannot read the request body: {e}"))
        }
    })
}

/// JSON syntax errors are 400; well-formed JSON with wrong fields or types is 422.
pub(super) fn parse_json<T: serde::de::DeserializeOwned>(body: &[u8]) -> Result<T, ApiError> {
    serde_json::from_slice(body).map_err(|e| match e.classify() {
        serde_json::error::Category::Data => ApiError::Invalid(format!("invalid request: {e}")),
        _ => ApiError::MalformedJson(e.to_string()),
    })
}

/// Fallback for unknown routes.
pub async fn not_found() -> ApiError {
    ApiError::NotFound("no such endpoint".into())
}
